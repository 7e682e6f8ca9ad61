"""Which GPU a benchmark's k-th worker or scene runs on, on a host of several (the run is bound by the host's
cores; processes that share one GPU take turns): `GPU_LIST` ("1,2,3": these GPUs) or `NGPUS` (GPUs 0..N-1),
shifted by `GPU_OFFSET`. None on a host of one GPU (the environment left as it is)."""

from __future__ import annotations

import os


def gpu_for(k: int, env=os.environ) -> str | None:
    gpus = [g for g in env.get("GPU_LIST", "").split(",") if g] or \
        [str(g) for g in range(int(env.get("NGPUS", "1") or 1))]
    if len(gpus) < 2 and not env.get("GPU_LIST"):
        return None
    return gpus[(k + int(env.get("GPU_OFFSET", "0") or 0)) % len(gpus)]
