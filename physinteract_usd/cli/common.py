"""Argument types and printing helpers shared by the verbs' CLI modules."""

from __future__ import annotations

import argparse
import sys


def positive_float(s: str) -> float:
    v = float(s)
    if not v > 0:
        raise argparse.ArgumentTypeError("must be positive")
    return v


def e_range(s: str):
    try:
        lo, hi = (float(x) for x in s.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected MIN,MAX in Pa, e.g. 1e3,1e6") from None
    return lo, hi


def progress_log(json_mode: bool):
    """Where progress lines go: stdout, or stderr when stdout carries JSON."""
    return (lambda m: print(m, file=sys.stderr)) if json_mode else print
