"""Known answers for the material fit: a clamped bar, lifted by a hand and let go, swinging and
sagging under gravity (tests/fit_scene.py), rendered by our own simulator at E = 1e4, 1e5 and
1e6 Pa; the fit, started from nothing but the allowed range (1e3 .. 1e7 Pa, four decades), must
recover E within 10%. The density scales with E (E / rho = 200 m^2/s^2), so every bar sags ~2 cm
and swings at ~5 Hz: what is tested is that the whole range is searched and resolved, at the same
cost, from the free motion after the release (what carries E for a stiff object) and the sag.

And the simulator against beam theory: the bar clamped at one end (L / h ~ 2.3: a stubby
beam, so Timoshenko's, with shear and rotary inertia, not Euler-Bernoulli's), its static tip sag
and first frequency at E 1e4, 1e5 and 1e6 Pa within 10%, at 3 cells through the thickness, with
the clamp band pin rule (simulation.CLAMP_BAND); the default pin rule's bias is a strict xfail
(docs/benchmarks/fit.md)."""

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


def test_uniform_e_recovered_from_a_preloaded_scan(tmp_path):
    # init --preload (sim.preload): the scan is the bar already carrying its weight on the clamp; the truth is rendered
    # from it prestressed, the fit's every forward starts prestressed at its E (the stretch's gradient through the
    # whole fit): E from the lift and the free swing alone, the sag no longer a cue, within 10%
    E = 1e5
    b = fs.build(tmp_path / "bar", E=E, density=E / E_OVER_RHO, n_frames=12, release=4, e_range=(1e3, 1e7),
                 lift=LIFT, preload=True)
    settings = dict(schedule="ladder", max_regions=1, sweep_points=7, search_evals=5, confidence_probes=0,
                    uniform_share=0.6, final_share=0.4, lr_material=0.1)
    out = api.fit(b["stage"], iterations=10, contact_from=b["gt"], joint=False, progress=False,
                  log=lambda *a: None, settings_overrides=settings)
    assert api.read_scene(b["stage"]).settings.preload
    e = float(np.median(out.result.youngs))
    assert abs(e / E - 1) < 0.10, (E, e, out.result.model.get("uniform_sweep"))


def timoshenko_cantilever(L: float, h: float, nu: float, n: int = 200) -> tuple[float, float]:
    """A Timoshenko cantilever (square section h x h, length L, shear coefficient 5/6, rotary
    inertia) against Euler-Bernoulli's: (tip sag under its own weight / q L^4 / (8 E I), first
    frequency / (1.875^2 / 2 pi) sqrt(E I / (rho A L^4))), by n two-node elements (linear w and
    theta, the shear at the element's midpoint: no locking). The bar here is stubby (L / h ~ 2.3):
    its shear adds ~19% to the sag and takes ~12% off the frequency, so Euler-Bernoulli is not its
    known answer. The sag agrees with the closed form q L^4 / (8 E I) + q L^2 / (2 kappa G A)."""
    import scipy.linalg

    E, rho, kappa = 1.0, 1.0, 5.0 / 6.0
    G, A, I, le = E / (2 * (1 + nu)), h * h, h ** 4 / 12, L / n
    N = 2 * (n + 1)
    K, M, q = np.zeros((N, N)), np.zeros((N, N)), np.zeros(N)
    B = np.array([-1 / le, -0.5, 1 / le, -0.5])                # shear strain w' - theta at the midpoint
    kb = E * I / le * np.array([[0, 0, 0, 0], [0, 1, 0, -1], [0, 0, 0, 0], [0, -1, 0, 1]])
    m = 0.5 * le * rho * np.diag([A, I, A, I])
    for e in range(n):
        d = np.arange(2 * e, 2 * e + 4)
        K[np.ix_(d, d)] += kb + kappa * G * A * le * np.outer(B, B)
        M[np.ix_(d, d)] += m
        q[d[[0, 2]]] += 0.5 * rho * A * le
    K, M, q = K[2:, 2:], M[2:, 2:], q[2:]                      # the clamped end's w and theta
    sag = np.linalg.solve(K, q)[-2]
    lam = scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=[0, 0])[0]
    return sag / (rho * A * L ** 4 / (8 * E * I)), math.sqrt(lam) / (1.875104 ** 2 * math.sqrt(E * I / (rho * A * L ** 4)))


def cantilever_vs_beam_theory(tmp_path, T: int = 100, fps: float = 240.0, grid=fs.GRID, E: float = 1e5,
                              theory: str = "timoshenko"):
    """The bar clamped at its left end, released from straight at rest, simulated with the
    stage's simulator: (tip sag / the beam's, first frequency / the beam's), the beam Timoshenko's
    (`timoshenko_cantilever`) or, with theory="euler", Euler-Bernoulli's. The sag is the tip's mean
    over whole periods (from the first lowest point to the last one: the swing is damped, ~5% per
    period at grid 16, so half the first lowest point reads 5-15% low), the frequency from the mean
    period between lowest points, each placed by a parabola through its neighbours. E / rho is
    fixed (200 m^2/s^2): the sag and the frequency do not depend on E itself."""
    import dataclasses

    from physinteract_usd.simulation import build_simulation
    from physinteract_usd.usd.stage import read_stage

    rho = E / E_OVER_RHO
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
    if theory == "timoshenko":
        s_t, f_t = timoshenko_cantilever(L, h, fs.NU_TRUE)
        sag, f1 = sag * s_t, f1 * f_t
    lows = [k for k in range(1, T - 1) if y[k] < y[k - 1] and y[k] <= y[k + 1]]
    assert len(lows) >= 2, "the tip does not swing twice"

    def when(k):
        den = y[k - 1] - 2 * y[k] + y[k + 1]
        return k + (0.5 * (y[k - 1] - y[k + 1]) / den if den > 0 else 0.0)

    period = (when(lows[-1]) - when(lows[0])) / (len(lows) - 1) / sd.fps
    return -float(y[lows[0]:lows[-1]].mean()) / sag, (1.0 / period) / f1


def test_timoshenko_reference_matches_its_closed_form_and_euler_for_a_slender_bar():
    """The reference: the sag against q L^4 / (8 E I) + q L^2 / (2 kappa G A); a slender bar is
    Euler-Bernoulli's (sag and frequency within 0.5% at L / h = 20)."""
    nu, h = 0.3, 0.05
    for L in (0.116, 0.5):
        s, _ = timoshenko_cantilever(L, h, nu)
        assert s == pytest.approx(1 + 2 * (1 + nu) * h ** 2 / (3 * (5 / 6) * L ** 2), rel=2e-3)
    s, f = timoshenko_cantilever(1.0, h, nu)
    assert abs(s - 1) < 5e-3 and abs(f - 1) < 5e-3
    s, f = timoshenko_cantilever(0.116, h, nu)
    assert 1.15 < s < 1.25 and 0.85 < f < 0.92, (s, f)       # the stubby test bar: far from Euler-Bernoulli


@pytest.mark.parametrize("E", [1e4, 1e5, 1e6])
def test_cantilever_with_the_clamp_band_against_beam_theory(tmp_path, monkeypatch, E):
    """The simulator against the Timoshenko beam at 3 cells through the thickness (grid 16), the
    clamp's grid blend a band (simulation.CLAMP_BAND): first frequency and static sag within 10%,
    at E 1e4, 1e5 and 1e6 Pa (measured 2026-11-26: 1.02x / 0.98-0.99x at each; docs/benchmarks/fit.md)."""
    from physinteract_usd import simulation

    monkeypatch.setattr(simulation, "PIN_RULE", simulation.CLAMP_BAND)
    sag, f = cantilever_vs_beam_theory(tmp_path, grid=16, E=E)
    assert abs(f - 1) < 0.10, f
    assert abs(sag - 1) < 0.10, sag


def test_cantilever_with_the_band_as_the_support_rule_against_beam_theory(tmp_path, monkeypatch):
    """The band as the supports' own rule (simulation.SUPPORT_RULE; the grasps keep the default): the clamp is a fixed
    contact, so the beam is the band's (within 10% of Timoshenko at grid 16, E 1e5)."""
    from physinteract_usd import simulation

    monkeypatch.setattr(simulation, "PIN_RULE", simulation.DEFAULT_PIN_RULE)
    monkeypatch.setattr(simulation, "SUPPORT_RULE", simulation.CLAMP_BAND)
    sag, f = cantilever_vs_beam_theory(tmp_path, grid=16, E=1e5)
    assert abs(f - 1) < 0.10, f
    assert abs(sag - 1) < 0.10, sag


@pytest.mark.xfail(strict=True, reason="the default clamp rule (a quarter held -> fully held) moves the clamp's face "
                   "~0.75 cell out: the beam's free length shorter, 1.36x the frequency and 0.57x the sag at grid 16 "
                   "(1.24x / 0.68x at grid auto, 1.16x / 0.79x at grid 32; docs/benchmarks/fit.md, issue #24)")
def test_cantilever_with_the_default_clamp_against_beam_theory(tmp_path):
    sag, f = cantilever_vs_beam_theory(tmp_path, grid=16)
    assert abs(f - 1) < 0.10, f
    assert abs(sag - 1) < 0.10, sag


def test_resolution_is_the_lever_for_bending(tmp_path):
    """The same cantilever (default clamp rule) at the coarse grid (10 cells: two across the 50 mm
    section) and at `init --grid auto`'s (24: ~5 across): the first frequency and the sag come
    toward the beam's, but slowly: the default rule's clamp face sits ~0.75 cell out (measured
    against Timoshenko: 1.69x / 0.32x at 10, 1.36x / 0.57x at 16, 1.24x / 0.68x at auto, 1.16x /
    0.79x at 32; docs/benchmarks/fit.md)."""
    coarse_sag, coarse_f = cantilever_vs_beam_theory(tmp_path / "coarse")
    sag, f = cantilever_vs_beam_theory(tmp_path / "auto", grid="auto")
    assert abs(f - 1) < 0.6 * abs(coarse_f - 1), (f, coarse_f)
    assert abs(sag - 1) < 0.6 * abs(coarse_sag - 1), (sag, coarse_sag)


def test_the_pin_rule_setting_reads_default_band_or_a_pair_and_refuses_others():
    """PHYSINTERACT_PIN_RULE (read by `simulation` at import): the default unless set; "band" the
    clamp band the cantilever passes with; "GAIN,FLOOR" any rule; anything else a one-line error
    naming the setting."""
    import os

    from physinteract_usd import simulation as S

    assert S.pin_rule(None) == S.pin_rule("") == S.pin_rule("Default") == S.DEFAULT_PIN_RULE == (4.0, 0.0)
    assert S.pin_rule("band") == S.CLAMP_BAND and S.pin_rule(" 1, 0 ") == (1.0, 0.0)
    for bad in ("clamp", "5", "0,0.2", "5,1.0"):
        with pytest.raises(ValueError, match="PHYSINTERACT_PIN_RULE"):
            S.pin_rule(bad)
    assert S.PIN_RULE == S.pin_rule(os.environ.get("PHYSINTERACT_PIN_RULE"))
