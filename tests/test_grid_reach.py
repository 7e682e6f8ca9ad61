"""The simulation's domain holds the object's reach, and a particle that walks past the grid's edge is reported as
"left the grid", not as an unstable step (#24; docs/sim.md "The domain").

Known answers on tiny grids: a bar pinned at one end and released horizontally swings down to ~its length below the
pin inside the automatic domain (`simulation.grid_covering` with the contacts), and leaves the stage's own domain
with a "left the grid" error naming the frame and the face; a block let go by a still hand falls g dt^2 n (n + 1) / 2
(n substeps: the discrete 1/2 g t^2) inside the automatic domain; a block thrown at a face goes non-finite ~a cell
past it, which before #24 read "non-finite ... dt too large" (kept as `stencil_check=False`) and now reads "left the
grid"."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd.contacts import ContactSet
from physinteract_usd.errors import SimulationError
from physinteract_usd.scene import SimSettings
from physinteract_usd.sim import Control, GridSpec, Rollout, SimModel, SimState
from physinteract_usd.sim.solver import MPMSolver
from physinteract_usd.simulation import grid_covering, sim_contact
from sim_helpers import block

pytestmark = pytest.mark.usefixtures("one_torch_thread")

DX = 0.02


def settings(x0: np.ndarray, pad: float = 0.3) -> SimSettings:
    """A stage's domain as init makes it: the object's box + pad x its extent (and the stencil's cell)."""
    ext = float(np.ptp(x0, 0).max())
    lo = x0.min(0) - pad * ext - DX
    res = tuple(int(v) for v in np.ceil((x0.max(0) + pad * ext + 2 * DX - lo) / DX))
    return SimSettings(domain_min=lo, domain_max=lo + np.array(res) * DX, grid_resolution=res, cell_size=DX,
                       particle_spacing=DX / 2, substeps=10)


def rollout(x0, contacts, grid, fps, T, E):
    m = SimModel.create(x0, 1e-6, 1000.0, E, 0.3, grid=grid, fps=fps, E_max=E, dtype="float32")
    ro = Rollout(m, Control([sim_contact(c) for c in contacts], n_frames=T - 1))
    with torch.no_grad():
        x, _ = ro(torch.full((len(x0),), E), torch.full((len(x0),), 0.3))
    return x.numpy(), m


def test_a_bar_pinned_at_one_end_swings_down_inside_the_automatic_domain():
    fps, T = 30.0, 10
    x0 = block((12, 2, 2), 0.01, (0.0, 0.3, 0.0))                 # 11 cm long, horizontal at rest
    pin = np.where(x0[:, 0] < 0.01)[0]
    cs = [ContactSet("support", "fixed", pin)]
    st = settings(x0)
    auto = grid_covering(st, x0, [], contacts=cs, fps=fps, n_frames=T)
    x, _ = rollout(x0, cs, auto, fps, T, 1e4)                     # no SimulationError
    tip = int(np.argmax(x0[:, 0]))
    pivot = x0[pin].mean(0)
    L = float(np.linalg.norm(x0[tip] - pivot))
    assert np.isfinite(x).all()
    # the tip swings down to the rigid pendulum's reach, L below the pin (it is 8 cm below its rest at frame 5)
    assert abs(float(x[:, tip, 1].min()) - (pivot[1] - L)) < DX
    assert x[:, tip, 1].min() < x0[tip, 1] - 0.08
    # the stage's own domain (the hand's rule alone: no hand here) is left at the frame the swing crosses its
    # valid box (the same lattice: the same rollout until then), and said so
    own = grid_covering(st, x0, [])
    out = np.any((x < own.valid_lower) | (x >= own.valid_upper), axis=(1, 2))
    k = int(np.argmax(out))
    assert out.any() and k >= 2
    with pytest.raises(SimulationError) as ei:
        rollout(x0, cs, own, fps, T, 1e4)
    e = ei.value
    assert e.kind == "domain" and e.frame == k and "left the grid" in str(e) and f"at frame {k}" in str(e)
    assert "face" in e.problem and "cells" in e.problem and "non-finite" not in e.problem
    assert e.face and f"nearest the {e.face} face" in e.problem


def test_a_block_let_go_falls_half_g_t2_inside_the_automatic_domain():
    fps, T, release = 50.0, 6, 1
    x0 = block((6, 6, 6), 0.01, (0.0, 0.3, 0.0))
    hand = ContactSet("hand", "pointAdherent", np.arange(len(x0)), 0, release, np.repeat(x0.mean(0)[None], T, 0))
    st = settings(x0, pad=0.1)
    auto = grid_covering(st, x0, [hand.trajectory], contacts=[hand], fps=fps, n_frames=T)
    x, m = rollout(x0, [hand], auto, fps, T, 1e4)
    drop = x0[:, 1].mean() - x[:, :, 1].mean(1)
    n = (np.arange(T) - release).clip(0) * m.substeps              # free substeps after the release
    g = 9.81
    assert np.allclose(drop, g * m.dt ** 2 * n * (n + 1) / 2, atol=2e-5)     # held, then the discrete free fall
    t = n * m.dt
    assert np.abs(drop - 0.5 * g * t ** 2).max() < 0.05 * DX        # = 1/2 g t^2 to the half step
    assert drop[-1] > 1.5 * DX                                      # it fell 3 cm: past the old domain's floor
    with pytest.raises(SimulationError) as ei:                      # the hand's rule alone: left at frame 5
        rollout(x0, [hand], grid_covering(st, x0, [hand.trajectory]), fps, T, 1e4)
    assert ei.value.kind == "domain" and "left the grid" in str(ei.value) and ei.value.frame is not None
    assert ei.value.face == "-y" and "nearest the -y face" in str(ei.value)     # it fell: the bottom, said and kept


def test_the_ground_bounds_the_fall_and_a_hanging_bar_pulled_a_little_keeps_its_grid():
    fps, T = 50.0, 40                                               # a long fall: 0.6 s
    x0 = block((6, 6, 6), 0.01, (0.0, 0.3, 0.0))
    hand = ContactSet("hand", "pointAdherent", np.arange(len(x0)), 0, 1, np.repeat(x0.mean(0)[None], T, 0))
    st = settings(x0, pad=0.1)
    free = grid_covering(st, x0, [hand.trajectory], contacts=[hand], fps=fps, n_frames=T)
    floor = grid_covering(st, x0, [hand.trajectory], contacts=[hand], fps=fps, n_frames=T,
                          effects={"ground": {"height": 0.27}})
    ext = float(np.ptp(x0, 0).max())
    assert free.lower[1] < st.domain_min[1] - 0.9 * ext              # capped (REACH_CAP x the extent), not 1.7 m
    assert 0.27 - 3 * DX <= floor.lower[1] < 0.27                    # down to the ground and the stencil's room
    # a bar hanging from a clip, its lower end pulled 2 cm aside and let go: inside the hand's rule, no growth
    bar = block((2, 12, 2), 0.01, (0.0, 0.2, 0.0))
    top = np.where(bar[:, 1] > bar[:, 1].max() - 0.005)[0]
    low = np.where(bar[:, 1] < bar[:, 1].min() + 0.015)[0]
    tr = np.repeat(bar[low].mean(0)[None], 10, 0)
    tr[1:5, 0] += np.linspace(0.005, 0.02, 4)
    tr[5:, 0] += 0.02
    cs = [ContactSet("clip", "fixed", top), ContactSet("hand", "pointAdherent", low, 1, 5, tr)]
    s2 = settings(bar)
    assert grid_covering(s2, bar, [tr], contacts=cs, fps=20.0, n_frames=10) == grid_covering(s2, bar, [tr])


def test_a_block_blowing_up_past_the_face_is_reported_as_left_the_grid_not_unstable():
    """Thrown at the +x face with no stress to speak of: its stencils clamp at the face and it goes non-finite
    about a cell past it within the frame. The frame's end saw only the non-finite state ("dt too large") before."""
    x0 = block((4, 4, 4), 0.01, (0.1, 0.1, 0.1))
    msgs = {}
    for check in (True, False):
        m = SimModel.create(x0, 1e-6, 1000.0, 1e4, 0.3, grid=GridSpec((0.0, 0.0, 0.0), DX, (12, 12, 12)), fps=2.0,
                            E_max=1e4, gravity=(0, 0, 0), dtype="float64", stencil_check=check)
        with pytest.raises(SimulationError) as ei:
            MPMSolver(m).simulate(2, SimState.rest(m, v0=(1.0, 0, 0)))
        msgs[check] = ei.value
    e = msgs[True]
    assert e.kind == "domain" and e.frame == 1 and "left the grid" in e.problem and "+x face" in e.problem
    assert "went non-finite after it" in e.problem and "dt" not in e.advice
    assert msgs[False].kind == "unstable" and "non-finite" in msgs[False].problem      # the old reading


@pytest.mark.parametrize("frame_graphs,gpu_paths", [(False, False), (True, False), (True, True)])
def test_left_the_grid_through_captured_frame_graphs_and_the_fused_kernels(monkeypatch, frame_graphs, gpu_paths):
    """The mark travels through the status row the frame-shape graphs copy (sim/frame_graphs.py) and is written by
    the fused p2g (the GPU's kernels, run on the CPU): the same frame and count as the eager per-frame path."""
    from physinteract_usd.sim import rollout as rollout_mod
    from physinteract_usd.sim import solver as solver_mod

    monkeypatch.setattr(rollout_mod, "FRAME_GRAPHS", frame_graphs)
    monkeypatch.setattr(rollout_mod, "EAGER_FORWARDS", 0)             # capture the first forward
    for flag in ("FUSED_ZERO", "FUSED_KERNELS", "GRID_BOX"):
        monkeypatch.setattr(solver_mod, flag, gpu_paths)
    x0 = block((4, 4, 4), 0.01, (0.1, 0.1, 0.1))
    m = SimModel.create(x0, 1e-6, 1000.0, 1e4, 0.3, grid=GridSpec((0.0, 0.0, 0.0), DX, (12, 12, 12)), fps=10.0,
                        E_max=1e4, gravity=(0, 0, 0), dtype="float64")
    ro = Rollout(m, Control([], n_frames=3), graphs=True)
    assert ro.frame_graphs is frame_graphs
    P = len(x0)
    v0 = torch.tensor([[1.0, 0.0, 0.0]] * P, dtype=torch.float64)
    for _ in range(2):                                              # the capture, then a replay
        with pytest.raises(SimulationError) as ei, torch.no_grad():
            ro(torch.full((P,), 1e4, dtype=torch.float64), torch.full((P,), 0.3, dtype=torch.float64), v0=v0)
        e = ei.value
        assert e.kind == "domain" and e.frame == 1 and "+x face" in e.problem
        marks = ro.status.numpy()[0]
        assert marks[4] > 0 and marks[5] > 1            # walked past mid-frame: marked by p2g, counted by the check


def test_a_particle_flung_off_alone_reads_left_the_grid_alone_and_a_non_finite_one_says_where_it_stood():
    """#24 dev_0255 (15k particles): a stray fill particle flung off by the released sheet's snap flew alone, F = I,
    to a face. The error now says it was alone (no other particle within its stencil) and what that means; a
    non-finite particle's message gives its speed, J, stretch, nearest neighbour and walls at the frame's start."""
    x0 = np.concatenate([block((4, 4, 4), 0.01, (0.06, 0.06, 0.06)), [[0.16, 0.11, 0.11]]])
    P = len(x0)
    m = SimModel.create(x0, 1e-6, 1000.0, 1e4, 0.3, grid=GridSpec((0.0, 0.0, 0.0), DX, (12, 12, 12)), fps=10.0,
                        E_max=1e4, gravity=(0, 0, 0), dtype="float64")
    ro = Rollout(m, Control([], n_frames=3), graphs=False)
    v0 = torch.zeros((P, 3), dtype=torch.float64)
    v0[-1, 0] = 0.5                                                 # the lone one, 4 cells from the block, to +x
    with pytest.raises(SimulationError) as ei, torch.no_grad():
        ro(torch.full((P,), 1e4, dtype=torch.float64), torch.full((P,), 0.3, dtype=torch.float64), v0=v0)
    e = ei.value
    assert e.kind == "domain" and "+x face" in e.problem and f"particle {P - 1}" in e.problem
    assert "alone: it had come off the object" in e.problem and "flung off the object alone" in e.advice
    # the block itself thrown at the face (test above): not alone, no such words
    m2 = SimModel.create(x0[:-1], 1e-6, 1000.0, 1e4, 0.3, grid=GridSpec((0.0, 0.0, 0.0), DX, (12, 12, 12)), fps=2.0,
                         E_max=1e4, gravity=(0, 0, 0), dtype="float64")
    with pytest.raises(SimulationError) as ei2:
        MPMSolver(m2).simulate(2, SimState.rest(m2, v0=(1.0, 0, 0)))
    assert ei2.value.kind == "domain" and "alone" not in str(ei2.value)
    # a non-finite particle's note (solver.bad_particle_note): where it stood at its frame's start
    sol = MPMSolver(m)
    st = {"x": x0, "v": v0.numpy(), "F": np.repeat(np.eye(3)[None], P, 0)}
    note = sol.bad_particle_note(P - 1, st)
    assert "speed 0.5 m/s" in note and "J 1," in note and "nearest other particle 3.42 cells (a lone particle" in note
    assert "cells inside the +x face" in note
    assert sol.bad_particle_note(0, st).count("lone") == 0 and sol.bad_particle_note(0, None) == ""
