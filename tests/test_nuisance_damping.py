"""`fit --nuisance-damping` (`FitSettings.nuisance_damping`, #24): a global damping fitted with E though
the stage has no damping effect, so that dissipation the model lacks (a video's, or a synthetic truth's
numerical one) goes into c rather than into E.

- The job switches damping on for the fit only (the stage's effects untouched), fitted and its start
  searched; d loss / d log c through that job's problem matches central finite differences in float64.
- Known answer: the bar's video damped with c = 8/s after the release; a fresh fit with the flag (the
  stage has no effect, 16 iterations; CPU: c 1.03x, E 0.98x) recovers c and E within 10%; the version records the setting; a refit without the
  flag is not taken for `effects remove damping`, and `effects add damping` starts from the fitted c;
  `diagnose` keeps the fitted c in its base model and says why damping is not a candidate (testing "more
  damping" at c's own optimum would score ~0: the fit's gradient in c is zero there).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import report_scene as rs
from physinteract_usd import api
from physinteract_usd.cli import _main as main

pytestmark = pytest.mark.usefixtures("one_torch_thread")
QUIET = dict(progress=False, log=lambda *a: None)
C_TRUE = 8.0


@pytest.fixture(scope="module")
def damped(tmp_path_factory):
    return rs.build(tmp_path_factory.mktemp("nuisance") / "damped", hidden_damping=C_TRUE, n_frames=14)


def test_the_job_switches_damping_on_for_the_fit_only_and_its_gradient_matches_fd(damped):
    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.fit import FitProblem
    from physinteract_usd.fit.effect_params import effect_parameters, effect_values

    stage = damped["stage"]
    plain = prepare_fit(stage, warm=False, log=lambda *a: None)
    assert "damping" not in plain.effects and plain.settings.fit_effects == ()
    job = prepare_fit(stage, warm=False, log=lambda *a: None, settings_overrides={"nuisance_damping": True})
    assert job.effects == {"damping": {"coefficient": 0.0}}
    assert job.settings.fit_effects == ("damping",) and job.settings.search_effects == ("damping",)
    assert "damping" not in api.read_scene(stage).effects            # the stage is not touched
    prob = FitProblem(job.scene, job.observations, job.contacts, effects=job.effects, dtype="float64")
    raw = effect_parameters(prob, job.settings.fit_effects, {"damping": {"coefficient": 3.0}})
    P = len(prob.x0)
    E = torch.full((P,), 4e3, dtype=torch.float64)
    nu = torch.full((P,), 0.3, dtype=torch.float64)

    def loss():
        return prob.loss(E, nu, effects=effect_values(raw, prob.traj_scale))["rec"]

    leaf = raw["damping"]["coefficient"]
    g, = torch.autograd.grad(loss(), [leaf])
    # h and the 1% bound: this 64x48 scene's loss carries FD noise of ~1e-3 relative below h ~ 1e-3 (the
    # renderer's pixel edges: the FD of log c wanders -0.02698 .. -0.02787 for h 3e-4 .. 1e-5, -0.0277 at 3e-3
    # and 1e-2, the gradient -0.02779); E's gradients are FD-checked in tests/test_sim_gradients.py
    h = 1e-2
    with torch.no_grad():
        x = float(leaf)
        leaf.fill_(x + h)
        lp = float(loss())
        leaf.fill_(x - h)
        lm = float(loss())
        leaf.fill_(x)
    fd = (lp - lm) / (2 * h)
    assert abs(fd) > 1e-6, "the loss does not depend on c"
    assert abs(float(g) - fd) <= 1e-2 * abs(fd), (float(g), fd)

def test_a_fresh_fit_recovers_the_damping_and_e_and_the_stage_keeps_its_effects(damped, tmp_path):
    import shutil

    src = damped["stage"].parent
    root = tmp_path / "s"
    shutil.copytree(src, root)
    stage = root / damped["stage"].name
    over = dict(confidence_probes=0, search_evals=6, levels=(1,), level_share=(1.0,), fit_poisson_levels=0)
    out = api.fit(stage, iterations=16, warm=False, keep_best=False,
                  settings_overrides={**over, "nuisance_damping": True}, **QUIET)
    c = out.result.effect_parameters["damping"]["coefficient"]
    E = float(np.median(out.result.youngs))
    assert abs(c / C_TRUE - 1) < 0.10, c
    assert abs(E / rs.E_TRUE - 1) < 0.10, E
    sd = api.read_scene(stage)
    assert "damping" not in sd.effects
    rep = sd.current_report
    assert rep["settings"]["nuisance_damping"] is True and "damping" in rep["effects"]
    # diagnose: the nuisance damping is in the base model at its fitted c, not a candidate, and says so
    diag = api.diagnose(stage, progress=False, log=lambda *a: None, refit=0, starts=1, candidates="damping,plasticity",
                        write_stage=False)
    assert all(cand["effect"] != "damping" for cand in diag.get("candidates", []))
    assert any("fitted with E as a nuisance" in n and "--nuisance-damping" in n for n in diag["notes"]), diag["notes"]
    # without the flag, the next fit is not a warm start after "-damping" (the user never switched it on)
    from physinteract_usd.app.fit import prepare_fit

    assert prepare_fit(stage, log=lambda *a: None).start is None
    # `effects add damping` warm-starts from the version and keeps the nuisance's fitted c as its start
    api.effects_add(stage, "damping")
    job = prepare_fit(stage, log=lambda *a: None)
    assert job.start is not None and job.start["effects"]["damping"]["coefficient"] == pytest.approx(c)
    assert job.settings.fit_effects == ("damping",) and job.settings.search_effects == ()   # not searched again
    assert job.settings.nuisance_damping is False


def test_the_cli_flag_reaches_the_settings(damped, tmp_path, monkeypatch):
    seen = {}

    def fake_fit(stage, **kw):
        seen.update(kw)
        raise SystemExit(0)

    monkeypatch.setattr(api, "fit", fake_fit)
    with pytest.raises(SystemExit):
        main(["fit", str(damped["stage"]), "--nuisance-damping", "--iterations", "1"])
    assert seen["settings_overrides"]["nuisance_damping"] is True
