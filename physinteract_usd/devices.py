"""Where work runs: the one way to turn a `--device` string into torch's and Warp's devices."""

from __future__ import annotations

from .errors import InputError


def torch_device(device):
    """torch.device for "cpu", "cuda" or "cuda:N" (Warp's names)."""
    import torch

    return torch.device("cpu" if str(device) == "cpu" else str(device))


def check_device(device) -> None:
    """InputError (one line) for a device that is not cpu/cuda, or cuda without a usable GPU."""
    if device is None or str(device) == "cpu":
        return
    if not str(device).startswith("cuda"):
        raise InputError("--device", f"must be cpu or cuda, not {device!r}")
    import torch

    if not torch.cuda.is_available():
        raise InputError("--device", "cuda was asked for, but this torch has no usable CUDA GPU: use --device cpu")


def cpu_threads(device) -> None:
    """On the CPU, Warp runs single-threaded and the fit's torch ops are small: torch's thread pool
    only adds synchronisation (8 ms per op measured on a busy 2-core machine)."""
    if str(device) == "cpu":
        import torch

        torch.set_num_threads(1)


def device_name(device) -> str:
    """A human name for where a run happened (the GPU's model, or the CPU and its threads)."""
    import torch

    if str(device).startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    import platform

    return f"cpu ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def quiet_warp_init_on_load(device=None) -> None:
    """`quiet_warp_init(device)` now if Warp is imported, else right after something imports it: a
    verb that never simulates or renders (`info`, `versions`, `export`, `--help`) does not load
    Warp at all (0.4 s of CPU)."""
    import sys

    if "warp" in sys.modules:
        quiet_warp_init(device)
        return
    import physinteract_usd

    physinteract_usd._ON_WARP.append(lambda wp: quiet_warp_init(device))


def quiet_warp_init(device=None) -> None:
    """Initialise Warp now, without the "Warp CUDA warning: Could not find or load the NVIDIA CUDA
    driver" line its native code prints on a machine without a GPU (when no GPU is asked for, that
    line is only noise before a command's output or its one-line error)."""
    import os
    import sys

    import warp as wp

    if str(device).startswith("cuda") or getattr(wp._src.context, "runtime", None) is not None:
        wp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        wp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
