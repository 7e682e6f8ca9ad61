"""`effects add | remove | list` and the refit they lead to.

- The verb edits the user's root layer only (the generated sublayers byte for byte the same), keeps
  what the user authored there, and refuses unknown, already-on and not-on effects in one line.
- The fitted effects' parameters have gradients that match central finite differences in float64.
- A refit after `effects add` warm-starts from the current version: with the effect at its null
  value (c = 0, fixed) its first iteration's loss is the previous version's final loss.
- Known answer: a bar swinging after the hand lets go, its video rendered with damping c = 8/s; the
  base model cannot settle it (it stiffens instead), `effects add damping` + fit recovers c within
  25% and halves the loss, as a new version.
"""

from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import pytest
import torch

import fit_scene as fs
import report_scene as rs
from physinteract_usd import api
from physinteract_usd.cli import _main as main

pytestmark = pytest.mark.usefixtures("one_torch_thread")
QUIET = dict(progress=False, log=lambda *a: None)


def _md5(p) -> str:
    return hashlib.md5(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return fs.build(tmp_path_factory.mktemp("effects") / "bar", n_frames=6, release=3)


# ------------------------------------------------------------------------------- the verb
def test_add_remove_list_touch_only_the_root_layer(bar, tmp_path, capsys):
    stage = fs.copy_scene(bar["root"], tmp_path / "s")
    init, fitl = stage.with_name("scene.init.usdc"), stage.with_name("scene.fit.usdc")
    before = {p: _md5(p) for p in (init, fitl)}
    # something the user authored in the root: kept through add and remove
    from pxr import Sdf

    root = Sdf.Layer.FindOrOpen(str(stage))
    spec = Sdf.CreatePrimInLayer(root, "/World/PhysInteract")
    Sdf.AttributeSpec(spec, "userNote", Sdf.ValueTypeNames.String).default = "mine"
    root.Save()

    assert main(["effects", "add", str(stage), "damping", "--coefficient", "2.5"]) == 0
    assert main(["effects", "add", str(stage), "ground", "--mu", "0.3", "--fixed"]) == 0
    capsys.readouterr()
    d = api.effects_list(stage)
    on = {e["effect"]: e for e in d["effects"] if e["on"]}
    assert set(on) == {"damping", "ground"}
    assert on["damping"]["fit"] is True and on["damping"]["parameters"]["coefficient"]["value"] == 2.5
    assert on["ground"]["fit"] is False and abs(on["ground"]["parameters"]["friction"]["value"] - 0.3) < 1e-6
    # the ground starts at the object's bottom
    y0 = api.read_scene(stage).particles_positions[:, 1].min()
    assert abs(on["ground"]["parameters"]["height"]["value"] - y0) < 0.01
    # the one reader: read_stage's SceneData.effects
    sd = api.read_scene(stage)
    assert sd.effects["damping"]["coefficient"] == 2.5 and sd.effects["damping"]["fit"] is True
    assert {p: _md5(p) for p in (init, fitl)} == before
    text = stage.read_text()
    assert "PhysInteractDampingAPI" in text and "userNote" in text

    # one-line errors, exit 2, nothing written
    for argv, words in ((["add", str(stage), "damping"], ("damping", "already on")),
                        (["add", str(stage), "friction"], ("unknown effect", "friction")),
                        (["remove", str(stage), "plasticity"], ("plasticity", "not on")),
                        (["add", str(stage), "plasticity", "--coefficient", "3"], ("plasticity", "coefficient")),
                        (["add", str(stage), "damping_x"], ("unknown",)),
                        (["add", str(stage), "viscoelasticity", "--modulus", "-5"], ("modulus",)),
                        (["list", str(tmp_path / "missing.usda")], ("missing.usda",))):
        snap = stage.read_text()
        assert main(["effects", *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and all(w in err for w in words), (argv, err)
        assert stage.read_text() == snap

    assert main(["effects", "list", str(stage), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert [e["effect"] for e in js["effects"] if e["on"]] == ["damping", "ground"]

    assert main(["effects", "remove", str(stage), "damping"]) == 0
    assert main(["effects", "remove", str(stage), "ground"]) == 0
    assert api.read_scene(stage).effects == {}
    text = stage.read_text()
    assert "damping" not in text and "Ground" not in text and "userNote" in text
    assert {p: _md5(p) for p in (init, fitl)} == before
    # the composed stage is still valid
    from pxr import Usd, UsdValidation

    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    api.effects_add(stage, "viscoelasticity")
    errors = [e for e in ctx.Validate(Usd.Stage.Open(str(stage))) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]


def test_an_effect_applied_in_a_weaker_layer_is_removed_from_the_root(bar, tmp_path):
    """An API applied by a sublayer (not ours to edit) is switched off by a delete entry in the root."""
    from pxr import Sdf

    stage = fs.copy_scene(bar["root"], tmp_path / "s")
    fitl = Sdf.Layer.FindOrOpen(str(stage.with_name("scene.fit.usdc")))
    spec = Sdf.CreatePrimInLayer(fitl, "/World/PhysInteract")
    spec.SetInfo("apiSchemas", Sdf.TokenListOp.Create(prependedItems=["PhysInteractDampingAPI"]))
    fitl.Save()
    assert "damping" in api.read_scene(stage).effects
    before = _md5(stage.with_name("scene.fit.usdc"))
    api.effects_remove(stage, "damping")
    assert "damping" not in api.read_scene(stage).effects
    assert _md5(stage.with_name("scene.fit.usdc")) == before
    api.effects_add(stage, "damping")      # and back on: the delete entry goes
    assert "damping" in api.read_scene(stage).effects


# ------------------------------------------------------------------------------- gradients
def test_effect_parameter_gradients_match_finite_differences_float64(bar):
    """d loss / d (log c, log E_v, log tau) through the simulator and renderer, float64."""
    from physinteract_usd.fit import FitProblem, Observations
    from physinteract_usd.fit.effect_params import effect_parameters, effect_values
    from physinteract_usd.usd.stage import read_stage

    sd = read_stage(bar["stage"])
    obs = Observations(frames=bar["frames"].astype(np.float32), masks=bar["masks"])
    specs = fs.contacts(sd, release=3)
    eff = {"damping": {"coefficient": 3.0}, "viscoelasticity": {"modulus": 2e3, "relaxationTime": 0.05}}
    prob = FitProblem(sd, obs, specs, effects=eff, dtype="float64")
    raw = effect_parameters(prob, ("damping", "viscoelasticity"))
    P = len(sd.particles_positions)
    E = torch.full((P,), 4e3, dtype=torch.float64)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)

    def loss():
        return prob.loss(E, nu, effects=effect_values(raw, prob.traj_scale))["rec"]

    total = loss()
    leaves = [raw["damping"]["coefficient"], raw["viscoelasticity"]["modulus"], raw["viscoelasticity"]["relaxationTime"]]
    grads = torch.autograd.grad(total, leaves)
    h = 1e-4
    for leaf, g in zip(leaves, grads):
        with torch.no_grad():
            x = float(leaf)
            leaf.fill_(x + h)
            lp = float(loss())
            leaf.fill_(x - h)
            lm = float(loss())
            leaf.fill_(x)
        fd = (lp - lm) / (2 * h)
        assert abs(fd) > 1e-6, "the loss does not depend on the parameter"
        assert abs(float(g) - fd) <= 2e-3 * abs(fd) + 1e-8, (float(g), fd)


# ------------------------------------------------------------------------------- the refit
def test_warm_start_begins_at_the_previous_versions_loss(bar, tmp_path):
    stage = fs.copy_scene(bar["root"], tmp_path / "s")
    over = dict(fs.SMOKE_SETTINGS, confidence_probes=0)
    v1 = api.fit(stage, iterations=fs.SMOKE_ITERATIONS, contact_from=bar["gt"], settings_overrides=over, **QUIET)
    # damping on at its null value and not fitted: the model is the previous one exactly
    api.effects_add(stage, "damping", {"c": 0.0}, fixed=True)
    logs = []
    v2 = api.fit(stage, iterations=1, contact_from=bar["gt"], settings_overrides=over, progress=False, log=logs.append,
                 keep_best=False)
    assert v2.version == v1.version + 1
    assert any("warm start from v1" in m for m in logs), logs
    assert v2.result.loss_history[0] == pytest.approx(v1.result.final_loss, rel=1e-4)
    assert api.read_scene(stage).reports[-1]["resumed_from"] == "warm:v1"
    # the default iterations of a warm start are fewer; --fresh refits from scratch
    from physinteract_usd.app.fit import DEFAULT_ITERATIONS, WARM_ITERATIONS, prepare_fit

    api.effects_remove(stage, "damping")
    assert prepare_fit(stage, contact_from=bar["gt"], log=lambda *a: None).settings.iterations == WARM_ITERATIONS
    fresh = prepare_fit(stage, contact_from=bar["gt"], log=lambda *a: None, warm=False)
    assert fresh.start is None and fresh.settings.iterations == DEFAULT_ITERATIONS > WARM_ITERATIONS


def test_a_warm_start_takes_the_hand_paths_from_the_fitted_the_measured_or_both(bar, tmp_path):
    """`fit --warm-path`: after `effects add` the field is the previous version's; the hand paths the previous
    version's (fitted), the measured ones (the previous path may have soaked up the effect just added) or both
    refits run and the lower final loss kept (the default)."""
    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.errors import InputError

    stage = fs.copy_scene(bar["root"], tmp_path / "s")
    over = dict(fs.SMOKE_SETTINGS, confidence_probes=0)
    api.fit(stage, iterations=fs.SMOKE_ITERATIONS, contact_from=bar["gt"], settings_overrides=over, **QUIET)
    api.effects_add(stage, "damping")
    warm = prepare_fit(stage, contact_from=bar["gt"], log=lambda *a: None, warm_path="fitted")
    assert warm.start["trajectories"] and warm.resumed_from == "warm:v1" and warm.alt_start is None
    logs = []
    meas = prepare_fit(stage, contact_from=bar["gt"], log=logs.append, warm_path="measured")
    assert "trajectories" not in meas.start and meas.resumed_from == "warm:v1" and meas.alt_start is None
    np.testing.assert_array_equal(meas.start["youngs"], warm.start["youngs"])
    assert any("--warm-path measured" in m for m in logs), logs
    both = prepare_fit(stage, contact_from=bar["gt"], log=lambda *a: None)        # the default: both, the lower kept
    assert both.start["trajectories"] and "trajectories" not in both.alt_start
    with pytest.raises(InputError, match="--warm-path"):
        prepare_fit(stage, contact_from=bar["gt"], log=lambda *a: None, warm_path="neither")
    # the refit from both: each start's final loss recorded, the lower one kept, its confidence estimated
    logs = []
    out = api.fit(stage, iterations=2, contact_from=bar["gt"], settings_overrides=dict(over, confidence_probes=2),
                  progress=False, log=logs.append, keep_best=False)
    wp = out.result.settings["warm_path"]
    assert set(wp["final_loss"]) == {"fitted", "measured"}
    assert wp["kept"] == min(wp["final_loss"], key=wp["final_loss"].get)
    assert out.result.final_loss == pytest.approx(min(wp["final_loss"].values()), rel=1e-9)
    assert any("kept the refit from the" in m for m in logs), logs
    assert out.confidence_estimated and np.all(np.isfinite(out.result.confidence))
    assert "damping" in out.result.effect_parameters


def test_added_damping_is_fitted_and_recovers_the_truth(tmp_path):
    """Known answer: the video's bar is damped with c = 8/s after the release (frame 5 of 14)."""
    c_true = 8.0
    b = rs.build(tmp_path / "damped", hidden_damping=c_true, n_frames=14)
    stage = b["stage"]
    over = dict(confidence_probes=0, search_evals=4, levels=(1,), level_share=(1.0,))
    base = api.fit(stage, iterations=4, warm=False, keep_best=False, settings_overrides=over, **QUIET)
    assert base.result.effect_parameters == {}
    added = api.effects_add(stage, "damping")
    assert added["values"] == {"coefficient": 1.0} and added["source"]["coefficient"] in ("default", "diagnose v2")
    logs = []
    out = api.fit(stage, iterations=6, settings_overrides=over, progress=False, log=logs.append)
    assert any("warm start" in m for m in logs) and any("damping: start coefficient" in m for m in logs)
    c = out.result.effect_parameters["damping"]["coefficient"]
    assert abs(c / c_true - 1) < 0.25, c
    assert out.result.final_loss < 0.5 * base.result.final_loss
    assert out.current == out.version
    # the stage says so: the list shows the fitted value, the report the error falling across versions
    d = api.effects_list(stage)["effects"][0]
    assert d["effect"] == "damping" and d["parameters"]["coefficient"]["fitted"] == pytest.approx(c)
    from physinteract_usd.app.report import versions as report_versions

    vs = report_versions(api.read_scene(stage))
    assert vs[-1]["effects"] == ["damping"] and vs[-1]["loss"] < 0.5 * vs[-2]["loss"]
    assert vs[-1]["psnr"] > vs[-2]["psnr"]
    # a refit after `effects remove` warm-starts too, without the effect
    api.effects_remove(stage, "damping")
    logs = []
    back = api.fit(stage, iterations=1, settings_overrides=over, progress=False, log=logs.append)
    assert any("-damping" in m for m in logs) and back.result.effect_parameters == {}
    assert back.result.final_loss > out.result.final_loss
    assert math.isfinite(back.result.final_loss)


def test_add_starts_from_the_diagnosis_estimate_when_there_is_one(tmp_path):
    """`diagnose` stores its result on the version it diagnosed; `effects add` starts from its estimate."""
    dio = pytest.importorskip("physinteract_usd.usd.diagnosis_io")
    b = rs.build(tmp_path / "d")
    sd = api.read_scene(b["stage"])
    dio.write_diagnosis(b["stage"], sd.fps, sd.n_frames, sd.current_version,
                        {"verdict": "missing_effect", "reason": "", "candidates": [
                            {"effect": "damping", "score": 3.0, "predicted_loss_drop": 0.01, "realized_loss_drop": None,
                             "estimate": {"coefficient": 6.5}, "evidence": ""}]})
    out = api.effects_add(b["stage"], "damping")
    assert out["values"]["coefficient"] == pytest.approx(6.5) and out["source"]["coefficient"] == "diagnose v1"
    out = api.effects_add(b["stage"], "ground", {"mu": 0.2})          # no estimate for it: defaults, and what was given
    assert out["source"] == {"height": "default", "friction": "given"}


def test_the_ladder_schedule_fits_an_added_effect_too(tmp_path):
    """The same refit through the "ladder" schedule: warm start, the effect's start searched, fitted."""
    b = rs.build(tmp_path / "damped", hidden_damping=8.0, n_frames=12)
    api.effects_add(b["stage"], "damping")
    over = dict(schedule="ladder", confidence_probes=0, max_regions=1)
    out = api.fit(b["stage"], iterations=3, keep_best=False, settings_overrides=over, **QUIET)
    assert out.result.model.get("resumed") and "damping" in out.result.model["effect_search"]
    c = out.result.effect_parameters["damping"]["coefficient"]
    assert 4.0 < c < 16.0, c
