"""How the simulation depends on its time step (#24; benchmarks/dt_convergence.py, docs/benchmarks/fit.md
"The time step's dependence is the transfer's dissipation").

Known answers on a clamped cantilever under gravity (float64; E 22.6 kPa, rho 150, nu 0.4: telephone_cable's
range): the elastic part of the step converges in dt (first frequency and mean sag the same at 150 and 300
substeps a frame, within 5% of Euler-Bernoulli), while the ringing's decay per period, which the undamped
continuum does not have, doubles when the substeps double: APIC's grid -> particle -> grid projection drops
a share of the motion once per substep, whatever the substep. With that projection acting at a rate per unit
time instead (the benchmark's host-side RateTransfer) the decay nearly stops depending on the step."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def bench():
    sys.path.insert(0, str(BENCH))
    try:
        import dt_convergence
        yield dt_convergence
    finally:
        sys.path.remove(str(BENCH))


def _run(bench, substeps, transfer="apic", frames=12, samples=4):
    y, _ = bench.simulate(substeps, transfer, frames, per_frame=samples)
    return bench.analyse(y, bench.FPS * samples)


def test_elastic_part_converges_and_the_transfer_dissipation_is_per_substep(bench):
    sag, f1 = bench.beam()
    a = _run(bench, 150)
    b = _run(bench, 300)
    for r in (a, b):
        assert r["lows"] >= 3
        assert 1.0 / r["period_s"] / f1 == pytest.approx(1.0, abs=0.05)
        assert r["mean_sag_m"] / sag == pytest.approx(1.0, abs=0.06)
    assert b["period_s"] == pytest.approx(a["period_s"], rel=0.01)
    assert b["mean_sag_m"] == pytest.approx(a["mean_sag_m"], rel=0.03)
    # the continuum rings undamped; the method's decay per period is ~0.08 at 150 substeps a frame and
    # twice that at 300: a share lost per substep (doubling the substeps doubles the dissipation)
    assert a["log_decrement"] > 0.04
    assert 1.7 < b["log_decrement"] / a["log_decrement"] < 2.3


@pytest.mark.slow      # the benchmark's host-side prototype (numpy per substep): ~10 CPU s
def test_a_rate_transfer_takes_the_step_out_of_the_decay(bench):
    a = _run(bench, 150, "rate:0.01")
    b = _run(bench, 300, "rate:0.01")
    apic = _run(bench, 150)
    assert a["log_decrement"] < 0.4 * apic["log_decrement"]
    assert b["log_decrement"] - a["log_decrement"] < 0.3 * apic["log_decrement"]
    assert b["period_s"] == pytest.approx(a["period_s"], rel=0.01)
