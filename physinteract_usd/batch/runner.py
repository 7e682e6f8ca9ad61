"""Running batch items in a local process pool.

`run_pool(tasks, fn, workers=N)` calls `fn(payload)` for every `(name, payload)` in worker
processes (spawned: no CUDA or Warp state is forked), at most N at a time, and reports through
`events` (an `Events`): `started(name)` when an item is handed to a worker, `finished(name,
record)` with what `fn` returned, `failed(name, error)` when it raised or its worker died,
`interrupted(name)` when a stop cut it short.

Stopping: the first SIGINT / SIGTERM to the driver stops handing out items and sends one SIGTERM to
each worker (workers sit in their own process group, so a terminal's Ctrl-C reaches them only this
way, once): a fit there writes its best iterate and the item comes back "interrupted". A second
signal sends a second SIGTERM (the workers quit without writing) and returns at once. A worker that
dies (killed, out of memory, a crash in native code) breaks the pool: the items that were running
are run again in a fresh pool, each alone (so that a death is its own), and an item whose worker
died while it ran alone is tried up to `retries` times more, then failed with the worker's exit.

Layer 2: the standard library and `stopping`.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import signal
from concurrent.futures.process import BrokenProcessPool

from .. import stopping


class Events:
    """What a runner reports (the application layer overrides these)."""

    def started(self, name: str) -> None: ...

    def finished(self, name: str, record: dict) -> None: ...

    def failed(self, name: str, error: str) -> None: ...

    def interrupted(self, name: str) -> None: ...

    def tick(self) -> None:
        """Called between waits (progress bars refresh their ETA here)."""


_BUSY = False        # in a worker: an item is running
_STOP_SEEN = False   # a SIGTERM came while none was (raising then would break the pool): the next one won't start


def _on_sigterm(signum, frame):
    global _STOP_SEEN
    if _BUSY:
        raise KeyboardInterrupt
    _STOP_SEEN = True


def worker_init(env: dict | None = None) -> None:
    """In each pool worker: `env` set (thread counts, before any library reads them), its own
    process group (a terminal's Ctrl-C goes to the driver, which forwards one SIGTERM), and SIGTERM
    raises KeyboardInterrupt in a running item outside a fit (inside one, the fit's own handler
    keeps its best iterate)."""
    os.environ.update(env or {})
    try:
        os.setpgrp()
    except OSError:
        pass
    signal.signal(signal.SIGTERM, _on_sigterm)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_task(fn, payload):
    global _BUSY
    if _STOP_SEEN:   # the stop came while this worker was still starting (importing) or idle
        raise KeyboardInterrupt("stopped before it started")
    _BUSY = True
    try:
        return fn(payload)
    finally:
        _BUSY = False


def _signal_workers(ex) -> None:
    procs = getattr(ex, "_processes", None) or {}
    for p in list(procs.values()):
        try:
            if p.is_alive():
                os.kill(p.pid, signal.SIGTERM)
        except (OSError, ValueError, AttributeError):
            pass


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def run_pool(tasks, fn, *, workers: int, events: Events, retries: int = 1, env: dict | None = None,
             poll_s: float = 0.25) -> list[str]:
    """Run `fn(payload)` for each `(name, payload)` of `tasks`; returns the names never started
    (a stop came first). `env`: environment variables for the workers (e.g. OMP_NUM_THREADS)."""
    queue = list(tasks)
    attempts: dict[str, int] = {}
    solo: set[str] = set()      # items running when a worker died among several: run alone next
    running: dict[cf.Future, tuple[str, object]] = {}
    ctx = mp.get_context("spawn")

    def new_pool():
        return cf.ProcessPoolExecutor(max_workers=max(1, int(workers)), mp_context=ctx, initializer=worker_init,
                                      initargs=(dict(env or {}),))

    ex = new_pool()
    try:
        with stopping.graceful(on_stop=lambda: _signal_workers(ex)):
            while queue or running:
                stop = stopping.requested() is not None
                while queue and len(running) < workers and not stop:
                    if any(n in solo for n, _ in running.values()) or (queue[0][0] in solo and running):
                        break   # a suspect runs alone, so that a death is its own
                    name, payload = queue.pop(0)
                    running[ex.submit(_run_task, fn, payload)] = (name, payload)
                    events.started(name)
                if not running:
                    break
                done, _ = cf.wait(list(running), timeout=poll_s, return_when=cf.FIRST_COMPLETED)
                events.tick()
                lost = []
                for fut in done:
                    name, payload = running.pop(fut)
                    try:
                        record = fut.result()
                    except BrokenProcessPool:
                        lost.append((name, payload))
                    except KeyboardInterrupt:
                        events.interrupted(name)
                    except BaseException as exc:  # noqa: BLE001  (fn catches its own; this is the pool's)
                        events.failed(name, _describe(exc))
                    else:
                        events.finished(name, record)
                if lost:
                    # the broken pool fails every future it held: collect them all, then start afresh
                    for fut in list(running):
                        lost.append(running.pop(fut))
                    codes = sorted({p.exitcode for p in (getattr(ex, "_processes", None) or {}).values()
                                    if p.exitcode not in (None, 0)})
                    ex.shutdown(wait=False, cancel_futures=True)
                    ex = new_pool()
                    why = "its worker process died" + (f" (exit code {', '.join(map(str, codes))})" if codes else "")
                    alone = len(lost) == 1
                    for name, payload in reversed(lost):
                        if alone:          # the death is this item's own
                            attempts[name] = attempts.get(name, 0) + 1
                        solo.add(name)
                        if stopping.requested() is not None:
                            events.interrupted(name)
                        elif attempts.get(name, 0) <= retries:
                            queue.insert(0, (name, payload))
                        else:
                            events.failed(name, f"{why}; tried {attempts[name]} times alone")
    except KeyboardInterrupt:   # a second signal: the workers get their second SIGTERM and quit
        _signal_workers(ex)
        for name, _ in running.values():
            events.interrupted(name)
        running.clear()
        ex.shutdown(wait=False, cancel_futures=True)
        return [n for n, _ in queue]
    ex.shutdown(wait=True, cancel_futures=True)
    return [n for n, _ in queue]
