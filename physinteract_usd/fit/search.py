"""One-dimensional searches the fit's start-ups share (no gradients)."""

from __future__ import annotations

import math

from ..errors import SimulationError

GOLDEN = (math.sqrt(5) - 1) / 2


def golden_section(f, a: float, b: float, evals: int) -> tuple[float, float]:
    """Golden-section search for a minimum of `f` on [a, b] with `evals` evaluations of `f` (the
    caller's `f` keeps what it saw); a non-finite value loses to a finite one. Returns the final
    bracket."""
    c, d = b - GOLDEN * (b - a), a + GOLDEN * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(max(int(evals) - 2, 0)):
        if fc < fd or (math.isfinite(fc) and not math.isfinite(fd)):
            b, d, fd = d, c, fc
            c = b - GOLDEN * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + GOLDEN * (b - a)
            fd = f(d)
    return a, b


def no_finite_uniform_probe() -> SimulationError:
    """The error of a start-up whose every uniform-E probe went unstable or left the grid."""
    return SimulationError("went unstable or left the grid at every uniform E tried", frame=None,
                           advice="check the contacts (extract) and the Young's modulus range (init "
                                  "--youngs-range); a wider grid padding (init --padding) if the object "
                                  "leaves the domain")
