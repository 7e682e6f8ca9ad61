"""Known answers for the material fit: a clamped bar, lifted by a hand and let go, swinging and
sagging under gravity (tests/fit_scene.py), rendered by our own simulator at E = 1e4, 1e5 and
1e6 Pa; the fit, started from nothing but the allowed range (1e3 .. 1e7 Pa, four decades), must
recover E within 10%. The density scales with E (E / rho = 200 m^2/s^2), so every bar sags ~2 cm
and swings at ~5 Hz: what is tested is that the whole range is searched and resolved, at the same
cost, from the free motion after the release (what carries E for a stiff object) and the sag.

And the simulator against beam theory at the same, coarse resolution (two cells through the
thickness): the Euler-Bernoulli cantilever's static tip sag q L^4 / (8 E I) and first frequency
(1.875^2 / 2 pi) sqrt(E I / (rho A L^4)) (a stated tolerance: MPM this coarse is softer than the
beam; docs/benchmarks/fit.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd import api

pytestmark = pytest.mark.usefixtures("one_torch_thread")

E_OVER_RHO = 200.0
LIFT = np.array([0.0, 0.03, 0.0])


@pytest.mark.parametrize("E", [1e4, 1e5, 1e6])
def test_uniform_e_recovered_across_three_decades(E, tmp_path):
    b = fs.build(tmp_path / "bar", E=E, density=E / E_OVER_RHO, n_frames=12, release=4, e_range=(1e3, 1e7),
                 lift=LIFT)
    settings = dict(schedule="ladder", max_regions=1, sweep_points=7, search_evals=5, confidence_probes=0,
                    uniform_share=0.6, final_share=0.4, lr_material=0.1)
    out = api.fit(b["stage"], iterations=10, contact_from=b["gt"], joint=False, progress=False,
                  log=lambda *a: None, settings_overrides=settings)
    e = float(np.median(out.result.youngs))
    assert abs(e / E - 1) < 0.10, (E, e, out.result.model.get("uniform_sweep"))


def cantilever_vs_beam_theory(tmp_path, T: int = 80, fps: float = 240.0, grid=fs.GRID):
    """The bar clamped at its left end (two grid cells thick), released from straight at rest,
    simulated with the stage's simulator: (tip sag / q L^4 / (8 E I), first frequency / the
    Euler-Bernoulli cantilever's). The sag is half the first lowest point (the swing's middle),
    the period from the first two lowest points."""
    import dataclasses

    from physinteract_usd.simulation import build_simulation
    from physinteract_usd.usd.stage import read_stage

    E, rho = 1e5, 1e5 / E_OVER_RHO
    b = fs.build(tmp_path / "beam", E=E, density=rho, n_frames=4, release=1, e_range=(1e3, 1e7), lift=0 * LIFT,
                 grid=grid)
    sd = dataclasses.replace(read_stage(b["stage"]), end_frame=T - 1, fps=fps)
    hand, support = fs.contacts(sd, lift=0 * LIFT, release=1)
    sim = build_simulation(sd, [hand.replace(trajectory=np.repeat(hand.trajectory[:1], T, 0)), support], T)
    P = len(sd.particles_positions)
    with torch.no_grad():
        x, _ = sim.simulate(torch.full((P,), E), torch.full((P,), fs.NU_TRUE))
    x = x.numpy()
    free = np.setdiff1d(np.arange(P), support.indices)
    tip = free[np.argsort(sd.particles_positions[free, 0])[-10:]]
    y = x[:, tip, 1].mean(1) - x[0, tip, 1].mean()
    # the clamp's face: the support's right edge; the free length from there to the bar's end
    L = float(sd.particles_positions[:, 0].max() - sd.particles_positions[support.indices, 0].max())
    h = fs.THICK
    sag = 1.5 * rho * 9.81 * L ** 4 / (E * h ** 2)          # q L^4 / (8 E I), q = rho g h^2, I = h^4 / 12
    f1 = 1.875 ** 2 / (2 * math.pi) * math.sqrt(E * h ** 2 / 12 / (rho * L ** 4))
    lows = [k for k in range(1, T - 1) if y[k] < y[k - 1] and y[k] <= y[k + 1]]
    assert len(lows) >= 2, "the tip does not swing twice"
    period = (lows[1] - lows[0]) / sd.fps
    return -0.5 * y[lows[0]] / sag, (1.0 / period) / f1


def test_cantilever_with_the_clamp_band_against_beam_theory(tmp_path, monkeypatch):
    """The simulator against beam theory at the fit's coarse resolution (two cells through the
    thickness), the clamp's grid blend a band (simulation.CLAMP_BAND): first frequency within 10%,
    static sag within 25% (the sag read from one swing)."""
    from physinteract_usd import simulation

    monkeypatch.setattr(simulation, "PIN_RULE", simulation.CLAMP_BAND)
    sag, f = cantilever_vs_beam_theory(tmp_path)
    assert abs(f - 1) < 0.10, f
    assert abs(sag - 1) < 0.25, sag


@pytest.mark.xfail(strict=True, reason="the default clamp rule (a quarter held -> fully held) stiffens a "
                   "two-cell-thick cantilever: 1.47x the frequency, 0.3x the sag (issue #24)")
def test_cantilever_with_the_default_clamp_against_beam_theory(tmp_path):
    sag, f = cantilever_vs_beam_theory(tmp_path)
    assert abs(f - 1) < 0.10, f
    assert abs(sag - 1) < 0.25, sag


def test_resolution_is_the_lever_for_bending(tmp_path):
    """The same cantilever (default clamp rule) at the coarse grid (10 cells: two across the 50 mm
    section) and at `init --grid auto`'s (24: ~5 across): the first frequency and the sag come
    toward beam theory's (measured: 1.47x / 0.30x at 10, 1.21x / 0.59x at 16, 1.11x / 0.77x at
    auto; docs/init.md)."""
    coarse_sag, coarse_f = cantilever_vs_beam_theory(tmp_path / "coarse")
    sag, f = cantilever_vs_beam_theory(tmp_path / "auto", grid="auto")
    assert abs(f - 1) < 0.15 and abs(f - 1) < 0.5 * abs(coarse_f - 1), (f, coarse_f)
    assert abs(sag - 1) < 0.3 and abs(sag - 1) < 0.5 * abs(coarse_sag - 1), (sag, coarse_sag)
