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


class UniformProbe:
    """The reconstruction loss at one uniform E, called with log E (no gradients) and cached per
    log E in `cache`. `loss_of(E)` takes the (P,) tensor of that E and returns the loss. A probe
    that goes unstable, leaves the grid or gives a non-finite loss is inf: it is logged and its E
    appended to `skipped`, so a search moves away from it and never returns it."""

    def __init__(self, loss_of, n: int, dtype, device, log=None, skipped: list | None = None):
        self.loss_of, self.n, self.dtype, self.device = loss_of, int(n), dtype, device
        self.log, self.skipped = log, skipped
        self.cache: dict[float, float] = {}

    def __call__(self, le) -> float:
        import torch

        le = float(le)
        if le in self.cache:
            return self.cache[le]
        E = torch.full((self.n,), math.exp(le), dtype=self.dtype, device=self.device)
        why = ""
        try:
            with torch.no_grad():
                v = float(self.loss_of(E))
            if not math.isfinite(v):
                why = f"loss {v}"
        except SimulationError as exc:
            v, why = float("inf"), exc.kind or "unstable"
        if why:
            v = float("inf")
            if self.skipped is not None:
                self.skipped.append(math.exp(le))
            if self.log:
                self.log(f"uniform E {math.exp(le):.4g} Pa: the simulation went unstable or left the grid ({why}): "
                         "skipped")
        elif self.log:
            self.log(f"uniform E {math.exp(le):.4g} Pa: loss {v:.5f}")
        self.cache[le] = v
        return v
