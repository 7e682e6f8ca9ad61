"""Substep tapes (sim/rollout.py TAPE_GRID, MPMSolver.new_tape): a backward that reads each substep's grid
and particle buffers from its forward's tape gives bitwise the gradients of one that recomputes them, in
float64 and float32, with every effect on, also when a later forward overwrote the stored frames (the
replay refills the tape), when only some frames have a tape (TAPE_BYTES), and for a second backward of
the same forward (retain_graph: the tape is left as its forward wrote it)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd.sim import rollout as rollout_mod
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel, effect_inputs
from sim_helpers import block

DX = 0.05
EFFECTS = {"damping": {"coefficient": 1.0}, "ground": {"height": 0.1, "friction": 0.4},
           "viscoelasticity": {"modulus": 1e3, "relaxationTime": 0.05},
           "plasticity": {"yieldStress": 400.0}}


def _scene(dtype="float64", T=3, substeps=8, effects=EFFECTS, ground_contact="nodes"):
    pts = block((4, 3, 3), DX / 2, (0.3, 0.12, 0.3))
    if ground_contact == "penalty" and "ground" in effects:
        # the particles' ground acts within half a spacing (DX / 4) of the plane: its bottom layer starts a fifth into it
        effects = {**effects, "ground": {**effects["ground"], "height": float(pts[:, 1].min() - 0.8 * DX / 4)}}
    traj = np.repeat(pts[-6:].mean(0)[None], T + 1, 0)
    traj[:, 0] += np.linspace(0, 0.03, T + 1)
    traj[:, 1] += np.linspace(0, 0.01, T + 1)
    ctrl = Control([Contact("pointAdherent", indices=np.arange(len(pts) - 6, len(pts)), trajectory=traj),
                    Contact("fixed", indices=np.arange(3))], n_frames=T)
    m = SimModel.create(pts, (DX / 2) ** 3, 1000.0, 3e3, 0.3, grid=GridSpec((0, 0, 0), DX, (12, 12, 12)), fps=20,
                        substeps=substeps, E_max=1e4, dtype=dtype, effects=effects, ground_contact=ground_contact)
    return m, ctrl, pts, traj


def _run(m, ctrl, pts, traj, tape, tape_bytes=None, interleaved=False, twice=False, graphs=True):
    """Gradients of two forwards at two E (in turn, or both forwards then both backwards)."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "TAPE_GRID", tape)
        mp.setattr(rollout_mod, "TAPE_BYTES", tape_bytes)
        ro = Rollout(m, ctrl, graphs=graphs)
        td = torch.float64 if m.dtype == "float64" else torch.float32
        ins = []
        for s_ in (1.0, 0.6):
            E = torch.linspace(2e3, 4e3, len(pts), dtype=td).mul(s_).requires_grad_(True)
            tr = torch.tensor(traj * (1 + 0.02 * s_), dtype=td, requires_grad=True)
            eff = effect_inputs(m, dtype=td)
            ins.append((E, tr, eff))

        def loss_of(E, tr, eff):
            x, F = ro(E, effects=eff, trajectories={0: tr})
            return (x[-1, :, 0].sum() + 0.3 * x[2, :, 1].sum() + F[2].sum() + F[-1, :, 0, 1].sum())

        if interleaved:
            losses = [loss_of(*i) for i in ins]
            for L in reversed(losses):
                L.backward()
        else:
            for i in ins:
                L = loss_of(*i)
                if twice:       # a second backward of the same forward (the confidence probes' way)
                    g1 = torch.autograd.grad(L, [i[0]], retain_graph=True)[0]
                    L.backward()
                    assert torch.equal(g1, i[0].grad)
                else:
                    L.backward()
        grads = []
        for E, tr, eff in ins:
            grads.append([E.grad.clone(), tr.grad.clone()] + [v.grad.clone() for ps in eff.values() for v in ps.values()])
        return ro, grads


def _equal(a, b):
    for ga, gb in zip(a, b):
        for u, v in zip(ga, gb):
            assert torch.equal(u, v), (u, v)


@pytest.mark.parametrize("dtype,ground_contact", [("float64", "nodes"), ("float32", "nodes"), ("float32", "penalty")])
def test_taped_backward_is_bitwise_the_recomputed_one(dtype, ground_contact):
    """(the particles' ground: its scattered velocity is not on the tape, the adjoint recomputes it)"""
    m, ctrl, pts, traj = _scene(dtype, ground_contact=ground_contact)
    ro_r, ref = _run(m, ctrl, pts, traj, tape=False)
    ro_t, got = _run(m, ctrl, pts, traj, tape=True)
    assert ro_r._tapes == [] and len(ro_t._tapes) == ctrl.n_frames and len(ro_t._tapes[0]) == m.substeps
    assert not ro_t._replay_graphs          # fresh states: no replay ran
    _equal(ref, got)
    assert not torch.equal(ref[0][0], ref[1][0]) and float(ref[0][0].abs().sum()) > 0
    assert all(float(g.abs().sum()) > 0 for g in ref[0][:2])


def test_taped_backward_after_an_overwriting_forward_partial_tapes_eager_and_a_second_backward():
    m, ctrl, pts, traj = _scene()
    _, ref = _run(m, ctrl, pts, traj, tape=False)
    # both forwards first: the first one's states and tapes are replayed (refilled) for its backward
    ro_i, mixed = _run(m, ctrl, pts, traj, tape=True, interleaved=True)
    assert ro_i._replay_graphs and len(ro_i._tapes) == ctrl.n_frames
    _equal(ref, mixed)
    # only the first frame has a tape (the budget): the others recompute
    one = ro_i.solver.tape_bytes(m.substeps)
    ro_p, part = _run(m, ctrl, pts, traj, tape=True, tape_bytes=one)
    assert len(ro_p._tapes) == 1
    _equal(ref, part)
    # eager launches, and two backwards of each forward
    _, eager = _run(m, ctrl, pts, traj, tape=True, graphs=False)
    _equal(ref, eager)
    _, twice = _run(m, ctrl, pts, traj, tape=True, twice=True)
    _, twice_ref = _run(m, ctrl, pts, traj, tape=False, twice=True)
    _equal(twice_ref, twice)


def test_tape_default_and_its_exclusions():
    m, ctrl, _, _ = _scene(effects={})
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rollout_mod, "TAPE_GRID", None)
        assert Rollout(m, ctrl).tape_on()                      # CPU default
        mp.setattr(rollout_mod, "FRAME_GRAPHS", True)
        assert not Rollout(m, ctrl).tape_on()                  # frame graphs keep the recompute
        mp.setattr(rollout_mod, "FRAME_GRAPHS", False)
        mp.setattr(rollout_mod, "TAPE_GRID", True)
        ro = Rollout(m, ctrl)
        ro.solver.grid_box = True
        assert not ro.tape_on()                                # the grid box keeps the recompute
        ro = Rollout(m, ctrl)
        ro.solver.fused_kernels = True
        assert not ro.tape_on()                                # so do the fused kernels (no vg / Cg)
        mp.setattr(rollout_mod, "TAPE_BYTES", 0)
        assert Rollout(m, ctrl).frames_to_tape(3) == 0
