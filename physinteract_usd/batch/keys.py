"""What makes a batch item's result reusable: a fingerprint of its inputs and one key per step.

A step's key hashes the inputs' fingerprint and the settings of that step and of every step before
it, so a changed hint re-runs extraction and everything after it, a changed iteration count only
the fit and after. An item whose recorded keys all equal the current ones (and that finished) is
skipped.

The fingerprint of a capture folder is every file's relative path, size and modification time
(`gt/` left out: no step reads it); of a stage, its root layer's and init layer's (the fit layer
and versions are what the batch writes). Touching a file re-runs the item; content is not hashed
(a catalogue of videos would be read in full on every rerun).

Layer 2: the standard library only.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

STEPS = ("init", "extract", "fit", "report", "diagnose", "export")

# the settings each step reads (besides the ones of the steps before it)
STEP_SETTINGS = {
    "init": ("grid", "fps", "youngs_range"),
    "extract": ("type", "grasp_frame", "release_frame", "hint_pixel", "hint_particles", "support_pixel",
                "support_particles", "grasp_radius"),
    "fit": ("iterations", "seed", "device", "schedule", "effects", "fit_settings"),
    "report": ("skip",),
    "diagnose": ("diagnose_available", "diagnose_settings"),
    "export": ("sim_ready",),
}


def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def fingerprint(source, kind: str) -> dict:
    """{relative path: [size, mtime_ns]} of the files the item's first step reads ({} when missing)."""
    source = Path(source)
    files: dict[str, list[int]] = {}
    if kind == "stage":
        stem = source.name[: -len(source.suffix)] if source.suffix else source.name
        paths = [source, source.with_name(f"{stem}.init.usdc")]
        base = source.parent
    else:
        if not source.is_dir():
            return {}
        paths = []
        for dirpath, dirnames, filenames in os.walk(source):
            rel = Path(dirpath).relative_to(source)
            dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and not (rel == Path(".") and d == "gt"))
            paths += [Path(dirpath) / f for f in sorted(filenames) if not f.startswith(".")]
        base = source
    for p in paths:
        try:
            st = p.stat()
        except OSError:
            continue
        files[str(p.relative_to(base))] = [st.st_size, st.st_mtime_ns]
    return files


def step_keys(settings: dict, inputs: dict, version: str = "") -> dict:
    """{step: key}: each step's key over the inputs' fingerprint, the package version and the
    settings of that step and the ones before it."""
    keys = {}
    prev = _digest({"inputs": inputs, "version": version})
    for step in STEPS:
        prev = _digest({"prev": prev, "step": step, "settings": {k: settings.get(k) for k in STEP_SETTINGS[step]}})
        keys[step] = prev
    return keys


def first_stale_step(recorded: dict | None, current: dict) -> str | None:
    """The first step whose recorded key differs from the current one (None: all are up to date)."""
    recorded = recorded or {}
    for step in STEPS:
        if recorded.get(step) != current.get(step):
            return step
    return None
