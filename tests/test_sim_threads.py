"""Independent forwards on two threads (simulation.py `Simulation.simulate_each`, SIM_THREADS): the
calling thread on its rollout's graphs, a second on an eager twin (Warp's CPU kernels and graph replays
release the GIL). Bitwise what one thread gives, job after job; the confidence's finite differences
(fit/optimize.py `_gn_diag_fd`) through it give the sequential loop's diagonal exactly."""

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd import simulation as simulation_mod
from physinteract_usd.errors import SimulationError
from physinteract_usd.fit import FitProblem
from physinteract_usd.fit import optimize
from physinteract_usd.usd.stage import read_stage
from test_fit_confidence import _field


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    sc = fs.build(tmp_path_factory.mktemp("threads") / "base")
    sd = read_stage(sc["stage"])
    return FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, sc["gt"])), sd


def test_two_threads_give_the_sequential_simulations(problem):
    prob, _ = problem
    sim = prob.sim
    P = len(prob.x0)
    nu = torch.full((P,), fs.NU_TRUE, dtype=prob.tdtype)
    top = fs.E_TRUE * 1.2
    sim.ensure_stable(top)
    Es = [torch.linspace(0.6, 1.0, P, dtype=prob.tdtype) * top * s for s in (1.0, 0.97, 0.93, 0.9, 0.95)]
    Es = [E for E in Es if sim.rung_wanted(float(E.max())) == sim.e_bound]
    assert len(Es) >= 4
    with torch.no_grad():
        ref = [sim.simulate(E, nu) for E in Es]
    got = sim.simulate_each([(E, nu, None, None) for E in Es], threads=2)
    assert sim._twins.get(sim.e_bound)                 # the second thread ran on a twin
    for (xr, Fr), (xg, Fg) in zip(ref, got):
        assert torch.equal(xr, xg) and torch.equal(Fr, Fg)
    assert not torch.equal(ref[0][0], ref[1][0])
    one = sim.simulate_each([(E, nu, None, None) for E in Es], threads=1)
    assert all(torch.equal(a[0], b[0]) for a, b in zip(one, got))
    # an E beyond the rung is refused; an unstable job comes back as its error
    with pytest.raises(ValueError):
        sim.simulate_each([(Es[0] * 10.0, nu, None, None)])
    neg = Es[1].clone()
    neg[0] = -1.0
    bad = sim.simulate_each([(Es[0], nu, None, None), (neg, nu, None, None), (Es[1], nu, None, None)], threads=2)
    assert torch.equal(bad[0][0], ref[0][0]) and isinstance(bad[1], SimulationError)
    assert torch.equal(bad[2][0], ref[1][0])


def test_finite_difference_confidence_on_two_threads_is_the_sequential_one(problem):
    prob, sd = problem
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(simulation_mod, "SIM_THREADS", 1)
        c1, d1, u1 = optimize.confidence(prob, _field(prob, sd), [], probes=4, method="fd", return_diag=True)
        mp.setattr(simulation_mod, "SIM_THREADS", 2)
        c2, d2, u2 = optimize.confidence(prob, _field(prob, sd), [], probes=4, method="fd", return_diag=True)
        mp.setattr(optimize, "_gn_diag_fd_threaded", lambda *a: False)      # the sequential loop
        c3, d3, u3 = optimize.confidence(prob, _field(prob, sd), [], probes=4, method="fd", return_diag=True)
    assert u1 == u2 == u3 == "fd" and np.all(d1 > 0)
    assert np.array_equal(d1, d2) and np.array_equal(d1, d3) and np.array_equal(c1, c2) and np.array_equal(c1, c3)
