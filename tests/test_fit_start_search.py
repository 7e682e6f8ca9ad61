"""The fit's uniform start search (the default schedule's golden-section search) never returns or
keeps a non-finite loss: a probe whose simulation goes unstable or leaves the grid, or whose loss is
not finite, is reported and skipped; when the first probes all fail, a sweep finds where the
simulation holds; when nothing holds, a SimulationError says so (not a silent inf)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from physinteract_usd.errors import SimulationError
from physinteract_usd.fit.material import MaterialField
from physinteract_usd.fit.optimize import golden_uniform_search


class Stub:
    """A problem whose loss is (log E - log E*)^2, unstable above `unstable` (SimulationError, as the
    simulator raises when a particle leaves the grid) and NaN below `nan_below`."""

    def __init__(self, e_star, unstable=math.inf, nan_below=0.0):
        self.e_star, self.unstable, self.nan_below = e_star, unstable, nan_below
        self.calls = []

    def loss(self, E, nu):
        e = float(E[0])
        self.calls.append(e)
        if e > self.unstable:
            raise SimulationError("a particle left the grid domain", frame=3, kind="domain")
        if e < self.nan_below:
            return {"rec": torch.tensor(float("nan"))}
        return {"rec": torch.tensor((math.log(e) - math.log(self.e_star)) ** 2)}


def _mat(lo=1e3, hi=1e6):
    return MaterialField(np.random.default_rng(0).random((20, 3)), (lo, hi), 0.45, dtype=torch.float64)


@pytest.mark.parametrize("unstable,nan_below", [(5e4, 0.0), (math.inf, 2e4), (5e4, 2e4)])
def test_unstable_and_nan_probes_are_reported_and_skipped(unstable, nan_below):
    # 1e3..1e6 Pa: the first two probes are at ~1.5e4 and ~6.5e4 Pa
    prob = Stub(e_star=3e4, unstable=unstable, nan_below=nan_below)
    logs, skipped = [], []
    e, loss = golden_uniform_search(prob, _mat(), 12, log=logs.append, with_loss=True, skipped=skipped)
    assert math.isfinite(loss) and abs(math.log(e / 3e4)) < 0.3
    # the failing probes were skipped and said so
    bad = [c for c in prob.calls if c > unstable or c < nan_below]
    assert bad and sorted(skipped) == sorted(bad)
    assert sum("skipped" in m for m in logs) == len(bad)
    assert not any("inf" in m or "nan" in m for m in logs if "skipped" not in m)


def test_both_first_probes_unstable_a_sweep_finds_the_stable_end():
    # stable only below 4e3 Pa (a narrow window at the low end of 1e3..1e6): both golden probes fail
    prob = Stub(e_star=2e3, unstable=4e3)
    skipped = []
    e, loss = golden_uniform_search(prob, _mat(), 8, with_loss=True, skipped=skipped)
    assert math.isfinite(loss) and e < 4e3
    assert len(skipped) >= 2


def test_nothing_stable_is_an_error_not_inf():
    prob = Stub(e_star=2e4, unstable=0.0)
    with pytest.raises(SimulationError, match="every uniform E"):
        golden_uniform_search(prob, _mat(), 6)
