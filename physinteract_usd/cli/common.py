"""Argument types and printing helpers shared by the verbs' CLI modules."""

from __future__ import annotations

import argparse
import math
import sys


def positive_float(s: str) -> float:
    v = float(s)
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError("must be a positive number")
    return v


def e_range(s: str):
    try:
        lo, hi = (float(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected MIN,MAX in Pa, e.g. 1e3,1e6") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise argparse.ArgumentTypeError(f"MIN and MAX must be finite numbers in Pa, got {s}")
    if not 0 < lo < hi:
        raise argparse.ArgumentTypeError(f"needs 0 < MIN < MAX, got {s}")
    if hi >= 3.4e38:
        raise argparse.ArgumentTypeError(f"MAX {hi:g} Pa does not fit the stage's 32-bit floats (< 3.4e38)")
    return lo, hi


def progress_log(json_mode: bool):
    """Where progress lines go: stdout, or stderr when stdout carries JSON."""
    return (lambda m: print(m, file=sys.stderr)) if json_mode else print
