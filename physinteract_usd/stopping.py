"""Stopping a long run cleanly: SIGINT (Ctrl-C) and SIGTERM (`timeout`, batch schedulers, Ray) ask
it to stop; the simulator checks between frames, so a stop is acted on within one frame's work,
not one optimiser iteration's.

    with stopping.graceful(on_stop=...):   # the first signal asks to stop, a second one quits
        ...                                  # sim/rollout.py calls stopping.check() per frame

`check()` raises `StopRequested` (a KeyboardInterrupt, so code that keeps its best result on
Ctrl-C keeps it here too) once per request, then lets the caller finish: the fit's last pass and
the write that follow the stop run to their end. `finishing()` tells the checks that the run is
past its interruptible part (forward passes no longer stop; backward passes, only the
confidence estimate's by then, still do). Outside `graceful()` nothing is requested and `check()`
costs one attribute read. Layer 1: the standard library only.
"""

from __future__ import annotations

import contextlib
import signal
import threading


class StopRequested(KeyboardInterrupt):
    """A stop was asked for (SIGINT or SIGTERM); `.signal` names it."""

    def __init__(self, signame: str = "SIGINT"):
        super().__init__(signame)
        self.signal = signame


class _State:
    def __init__(self):
        self.reset()

    def reset(self):
        self.requested: str | None = None   # the signal's name, once asked
        self.raised = False                  # check() raised for this request
        self.finishing = False               # past the interruptible part: forward checks pass
        self.active = False                  # inside graceful()


_STATE = _State()


def requested() -> str | None:
    """The name of the signal that asked to stop (None: none did)."""
    return _STATE.requested


def request(signame: str = "SIGINT") -> None:
    """Ask the run to stop, as a signal does (tests and embedding code call it directly)."""
    if _STATE.requested is None:
        _STATE.requested = signame


def finishing() -> None:
    """The interruptible part of the run is over: forward passes run to their end from now on."""
    if _STATE.active:           # (outside graceful() there is nothing to finish)
        _STATE.finishing = True


def is_finishing() -> bool:
    """Whether the run said its interruptible part is over (`finishing()`)."""
    return _STATE.finishing


def check(kind: str = "forward") -> None:
    """Raise StopRequested if a stop was asked for and not yet acted on (`kind`: "forward" or
    "backward": the simulator pass that checks)."""
    st = _STATE
    if st.requested is None or st.raised:
        return
    if st.finishing and kind == "forward":
        return
    st.raised = True
    raise StopRequested(st.requested)


@contextlib.contextmanager
def graceful(on_stop=None):
    """Within the block the first SIGINT or SIGTERM asks to stop (`on_stop()` is called from the
    handler: keep it tiny) and a second one raises KeyboardInterrupt at once. Handlers are
    installed only in the main thread; the previous handlers and a clean state come back after."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _STATE.reset()
    _STATE.active = True

    def handler(signum, frame):
        if _STATE.requested is not None:
            raise KeyboardInterrupt
        _STATE.requested = signal.Signals(signum).name
        if on_stop is not None:
            on_stop()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        _STATE.reset()


@contextlib.contextmanager
def sigterm_as_interrupt():
    """Within the block SIGTERM raises KeyboardInterrupt like Ctrl-C (main thread only): temp files
    are removed and the command exits 130 instead of dying where it stood."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
