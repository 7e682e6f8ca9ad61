"""A parts start that is not taken leaves the fit as it found it: the field and the adaptive substep's rung
(fit/parts_start.py). The probes simulate stiffer fields; the substep's hysteresis may keep their rung, and the
fit then goes on at another step (the H200's hemp_rope, 2026-11-26: a start not taken, MA 0.801 -> 0.485)."""

from __future__ import annotations

import math
import types

import numpy as np
import torch

from physinteract_usd.fit import parts_start as ps
from physinteract_usd.fit import select


class _Sim:
    def __init__(self):
        self.e_bound, self.adaptive, self.used = 1.0e4, True, []

    def _use_bound(self, b):
        self.used.append(b)
        self.e_bound = b


class _Mat:
    lo, hi = np.log(1e3), np.log(6e4)

    def __init__(self):
        self.theta = torch.zeros(8, requires_grad=True)

    def log_e(self):
        return torch.full((6,), float(np.log(1e4)))

    def poisson(self):
        return torch.full((6,), 0.3)

    def set_values(self, e):
        with torch.no_grad():
            self.theta = torch.ones(8, requires_grad=True)


def _run(monkeypatch, losses, found=0.01):
    sim = _Sim()
    prob = types.SimpleNamespace(sim=sim, T=4)
    labels = np.array([0, 0, 0, 1, 1, 1])
    monkeypatch.setattr(select, "part_candidates", lambda *a: [{"kind": "appearance", "parts": 2, "labels": labels}])

    class Probe:
        def __init__(self, *a, **k):
            self.cache = {}

        def __call__(self, x):
            return 0.02

    def refine(f, start, lo, hi, n, step, **kw):
        sim.e_bound = 5.6e4          # the probes' stiff fields moved the rung (as prob.simulate's ensure_stable does)
        return {"log_e": [np.log(3e4), np.log(8e3)], "loss": found}

    monkeypatch.setattr(select, "PartProbe", Probe)
    monkeypatch.setattr(select, "part_refine", refine)
    it = iter(losses)
    mat = _Mat()
    out = ps.parts_start(prob, mat, types.SimpleNamespace(select_sweep_batch=1), None, None, lambda: next(it), 20)
    return out, sim, mat


def test_a_start_not_taken_restores_the_rung_and_the_field(monkeypatch):
    out, sim, mat = _run(monkeypatch, [0.010, 0.012])      # the parts' field renders worse: not taken
    assert not out["used"]
    assert sim.e_bound == 1.0e4 and sim.used == [1.0e4]
    assert float(mat.theta.abs().max()) == 0.0


def test_a_start_taken_keeps_its_field_but_not_the_probes_rung(monkeypatch):
    """Taken: the field stays; the probes' rung does not (the fit's next forward takes the rung of the field it
    starts from, as `ensure_stable` gives it from the rung before the probes)."""
    out, sim, mat = _run(monkeypatch, [0.010, 0.004])      # better by more than half the parts' gain (0.01)
    assert out["used"]
    assert sim.e_bound == 1.0e4 and sim.used == [1.0e4] and float(mat.theta.min()) == 1.0


def test_a_simplex_that_found_nothing_gives_no_start(monkeypatch):
    """The parts' simplex ended at its start (gain 0: the H200's toy_rope, tow_rope, basketball): no start, even where
    the bumps' projection renders a hair better (it was taken and charged 6 iterations for nothing)."""
    out, sim, mat = _run(monkeypatch, [0.010, 0.0099], found=0.02)
    assert not out["used"] and out["parts_gain"] == 0.0
    assert float(mat.theta.abs().max()) == 0.0


class _RungProb:
    """A problem whose every forward moves the adaptive rung to a stiffer one (as a stiff probe's
    `ensure_stable` does) and, when `fail`, then raises SimulationError (a probe that went unstable)."""

    def __init__(self, fail=False):
        self.sim, self.fail = _Sim(), fail
        self.tdtype, self.tdev, self.T, self.x0 = torch.float64, "cpu", 3, np.zeros((6, 3))
        self.batch_frames = False

    def loss(self, E, nu, trajs=None, effects=None, frames=None, **kw):
        from physinteract_usd.errors import SimulationError

        self.sim.e_bound = 5.6e4
        if self.fail:
            raise SimulationError("a probe left the grid")
        return {"rec": torch.tensor(0.02)}


def test_a_rejected_probe_leaves_the_rung_unchanged():
    """select's part probes (PartProbe: the parts start's simplex, select's sweeps) run under one guard
    (substep.kept_rung): a probe that failed, and one that did not, leave the rung where they found it."""
    labels = np.array([0, 0, 0, 1, 1, 1])
    for fail in (True, False):
        prob = _RungProb(fail)
        f = select.PartProbe(prob, [1, 2], labels, torch.full((6,), 0.3), None, None, batch="never")
        v = f(np.log([3e4, 8e3]))
        assert (v == float("inf")) == fail
        assert prob.sim.e_bound == 1.0e4 and prob.sim.used == [1.0e4], (fail, prob.sim.used)


def test_a_batched_probe_leaves_the_rung_unchanged():
    """`FitProblem.losses_batch` (select's batched sweeps, PartProbe.many) is a probe too: the rung it found is
    restored after the tiled rollout, also when the rollout raised."""
    from physinteract_usd.errors import SimulationError
    from physinteract_usd.fit.problem import FitProblem

    for fail in (True, False):
        prob = types.SimpleNamespace(sim=_Sim())

        def simulate_batch(E, nu, trajectories=None, effects=None, sim=prob.sim, fail=fail):
            sim.e_bound = 5.6e4
            if fail:
                raise SimulationError("a copy left the grid")
            return torch.zeros(len(E), 2, 6, 3), torch.zeros(len(E), 2, 6, 3, 3), np.ones(len(E), bool)

        prob.sim.simulate_batch = simulate_batch
        prob.T, prob.batch_frames = 2, False
        try:
            FitProblem.losses_batch(prob, torch.ones(2, 6), torch.full((6,), 0.3))
        except SimulationError:
            assert fail
        assert prob.sim.e_bound == 1.0e4 and prob.sim.used == [1.0e4], (fail, prob.sim.used)


def test_the_probe_budget_scales_with_the_parts():
    """Two parts get 9 probes, three 12, under the fit's cap; never fewer than a simplex and one move."""
    assert ps.probe_budget(2, 20) == 9 and ps.probe_budget(3, 20) == 12 and ps.probe_budget(4, 20) == 15
    assert ps.probe_budget(2, 6) == 6 and ps.probe_budget(3, 1) == 5


class _Flat:
    """A flat loss: the parts' spread hardly matters (the simplex should find nothing and stop)."""

    def __init__(self):
        self.cache = {}

    def __call__(self, le):
        v = 0.02 * (1 + 1e-4 * float(np.sum(np.abs(le))))
        self.cache[tuple(np.round(le, 10))] = v
        return v


def test_the_simplex_stops_when_it_stalls():
    """A flat loss (the parts' spread does not matter): the simplex stops after its first simplex and
    one more round of probes, not at its budget; a valley it descends is not cut short."""
    f = _Flat()
    r = select.part_refine(f, np.log([1e4, 1e4]), np.log(1e3), np.log(1e7), 20, step=np.log(2.0), stall=(6, 0.005))
    assert r.get("stalled") and len(f.cache) <= 8, len(f.cache)
    import test_fit_parts as tfp

    target = np.log([1e4, 1e5])
    g = tfp._Valley(target)
    start = target + np.log([1.45, 1 / 1.45])
    r = select.part_refine(g, start, np.log(1e3), np.log(1e7), 24, stall=(6, 0.005))
    floor = 0.01                                        # the valley's minimum
    assert r["loss"] < g(start) - 0.7 * (g(start) - floor), (r, g(start))   # most of the descent kept (measured 75%)


class _Bowl:
    """Two parts' loss, a bowl in (common, contrast) log E: the uniform E (the start) is the common mode's minimum,
    and the parts' minimum has the second part 2.5x softer and the first 1.14x stiffer (the demo's foam_bar:
    uniform 25 kPa, parts 28.5 / 9.9 kPa)."""

    def __init__(self, a=0.02, b=0.004):
        self.opt, self.a, self.b, self.cache = np.log([2.85e4, 9.86e3]), a, b, {}

    def __call__(self, le):
        d = np.asarray(le, float) - self.opt
        c, k = (d[0] + d[1]) / 2, (d[0] - d[1]) / 2
        v = 0.0067 + self.a * c * c + self.b * k * k
        self.cache[tuple(np.round(le, 10))] = v
        return v


def test_a_two_sided_first_simplex_finds_a_softer_part_within_the_budget():
    """From the uniform E the soft part must go down: a first simplex all on the stiff side (x2 each part) spends
    its few probes finding the way (71-84% of the gain in 9 probes), one that turns a part's vertex to x0.5
    where x2 is worse keeps >= 90% of it at the parts start's budget and stall window (9 + at most 2 probes;
    measured 90-98%)."""
    x0 = np.log([2.5e4, 2.5e4])
    for a, b in ((0.02, 0.004), (0.05, 0.002), (0.005, 0.01)):
        f = _Bowl(a, b)
        s0 = f(x0)
        r = select.part_refine(f, x0, np.log(1e3), np.log(6e4), ps.probe_budget(2, 20), step=ps.SIMPLEX_STEP,
                               stall=(ps.stall_window(2), ps.STALL_TOL), two_sided=True)
        assert (s0 - r["loss"]) / (s0 - 0.0067) >= 0.89, (a, b, r)
        assert len(f.cache) <= ps.probe_budget(2, 20) + 2


class _Cable:
    """Three parts' loss shaped as the H200's telephone_cable start (2026-11-27, rows stall_suite_cheap_parts.jsonl):
    from the uniform E the coil (part 0, most of the pixels) wants 0.86x, steep both ways; the two plugs want 2.5x and
    1.2x, shallow. The cheap start's simplex (two-sided, stall window m + 1 counted from its first vertices) ended at
    [start, x2, start] as the GPU's did (gain 2.3% of the loss here, 1.8% there) and the 20-probe one found the coil
    (3.4% here, 3.2% there)."""

    opt = np.array([-0.15, 0.9, 0.2])

    def __init__(self):
        self.cache = {}

    def __call__(self, le):
        d = np.asarray(le, float) - self.opt
        v = 0.0753 * (1 + 0.45 * d[0] ** 2 + 0.03 * (d[1] ** 2 + d[2] ** 2))
        self.cache[tuple(np.round(le, 10))] = v
        return v


def _refine(f, x0, parts, cap=20, cheap=True, **over):
    kw = {**ps.refine_kwargs(parts, cap, cheap=cheap), **over}
    return select.part_refine(f, x0, -3.0, 3.0, kw.pop("evals"), kw.pop("step"), **kw)


def test_on_cuda_the_simplex_runs_its_cap_uncut():
    """On CUDA (a forward ~1 s) the simplex gets the cap's probes and no stall stop; the telephone_cable-shaped loss
    then keeps >= 90% of its gain, as the H200's 20-probe start did (0.728), where the cut one (the CPU's rule, as
    the H200 ran it on 2026-11-27b) stops at [start, x2, start] with 65% (MA 0.228 there)."""
    f, g = _Cable(), _Cable()
    x0 = np.zeros(3)
    s0, floor = _Cable()(x0), _Cable()(_Cable.opt)
    r = _refine(f, x0, 3, cheap=False)
    assert (s0 - r["loss"]) / (s0 - floor) >= 0.9 and abs(r["log_e"][0] - _Cable.opt[0]) < 0.1, r
    assert not r.get("stalled") and len(f.cache) <= 20 + 3
    r_cut = _refine(g, x0, 3)
    assert (s0 - r_cut["loss"]) / (s0 - floor) < 0.7 and r_cut.get("stalled")
    assert list(g.cache) == list(f.cache)[:len(g.cache)]             # the uncut run extends the cut one's path


def test_parts_start_gives_the_cap_on_cuda_and_the_cut_on_the_cpu(monkeypatch):
    """`parts_start` asks for the uncut simplex where the problem's tensors are on CUDA, the cut one elsewhere."""
    seen = {}
    for dev in ("cpu", "cuda:0"):
        def refine(f, start, lo, hi, n, step, dev=dev, **kw):
            seen[dev] = (n, kw.get("stall"))
            return {"log_e": list(start), "loss": 0.02}

        sim = _Sim()
        prob = types.SimpleNamespace(sim=sim, T=4, tdev=dev)
        labels = np.array([0, 0, 1, 1, 2, 2])
        monkeypatch.setattr(select, "part_candidates", lambda *a: [{"kind": "appearance", "parts": 3, "labels": labels}])

        class Probe:
            def __init__(self, *a, **k):
                self.cache = {}

            def __call__(self, x):
                return 0.02

        monkeypatch.setattr(select, "PartProbe", Probe)
        monkeypatch.setattr(select, "part_refine", refine)
        it = iter([0.02, 0.02])
        ps.parts_start(prob, _Mat(), types.SimpleNamespace(select_sweep_batch=1), None, None, lambda: next(it), 20)
    assert seen["cpu"] == (12, (4, ps.STALL_TOL)) and seen["cuda:0"] == (20, None), seen


def test_a_part_worse_both_ways_gets_its_parabolas_vertex():
    """`part_refine(bracket=True)` (an option, off in the parts start: on the CPU's foam_bar at grid 12 its 1.09x
    vertex sent the cut simplex to MA 0.509 instead of 0.979): the telephone_cable's coil, x2 and x0.5 both worse,
    gets the parabola's vertex through the three probes as its first vertex, and the cut simplex keeps >= 90% of the
    gain within its budget (without: 65%, stalled 3 probes after its first simplex)."""
    f = _Cable()
    x0 = np.zeros(3)
    s0, floor = f(x0), f(_Cable.opt)
    r = _refine(f, x0, 3, bracket=True, stall_after_simplex=True)
    assert (s0 - r["loss"]) / (s0 - floor) >= 0.9, r
    assert abs(r["log_e"][0] - _Cable.opt[0]) < 0.05, r            # the coil found: 0.86x, not left at 1x
    assert len(f.cache) <= ps.probe_budget(3, 20) + 3               # the budget + the two-sided probes


def test_the_bracket_vertex_is_a_parabolas():
    """Known answer: on a parabola the vertex and the drop are exact, also from uneven sides; flat or non-finite
    probes give none."""
    f = lambda x: 2.0 + 3.0 * (x - 0.2) ** 2                       # noqa: E731
    d, drop = select._bracket_vertex(0.7, f(0.7), -0.7, f(-0.7), f(0.0))
    assert abs(d - 0.2) < 1e-12 and abs(drop - 3.0 * 0.04) < 1e-12
    d, drop = select._bracket_vertex(0.5, f(0.5 + 0.25), -0.7, f(-0.7 + 0.25), f(0.25))   # uneven sides
    assert abs(d + 0.05) < 1e-12 and abs(drop - 3.0 * 0.0025) < 1e-12
    assert select._bracket_vertex(0.7, 1.0, -0.7, 1.0, 1.0) is None
    assert select._bracket_vertex(0.7, float("inf"), -0.7, 2.0, 1.0) is None


def test_a_loss_flat_both_ways_on_every_part_stops_after_the_axes():
    """Every part worse both ways and the parabolas predict less than the stall tolerance (the H200's toy_rope,
    tow_rope, basketball, hemp_rope, knit_cap: the simplex found 0.00000 in 6-8 probes): the start stops after the
    axes' 2 m + 1 probes and gives nothing; a loss with a part worth more than the tolerance goes on."""
    for m in (2, 3, 4):
        class Flat:
            def __init__(self):
                self.cache = {}

            def __call__(self, le):
                v = 0.02 * (1 + 0.002 * float(np.sum(np.asarray(le) ** 2)))
                self.cache[tuple(np.round(le, 10))] = v
                return v

        f = Flat()
        r = _refine(f, np.zeros(m), m, bracket=True)
        assert r.get("stalled") and len(f.cache) == 2 * m + 1 and r["loss"] == f(np.zeros(m)), (m, len(f.cache))
    f = _Cable()
    _refine(f, np.array([-0.15, 0.9, 0.2]) + [0.3, 0.0, 0.0], 3, bracket=True)
    assert len(f.cache) > 7                                          # the coil 1.35x off its minimum: worth a simplex


def test_the_demos_two_parts_cost_no_more_probes():
    """The demo's two parts (one stiffer, one softer: no part worse both ways) take the same probes and gain as
    the cheap start of acf1acc (the bracket and the stall clock change nothing there)."""
    x0 = np.log([2.5e4, 2.5e4])
    for a, b in ((0.02, 0.004), (0.05, 0.002), (0.005, 0.01)):
        f, g = _Bowl(a, b), _Bowl(a, b)
        r_new = select.part_refine(f, x0, np.log(1e3), np.log(6e4), **ps.refine_kwargs(2, 20), bracket=True,
                                   stall_after_simplex=True)
        r_old = select.part_refine(g, x0, np.log(1e3), np.log(6e4), ps.probe_budget(2, 20), step=ps.SIMPLEX_STEP,
                                   stall=(ps.stall_window(2), ps.STALL_TOL), two_sided=True)
        assert len(f.cache) <= len(g.cache) and r_new["loss"] <= r_old["loss"] + 1e-12, (a, b)


def test_a_part_bracketed_at_its_start_costs_no_probe():
    """The CPU demo's stiff part (2026-11-27 trace, benchmarks/parts_simplex_trace.py): x2 +96%, x0.5 +101%, its
    minimum 1.01x the start; the soft part wants ~0.55x. The bracket leaves that vertex at x2 (no probe for a part
    already in place): the same probes and start as the cheap rule without the bracket."""
    class Demo:
        def __init__(self):
            self.cache = {}

        def __call__(self, le):
            x = np.asarray(le, float)
            v = 0.01485 * (1 + 2.047 * ((x[0] - 0.0081) ** 2 - 0.0081 ** 2) + 0.5 * ((x[1] + 0.6) ** 2 - 0.36))
            self.cache[tuple(np.round(le, 10))] = v
            return v

    f, g = Demo(), Demo()
    r_new = _refine(f, np.zeros(2), 2, bracket=True, stall_after_simplex=True)
    r_old = select.part_refine(g, np.zeros(2), -3.0, 3.0, ps.probe_budget(2, 20), step=ps.SIMPLEX_STEP,
                               stall=(ps.stall_window(2), ps.STALL_TOL), two_sided=True)
    assert list(f.cache) == list(g.cache) and r_new["loss"] == r_old["loss"]


def test_the_parts_starts_default_is_on_for_cuda_and_off_on_the_cpu(monkeypatch):
    """FitSettings.parts_start None (the default): `fit.fit` resolves it from the problem's device (20 probes where
    the tensors are on CUDA, 0 = off on the CPU) and passes the resolved number on, so the version records it; an
    explicit number, 0 included, always wins."""
    import physinteract_usd.fit as F

    assert F.FitSettings().parts_start is None
    cpu, gpu = types.SimpleNamespace(tdev="cpu"), types.SimpleNamespace(tdev="cuda:0")
    assert ps.default_probes(cpu, None) == 0 and ps.default_probes(gpu, None) == ps.PARTS_START_CUDA == 20
    assert ps.default_probes(gpu, 0) == 0 and ps.default_probes(cpu, 7) == 7
    seen = {}

    def schedule(prob, s, **kw):
        seen[prob.tdev] = (s.parts_start, "before_finest" in kw)
        return "done"

    monkeypatch.setitem(F.SCHEDULES, "bumps", schedule)
    for prob in (cpu, gpu):
        prob.weights, prob.tracks = types.SimpleNamespace(track=0.0), None
        assert F.fit(prob, F.FitSettings(schedule="bumps", unconstrained_floor=0.0)) == "done"
    assert seen == {"cpu": (0, False), "cuda:0": (20, True)}, seen
    F.fit(gpu, F.FitSettings(schedule="bumps", parts_start=0))
    assert seen["cuda:0"] == (0, True)              # the trend start's default (on CUDA) still asks for the hook
    F.fit(gpu, F.FitSettings(schedule="bumps", parts_start=0, trend_start=0))
    assert seen["cuda:0"] == (0, False)


def test_the_trend_starts_default_is_on_for_cuda_and_off_on_the_cpu():
    import physinteract_usd.fit as F
    from physinteract_usd.fit import trend_start as ts

    assert F.FitSettings().trend_start is None
    cpu, gpu = types.SimpleNamespace(tdev="cpu"), types.SimpleNamespace(tdev="cuda:0")
    assert ts.default_trend_probes(cpu, None) == 0 and ts.default_trend_probes(gpu, None) == ts.TREND_START_CUDA == 20
    assert ts.default_trend_probes(gpu, 0) == 0 and ts.default_trend_probes(cpu, 9) == 9


def test_the_default_is_resolved_in_the_callers_settings_object(monkeypatch):
    """`fit.fit` resolves the default in the settings object it was given, not in a copy: a stop mutates that object
    while the fit runs (SIGTERM sets confidence_probes = 0 for the estimate afterwards; tests/test_fit_stop.py)."""
    import physinteract_usd.fit as F

    seen = []
    monkeypatch.setitem(F.SCHEDULES, "bumps", lambda prob, s, **kw: seen.append(s))
    prob = types.SimpleNamespace(tdev="cpu", weights=types.SimpleNamespace(track=0.0), tracks=None)
    s = F.FitSettings(schedule="bumps")
    F.fit(prob, s)
    assert seen == [s] and seen[0] is s and s.parts_start == 0


class _NestMat(_Mat):
    base = None

    def set_base(self, e):
        self.base = np.asarray(e, np.float64)
        self.theta = torch.zeros(8, requires_grad=True)


def _run_nested(monkeypatch, keep, losses, rule=None):
    """The parts start with `parts_nest` (opt-in): its simplex on the training frames, the held-back test deciding."""
    sim = _Sim()
    prob = types.SimpleNamespace(sim=sim, T=12, tdtype=torch.float64, tdev="cpu", contacts=[])
    labels = np.array([0, 0, 0, 1, 1, 1])
    seen = {}
    monkeypatch.setattr(select, "part_candidates", lambda *a: [{"kind": "appearance", "parts": 2, "labels": labels}])

    class Probe:
        def __init__(self, prob_, frames, *a, **k):
            self.cache, seen["frames"] = {}, list(frames)

        def __call__(self, x):
            return 0.02

    def held(prob_, s, E0, E1, added, *a):
        seen["held"] = (np.array(E1, copy=True), added, list(a[-1]))
        return {"keep": keep, "why": "test", "sign_p": 0.06 if keep else 0.5, "rule": rule or {}}

    monkeypatch.setattr(select, "PartProbe", Probe)
    monkeypatch.setattr(select, "part_refine", lambda *a, **k: {"log_e": [np.log(3e4), np.log(8e3)], "loss": 0.01})
    monkeypatch.setattr(select, "heldback_test", held)
    it = iter(losses)
    mat = _NestMat()
    s = types.SimpleNamespace(select_sweep_batch=1, parts_nest=True, select_holdout_every=3)
    out = ps.parts_start(prob, mat, s, None, None, lambda: next(it), 20)
    return out, mat, seen


def test_a_nested_parts_start_is_judged_on_frames_its_simplex_did_not_see(monkeypatch):
    out, mat, seen = _run_nested(monkeypatch, keep=True, losses=[0.010, 0.004])
    train, val = select.holdout_frames(12, 3)
    assert seen["frames"] == train and seen["held"][2] == val and not set(train) & set(val)
    np.testing.assert_allclose(seen["held"][0], [3e4] * 3 + [8e3] * 3)      # the parts' own field, tested as it is
    assert seen["held"][1] == 1                                             # one coefficient more than one E
    assert out["used"] and out.get("nested")
    np.testing.assert_allclose(mat.base, [3e4] * 3 + [8e3] * 3)             # held exactly, as the nested base
    assert float(mat.theta.abs().max()) == 0.0


def test_a_nested_parts_start_the_held_back_frames_refuse_changes_nothing(monkeypatch):
    out, mat, _ = _run_nested(monkeypatch, keep=False, losses=[])          # no total loss is even asked for
    assert not out["used"] and mat.base is None and float(mat.theta.abs().max()) == 0.0


def test_a_nested_parts_start_with_a_clear_drop_is_kept_on_few_lower_frames():
    """`clear_drop`: the sign test (all 4 of a short clip's held-back frames) refused foam_bar's true parts on the H200
    (3 of 4 lower, the held-back loss 45% lower); a drop of at least PARTS_CLEAR_DROP of the held-back loss that beats
    the coefficients' price keeps them; a small one (balloon_dog's 6%) or one below the price does not."""
    def hb(drop, loss0=0.012, penalty=3e-5, keep=False):
        return {"keep": keep, "why": "w", "sign_p": 0.312, "rule": {"mean_drop": drop, "loss0": loss0, "penalty": penalty}}

    assert ps.clear_drop(hb(0.45 * 0.012))[0] and "45%" in ps.clear_drop(hb(0.45 * 0.012))[1]
    assert not ps.clear_drop(hb(0.06 * 0.012))[0]
    assert not ps.clear_drop(hb(0.5 * 0.012, penalty=0.007))[0]            # beyond the share, not the price
    assert ps.clear_drop(hb(0.0, keep=True))[0]                            # the test's own keep stands
    assert not ps.clear_drop({"keep": False, "why": "w", "sign_p": 1.0, "rule": {}})[0]


def test_the_clear_drop_keeps_a_nested_parts_start_through_the_start(monkeypatch):
    out, mat, _ = _run_nested(monkeypatch, keep=False, losses=[0.010, 0.004],
                              rule={"keep_field": True, "mean_drop": 0.0054, "loss0": 0.012, "penalty": 2.4e-5})
    assert out["used"] and "45%" in out["heldback"] and mat.base is not None


def test_the_uncut_simplex_goes_on_past_its_cap_while_still_descending():
    """`refine_kwargs(..., cheap=False, extend=True)` (the parts start on CUDA): a simplex still descending a narrow
    valley at its cap goes on (foam_bar at 36 frames stopped at the cap 1.4x off its soft part's truth and was refused),
    stops once two simplices' worth of probes bring nothing new, and never passes EXTEND_CAP x the cap; without
    `extend` it stops at the cap, as before; a flat loss costs nothing more."""
    class Valley:      # a quadratic valley across the axes, 30x steeper across than along its floor
        def __init__(self, target):
            self.target, self.cache = np.asarray(target, float), {}

        def __call__(self, le):
            d = np.asarray(le, float) - self.target
            across, along = (d[0] + d[1]) / math.sqrt(2), (d[0] - d[1]) / math.sqrt(2)
            v = 0.01 * (1 + 30.0 * across ** 2 + along ** 2)
            self.cache[tuple(np.round(le, 10))] = v
            return v

    target = np.log([1e4, 1e5])
    start = target + np.log([3.0, 1 / 3.0])            # far along the valley's floor
    lo, hi = np.log(1e3), np.log(1e7)
    kw_cut = ps.refine_kwargs(2, 12, cheap=False)
    kw_ext = ps.refine_kwargs(2, 12, cheap=False, extend=True)
    assert "extend" not in kw_cut and kw_ext["extend"] == (ps.EXTEND_CAP * 12, ps.extend_window(2), ps.STALL_TOL)
    g0, g1 = Valley(target), Valley(target)
    r0 = select.part_refine(g0, start, lo, hi, **kw_cut)
    r1 = select.part_refine(g1, start, lo, hi, **kw_ext)
    err0, err1 = (float(np.max(np.abs(r["log_e"] - target))) for r in (r0, r1))
    assert r0.get("extended", 0) == 0 and r1["extended"] > 0, (r0, r1)
    assert err1 < math.log(1.1) < err0, (np.exp(r0["log_e"]), np.exp(r1["log_e"]))
    assert r1["loss"] < r0["loss"] and len(g1.cache) <= ps.EXTEND_CAP * 12 + 4, len(g1.cache)

    f = _Flat()
    r = select.part_refine(f, np.log([1e4, 1e4]), lo, hi, **ps.refine_kwargs(2, 12, cheap=False, extend=True))
    assert r["extended"] == 0 and len(f.cache) <= 12 + 3, (r, len(f.cache))
