"""What a run will cost, before it starts: settings that would take hours are refused (one line,
exit 2) with the cost named, unless the user says `--yes`.

The model: one fit iteration = a forward and a backward rollout (the backward replays the forward
and runs the adjoint: ~3 forward passes) of T frames x S substeps, each substep touching every
particle and grid cell; rendering is small beside it. Constants measured on the bundled sample
(1,769 particles, 14x24x14 cells, 239 substeps, 14 frames: ~7.5 s per iteration on one core of
the 2-core CPU box) and, for CUDA, on an H100 (docs/benchmarks: 157k particles, 1M cells, 774
substeps, 36 frames: ~60 s per iteration; small scenes are bound by ~60 us of launch latency per
substep pass). Good to a factor of two: enough to tell minutes from hours.
"""

from __future__ import annotations

import math

from ..errors import InputError

CPU_S_PER_PARTICLE = 0.30e-6      # per substep pass
CPU_S_PER_CELL = 0.06e-6
GPU_S_PER_PARTICLE = 2.0e-9
GPU_S_PER_CELL = 0.4e-9
GPU_S_PER_PASS_MIN = 60e-6        # launch latency floor per substep pass
PASSES_PER_ITERATION = 3.0        # forward + backward (replay + adjoint)

MAX_SUBSTEPS = 10_000             # per frame: beyond this init asks for --yes
MAX_FIT_SECONDS = 2 * 3600.0      # a fit estimated longer than this asks for --yes


def substep_seconds(particles: int, cells: int, device: str = "cpu") -> float:
    if str(device).startswith("cuda"):
        return max(GPU_S_PER_PASS_MIN, particles * GPU_S_PER_PARTICLE + cells * GPU_S_PER_CELL)
    return particles * CPU_S_PER_PARTICLE + cells * CPU_S_PER_CELL


def iteration_seconds(particles: int, cells: int, substeps: int, frames: int, device: str = "cpu") -> float:
    """Estimated seconds of one fit iteration (frames: the video's frame count)."""
    return PASSES_PER_ITERATION * max(frames - 1, 1) * substeps * substep_seconds(particles, cells, device)


def fit_seconds(iterations: int, particles: int, cells: int, substeps: int, frames: int, device: str = "cpu",
                search_evals: int = 7, confidence_probes: int = 4) -> float:
    """Estimated seconds of a whole fit: the uniform-E search (forward passes), the iterations,
    the confidence estimate."""
    it = iteration_seconds(particles, cells, substeps, frames, device)
    return it * (iterations + confidence_probes) + it / PASSES_PER_ITERATION * search_evals


def duration(seconds: float) -> str:
    """A duration in words: '45 s', '12 min', '3.5 h', '2,100,000 h'."""
    if not math.isfinite(seconds):
        return "forever"
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    h = seconds / 3600
    return f"{h:.1f} h" if h < 100 else f"{h:,.0f} h"


def where(device: str) -> str:
    return "on the GPU" if str(device).startswith("cuda") else "on the CPU"


def check_substeps(substeps: int, particles: int, cells: int, frames: int, *, flag: str, yes: bool,
                   detail: str = "") -> None:
    """InputError (blaming `flag`) when a frame needs more than MAX_SUBSTEPS substeps, unless `yes`."""
    if substeps <= MAX_SUBSTEPS or yes:
        return
    it = iteration_seconds(particles, cells, substeps, frames, "cpu")
    raise InputError(flag, f"{substeps:,} substeps per frame{detail}: one fit iteration would take about "
                     f"{duration(it)} on the CPU; lower the largest E, or pass --yes to go on")


def check_fit_cost(iterations: int, particles: int, cells: int, substeps: int, frames: int, device: str, *,
                   yes: bool, stage: str = "stage", search_evals: int = 7, confidence_probes: int = 4) -> float:
    """The estimated fit time; InputError when it exceeds MAX_FIT_SECONDS, unless `yes` (blaming
    --iterations when they are what makes it long, else the stage)."""
    total = fit_seconds(iterations, particles, cells, substeps, frames, device, search_evals, confidence_probes)
    if total > MAX_FIT_SECONDS and not yes:
        it = iteration_seconds(particles, cells, substeps, frames, device)
        flag = "--iterations" if iterations > 1000 else str(stage)
        raise InputError(flag, f"this fit would take about {duration(total)} {where(device)} ({iterations:,} "
                         f"iterations of ~{duration(it)}: {substeps:,} substeps per frame, {frames} frames, "
                         f"{particles:,} particles); use fewer iterations or a coarser stage (`init --grid`, a lower "
                         "--youngs-range max), or pass --yes to go on")
    return total
