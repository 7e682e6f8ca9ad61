"""Independent CPU work on the machine's other cores (#22, #26).

Warp runs a CPU kernel on one thread, so a CPU fit or diagnosis leaves every core but one idle. Where the
work is several independent simulations (a diagnosis's base starts, its candidates' refits), `fork_map`
runs them in forked child processes, as many at once as the process may use cores: each child starts
from the parent's state as it is at the call (the problem, its simulator, the compiled kernels: shared
copy-on-write, nothing to rebuild), computes one item and hands back its result (pickled through a
file); the parent gathers them in the items' order. The results are the ones a call in the parent
would return from that state.

One process at a time where that cannot help or is not safe: one item, one core, CUDA (a forked child
cannot use its parent's CUDA context; the GPU batches in one process instead), a platform without
`fork` (only Linux is used: macOS's system libraries are not fork-safe). `PHYSINTERACT_WORKERS`
caps the processes (1: none forked); an item whose child dies (e.g. killed for memory) is computed
again in the parent, so a result never goes missing.
"""

from __future__ import annotations

import os
import pickle
import shutil
import signal
import sys
import tempfile
import time
import traceback
from typing import Callable, Iterable

from .errors import InputError

ENV = "PHYSINTERACT_WORKERS"
_IN_WORKER = False      # True in a `fork_map` child: it forks no workers of its own


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def workers_for(n_items: int) -> int:
    """How many processes `fork_map` runs at once for `n_items` items: the cores (or PHYSINTERACT_WORKERS),
    at most one per item."""
    if _IN_WORKER:
        return 1        # a worker's own independent runs stay in it (the cores are its siblings')
    v = os.environ.get(ENV, "").strip()
    if v:
        try:
            n = int(v)
        except ValueError:
            n = 0
        if n < 1:
            raise InputError(ENV, f"must be a whole number >= 1 (1: no worker processes), got {v!r}")
    else:
        n = cores()
    return max(1, min(n, int(n_items)))


def can_fork(device="cpu") -> bool:
    """Whether `fork_map` may fork here: Linux, and the work on the CPU."""
    return sys.platform.startswith("linux") and hasattr(os, "fork") and not str(device).startswith("cuda")


def forks(n_items: int, device="cpu") -> bool:
    """Whether `fork_map` would run `n_items` items in worker processes here (else in this process, in order: a
    caller that shows progress item by item can then do so itself)."""
    return n_items > 1 and can_fork(device) and workers_for(n_items) > 1


class WorkerError(RuntimeError):
    """An item failed in its worker with an exception that could not be handed back as it was."""


def fork_map(fn: Callable, items: Iterable, *, device="cpu", workers: int | None = None, log=None) -> list:
    """[fn(item) for item in items], the items computed in forked child processes, `workers` at once
    (default `workers_for`); in order. An exception raised by fn for an item is raised here, for the
    first such item in order. `log(message)` hears when the items go to several processes."""
    items = list(items)
    w = workers if workers is not None and not _IN_WORKER else workers_for(len(items))
    if w <= 1 or len(items) <= 1 or not can_fork(device):     # (`forks`' test, with `workers` given or not)
        return [fn(x) for x in items]
    if log is not None:
        log(f"({len(items)} independent runs on {w} processes)")
    tmp = tempfile.mkdtemp(prefix="physinteract-workers-")
    results: list = [None] * len(items)
    done = [False] * len(items)
    running: dict[int, int] = {}
    nxt = 0
    try:
        while nxt < len(items) or running:
            while nxt < len(items) and len(running) < w:
                sys.stdout.flush()
                sys.stderr.flush()
                path = os.path.join(tmp, f"{nxt}.pkl")
                pid = os.fork()
                if pid == 0:               # the child: one item, then out without running the parent's exit code
                    _child(fn, items[nxt], path)
                running[pid] = nxt
                nxt += 1
            pid, status = _wait_any(running)
            i = running.pop(pid)
            results[i], done[i] = _collect(os.path.join(tmp, f"{i}.pkl"), status)
        out = []
        for i, x in enumerate(items):
            if not done[i]:
                # its worker died without a word (killed for memory, a signal): computed here instead
                results[i] = ("ok", fn(x))
            kind, *rest = results[i]
            if kind == "err":
                exc, tb = rest
                if isinstance(exc, BaseException):
                    raise exc
                raise WorkerError(f"an independent run failed in its worker process:\n{tb}")
            out.append(rest[0])
        return out
    finally:
        for pid in running:
            try:
                os.kill(pid, signal.SIGTERM)
                os.waitpid(pid, 0)
            except OSError:
                pass
        shutil.rmtree(tmp, ignore_errors=True)


def _child(fn, item, path: str) -> None:
    global _IN_WORKER
    code = 0
    _IN_WORKER = True
    try:
        _die_with_parent()
        if "torch" in sys.modules:
            # one torch thread: a parent whose OpenMP pool ran with more leaves the child a pool without threads,
            # in which the next parallel op waits forever (libgomp is not fork-safe); one process per core anyway
            sys.modules["torch"].set_num_threads(1)
        try:
            out = ("ok", fn(item))
        except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
            out = ("err", exc, traceback.format_exc())
        try:
            blob = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 - an unpicklable result or exception: its text instead
            tb = out[2] if out[0] == "err" else traceback.format_exc()
            blob = pickle.dumps(("err", None, tb), protocol=pickle.HIGHEST_PROTOCOL)
        with open(path + ".part", "wb") as f:
            f.write(blob)
        os.replace(path + ".part", path)
    except BaseException:  # noqa: BLE001 - nothing may return into the parent's code
        code = 1
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _die_with_parent() -> None:
    """A worker ends with its parent (SIGTERM when the parent dies, even by SIGKILL): no orphan computes on
    for minutes. The parent's own SIGTERM / Ctrl-C ends the workers through `fork_map`'s cleanup."""
    import ctypes

    try:
        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM), 0, 0, 0)      # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _wait_any(running: dict) -> tuple[int, int]:
    """The first of `running`'s children to end: (pid, status). Only this call's own children are waited
    for (a caller's other child processes are left alone)."""
    while True:
        for pid in list(running):
            got, status = os.waitpid(pid, os.WNOHANG)
            if got == pid:
                return pid, status
        time.sleep(0.01)


def _collect(path: str, status: int):
    """(the child's (kind, ...) record, True), or (None, False) when it left none."""
    if not os.path.exists(path):
        return None, False
    try:
        with open(path, "rb") as f:
            rec = pickle.load(f)
    except Exception:  # noqa: BLE001 - e.g. an exception class that cannot be rebuilt here
        return ("err", None, f"(its result could not be read back; exit status {status})"), True
    return rec, True


__all__ = ["ENV", "cores", "workers_for", "can_fork", "forks", "fork_map", "WorkerError"]
