"""Running batch items on a Ray cluster: one Ray task per item.

`run_ray(tasks, fn, address=...)` connects to the cluster at `address` ("" or None: a Ray instance
this process already joined, else the one RAY_ADDRESS names, else a new local one), submits
`fn(payload)` for every `(name, payload)` as a task needing 1 CPU and `gpus(payload)` GPUs
(fractional: several small fits share a GPU), retried up to `retries` times when its worker dies
(`max_retries`: a killed node or worker, not an exception `fn` raised: `fn` records those itself),
and reports through `events` like the process pool (`runner.Events`).

Every node must see the manifest's paths and the output folder at the same place (a shared file
system) and have physinteract-usd installed (or pass a runtime_env when joining the cluster).

Stopping: the first SIGINT / SIGTERM cancels the items not started and asks the running ones to
stop (`ray.cancel`, a KeyboardInterrupt in the task: a fit keeps its best iterate); they come back
"interrupted". A second signal force-cancels them (their workers are killed) and returns.

Layer 2: the standard library and `stopping`; `ray` is imported here only (an optional extra).
"""

from __future__ import annotations

import os
import time

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


def _describe(exc: BaseException) -> str:
    text = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
    last = text[-1].strip() if text else ""
    return f"{type(exc).__name__}: {last}" if last else type(exc).__name__


def run_ray(tasks, fn, *, address: str | None, events: Events, gpus=lambda payload: 0.0, retries: int = 2,
            poll_s: float = 0.25, grace_s: float = 60.0) -> list[str]:
    """Run `fn(payload)` for each `(name, payload)` of `tasks` as Ray tasks; returns the names
    never started (a stop came first)."""
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
    try:
        with stopping.graceful():
            for name, payload in tasks:
                ref = remote.options(num_cpus=1, num_gpus=float(gpus(payload)), max_retries=int(retries),
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
                    for ref in refs:
                        ray.cancel(ref, force=False)
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
                        events.interrupted(name)
                    except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as exc:
                        events.failed(name, f"its Ray worker died ({type(exc).__name__}); tried {int(retries) + 1} times")
                    except ray.exceptions.RayTaskError as exc:
                        cause = getattr(exc, "cause", None)
                        if isinstance(cause, KeyboardInterrupt):
                            events.interrupted(name)
                        else:
                            events.failed(name, _describe(cause if isinstance(cause, BaseException) else exc))
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
        if started_here:
            ray.shutdown()
    return []
