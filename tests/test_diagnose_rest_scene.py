"""`--floor-rule rest` on a simulated bar with a frame before contact (tests/diagnose_rest_scene.py; issue #22,
docs/diagnose.md "`--floor-rule rest`"): with the superset's substeps matched to the fit's, the control's
rendering floor (soft alpha against binary masks) leans along the gravity probe over the moving frames and
`camera:depth_scale` is significant (a false alarm); judged on the rest frame it is not. A real depth-scale
error (the video's gravity x 1.2) is significant on the rest frame and selected."""

import pytest
import torch

import diagnose_rest_scene as drs
import report_scene as rs

pytestmark = pytest.mark.usefixtures("one_torch_thread")
CANDS = ("camera:depth_scale", "camera:time_offset")


def _diagnose(info, **kw):
    from physinteract_usd import api
    from physinteract_usd.app.adapters import load_observations
    from physinteract_usd.app.diagnose import superset_effects
    from physinteract_usd.diagnose import BaseState, DiagnoseSettings, diagnose_problem
    from physinteract_usd.fit import FitProblem

    sd = api.read_scene(info["stage"])
    eff = superset_effects(sd, {})
    prob = FitProblem(sd, load_observations(sd), info["specs"], effects=eff)
    P = len(sd.particles_positions)
    base = BaseState(torch.full((P,), rs.E_TRUE, dtype=prob.tdtype), torch.full((P,), 0.3, dtype=prob.tdtype), eff)
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=CANDS, confirmed=True, **kw))
    return d, {c.effect: c for c in d.results}


def test_control_depth_scale_false_alarm_is_gone_on_the_rest_frame(tmp_path):
    info = drs.build(tmp_path / "control", noise=0.015, seed=0)
    d, m = _diagnose(info, floor_rule="match")
    assert m["camera:depth_scale"].significant and m["camera:depth_scale"].marginal[0] < 0.005   # the false alarm
    d, r = _diagnose(info, floor_rule="rest")
    assert d.noise["camera_rest_frames"] == [1]
    assert r["camera:depth_scale"].rest_only and r["camera:depth_scale"].marginal[0] > 0.5
    assert d.significant == []


def test_real_depth_scale_error_is_selected_on_the_rest_frame(tmp_path):
    info = drs.build(tmp_path / "gravity", gravity_scale=1.2, noise=0.015, seed=0)
    d, r = _diagnose(info, floor_rule="rest")
    assert d.significant and d.significant[0].effect == "camera:depth_scale"
    assert r["camera:depth_scale"].rest_only and r["camera:depth_scale"].estimate["scale"] < 1.0
