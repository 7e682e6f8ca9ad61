"""The start search's uniform-E probes two at a time (fit/search.py `UniformProbe.prefetch`, fit/optimize.py
`_probes_beside`, simulation.py `Simulation.forward_at`; on with `simulation.SIM_THREADS` >= 2): the first
two probes at once, then each with the one most likely to follow it. The one-thread search's probes,
values, log, chosen E and rung, bitwise; a wrong guess is dropped, never used."""

import math

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd import simulation as simulation_mod
from physinteract_usd.fit import FitProblem, MaterialField
from physinteract_usd.fit import optimize
from physinteract_usd.fit.search import UniformProbe, golden_section
from physinteract_usd.usd.stage import read_stage


class _Recorder:
    """A pure-Python f with prefetch: which points were asked for, which computed ahead."""

    def __init__(self, fn):
        self.fn, self.asked, self.ahead, self.cache = fn, [], [], {}

    def prefetch(self, points, maybe=None):
        self.ahead.append((list(points), maybe))

    def __call__(self, x):
        self.asked.append(x)
        return self.fn(x)


@pytest.mark.parametrize("fn", [lambda x: (x - 0.3) ** 2, lambda x: -math.cos(3 * x), lambda x: abs(x - 0.9),
                                lambda x: float("inf") if x > 0.6 else (x - 0.2) ** 2])
def test_the_search_asks_the_same_points_with_prefetch(fn):
    plain = []
    golden_section(lambda x: plain.append(x) or fn(x), 0.0, 1.0, 9)
    rec = _Recorder(fn)
    golden_section(rec, 0.0, 1.0, 9)
    assert rec.asked == plain
    # the first two together; then each asked point is the one handed first; the guess, when right, is
    # the next point asked
    assert rec.ahead[0] == ([plain[0], plain[1]], None)
    for i, (pts, maybe) in enumerate(rec.ahead[1:]):
        assert pts == [plain[i + 2]]
        assert (maybe is None) == (i == len(rec.ahead) - 2)


def test_the_guess_is_mostly_right_on_a_smooth_valley():
    rec = _Recorder(lambda x: (x - 0.37) ** 2 + 0.1 * (x - 0.37) ** 3)
    golden_section(rec, 0.0, 1.0, 7)
    hits = sum(maybe == rec.asked[i + 3] for i, (_, maybe) in enumerate(rec.ahead[1:-1]))
    assert hits >= 3          # of 4 guesses


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    sc = fs.build(tmp_path_factory.mktemp("probes") / "base")
    sd = read_stage(sc["stage"])
    return sd, api.load_observations(sd), api.true_contacts(sd, sc["gt"])


def _search(problem, threads, evals=6):
    sd, obs, contacts = problem
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(simulation_mod, "SIM_THREADS", threads)
        prob = FitProblem(sd, obs, contacts)
        st = sd.settings
        mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype,
                            device=prob.tdev)
        mat.set_uniform(math.sqrt(st.youngs_min * st.youngs_max), min(st.poisson_default, 0.98 * st.poisson_max))
        lines, skipped, seen = [], [], {}
        e, loss = optimize.golden_uniform_search(prob, mat, evals, lines.append, with_loss=True, skipped=skipped,
                                                 seen=seen)
        return e, loss, [ln for ln in lines if ln.startswith("uniform E")], lines, skipped, seen, prob


def test_two_threads_give_the_one_thread_search(problem):
    e1, l1, log1, _, sk1, seen1, p1 = _search(problem, 1)
    e2, l2, log2, all2, sk2, seen2, p2 = _search(problem, 2)
    assert e1 == e2 and l1 == l2 and log1 == log2 and sk1 == sk2 and seen1 == seen2
    assert len(seen1) == 6 and len(set(seen1.values())) > 1
    assert p1.sim.e_bound == p2.sim.e_bound and p1.sim.substeps == p2.sim.substeps   # the rung left as one thread
    assert not p2.sim._probe_twins                                                  # freed after the search
    used = [ln for ln in all2 if ln.startswith("start search on two threads")]
    assert len(used) == 1 and not used[0].startswith("start search on two threads: 0 ")
    assert not any(ln.startswith("start search on two threads") for ln in _search(problem, 1)[3])
    # a fit after the search starts from the same rung: the next forward is bitwise the one-thread one
    E = torch.full((len(p1.x0),), e1, dtype=p1.tdtype)
    nu = torch.full((len(p1.x0),), fs.NU_TRUE, dtype=p1.tdtype)
    with torch.no_grad():
        x1, _ = p1.simulate(E, nu)
        x2, _ = p2.simulate(E, nu)
    assert torch.equal(x1, x2)


def test_forward_at_is_simulate_at_that_rung(problem):
    sd, obs, contacts = problem
    prob = FitProblem(sd, obs, contacts)
    sim = prob.sim
    P = len(prob.x0)
    nu = torch.full((P,), fs.NU_TRUE, dtype=prob.tdtype)
    E = torch.linspace(0.6, 1.0, P, dtype=prob.tdtype) * fs.E_TRUE
    bound = sim.rung_wanted(float(E.max()))
    sim.twin_at(bound, 0)
    sim.twin_at(bound, 1)
    assert sim._probe_twins[(bound, 0)] is not sim._probe_twins[(bound, 1)]
    x0, F0 = sim.forward_at(bound, E, nu, slot=1)
    with torch.no_grad():
        x, F = sim.simulate(E, nu)
    assert torch.equal(x, x0) and torch.equal(F, F0)
    assert sim.model is sim._probe_twins[(bound, 1)].model      # one model per rung, shared
    # the rung after a sequence: from a given current rung, as ensure_stable would move
    up = sim.bound_for(1.2 * bound)
    assert up > bound and sim.bound_for(0.95 * bound) == bound
    assert sim.rung_wanted(0.95 * bound, current=up) == up          # hysteresis: within 10% of the rung stays
    assert sim.rung_wanted(0.95 * bound, current=bound) == bound
    assert sim.rung_wanted(1.2 * bound, current=bound) == up        # up: always


def test_a_wrong_guess_is_dropped():
    calls = []

    def many(Es):
        vals = [float(E[0]) for E in Es]
        calls.append(vals)
        return [lambda v=v: v + 1.0 for v in vals]

    f = UniformProbe(lambda E: float(E[0]) + 1.0, 3, torch.float64, "cpu", many=many)
    f.prefetch([0.0], maybe=1.0)
    assert f(0.0) == 2.0 and f.ahead_used == 1
    assert f(2.0) == math.exp(2.0) + 1.0 and f.ahead_wasted == 1 and not f._ahead      # not the guess: dropped
    assert np.isclose(calls[0][1], math.e)


def test_simulate_each_before_any_capture_runs_every_job_eagerly(problem):
    """A rung whose forward graphs are not captured yet: the calling thread takes an eager twin too (no
    capture while another thread launches); the same simulations as one thread's."""
    sd, obs, contacts = problem
    P = len(sd.particles_positions)
    nu = torch.full((P,), fs.NU_TRUE)
    Es = [torch.linspace(0.6, 1.0, P) * fs.E_TRUE * s for s in (1.0, 0.97, 0.94)]
    out = {}
    for threads in (1, 2):
        sim = FitProblem(sd, obs, contacts).sim
        sim.ensure_stable(float(Es[0].max()))
        jobs = [(E.to(sim.tdtype), nu.to(sim.tdtype), None, None) for E in Es]
        out[threads] = sim.simulate_each(jobs, threads=threads)
        ro = sim.rollout
        if threads == 2:
            assert len(sim._twins[sim.e_bound]) == 2 and not ro._fwd_graphs     # nothing captured, two twins
    for (x1, F1), (x2, F2) in zip(out[1], out[2]):
        assert torch.equal(x1, x2) and torch.equal(F1, F2)
    assert not torch.equal(out[1][0][0], out[1][1][0])


def test_sim_threads_takes_the_second_core_only_where_one_sits_idle(monkeypatch):
    from physinteract_usd.sim import lanes

    monkeypatch.setattr(simulation_mod, "SIM_THREADS", None)
    monkeypatch.setattr(lanes, "free_cores", lambda: 2)
    monkeypatch.setattr(lanes, "spare_cores", lambda interval=0.1: 0.9)
    assert simulation_mod.sim_threads("cpu") == 2
    assert simulation_mod.sim_threads("cuda:0") == 1                 # the GPU batches its probes instead
    monkeypatch.setattr(lanes, "spare_cores", lambda interval=0.1: 0.2)
    assert simulation_mod.sim_threads("cpu") == 1                    # a busy machine: the second thread would wait
    reads = iter([0.1, 0.95])
    monkeypatch.setattr(lanes, "spare_cores", lambda interval=0.1: next(reads))
    assert simulation_mod.sim_threads("cpu") == 2                    # a blip in the first window: the second decides
    monkeypatch.setattr(lanes, "spare_cores", lambda interval=0.1: 0.9)
    monkeypatch.setattr(lanes, "free_cores", lambda: 1)
    assert simulation_mod.sim_threads("cpu") == 1
    monkeypatch.setattr(simulation_mod, "AUTO_THREADS", False)
    monkeypatch.setattr(lanes, "free_cores", lambda: 2)
    assert simulation_mod.sim_threads("cpu") == 1
    monkeypatch.setattr(simulation_mod, "SIM_THREADS", 2)
    assert simulation_mod.sim_threads("cpu") == 2                    # the environment's choice wins


def test_probes_that_fail_on_either_thread_are_skipped_alike(problem, monkeypatch):
    """A probe whose simulation fails (here: every E above a threshold, on whichever thread it runs) is
    skipped, logged and never the answer, as on one thread."""
    from physinteract_usd.errors import SimulationError

    sd = problem[0]
    thr = math.sqrt(sd.settings.youngs_min * sd.settings.youngs_max)
    from physinteract_usd.sim.rollout import Rollout

    orig = Rollout.__call__

    def failing(self, E, *a, **kw):        # the simulator itself fails: the rung was taken before, as for real
        if float(torch.as_tensor(E).max()) > thr:
            raise SimulationError("test: unstable", frame=1)
        return orig(self, E, *a, **kw)
    monkeypatch.setattr(Rollout, "__call__", failing)
    e1, l1, log1, _, sk1, seen1, _ = _search(problem, 1)
    e2, l2, log2, _, sk2, seen2, _ = _search(problem, 2)
    assert sk1 and sk1 == sk2 and log1 == log2 and seen1 == seen2 and (e1, l1) == (e2, l2)
    assert e1 < thr and any(v is None for v in seen1.values())
