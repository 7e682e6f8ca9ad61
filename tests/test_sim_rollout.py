"""The torch entry point: shapes, errors, memory layout, gradients at null values, an optimiser step."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd.errors import SimulationError
from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import (Contact, Control, GridSpec, MPMSolver, Rollout, SimModel, effect_inputs,
                                  simulate, substeps_per_frame, stable_dt)
from sim_helpers import block, directional_check, rel_err

DX = 0.05


def _scene(dtype="float64", effects=None, T=2, substeps=10):
    pts = block((4, 3, 3), DX / 2, (0.3, 0.12, 0.3))
    traj = np.repeat(pts[-6:].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0, 0.02, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=np.arange(len(pts) - 6, len(pts)), trajectory=traj),
                    Contact("fixed", indices=np.arange(3))], n_frames=T)
    m = SimModel.create(pts, (DX / 2) ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (12, 12, 12)), fps=20,
                        substeps=substeps, E_max=1e4, dtype=dtype, effects=effects or {})
    return m, ctrl, pts, traj


def test_outputs_shapes_rest_frame_and_agreement_with_solver():
    m, ctrl, pts, _ = _scene()
    x, F = simulate(m, ctrl)
    P = len(pts)
    assert x.shape == (ctrl.n_frames + 1, P, 3) and F.shape == (ctrl.n_frames + 1, P, 3, 3)
    assert x.dtype == torch.float64
    np.testing.assert_array_equal(x[0].numpy(), pts)
    np.testing.assert_array_equal(F[0].numpy(), np.broadcast_to(np.eye(3), (P, 3, 3)))
    ref = MPMSolver(m, ctrl).simulate(ctrl.n_frames)
    np.testing.assert_array_equal(x.numpy(), ref["x"])
    np.testing.assert_array_equal(F.numpy(), ref["F"])


def test_log_E_input_and_optimizer_step_reduces_loss():
    """A torch optimiser drives the rollout: fit log E so that the tip reaches a target."""
    m, ctrl, pts, _ = _scene(dtype="float32", effects={"damping": {"coefficient": 2.0}})
    ro = Rollout(m, ctrl)
    with torch.no_grad():
        x_t, _ = ro(torch.full((len(pts),), 5e3))
    target = x_t[-1].clone()
    logE = torch.full((len(pts),), float(np.log(2e3)), requires_grad=True)
    opt = torch.optim.Adam([logE], lr=0.1)
    losses = []
    for _ in range(8):
        opt.zero_grad()
        x, _ = ro(torch.exp(logE))
        loss = ((x[-1] - target) ** 2).sum()
        loss.backward()
        assert torch.isfinite(logE.grad).all()
        opt.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.5 * losses[0]


def test_errors_for_bad_inputs():
    m, ctrl, pts, _ = _scene()
    ro = Rollout(m, ctrl)
    with pytest.raises(SimulationError, match="E_max"):
        ro(torch.full((len(pts),), 2e4, dtype=torch.float64))
    with pytest.raises(SimulationError):
        ro(nu=torch.full((len(pts),), 0.5, dtype=torch.float64))
    with pytest.raises(ValueError, match="off in this model"):
        ro(effects={"damping": {"coefficient": torch.tensor(1.0)}})
    with pytest.raises(ValueError, match="fixed"):
        ro(trajectories={1: torch.zeros(3, 3)})
    with pytest.raises(ValueError, match="shape"):
        ro(trajectories={0: torch.zeros(2, 3)})
    with pytest.raises(ValueError, match="shares particles"):
        Rollout(m, Control([Contact("fixed", indices=[0, 1]), Contact("fixed", indices=[1, 2])], n_frames=2))


def test_gradients_at_null_values_and_initial_velocity():
    """At the null value (damping c = 0, Maxwell E_v = 0) the gradient exists and matches a
    one-sided second-order difference (the parameters may not go negative), so a diagnosis can
    score an effect that is off; dL/dv0 is returned too (central difference)."""
    eff = {"damping": {"coefficient": 0.0}, "viscoelasticity": {"modulus": 0.0, "relaxationTime": 0.05}}
    m, ctrl, pts, traj = _scene(effects=eff, T=3, substeps=20)
    ro = Rollout(m, ctrl)
    W = torch.randn(ctrl.n_frames + 1, len(pts), 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def loss(c, ev, v0):
        x, _ = ro(effects={"damping": {"c": c}, "viscoelasticity": {"E_v": ev}}, v0=v0)
        return (x * W).sum()

    c = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    ev = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    v0 = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    loss(c, ev, v0).backward()
    z = torch.tensor(0.0, dtype=torch.float64)
    with torch.no_grad():
        for grad, h, f in ((c.grad, 1e-3, lambda t: loss(t, z, torch.zeros(3, dtype=torch.float64))),
                           (ev.grad, 1.0, lambda t: loss(z, t, torch.zeros(3, dtype=torch.float64)))):
            fd = float((-3 * f(z) + 4 * f(z + h) - f(z + 2 * h)) / (2 * h))
            assert abs(fd) > 1e-8 and rel_err(float(grad), fd) < 1e-4, (float(grad), fd)
    res = directional_check(lambda v: loss(z, z, v), [torch.zeros(3, dtype=torch.float64)], [0.1], eps=1e-5)
    for an, fd in res:
        assert abs(fd) > 1e-8 and rel_err(an, fd) < 1e-4, res


def test_effect_inputs_helper_and_memory_layout():
    """effect_inputs gives leaf tensors for the enabled effects; beyond STORE_STATES_BYTES the
    backward keeps S+1 particle states (a replay) and ONE grid (and its adjoint), whatever the
    number of substeps and frames; within it, every substep's state of every frame."""
    eff = {"ground": {"height": 0.1, "friction": 0.4}, "damping": {"coefficient": 1.0}}
    m, ctrl, pts, _ = _scene(effects=eff)
    ei = effect_inputs(m)
    assert set(ei) == {"ground", "damping"} and set(ei["ground"]) == {"height", "friction"}
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
        ro = Rollout(m, ctrl)
        x, F = ro(effects=ei)
        (x.sum() + F.sum()).backward()
    assert ei["ground"]["height"].grad is not None and ei["damping"]["coefficient"].grad is not None
    assert len(ro._replay) == m.substeps + 1 and ro._states is None
    stored = Rollout(m, ctrl)
    x, F = stored(effects=effect_inputs(m))
    (x.sum() + F.sum()).backward()
    assert stored._replay is None and len(stored._states) == ctrl.n_frames
    assert all(len(st) == m.substeps + 1 for st in stored._states)
    grid_arrays = [a for a in vars(ro.solver).values() if hasattr(a, "shape") and tuple(a.shape) == m.grid.resolution]
    adj_grid = list(ro.solver._adj_grid.values())
    assert len(grid_arrays) == 6 and len(adj_grid) == 6        # kernels.SCATTERED and the velocity


def test_cfl_substeps():
    dt = stable_dt(0.01, 1e5, 0.45, 1000.0)
    c = np.sqrt(1e5 * 0.55 / (1.45 * 0.1 * 1000.0))
    assert dt == pytest.approx(0.4 * 0.01 / c)
    S = substeps_per_frame(30.0, 0.01, 1e5, 0.45, 1000.0)
    assert 1 / (30 * S) <= dt < 1 / (30 * (S - 1))
    m, _, _, _ = _scene()
    m2 = SimModel.create(m.x0, m.volume, 1000.0, 3e3, 0.3, grid=m.grid, fps=20, E_max=1e5, nu_max=0.45)
    assert m2.dt <= stable_dt(m.grid.dx, 1e5, 0.45, 1000.0)


def test_graphs_match_eager_launches():
    """The captured per-frame graphs (CPU graphs here, CUDA graphs on a GPU) give bitwise the eager
    results, forward and backward, over repeated calls with changing inputs."""
    eff = {"damping": {"coefficient": 1.0}, "ground": {"height": 0.1, "friction": 0.4}}
    m, ctrl, pts, traj = _scene(effects=eff, T=3)
    ros = {g: Rollout(m, ctrl, graphs=g) for g in (True, False)}
    outs = {}
    for g, ro in ros.items():
        res = []
        for scale in (1.0, 0.7):
            E = torch.full((len(pts),), 3e3 * scale, dtype=torch.float64, requires_grad=True)
            tr = torch.tensor(traj * (1 + 0.01 * scale), requires_grad=True)
            x, F = ro(E, trajectories={0: tr})
            (x[-1, :, 0].sum() + F[2].sum()).backward()
            res.append((x.detach().clone(), E.grad.clone(), tr.grad.clone()))
        outs[g] = res
    assert ros[True].graphs and len(ros[True]._fwd_store_graphs) == 3 and len(ros[True]._adj_graphs) == 3
    for a, b in zip(outs[True], outs[False]):
        for u, v in zip(a, b):
            assert torch.equal(u, v)
    assert not torch.equal(outs[True][0][1], outs[True][1][1])


def test_stored_states_give_the_replayed_gradients_also_when_a_later_forward_overwrote_them():
    """A backward from the states its forward stored equals, bitwise, one that replays them from
    the frames' checkpoints; a backward whose states a later forward overwrote (two losses built,
    then both backwards) replays and still gets its own forward's gradient."""
    eff = {"damping": {"coefficient": 1.0}}
    m, ctrl, pts, traj = _scene(effects=eff, T=3)

    def run(store: bool, interleaved: bool):
        with pytest.MonkeyPatch.context() as mp:
            if not store:
                mp.setattr(rollout_mod, "STORE_STATES_BYTES", 0)
            ro = Rollout(m, ctrl)
            Es = [torch.full((len(pts),), 3e3 * s_, dtype=torch.float64, requires_grad=True) for s_ in (1.0, 0.6)]
            if interleaved:     # both forwards, then both backwards: the first one's states are gone
                outs = [ro(E) for E in Es]
                for (x, F) in reversed(outs):
                    (x[-1, :, 0].sum() + F[2].sum()).backward()
            else:
                for E in Es:
                    x, F = ro(E)
                    (x[-1, :, 0].sum() + F[2].sum()).backward()
            return ro, [E.grad.clone() for E in Es]

    ro_r, ref = run(False, False)
    ro_s, got = run(True, False)
    ro_i, mixed = run(True, True)
    assert ro_r._states is None and ro_s._states is not None and ro_i._replay_graphs
    assert not ro_s._replay_graphs                     # the states were fresh: no replay ran
    for a, b, c in zip(ref, got, mixed):
        assert torch.equal(a, b) and torch.equal(a, c)
    assert not torch.equal(ref[0], ref[1])
    # states dropped between a forward and its backward (the simulation changed rung): replayed
    E = torch.full((len(pts),), 3e3, dtype=torch.float64, requires_grad=True)
    x, F = ro_s(E)
    ro_s.drop_states()
    (x[-1, :, 0].sum() + F[2].sum()).backward()
    assert ro_s._states is None and torch.equal(E.grad, ref[0])


def test_effect_parameters_outside_their_domain_are_refused():
    eff = {"damping": {"coefficient": 1.0}, "viscoelasticity": {"modulus": 1e3, "relaxationTime": 0.1}}
    m, ctrl, pts, _ = _scene(effects=eff)
    ro = Rollout(m, ctrl)
    with pytest.raises(SimulationError, match="relaxationTime"):
        ro(effects={"viscoelasticity": {"tau": torch.tensor(-0.1, dtype=torch.float64)}})
    with pytest.raises(SimulationError, match="damping.coefficient"):
        ro(effects={"damping": {"c": -1.0}})


def test_a_forward_without_gradients_captures_its_graphs_at_its_second_use():
    """rollout.EAGER_FORWARDS: a one-off forward (a start-search probe at a new rung) runs eagerly and
    captures nothing; the second captures the frames' graphs, later ones replay them; every call
    bitwise equal to eager launches."""
    m, ctrl, pts, traj = _scene(effects={"damping": {"coefficient": 1.0}}, T=3)
    ro, ref = Rollout(m, ctrl), Rollout(m, ctrl, graphs=False)
    for i, scale in enumerate((1.0, 0.7, 1.3)):
        E = torch.full((len(pts),), 3e3 * scale, dtype=torch.float64)
        with torch.no_grad():
            x, F = ro(E)
            xr, Fr = ref(E)
        assert len(ro._fwd_graphs) == (0 if i == 0 else 3), i
        assert torch.equal(x, xr) and torch.equal(F, Fr)
    assert not ro._fwd_store_graphs and ro.graphs


def test_a_forward_from_another_forwards_frame_is_the_whole_forward_bitwise():
    """`Rollout.forward_from` (the interaction check's release / grasp counterfactuals): a control whose
    release moved from frame 3 to 2 or 4 agrees with the first one's before frame 2 or 3, so frames from there
    on, started from the first forward's checkpoint, give the whole forward bitwise (every effect's state on:
    the Maxwell branch's Fv); started a frame too late, they do not."""
    eff = {"damping": {"coefficient": 1.0}, "viscoelasticity": {"modulus": 2e3, "relaxationTime": 0.05}}
    m, ctrl, pts, traj = _scene(effects=eff, T=6)
    idx = np.arange(len(pts) - 6, len(pts))

    def control(release):
        return Control([Contact("pointAdherent", indices=idx, trajectory=traj, release_frame=release),
                        Contact("fixed", indices=np.arange(3))], n_frames=6)

    E = torch.linspace(2e3, 4e3, len(pts), dtype=torch.float64)
    base = Rollout(m, control(3), graphs=False)
    with torch.no_grad():
        base(E, effects=eff)
    states = base.checkpoints()
    for release, start in ((2, 2), (4, 3)):
        whole = Rollout(m, control(release), graphs=False)
        with torch.no_grad():
            xw, Fw = whole(E, effects=eff)
        part = Rollout(m, control(release), graphs=False)
        x, F = part.forward_from(start, states, E, effects=eff)
        assert torch.equal(x, xw) and torch.equal(F, Fw), release
        assert not torch.equal(xw, states["x"].view_as(xw))          # the release changed the motion
        late = Rollout(m, control(release), graphs=False).forward_from(start + 1, states, E, effects=eff)[0]
        assert not torch.equal(late, xw), release
    with pytest.raises(ValueError):
        base.run_forward(store=True, start=2)


def test_a_forward_from_on_frame_shape_graphs_is_the_whole_forward(monkeypatch):
    """With frame-shape graphs (CUDA's default; forced here) `forward_from` ignores the states and runs the
    whole forward: the same frames whatever states it is given."""
    monkeypatch.setattr(rollout_mod, "FRAME_GRAPHS", True)
    m, ctrl, pts, traj = _scene(T=3)
    E = torch.full((len(pts),), 3e3, dtype=torch.float64)
    ro = Rollout(m, ctrl)
    ref = Rollout(m, ctrl, graphs=False)
    with torch.no_grad():
        xr, Fr = ref(E)
    junk = {k: torch.zeros_like(t) for k, t in ref.checkpoints().items()}
    x, F = ro.forward_from(2, junk, E)
    assert torch.equal(x, xr) and torch.equal(F, Fr)
