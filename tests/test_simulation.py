"""simulation.build_simulation: the substep follows the field being simulated (the CFL bound at its
largest E, not at the top of the allowed range), and a rollout at the field's substep agrees with
one at the range's (finer) substep."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd.sim.cfl import substeps_per_frame
from physinteract_usd.simulation import CFL, build_simulation
from physinteract_usd.usd.stage import read_stage

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    built = fs.build(tmp_path_factory.mktemp("sim") / "bar")
    sd = read_stage(built["stage"])
    return sd, fs.contacts(sd)


def test_substep_follows_the_field_and_agrees_with_the_range_top(bar):
    sd, contacts = bar
    st = sd.settings
    P = len(sd.particles_positions)
    E = torch.full((P,), fs.E_TRUE, dtype=torch.float32)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float32)
    fixed = build_simulation(sd, contacts, adaptive_substeps=False)
    adaptive = build_simulation(sd, contacts)
    with torch.no_grad():
        x_ref, _ = fixed.simulate(E, nu)
        x, _ = adaptive.simulate(E, nu)
    assert fixed.substeps == st.substeps
    # the rung above E_TRUE (5e3) on a sqrt(2) ladder below the range's top (5e4): far fewer substeps
    assert fs.E_TRUE <= adaptive.e_bound < np.sqrt(2) * fs.E_TRUE
    cfl = substeps_per_frame(sd.fps, st.cell_size, adaptive.e_bound, st.poisson_max, st.density, cfl=CFL)
    assert adaptive.substeps == cfl < 0.5 * st.substeps
    x, x_ref = x.numpy(), x_ref.numpy()
    moved = float(np.abs(x_ref[-1] - x_ref[0]).max())
    assert moved > 0.01                                           # the bar really moves (1 cm and more)
    assert float(np.abs(x - x_ref).max()) < 0.05 * moved          # the coarser stable step agrees


def test_a_stiffer_field_rebuilds_the_model_with_more_substeps(bar):
    sd, contacts = bar
    P = len(sd.particles_positions)
    sim = build_simulation(sd, contacts)
    nu = torch.full((P,), fs.NU_TRUE, dtype=torch.float32)
    with torch.no_grad():
        sim.simulate(torch.full((P,), 2e3), nu)
        soft = sim.substeps
        x, _ = sim.simulate(torch.full((P,), 0.9 * sd.settings.youngs_max), nu)   # no SimulationError
        assert sim.substeps > 2 * soft and torch.isfinite(x).all()
        sim.simulate(torch.full((P,), 2e3), nu)                   # back down: the softer rung again
    assert sim.substeps == soft
