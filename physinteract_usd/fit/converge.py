"""The fit's convergence stop (one rule, shared by the schedules' gradient loops).

A level of the schedule (one basis size, one optimiser) has plateaued when none of its last
`patience` losses is more than `tol` (relative) below the best loss before them. It then ends
from its best iterate, with an optional short tail: `tail` more iterations with the learning rate
annealed from where it was down to the floor (a cosine), instead of the rest of the level's budget
(FitSettings' defaults: patience 3, tail 4; a shorter stop cost hemp_rope half its MA, see
docs/benchmarks/cpu.md, "Reverted the same day"); a level that never got below its first loss ends
at once (nothing to anneal). On the demo (samples/foam_bar, docs/benchmarks/cpu.md) the bumps level
plateaus after ~20 of its 45 iterations; what the rest of the budget, the patience and the tail
bought is measured there.
"""

from __future__ import annotations

import math

LR_FLOOR = 0.1   # the cosine schedule's last learning rate, as a share of the first


def plateaued(losses, patience: int, tol: float) -> bool:
    """True when none of the last `patience` of `losses` (one level's, in order) is more than `tol`
    (relative) below the lowest before them; False while there are not more than `patience`
    losses, or when `patience` is 0 (the stop is off). Non-finite losses never count as better."""
    patience = int(patience)
    if patience <= 0 or len(losses) <= patience:
        return False
    finite = [v for v in losses[:-patience] if math.isfinite(v)]
    if not finite:
        return False
    before = min(finite)
    return not any(math.isfinite(v) and v < before - tol * abs(before) for v in losses[-patience:])


def level_patience(patience: int, searched_uniform: bool, patience_searched: int) -> int:
    """The patience of one level: `patience_searched` (when smaller and the stop is on) for a
    uniform level that starts at the start search's minimum, `patience` for every other level. The
    search has already minimised the same loss over the same one E (at the default nu): its first
    gradient step says whether nu and the last digits of E pay, and on the demo it never did (the
    level's 4 iterations kept their first: docs/benchmarks/cpu.md, "Levers, session 9")."""
    patience = int(patience)
    if searched_uniform and patience > 0:
        return max(1, min(patience, int(patience_searched)))
    return patience


def improved(losses, tol: float) -> bool:
    """Whether a level's best loss is more than `tol` (relative) below its first one (a level
    that plateaus without that ends without a tail)."""
    finite = [v for v in losses if math.isfinite(v)]
    return bool(finite) and math.isfinite(losses[0]) and min(finite) < losses[0] - tol * abs(losses[0])


def lr_scale(j: int, n: int, tail: tuple | None = None) -> float:
    """The learning-rate factor at iteration `j` of a level of `n` iterations: a cosine from 1 down
    to LR_FLOOR; in a plateau's tail (`tail` = (first iteration of the tail, the factor there,
    the tail's length)) a cosine from that factor down to LR_FLOOR over the tail."""
    if tail is None:
        return LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * j / max(n, 1)))
    j0, s0, m = tail
    frac = min(max(j - j0 + 1, 0) / max(m, 1), 1.0)
    return LR_FLOOR + (s0 - LR_FLOOR) * 0.5 * (1 + math.cos(math.pi * frac))
