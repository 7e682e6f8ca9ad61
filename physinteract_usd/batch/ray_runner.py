"""Running batch items on a Ray cluster: one Ray task per item.

`run_ray(tasks, fn, address=...)` connects to the cluster at `address` ("" or None: a Ray instance
this process already joined, else the one RAY_ADDRESS names, else a new local one), submits
`fn(payload)` for every `(name, payload)` as a task needing 1 CPU and `gpus(payload)` GPUs
(fractional: several small fits share a GPU), retried up to `retries` times when its worker dies
(`max_retries`: a killed node or worker, not an exception `fn` raised: `fn` records those itself),
and reports through `events` like the process pool (`runner.Events`).

Every node must see the manifest's paths and the output folder at the same place (a shared file
system) and have physinteract-usd installed (or pass a runtime_env when joining the cluster).

Stopping: the first SIGINT / SIGTERM cancels the items not started and creates `stop_file`, which
the running tasks watch (a signal cannot reach a task; Ray's own cancel raises KeyboardInterrupt
wherever the task stands): a fit there writes its best iterate and the item comes back
"interrupted". A second signal, or `grace_s` without an end, force-cancels them (their workers
are killed) and returns.

Layer 2: the standard library and `stopping`; `ray` is imported here only (an optional extra).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from .. import stopping
from ..errors import InputError
from .runner import Events

INSTALL_HINT = "Ray is not installed: pip install physinteract-usd[ray]"


def import_ray():
    """The `ray` module, or InputError naming `--ray` with how to install it."""
    try:
        import ray
    except ImportError:
        raise InputError("--ray", INSTALL_HINT) from None
    return ray


def _describe(exc: BaseException, first: bool = False) -> str:
    """One line: the exception's first line (its own), or the last (Ray's wrappers end with it)."""
    text = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
    line = (text[0] if first else text[-1]).strip() if text else ""
    return f"{type(exc).__name__}: {line}" if line else type(exc).__name__


def run_ray(tasks, fn, *, address: str | None, events: Events, gpus=lambda payload: 0.0, retries: int = 2,
            stop_file=None, poll_s: float = 0.25, grace_s: float = 60.0) -> list[str]:
    """Run `fn(payload)` for each `(name, payload)` of `tasks` as Ray tasks; returns the names
    never started (a stop came first). `stop_file`: created on the first stop (the tasks watch it
    and stop cleanly; without one, running tasks get Ray's cancel), removed at the end."""
    ray = import_ray()
    started_here = False
    if not ray.is_initialized():
        kw = dict(log_to_driver=False, include_dashboard=False, configure_logging=False)
        addr = address or os.environ.get("RAY_ADDRESS") or None
        try:
            ray.init(address=addr, **kw)
        except ConnectionError as exc:
            raise InputError("--ray", f"cannot join the Ray cluster at {addr}: {exc}") from None
        started_here = True
    remote = ray.remote(fn)
    refs: dict = {}
    # Ray does not say cheaply which tasks run and which wait: the first ones, as many as the
    # cluster has CPUs, are reported as started, then one more as each ends (Ray runs tasks of one
    # shape roughly in submission order)
    try:
        slots = max(1, int(ray.cluster_resources().get("CPU", 1)))
    except Exception:  # noqa: BLE001
        slots = 1
    waiting: list[str] = []
    dropped: set[str] = set()       # waiting when the stop came: cancelled before they ran
    not_started: list[str] = []
    try:
        with stopping.graceful():
            for name, payload in tasks:
                # one CPU a task: its diagnosis forks no worker processes of its own (`workers.fork_map`)
                ref = remote.options(num_cpus=1, num_gpus=float(gpus(payload)), max_retries=int(retries),
                                     runtime_env={"env_vars": {"PHYSINTERACT_WORKERS": "1"}},
                                     name=f"physinteract-batch:{name}").remote(payload)
                refs[ref] = name
                if len(refs) <= slots:
                    events.started(name)
                else:
                    waiting.append(name)
            stop_at = None
            while refs:
                if stopping.requested() is not None and stop_at is None:
                    stop_at = time.monotonic()
                    if stop_file is not None:
                        Path(stop_file).touch()
                    for ref, name in refs.items():   # the waiting ones are dropped; running ones stop
                        if stop_file is None or name in waiting:
                            ray.cancel(ref, force=False)
                    dropped = set(waiting)
                if stop_at is not None and time.monotonic() - stop_at > grace_s:
                    raise KeyboardInterrupt
                ready, _ = ray.wait(list(refs), num_returns=1, timeout=poll_s)
                events.tick()
                for ref in ready:
                    name = refs.pop(ref)
                    if name in waiting:          # ended before it was reported as started
                        waiting.remove(name)
                    elif waiting:
                        events.started(waiting.pop(0))
                    try:
                        record = ray.get(ref)
                    except ray.exceptions.TaskCancelledError:
                        if name in dropped:
                            not_started.append(name)
                        else:
                            events.interrupted(name)
                    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as exc:
                        events.failed(name, f"its Ray worker died ({type(exc).__name__}); tried {int(retries) + 1} times")
                    except ray.exceptions.RayTaskError as exc:
                        cause = getattr(exc, "cause", None)
                        if isinstance(cause, KeyboardInterrupt):
                            events.interrupted(name)
                        elif isinstance(cause, BaseException):
                            events.failed(name, _describe(cause, first=True))
                        else:
                            events.failed(name, _describe(exc))
                    except Exception as exc:  # noqa: BLE001  (object lost, out of memory, ...)
                        events.failed(name, _describe(exc))
                    else:
                        events.finished(name, record)
    except KeyboardInterrupt:
        for ref, name in list(refs.items()):
            ray.cancel(ref, force=True)
            events.interrupted(name)
        refs.clear()
    finally:
        if stop_file is not None:
            Path(stop_file).unlink(missing_ok=True)
        if started_here:
            ray.shutdown()
    return not_started
