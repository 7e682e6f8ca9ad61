"""Errors the user sees.

`InputError` is bad input: the CLI prints its one line (``error: <file>: <problem>``) and exits 2.
`SimulationError` is a simulation that went unstable or left its domain: it says when and what to
change. Neither carries a traceback to the user.
"""

from __future__ import annotations

import os


class InputError(ValueError):
    """Bad user input: a file that is missing, malformed or inconsistent with another."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(self.oneline())

    def oneline(self) -> str:
        return f"{self.path}: {self.problem}" if self.path else self.problem


class SimulationError(RuntimeError):
    """The simulation became unstable (non-finite state) or a particle left the grid domain."""

    def __init__(self, problem: str, frame: int | None = None, substep: int | None = None,
                 advice: str = "", kind: str = "", face: str = ""):
        self.problem = problem
        self.frame = frame
        self.substep = substep
        self.advice = advice
        self.kind = kind          # "unstable" | "domain" | "": lets a front end give its own advice
        self.face = face          # "domain": the grid face the first particle out was nearest ("-y": it fell), or ""
        super().__init__(self.message())

    def message(self, advice: str | None = None) -> str:
        """The one-line message, with `advice` instead of the simulator's own when given."""
        where = ""
        if self.frame is not None:
            where = f" at frame {self.frame}" + (f" (substep {self.substep})" if self.substep is not None else "")
        msg = f"simulation {self.problem}{where}"
        advice = self.advice if advice is None else advice
        if advice:
            msg += f"; {advice}"
        return msg
