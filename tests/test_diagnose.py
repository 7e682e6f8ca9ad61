"""`diagnose` on tiny scenes with a known answer (tests/diagnose_scene.py: report_scene's bar, whose
video has what the fitted model lacks): the hidden effect is ranked first with a sound estimate,
the predicted drop matches the realised Gauss-Newton step, the score's derivative matches float64
finite differences, a control scene with realistic noise is `adequate`, and the CLI's exit codes,
JSON schema and stored diagnosis."""

import json

import numpy as np
import pytest

import diagnose_scene as ds
import report_scene as rs

pytestmark = pytest.mark.usefixtures("one_torch_thread")

KEYS = {"effect", "score", "predicted_loss_drop", "realized_loss_drop", "estimate", "evidence"}
C_TRUE = 6.0


@pytest.fixture(scope="module")
def damped(tmp_path_factory):
    return ds.build(tmp_path_factory.mktemp("damped"), hidden={"damping": {"coefficient": C_TRUE}}, noise=0.015)


@pytest.fixture(scope="module")
def control(tmp_path_factory):
    return ds.build(tmp_path_factory.mktemp("control"), noise=0.015, seed=1)


def _problem(info, dtype="float32"):
    """The stage's problem with the superset effects and the fitted state (as app.diagnose builds)."""
    import torch

    from physinteract_usd import api
    from physinteract_usd.app.adapters import load_observations
    from physinteract_usd.app.diagnose import superset_effects
    from physinteract_usd.diagnose import BaseState
    from physinteract_usd.fit import FitProblem

    sd = api.read_scene(info["stage"])
    eff = superset_effects(sd, {})
    prob = FitProblem(sd, load_observations(sd), info["specs"], effects=eff, dtype=dtype)
    P = len(sd.particles_positions)
    base = BaseState(torch.full((P,), rs.E_TRUE, dtype=prob.tdtype), torch.full((P,), 0.3, dtype=prob.tdtype), eff)
    return prob, base


def test_hidden_damping_is_ranked_first_and_the_drop_is_realised(damped):
    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem, realised_gauss_newton

    prob, base = _problem(damped)
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("damping", "ground", "camera:time_offset")))
    top = d.significant[0]
    assert top.effect == "damping"
    assert top.p_value < 0.01
    assert top.estimate["coefficient"] == pytest.approx(C_TRUE, rel=0.3)
    # the predicted drop is what the Gauss-Newton step (damping at its estimate, the base adjusted
    # jointly) realises when simulated for real
    real = realised_gauss_newton(d, top)
    assert real == pytest.approx(top.drop, rel=0.2)
    # the confusable ground explains part of it alone, but nothing once damping is in
    ground = next(c for c in d.results if c.effect == "ground")
    assert not ground.significant


def test_score_is_the_float64_derivative_of_the_loss(damped):
    """The damping probe's column at the null is dr/dc: 2 r.j equals the autograd derivative of
    sum r^2 w.r.t. c at c = 0, and both match a float64 finite difference."""
    import torch

    from physinteract_usd.diagnose.residual import ImageResidual

    prob, base = _problem(damped, "float64")
    res = ImageResidual(prob, max_pixels=1500)
    c = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    eff = {e: dict(p) for e, p in base.effects.items()}
    eff["damping"] = {"coefficient": c}
    x, F = prob.simulate(base.E, base.nu, None, effects=eff)
    r = res.torch(x, F)
    (r * r).sum().backward()
    g_auto = float(c.grad)

    def L(cv):
        e2 = {k: dict(v) for k, v in base.effects.items()}
        e2["damping"] = {"coefficient": cv}
        with torch.no_grad():
            x, F = prob.simulate(base.E, base.nu, None, effects=e2)
        return res(x, F)

    # h = 1e-5: at 1e-4 the difference quotient is off by 1e-3 (the loss bends within 2e-4 of c = 0
    # at the adaptive substep's CFL 0.6); at 1e-5 and 1e-6 it agrees with autograd to 1e-7
    h = 1e-5
    r0, r1, r2 = L(0.0), L(h), L(2 * h)
    g_fd = (4 * np.sum(r1 ** 2) - 3 * np.sum(r0 ** 2) - np.sum(r2 ** 2)) / (2 * h)   # one-sided, second order
    j = (4 * r1 - 3 * r0 - r2) / (2 * h)
    assert abs(g_auto) > 1e-6
    assert g_auto == pytest.approx(g_fd, rel=1e-4)
    assert 2 * float(r0 @ j) == pytest.approx(g_auto, rel=1e-4)


def t_note(d, effect):
    return next(t for t in d["tested"] if t["effect"] == effect)["note"]


def test_diagnose_verb_names_damping_and_stores_it(damped):
    from physinteract_usd import api
    from physinteract_usd.usd.diagnosis_io import read_diagnosis

    d = api.diagnose(damped["stage"], refit=1, refit_iterations=2, progress=False, log=lambda *a: None,
                     candidates="damping,ground,camera:time_offset")
    assert d["verdict"] == "missing_effect"
    assert d["candidates"] and all(set(c) == KEYS for c in d["candidates"])
    top = d["candidates"][0]
    assert top["effect"] == "damping"
    assert top["realized_loss_drop"] is not None and top["realized_loss_drop"] > 0
    assert top["estimate"]["coefficient"] == pytest.approx(C_TRUE, rel=0.3)
    assert "after release at frame" in top["evidence"]
    # the ground, accepted as its mimic, and damping refitted together: the pair step's drop-one costs in the evidence
    # and in `tested[].pair_test` (issue #22)
    assert "removing ground given damping" in top["evidence"] and "damping is needed" in top["evidence"]
    pt = next(t for t in d["tested"] if t["effect"] == "damping")["pair_test"]
    assert pt["winner"] == "damping" and set(pt["pair"]) == {"damping", "ground"}
    # told apart (damping needed given the ground, not the reverse): no confusable verdict, damping named alone
    assert d["confusable"] is None and "told apart from ground" in top["evidence"] + t_note(d, "damping")
    # accepted by the paired test over the held-back blocks: its drop, standard error and p-value
    t = next(t for t in d["tested"] if t["effect"] == "damping")
    assert t["accepted"] and t["held_back_drop"] > 0 and t["held_back_se"] > 0 and t["held_back_p"] < 0.05
    json.dumps(d, allow_nan=False)
    stored = read_diagnosis(damped["stage"], d["version"])
    assert stored["verdict"] == "missing_effect" and stored["candidates"][0]["effect"] == "damping"


def test_control_scene_with_noise_is_adequate(control):
    """The effects and the render-only cause (the simulator-rebuilding interaction probes are in the
    slow test below)."""
    from physinteract_usd import api

    d = api.diagnose(control["stage"], refit=0, progress=False, log=lambda *a: None, write_stage=False,
                     candidates="damping,plasticity,ground,viscoelasticity,camera:time_offset")
    assert d["verdict"] == "adequate", d["reason"]
    assert d["candidates"] == []
    assert {t["effect"] for t in d["tested"]} == {"damping", "plasticity", "ground", "viscoelasticity",
                                                   "camera:time_offset"}


def test_with_refits_the_size_gate_still_stops_a_rendering_error(control):
    """With refits confirming (`DiagnoseSettings.confirmed`), the 3% size gate still applies: the
    control's `camera:depth_scale` (p at the sign flips' floor: the rendering's soft alpha against
    the binary masks, ~1.8% of the loss) is not significant, so nothing goes to a refit and nothing
    is named. Without the gate the held-back test rejected it here, but on the H200's foam_bar
    controls the same kind of systematic error passed it on 5 of 20 (`core.min_drop`)."""
    from physinteract_usd import api

    d = api.diagnose(control["stage"], refit=3, refit_iterations=2, progress=False, log=lambda *a: None,
                     write_stage=False, starts=1, candidates="damping,viscoelasticity,camera:depth_scale")
    t = {x["effect"]: x for x in d["tested"]}
    ds_ = t["camera:depth_scale"]
    assert 0 < ds_["relative_drop"] < 0.03 and not ds_["significant"]
    assert ds_.get("accepted") is None                                   # never refitted
    assert d["candidates"] == []
    assert d["verdict"] == "adequate", d["reason"]


def test_a_refit_on_a_scene_without_the_effect_is_not_accepted(control):
    """Damping refitted on the control scene (no hidden effect) from c = 2/s, against the base and
    the base refitted alike on the same held-back frames: not accepted, with its drop's standard
    error and p-value reported (the old rule accepted any lower held-back loss)."""
    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem
    from physinteract_usd.diagnose.refit import held_back_frames, refit_effect, refit_null

    prob, base = _problem(control)
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("damping",)))
    cr = d.results[0]
    assert not cr.significant
    val = held_back_frames(prob.T, 4, d._ctx["res"], cr.probes[cr.best].column if cr.best >= 0 else None)
    null = refit_null(d, val, iterations=2)
    cr.estimate = {"coefficient": 2.0}
    refit_effect(d, cr, iterations=2, frames=val, null=null)
    assert cr.held_back_se is not None and cr.held_back_se > 0 and 0 < cr.held_back_p <= 1
    assert cr.accepted is False, cr.note
    assert "not accepted" in cr.note


@pytest.mark.slow
def test_control_scene_with_noise_is_adequate_over_every_candidate(control):
    from physinteract_usd import api
    from physinteract_usd.diagnose import CANDIDATES

    d = api.diagnose(control["stage"], refit=0, progress=False, log=lambda *a: None, write_stage=False)
    assert d["verdict"] == "adequate", d["reason"]
    assert d["candidates"] == []
    assert {t["effect"] for t in d["tested"]} == set(CANDIDATES)


def test_cli_json_exit_codes_and_errors(damped, tmp_path, capsys):
    from physinteract_usd import api
    from physinteract_usd.cli import main

    code = main(["diagnose", str(damped["stage"]), "--json", "--refit", "0", "--no-stage", "--starts", "1",
                 "--candidates", "damping,camera:time_offset"])
    out = capsys.readouterr().out
    assert code == 0
    d = json.loads(out)
    assert set(d) >= {"verdict", "reason", "candidates", "trajectory_check", "base_starts"}
    tc = d["trajectory_check"]
    assert tc["sigma_px"] == 2.0 and tc["bounded"] and tc["contacts"][0]["contact"] == "hand"
    assert set(tc["contacts"][0]) == {"contact", "fitted", "free_step", "bounded_step"}
    assert d["base_starts"]["starts"] == [] and d["base_starts"]["chosen"] is None
    assert d["verdict"] in ("adequate", "missing_effect", "unexplained")
    assert all(set(c) == KEYS for c in d["candidates"])
    assert d["candidates"][0]["effect"] == "damping"
    # a stage without a fit: one line naming the file, exit 2
    bare = tmp_path / "bare.usda"
    api.init(bare, damped["capture"], grid=8, padding=0.3, youngs_range=(5e2, 5e4), max_poisson=0.4)
    code = main(["diagnose", str(bare)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and str(bare) in err[0] and "no fit" in err[0]
    assert main(["diagnose", str(tmp_path / "missing.usda")]) == 2
    assert main(["diagnose", str(damped["stage"]), "--candidates", "gravity"]) == 2
    assert "unknown candidate" in capsys.readouterr().err
    assert main(["diagnose", str(damped["stage"]), "--refit", "-1"]) == 2
    assert main(["diagnose", str(damped["stage"]), "--starts", "4"]) == 2
    assert main(["diagnose", str(damped["stage"]), "--trajectory-sigma", "0"]) == 2
    assert main(["diagnose", str(damped["stage"]), "--refit-folds", "3"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--starts" in err[-3] and "--trajectory-sigma" in err[-2] and "--refit-folds" in err[-1]


def test_a_bad_worker_count_stops_diagnose_at_once(damped, monkeypatch, capsys):
    from physinteract_usd.cli import main

    monkeypatch.setenv("PHYSINTERACT_WORKERS", "0")
    assert main(["diagnose", str(damped["stage"]), "--no-stage"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "PHYSINTERACT_WORKERS" in err[0] and "'0'" in err[0]


@pytest.fixture(scope="module")
def plastic(tmp_path_factory):
    return ds.build(tmp_path_factory.mktemp("plastic"), hidden={"plasticity": {"yieldStress": 400.0}}, noise=0.015)


def test_hidden_plasticity_is_ranked_first_with_its_yield_stress(plastic):
    """A bar that keeps part of its bend after release: plasticity first (not damping, not a softer
    part), its yield stress from the threshold search within 30%, the evidence about the rest shape."""
    from physinteract_usd import api

    d = api.diagnose(plastic["stage"], refit=0, progress=False, log=lambda *a: None, write_stage=False, starts=1,
                     candidates="plasticity,damping,heterogeneity,camera:time_offset")
    assert d["verdict"] == "missing_effect"
    top = d["candidates"][0]
    assert top["effect"] == "plasticity"
    assert top["estimate"]["yieldStress"] == pytest.approx(400.0, rel=0.3)
    assert "rest shape" in top["evidence"]



def test_grasp_size_and_support_probes_resize_their_own_contacts(control):
    """interaction:grasp_size probes grow / shrink the hand's grasp (with its radius),
    interaction:support probes a fixed support: each only its own kind of contact."""
    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem

    prob, base = _problem(control)
    kinds = {c.name: ("grasp" if c.is_interaction else c.type) for c in prob.contacts}
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("interaction:grasp_size", "interaction:support")))
    by = {r.effect: r for r in d.results}
    grasp, support = by["interaction:grasp_size"].probes, by["interaction:support"].probes
    assert grasp and support
    assert {kinds[p.meta["contact"]] for p in grasp} == {"grasp"}
    assert {kinds[p.meta["contact"]] for p in support} == {"fixed"}
    assert all("radius" in p.meta for p in grasp) and not any("radius" in p.meta for p in support)
    assert {p.meta["direction"] for p in grasp + support} <= {"more", "less"}


def _smooth_base(prob, base, amplitude: float = 0.35):
    """The base with a smooth, non-uniform E field (a gradient along the bar, about E_TRUE on
    average), as the default bumps fit leaves one: not piecewise constant (no regions)."""
    import torch

    from physinteract_usd.diagnose import BaseState

    x = np.asarray(prob.x0, np.float64)[:, 0]
    g = (x - x.mean()) / max(float(np.ptp(x)), 1e-9)
    E = base.E * torch.as_tensor(np.exp(amplitude * g), dtype=base.E.dtype)
    return BaseState(E, base.nu, base.effects, None)


def test_a_refit_starts_at_the_base_field_and_a_refit_that_can_only_help_is_not_made_worse(damped):
    """The confirmation refit starts exactly at the base (its smooth E field, nu, path), not at a
    uniform E at the field's median (the flattening that made diagnose's refits worse than the base
    on the H200's foam_bar); with the true effect at its score estimate the refit step does not make
    the held-back frames worse than its own start, nor than the base, and with 2 folds every strong
    frame is judged once."""
    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem
    from physinteract_usd.diagnose import refit as RF
    from physinteract_usd.diagnose.residual import loss
    from physinteract_usd.fit.ladder import _Ladder
    from physinteract_usd.fit.optimize import FitSettings

    prob, base0 = _problem(damped)
    base = _smooth_base(prob, base0)
    lad = _Ladder(prob, FitSettings(iterations=1), progress=False)
    RF.warm_start(lad, base, "field")
    E = base.E.detach().cpu().numpy()
    assert np.allclose(lad.mat.youngs().detach().cpu().numpy(), E, rtol=1e-4)
    RF.warm_start(lad, base, "regions")          # the old start: one E, the field's median
    assert np.max(np.abs(lad.mat.youngs().detach().cpu().numpy() / E - 1)) > 0.1

    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("damping",)))
    cr = d.results[0]
    assert cr.significant and cr.estimate["coefficient"] > 0
    folds = RF.held_back_folds(prob.T, 4, d._ctx["res"], cr.probes[cr.best].column, 2)
    assert len(folds) == 2 and not set(folds[0]) & set(folds[1])
    val = folds[0]
    m = RF._frame_mask(d._ctx["res"], val)
    # the start itself (no iteration: the base's field and path, damping at the score's estimate)
    r_start, _, s0 = RF._refit(d, "damping", dict(cr.estimate), val, 0, 4, None)
    assert np.allclose(s0["E"].cpu().numpy(), E, rtol=1e-4)
    r_base = d._ctx["r0"]
    assert loss(r_start[m]) < loss(r_base[m])    # the true effect at its estimate helps already
    r_fit, _, s1 = RF._refit(d, "damping", dict(cr.estimate), val, 3, 4, None)
    assert loss(r_fit[m]) <= 1.02 * loss(r_start[m])
    assert loss(r_fit[m]) < loss(r_base[m])
    # accepted against the base and the control (each refitted alike, 2 folds pooled)
    null = RF.refit_null(d, folds, iterations=3)
    RF.refit_effect(d, cr, iterations=3, frames=folds, null=null)
    assert cr.accepted, cr.note
    assert "2 folds" in cr.note and cr.held_back_drop > 0



def test_ground_probes_reach_below_the_lowest_point(control):
    """A ground plane acts on the grid's nodes, so it stops particles up to `ground_reach` (1.5 cells + half
    the contact band) above it: a plane that far below the lowest point still changes the motion, one
    beyond it does not. The ground candidate's probes must cover that range (issue #22: on foam_bar the
    synth's hidden plane sat 0.12 reach below the base fit's lowest point, every probe was at or above it,
    the candidate gained nothing and damping was named instead)."""
    import torch

    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem
    from physinteract_usd.diagnose.core import ground_reach

    prob, base = _problem(control)
    reach = ground_reach(prob)
    assert reach == pytest.approx(1.5 * prob.grid.dx + 0.5 * prob.model.contact_band)
    held = prob.held_particles()

    def run(eff):
        with torch.no_grad():
            x, _ = prob.sim.simulate(base.E, base.nu, None, effects=eff)
        return x.cpu().numpy()

    x = run({})
    free = x[:, ~held, 1]
    low = float(x[..., 1].min())
    lowest_free = float(free.min())
    near = run({"ground": {"height": lowest_free - 0.5 * reach, "friction": 0.6}})
    far = run({"ground": {"height": low - 1.2 * reach, "friction": 0.6}})
    assert np.abs(near - x).max() > 1e-4          # half its reach below every particle, it still acts
    assert np.abs(far - x).max() < 1e-9           # beyond its reach, nothing
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=("ground",)))
    hs = sorted(p.meta["height"] for p in d.results[0].probes)
    assert hs[0] < low - 0.5 * reach and hs[0] >= low - reach    # probes below the lowest point, within reach
    assert hs[-1] > low


GROUND_H = 0.072     # the tiny bar falls to y 0.073 after its release (frame 9): a plane just below it stops its end


@pytest.fixture(scope="module")
def grounded(tmp_path_factory):
    return ds.build(tmp_path_factory.mktemp("grounded"), hidden={"ground": {"height": GROUND_H, "friction": 0.6}},
                    noise=0.015)


def _group_refits(info, effects):
    """The candidates `effects` refitted as a confusable group is (from their marginal estimates, on shared held-back
    frames, 2 iterations, one fold), as `app.diagnose.refit_confusable` does before the pair step: a physical effect
    refitted, any other judged as its probe (its amplitude and the base's linear re-adjustment without the held-back
    frames). Returns the diagnosis and the candidates in the order asked."""
    from physinteract_usd.diagnose import DiagnoseSettings, diagnose_problem
    from physinteract_usd.diagnose import refit as RF
    from physinteract_usd.diagnose.core import PHYSICAL, estimate_of

    prob, base = _problem(info)
    d = diagnose_problem(prob, base, DiagnoseSettings(candidates=tuple(effects)))
    by = {c.effect: c for c in d.results}
    cs = [by[e] for e in effects]
    for c in cs:
        c.best, c.step = c.marginal_probe
        c.estimate = estimate_of(c, prob)
    val = RF.group_frames(d, cs, folds=1)
    null = RF.refit_null(d, val, iterations=2)
    for c in cs:
        if c.effect in PHYSICAL:
            RF.refit_effect(d, c, iterations=2, frames=val, null=null)
        else:
            RF.judge_probe(d, c, frames=val)
    return (d, *cs)


def _pair_refits(info):
    """damping and ground refitted as a confusable group is (`_group_refits`)."""
    return _group_refits(info, ("damping", "ground"))


def test_a_hidden_ground_is_told_from_damping_by_its_signature_and_by_nesting(grounded):
    """Issue #22's confusable pair, the ground side: on the tiny bar whose video has a floor just below where its
    free end falls, the ground's refitted model fits the lowest points better than damping's (the signature,
    `refit.bottom_signature`), and refitted together, removing the ground costs held-back loss while removing
    damping does not (`refit.nested_pair`): ground, not damping."""
    from physinteract_usd.diagnose import refit as RF

    d, dm, g = _pair_refits(grounded)
    assert g.accepted, g.note
    sig = RF.bottom_signature(d, dm, g)
    assert sig["ground_signature"] and sig["bottom"]["p"] < 0.05, sig["why"]
    pt = RF.nested_pair(d, dm, g, iterations=2)
    assert pt["winner"] == "ground", pt["why"]
    assert pt["adds"]["ground"]["needed"] and not pt["adds"]["damping"]["needed"]


def test_a_hidden_damping_that_a_ground_mimics_stays_damping(damped):
    """The damping side: on the damped tiny bar a ground also lowers the held-back loss (it mimics the slowing; in
    `diagnose` with two folds it passes the held-back test, p 0.004: a real confusable pair), but its model is no
    better at the lowest points (no signature) and given damping it adds nothing, while damping given the ground
    does: damping, not ground."""
    from physinteract_usd.diagnose import refit as RF

    d, dm, g = _pair_refits(damped)
    assert dm.accepted, dm.note
    sig = RF.bottom_signature(d, dm, g)
    assert not sig["ground_signature"], sig["why"]
    pt = RF.nested_pair(d, dm, g, iterations=2)
    assert pt["winner"] == "damping", pt["why"]


def _mixed_refits(info):
    """damping refitted and `interaction:timing` judged as its probe on shared held-back frames (`_group_refits`)."""
    return _group_refits(info, ("damping", "interaction:timing"))


@pytest.fixture(scope="module")
def released_early(tmp_path_factory):
    # the true hand lets go 2 frames before the stage says (a wrong interaction that also takes energy out of the swing)
    return ds.build(tmp_path_factory.mktemp("released_early"), release_shift=-2, noise=0.015)


def test_a_physical_effect_and_the_interaction_that_mimics_it_are_told_apart_by_nesting(damped, released_early):
    """Issue #22, the mixed pair (`refit.nested_with_interaction`): damping refitted under the timing candidate's
    change, every model re-adjusted alike. On the damped bar damping is needed given the timing change and the timing
    change is not; on the bar released 2 frames early the timing change (found: the release moved 2 frames earlier)
    is needed given damping and damping is not. The problem's own contacts are back after each."""
    from physinteract_usd.diagnose import refit as RF

    d, dm, tm = _mixed_refits(damped)
    before = list(d._ctx["prob"].contacts)
    pt = RF.nested_with_interaction(d, dm, tm, iterations=2)
    assert pt["winner"] == "damping", pt["why"]
    assert pt["adds"]["damping"]["needed"] and not pt["adds"]["interaction:timing"]["needed"]
    assert d._ctx["prob"].contacts == before

    d, dm, tm = _mixed_refits(released_early)
    assert tm.probes[tm.best].meta["what"] == "release_frame" and tm.probes[tm.best].meta["frame"] == \
        tm.probes[tm.best].meta["was"] - 2
    pt = RF.nested_with_interaction(d, dm, tm, iterations=2)
    assert pt["winner"] == "interaction:timing", pt["why"]
    assert pt["adds"]["interaction:timing"]["needed"] and not pt["adds"]["damping"]["needed"]


@pytest.fixture(scope="module")
def viscous(tmp_path_factory):
    # the suite's tiny-bar viscoelasticity at 1x (benchmarks/diagnose_suite.hidden_for): E_v 0.3 E, tau 0.1 s
    return ds.build(tmp_path_factory.mktemp("viscous"), noise=0.015,
                    hidden={"viscoelasticity": {"modulus": 0.3 * rs.E_TRUE, "relaxationTime": 0.1}})


def test_a_hidden_viscoelastic_bar_is_named_viscoelasticity_or_within_its_confusable_pair(viscous):
    """Issue #22's viscoelasticity, known answer: on the tiny bar whose video has a Maxwell branch the base lacks,
    with the same call that leaves the control `adequate` (`test_with_refits_the_size_gate_still_stops_a_rendering_
    error`: refits confirming, damping its confusable mate among the candidates), the diagnosis names
    viscoelasticity first, or says "damping or viscoelasticity: the frames cannot tell them apart" with
    viscoelasticity in the pair; never damping alone. (On foam_bar the GPU's base fit absorbs a 1x branch into its
    E field: docs/benchmarks/diagnose_named.md, 17th; here the base is the truth without it, so the test checks the
    probes and the verdict, not that absorption.)"""
    from physinteract_usd import api

    d = api.diagnose(viscous["stage"], refit=3, refit_iterations=2, progress=False, log=lambda *a: None,
                     write_stage=False, starts=1, candidates="damping,viscoelasticity,camera:depth_scale")
    assert d["verdict"] == "missing_effect", d["reason"]
    cf = d["confusable"]
    if cf is None:
        assert d["candidates"][0]["effect"] == "viscoelasticity", d["reason"]
        t = next(t for t in d["tested"] if t["effect"] == "viscoelasticity")
        assert t["accepted"] and t["held_back_p"] < 0.05
    else:
        assert set(cf["pair"]) == {"damping", "viscoelasticity"}, d["reason"]
        assert d["reason"].startswith(f"{cf['pair'][0]} or {cf['pair'][1]}: the frames cannot tell them apart")
        assert "held still" in cf["to_separate"] or "held load" in cf["to_separate"]
    assert "camera:depth_scale" not in [c["effect"] for c in d["candidates"]]


def test_the_refits_in_worker_processes_give_the_diagnosis_of_one_process(damped, monkeypatch):
    """The base starts, the candidates' probes and their refits run in forked processes where the CPU has the cores
    (`workers.fork_map`, PHYSINTERACT_WORKERS): the diagnosis is the one a single process gives, number for number
    (each refit starts from the state the sequential one starts from: the rival's own estimate, the base's substep;
    each probe is a forward from the base), and its cost counts the workers' forwards."""
    import sys

    from physinteract_usd import api

    if not sys.platform.startswith("linux"):
        pytest.skip("worker processes are forked on Linux only")
    out = {}
    for n in ("1", "2"):
        monkeypatch.setenv("PHYSINTERACT_WORKERS", n)
        out[n] = api.diagnose(damped["stage"], refit=2, refit_iterations=2, starts=2, progress=False,
                              log=lambda *a: None, candidates="damping,ground,camera:time_offset,interaction:timing",
                              write_stage=False)
    one, two = out["1"], out["2"]
    assert one["cost"]["forwards"] == two["cost"]["forwards"] > 20, (one["cost"], two["cost"])
    assert [s["loss"] for s in one["base_starts"]["starts"]] == [s["loss"] for s in two["base_starts"]["starts"]]
    drop = lambda d: [(t["effect"], t.get("accepted"), t.get("held_back_drop"), t.get("held_back_p"))  # noqa: E731
                      for t in d["tested"]]
    assert drop(one) == drop(two)
    assert any(t[2] is not None for t in drop(one))          # something was refitted
    assert one["verdict"] == two["verdict"] and one["candidates"] == two["candidates"]


def test_diagnose_names_a_late_release_that_damping_mimics(tmp_path):
    """The mixed pair through `api.diagnose` (`app.diagnose.pair_step`): the hand let go 2 frames later than the stage
    says; damping passes the held-back test too (a mimic: the late release takes energy out of the swing), the pair
    step refits them together and the verdict names the release, with its fix."""
    from physinteract_usd import api

    info = ds.build(tmp_path, release_shift=2, noise=0.015)
    d = api.diagnose(info["stage"], refit=3, refit_iterations=2, progress=False, log=lambda *a: None,
                     write_stage=False, starts=1, candidates="damping,interaction:timing,camera:depth_scale")
    assert d["verdict"] == "missing_effect" and d["candidates"][0]["effect"] == "interaction:timing", d["reason"]
    assert "--release-frame 7" in d["reason"]
    by = {t["effect"]: t for t in d["tested"]}
    assert by["damping"]["accepted"] and by["interaction:timing"]["accepted"]
    pt = by["damping"]["pair_test"]
    assert pt["winner"] == "interaction:timing" and pt["adds"]["interaction:timing"]["needed"], pt["why"]
    assert not pt["adds"]["damping"]["needed"]
