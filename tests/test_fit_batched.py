"""Fits from several starts in lockstep (fit/batched.py): one tiled rollout per iteration gives every
copy its own loss and gradient (against its own rollout, and finite differences), each start's fit
equals the same start fitted alone, a copy that leaves its box is dropped and reported while the
others go on, and `fit --starts` keeps the best start and records them all.

Tiny: the cantilever of tests/fit_scene.py (~200 particles, grid 10, 5 frames), float64 where
values are compared, 2-3 iterations."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.fit import FitProblem, FitSettings, fit_bumps
from physinteract_usd.fit.batched import (START_FACTORS, Start, batch_losses, default_starts, fit_bumps_batched,
                                         fit_starts, start_e)
from physinteract_usd.sim.cfl import rung, substeps_per_frame
from physinteract_usd.usd.stage import read_stage

pytestmark = pytest.mark.usefixtures("one_torch_thread")

QUIET = dict(progress=False, log=None)
SETTINGS = dict(levels=(1, 6), level_share=(0.5, 0.5), search_evals=2, lr_material=0.2, lr_poisson=0.03,
                lr_trajectory=2e-4, basis_width=0.6, trajectory_levels=1, weight_decay=0.0, confidence_probes=0,
                fit_poisson_levels=1, plateau_patience=0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return fs.build(tmp_path_factory.mktemp("batched") / "base")


def _problem(scene, dtype="float64"):
    sd = read_stage(scene["stage"])
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, scene["gt"]), dtype=dtype)
    # one substep for every field (the range top's): a copy's rollout in the batch and alone take the
    # same time step
    prob.sim.ensure_stable(float(sd.settings.youngs_max))
    prob.sim.adaptive = False
    return prob


def _fields(prob, B=2):
    P = len(prob.x0)
    rng = np.random.default_rng(1)
    E = torch.as_tensor(np.stack([fs.E_TRUE * f * np.exp(0.3 * rng.standard_normal(P)) for f in (1.0, 2.5)][:B]),
                        dtype=torch.float64)
    nu = torch.full((B, P), fs.NU_TRUE, dtype=torch.float64)
    t0 = prob.initial_trajectories()
    trajs = [torch.stack([t + 1e-3 * b * torch.ones_like(t) for b in range(B)]) for t in t0]
    return E, nu, trajs


def test_batched_step_gives_each_copy_its_own_loss_and_gradient(scene):
    prob = _problem(scene)
    E, nu, trajs = _fields(prob)
    Eb = E.clone().requires_grad_(True)
    tb = [t.clone().requires_grad_(True) for t in trajs]
    outs, bad = batch_losses(prob, Eb, nu, tb)
    assert not bad.any()
    total = sum(o["rec"] + o["reg_traj"] for o in outs)
    total.backward()
    for b in range(2):
        Es = E[b].clone().requires_grad_(True)
        ts = [t[b].clone().requires_grad_(True) for t in trajs]
        ref = prob.loss(Es, nu[b], ts)
        (ref["rec"] + ref["reg_traj"]).backward()
        assert float(outs[b]["rec"].detach()) == pytest.approx(float(ref["rec"].detach()), rel=1e-10)
        assert torch.allclose(Eb.grad[b], Es.grad, rtol=1e-7, atol=1e-10 * float(Es.grad.abs().max()))
        for g, r in zip(tb, ts):
            assert torch.allclose(g.grad[b], r.grad, rtol=1e-7, atol=1e-10 * float(r.grad.abs().max()))
    # the copies differ (so the test can tell them apart)
    assert abs(float(outs[0]["rec"].detach() - outs[1]["rec"].detach())) > 1e-3 * float(outs[0]["rec"].detach())


def test_batched_loss_gradient_matches_finite_differences(scene):
    """d(sum of the copies' losses) / d(each copy's log E scale), against central differences."""
    prob = _problem(scene)
    E, nu, trajs = _fields(prob)

    def f(a):
        outs, bad = batch_losses(prob, E * torch.exp(a)[:, None], nu, trajs)
        assert not bad.any()
        return sum(o["rec"] for o in outs)

    a = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    f(a).backward()
    h = 1e-6
    for b in range(2):
        d = torch.zeros(2, dtype=torch.float64)
        d[b] = h
        with torch.no_grad():
            fd = (float(f(d)) - float(f(-d))) / (2 * h)
        assert float(a.grad[b]) == pytest.approx(fd, rel=1e-3, abs=1e-9), (b, float(a.grad[b]), fd)
    assert abs(float(a.grad[0])) > 1e-6 and abs(float(a.grad[1])) > 1e-6


def test_a_copy_that_leaves_its_box_is_reported_the_other_kept(scene):
    prob = _problem(scene)
    E, nu, trajs = _fields(prob)
    far = [t.clone() for t in trajs]
    for t in far:       # the second copy's hand drags the bar a metre away by the last frame
        t[1] += torch.linspace(0, 1.0, t.shape[1], dtype=t.dtype)[:, None] * torch.tensor([1.0, 0.0, 0.0],
                                                                                        dtype=t.dtype)
    Eb = E.clone().requires_grad_(True)
    outs, bad = batch_losses(prob, Eb, nu, far)
    assert bad.tolist() == [False, True] and outs[1] is None
    outs[0]["rec"].backward()
    Es = E[0].clone().requires_grad_(True)
    ref = prob.loss(Es, nu[0], [t[0] for t in far])
    ref["rec"].backward()
    assert float(outs[0]["rec"].detach()) == pytest.approx(float(ref["rec"].detach()), rel=1e-10)
    assert torch.isfinite(Eb.grad).all()
    assert torch.allclose(Eb.grad[0], Es.grad, rtol=1e-7, atol=1e-10 * float(Es.grad.abs().max()))
    assert float(Eb.grad[1].abs().max()) == 0.0


def test_each_start_converges_to_its_own_fit(scene):
    """Two starts in lockstep end where each start's own fit_bumps ends (histories and fields)."""
    prob = _problem(scene)
    s = FitSettings(iterations=3, joint=True, **SETTINGS)
    starts = [Start(1.0, 0), Start(2.0, 1)]
    e_u = 4.0e3
    res = fit_bumps_batched(prob, s, starts, uniform_e=e_u, **QUIET)
    for sp, r in zip(starts, res):
        import dataclasses

        ref = fit_bumps(_problem(scene), dataclasses.replace(s, seed=sp.seed), uniform_e=e_u * sp.factor, **QUIET)
        assert len(r.loss_history) == len(ref.loss_history) == 3
        np.testing.assert_allclose(r.loss_history, ref.loss_history, rtol=1e-8)
        np.testing.assert_allclose(r.youngs, ref.youngs, rtol=1e-7)
        for n in ref.trajectories:
            np.testing.assert_allclose(r.trajectories[n], ref.trajectories[n], rtol=0, atol=1e-9)
        assert r.final_loss == pytest.approx(ref.final_loss, rel=1e-8)
        assert r.model["start"]["status"] == "converged"
    # the starts really are different fits
    assert abs(res[0].loss_history[0] - res[1].loss_history[0]) > 1e-6


def test_a_copy_that_goes_bad_mid_fit_is_dropped_and_keeps_its_best(scene, monkeypatch):
    prob = _problem(scene, dtype="float32")
    real = prob.sim.simulate_batch
    calls = []

    def flaky(E, nu, trajectories=None, effects=None, copies_per_rollout=None):
        calls.append(len(E))
        if len(calls) == 2 and trajectories:   # the second iteration: copy 1's hand drags the bar away
            trajectories = [t.clone() for t in trajectories]
            for t in trajectories:
                t[1] = t[1] + torch.linspace(0, 1.0, t.shape[1], dtype=t.dtype)[:, None] * \
                    torch.tensor([1.0, 0.0, 0.0], dtype=t.dtype)
        return real(E, nu, trajectories, effects, copies_per_rollout)

    monkeypatch.setattr(prob.sim, "simulate_batch", flaky)
    s = FitSettings(iterations=3, joint=True, **{**SETTINGS, "levels": (1,), "level_share": (1.0,)})
    notes = []
    res = fit_bumps_batched(prob, s, [Start(1.0, 0), Start(2.0, 1)], uniform_e=4e3, progress=False,
                            log=notes.append)
    # the failed tiled rollout is retried copy by copy (a second call of 2), then the batch shrinks
    assert calls == [2, 2, 2, 1]
    ok, gone = res
    assert len(ok.loss_history) == 3 and np.isfinite(ok.final_loss)
    assert gone.model["start"]["status"] == "unstable" and "dropped at iteration 1" in gone.model["start"]["note"]
    assert len(gone.loss_history) == 1 and np.isfinite(gone.final_loss)    # its best iterate: the first
    assert gone.final_loss == pytest.approx(gone.loss_history[0], rel=1e-5)
    assert any("dropped" in n for n in notes)


def test_fit_starts_keeps_the_lowest_loss_and_records_every_start(scene):
    prob = _problem(scene, dtype="float32")
    s = FitSettings(iterations=2, joint=False, **{**SETTINGS, "levels": (1,), "level_share": (1.0,)})
    r = fit_starts(prob, s, 3, batched=False, uniform_e=4e3, **QUIET)
    table = r.model["starts"]
    assert [d["factor"] for d in table] == list(START_FACTORS[:3]) and r.model["starts_mode"] == "sequential"
    losses = [d["final_loss"] for d in table]
    assert r.model["starts_chosen"] == int(np.argmin(losses))
    assert r.final_loss == pytest.approx(min(losses))
    assert r.settings["starts"] == 3
    rb = fit_starts(_problem(scene, dtype="float32"), s, 3, batched=True, uniform_e=4e3, **QUIET)
    assert rb.model["starts_mode"] == "batched"
    np.testing.assert_allclose([d["final_loss"] for d in rb.model["starts"]], losses, rtol=2e-3)


def test_cli_fit_starts_writes_every_start_into_the_version(scene, tmp_path, capsys):
    from physinteract_usd.cli import main

    stage = fs.copy_scene(scene["root"], tmp_path / "starts")
    out = api.fit(stage, iterations=2, contact_from=stage.parent / "gt", starts=2, progress=False,
                  log=lambda *a: None, settings_overrides={**SETTINGS, "levels": (1,), "level_share": (1.0,),
                                                           "confidence_probes": 1})
    summ = out.summary()
    assert len(summ["starts"]) == 2 and summ["starts_mode"] == "sequential"
    assert out.confidence_estimated and not np.allclose(out.result.confidence, 1.0)
    # the starts' own phases (#26): the fits of both starts, then the chosen one's confidence, on the fit's clock
    ph = summ["phases_s"]
    assert ph["iterations"] > 0 and ph["confidence"] > 0 and "start_search" in ph
    assert sum(ph[k] for k in ("start_search", "iterations", "confidence")) == pytest.approx(summ["runtime_s"],
                                                                                           rel=0.05, abs=0.2)
    sd = read_stage(stage)
    mm = sd.current_report["material_model"]
    mm = json.loads(mm) if isinstance(mm, str) else mm
    assert [d["factor"] for d in mm["starts"]] == list(START_FACTORS[:2])
    assert main(["fit", str(stage), "--starts", "99"]) == 2
    assert "--starts" in capsys.readouterr().err


def test_region_refits_in_lockstep_equal_the_ladders_one_by_one(scene):
    """The diagnosis's short base refits (diagnose.refit.refit_base: the ladder's optimise on the
    regions' log E) from several starts, batched, end where each one alone ends."""
    import math
    from types import SimpleNamespace

    from physinteract_usd.diagnose.refit import refit_base
    from physinteract_usd.fit.batched import refit_regions_batched

    prob = _problem(scene)
    P = len(prob.x0)
    labels = (prob.x0[:, 0] > np.median(prob.x0[:, 0])).astype(np.int64)     # two regions
    E = torch.as_tensor(np.where(labels == 1, 8e3, 3e3), dtype=torch.float64)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)
    base = SimpleNamespace(E=E, nu=nu, labels=labels, effects=None)
    factors = (1.0, 0.5)
    starts = [np.log([f * 3e3, f * 8e3]) for f in factors]
    got = refit_regions_batched(prob, labels, starts, fs.NU_TRUE, 2)
    for f, g in zip(factors, got):
        ref = refit_base(_problem(scene), base, f, iterations=2)
        assert g["iterations"] == 2 and math.isfinite(g["fit_loss"])
        assert g["fit_loss"] == pytest.approx(ref["fit_loss"], rel=1e-8)
        np.testing.assert_allclose(g["E"].numpy(), ref["E"].numpy(), rtol=1e-7)
    assert abs(got[0]["fit_loss"] - got[1]["fit_loss"]) > 1e-6


def test_diagnose_base_starts_batched_choose_as_one_by_one(scene, monkeypatch):
    """app.diagnose's base refits from several starts (x 1, 0.5, 2), batched (as on a GPU) and one
    by one, report the same losses."""
    from physinteract_usd.app import diagnose as app_diag
    from physinteract_usd.diagnose import BaseState, DiagnoseSettings

    prob = _problem(scene)
    P = len(prob.x0)
    E = torch.full((P,), 2.5 * fs.E_TRUE, dtype=torch.float64)          # a base far from the truth
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float64)
    base = BaseState(E, nu, {}, None)
    outs = {}
    for mode in ("never", "always"):
        monkeypatch.setattr(app_diag, "BATCHED_REFITS", mode)
        _, outs[mode] = app_diag._best_start(_problem(scene), base, DiagnoseSettings(max_pixels=2000), 3, 2,
                                             lambda *a: None)
    one, bat = outs["never"], outs["always"]
    assert [d["factor"] for d in bat["starts"]] == [1.0, 0.5, 2.0]
    np.testing.assert_allclose([d["loss"] for d in bat["starts"]], [d["loss"] for d in one["starts"]], rtol=1e-7)
    assert bat["chosen"] == one["chosen"] and bat["base_loss"] == pytest.approx(one["base_loss"], rel=1e-10)


def test_a_stop_during_a_batched_fit_writes_the_best_start(scene, tmp_path, monkeypatch):
    """SIGTERM in the lockstep loop (batched as on a GPU): every start keeps its best iterate, the
    best is written as an interrupted version with every start's loss, no confidence estimate."""
    from physinteract_usd import stopping
    from physinteract_usd.fit import batched

    stage = fs.copy_scene(scene["root"], tmp_path / "stop")
    real = batched.batch_losses
    calls = []

    def stopping_losses(*a, **kw):
        calls.append(1)
        if len(calls) == 2:
            stopping.request("SIGTERM")
        return real(*a, **kw)

    monkeypatch.setattr(batched, "batching_pays", lambda prob, s: True)
    monkeypatch.setattr(batched, "batch_losses", stopping_losses)
    out = api.fit(stage, iterations=4, contact_from=stage.parent / "gt", starts=2, progress=False,
                  log=lambda *a: None, settings_overrides={**SETTINGS, "confidence_probes": 2})
    assert out.stopped_by == "SIGTERM" and out.result.interrupted and not out.confidence_estimated
    assert len(calls) == 2 and len(out.result.loss_history) == 1
    (v1,) = read_stage(stage).reports
    assert v1["status"] == "interrupted"
    mm = v1["material_model"]
    assert mm["starts_mode"] == "batched" and [d["status"] for d in mm["starts"]] == ["interrupted"] * 2
    assert all(d["final_loss"] is not None for d in mm["starts"])


def test_copies_stop_on_their_own_and_the_batch_shrinks(scene):
    """With the convergence stop on, the starts stop at different iterations; the batch goes on
    with the copy left (a smaller tiled rollout) and each history is its own fit's."""
    import dataclasses

    s = FitSettings(iterations=8, joint=False, **{**SETTINGS, "levels": (1,), "level_share": (1.0,),
                                                  "plateau_patience": 1, "plateau_tail": 1, "plateau_tol": 0.02})
    starts = [Start(1.0, 0), Start(0.25, 1)]
    res = fit_bumps_batched(_problem(scene), s, starts, uniform_e=4e3, **QUIET)
    lens = []
    for sp, r in zip(starts, res):
        ref = fit_bumps(_problem(scene), dataclasses.replace(s, seed=sp.seed), uniform_e=4e3 * sp.factor, **QUIET)
        assert len(r.loss_history) == len(ref.loss_history)
        np.testing.assert_allclose(r.loss_history, ref.loss_history, rtol=1e-8)
        lens.append(len(r.loss_history))
    assert lens[0] < lens[1] <= 8, lens


# ------------------------------------------------------------------ the starts' substep rung
@pytest.mark.parametrize("e_range", [(1e3, 6e4), (1e4, 1e6), (5e2, 2e5)])
def test_every_default_start_takes_the_x1_starts_substep_count(e_range):
    """The default starts (x 1, 1/sqrt(2), 1/2, ...) never need more substeps than the x1 start: at
    any searched uniform E in the range, every start's rung (the adaptive substep's E) maps to at
    most the x1 start's substep count, and a start at x2 (the old factors) would need more."""
    lo, hi = e_range
    fps, dx, nu_max, density = 24.0, 0.01, 0.4, 150.0
    assert START_FACTORS[0] == 1.0 and all(a > b for a, b in zip(START_FACTORS, START_FACTORS[1:]))

    def steps(e, speed=0.0):
        return substeps_per_frame(fps, dx, rung(e, hi), nu_max, density, cfl=0.6, max_speed=speed)

    raised = 0
    for e_u in np.geomspace(lo * 1.01, hi * 0.99, 23):
        for speed in (0.0, 0.5):
            n1 = steps(start_e(e_u, 1.0, e_range), speed)
            for sp in default_starts(len(START_FACTORS)):
                assert steps(start_e(e_u, sp.factor, e_range), speed) <= n1, (e_range, e_u, sp.factor)
            assert steps(start_e(e_u, START_FACTORS[1], e_range), speed) >= steps(start_e(e_u, START_FACTORS[2], e_range), speed)
            raised += steps(start_e(e_u, 2.0, e_range), speed) > n1
    assert raised > 10       # the check can fail: a x2 start raises the count almost everywhere


def _adaptive_problem(scene):
    sd = read_stage(scene["stage"])
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, scene["gt"]), dtype="float32")
    assert prob.sim.adaptive
    return prob


def test_a_batch_of_default_starts_runs_at_the_one_fits_substep(scene):
    """Four default starts in lockstep take the substep count the one fit from x1 takes (the
    adaptive rung of the x1 start's E), at the first iteration."""
    e_u = 0.3 * float(read_stage(scene["stage"]).settings.youngs_max)    # x2 would go two rungs up
    seen = {}
    for name, B in (("one", 1), ("batch", 4)):
        prob = _adaptive_problem(scene)
        sim = prob.sim
        for attr in ("simulate", "simulate_batch"):
            real = getattr(sim, attr)

            def rec(*a, _real=real, **kw):
                out = _real(*a, **kw)
                seen.setdefault(name, []).append(sim.substeps)
                return out
            setattr(sim, attr, rec)
        s = FitSettings(iterations=1, joint=False, **{**SETTINGS, "levels": (1,), "level_share": (1.0,)})
        if B == 1:
            fit_bumps(prob, s, uniform_e=e_u, **QUIET)
        else:
            fit_bumps_batched(prob, s, default_starts(B), uniform_e=e_u, **QUIET)
    assert seen["batch"][0] == seen["one"][0], seen
    prob = _adaptive_problem(scene)
    prob.sim.ensure_stable(2.0 * e_u)
    assert prob.sim.substeps > seen["one"][0]          # what the old x2 start took


def test_the_shared_substep_follows_the_stiffest_copys_field(scene):
    """When one copy's field stiffens past the rung, the tiled rollout takes the rung of the largest
    E of all copies (so its substep stays stable), and steps back when that copy softens."""
    prob = _adaptive_problem(scene)
    sim, P = prob.sim, len(prob.x0)
    hi = float(read_stage(scene["stage"]).settings.youngs_max)
    e1 = hi / 4.5       # inside its rung (hi / 4) by more than the step-down hysteresis (10%)
    nu = torch.full((P,), fs.NU_TRUE)

    def run(*scales):
        E = torch.stack([torch.full((P,), e1 * f) for f in scales])
        x, F, bad = sim.simulate_batch(E, nu)
        assert not bad.any()
        return sim.substeps, sim.e_bound

    n1, b1 = run(1.0, 0.5)
    n2, b2 = run(1.0, 2.5)                      # copy 1 drifted up two rungs and more
    assert b2 == sim.bound_for(2.5 * e1) > b1 and n2 > n1
    E = torch.full((1, P), e1)
    E[0, 7] = 2.5 * e1                          # one particle of one copy is enough
    sim.simulate_batch(torch.cat([torch.full((1, P), 0.5 * e1), E]), nu)
    assert sim.e_bound == b2
    n3, b3 = run(1.0, 0.5)                      # softened again: back to the x1 rung
    assert (n3, b3) == (n1, b1)


def test_batched_renders_equal_the_per_copy_renders_in_one_pass(scene, monkeypatch):
    """The copies' renders and loss terms in one rasterizer pass (BATCH_RENDERS) against one render
    and one loss per copy and frame: the same losses and gradients (float32: to 1e-6), one
    rasterizer pass instead of B x (T - 1)."""
    import physinteract_usd.fit.batched as fb
    import physinteract_usd.render.rasterizer as R

    prob = _problem(scene, dtype="float32")
    E, nu, trajs = _fields(prob)
    E, nu, trajs = E.float(), nu.float(), [t.float() for t in trajs]
    calls = []
    fwd = R.forward
    monkeypatch.setattr(R, "forward", lambda *a, **k: calls.append(1) or fwd(*a, **k))
    res = {}
    for on in (True, False):
        monkeypatch.setattr(fb, "BATCH_RENDERS", on)
        calls.clear()
        Eb = E.clone().requires_grad_(True)
        tb = [t.clone().requires_grad_(True) for t in trajs]
        outs, bad = batch_losses(prob, Eb, nu, tb)
        assert not bad.any()
        sum(o["rec"] + o["reg_traj"] for o in outs).backward()
        res[on] = ([float(o["rec"].detach()) for o in outs], Eb.grad.clone(), [t.grad.clone() for t in tb], len(calls))
    (l1, g1, t1, n1), (l0, g0, t0, n0) = res[True], res[False]
    assert n1 == 1 and n0 == 2 * (prob.T - 1), (n1, n0)
    for a, b in zip(l1, l0):
        assert a == pytest.approx(b, rel=1e-6)
    assert float((g1 - g0).abs().max()) <= 1e-5 * float(g0.abs().max())
    for a, b in zip(t1, t0):
        assert float((a - b).abs().max()) <= 1e-5 * float(b.abs().max()) + 1e-12
    assert abs(l1[0] - l1[1]) > 1e-3 * l1[0]


@pytest.mark.parametrize("dtype,tol", [("float32", 1e-6), ("float64", 1e-12)])
def test_a_fits_frames_rendered_in_one_pass_equal_one_by_one(scene, monkeypatch, dtype, tol):
    """`FitProblem.loss` with its frames batched (problem.BATCH_FRAMES, the CUDA default) against one
    render and one loss per frame: the same loss and gradients (to float rounding) and the same kept
    renders, bit for bit."""
    import physinteract_usd.fit.problem as fp

    prob = _problem(scene, dtype=dtype)
    E, nu, trajs = _fields(prob)
    td = torch.float32 if dtype == "float32" else torch.float64
    res = {}
    for on in (True, False):
        monkeypatch.setattr(fp, "BATCH_FRAMES", on)
        Eb = E[0].to(td).clone().requires_grad_(True)
        tb = [t[0].to(td).clone().requires_grad_(True) for t in trajs]
        out = prob.loss(Eb, nu[0].to(td), tb, keep_renders=True)
        (out["rec"] + out["reg_traj"]).backward()
        res[on] = (float(out["rec"].detach()), Eb.grad.clone(), [t.grad.clone() for t in tb], out["renders"])
    (l1, g1, t1, r1), (l0, g0, t0, r0) = res[True], res[False]
    assert l1 == pytest.approx(l0, rel=tol)
    assert float((g1 - g0).abs().max()) <= 10 * tol * float(g0.abs().max())
    for a, b in zip(t1, t0):
        assert float((a - b).abs().max()) <= 10 * tol * float(b.abs().max()) + 1e-12
    assert sorted(r1) == sorted(r0) == list(range(1, prob.T))
    for k in r0:
        for name in ("rgb", "alpha", "depth"):
            assert torch.equal(r1[k][name], r0[k][name]), (k, name)
