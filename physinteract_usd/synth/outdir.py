"""The capture folder a generator writes: replaced only when it is one of ours.

A folder is ours when it holds a finished capture's gt/gt.json, or the marker a generator leaves while it
writes (so a generator stopped half-way, by a signal or a crash, leaves a folder `--force` may replace,
and never a folder a user made)."""
from __future__ import annotations

import shutil
from pathlib import Path

from ..errors import InputError

WRITING = ".synth-writing"


def make_room(out: Path, force: bool) -> None:
    """Raise unless `out` is absent, empty, or a capture folder of ours and `force` is set; then remove it."""
    if out.exists() and any(out.iterdir()):
        if not force:
            raise InputError(out, "exists and is not empty (use --force to replace it)")
        if not ((out / "gt" / "gt.json").exists() or (out / WRITING).exists()):
            raise InputError(out, "is not a synth capture folder: refusing to replace it")
        shutil.rmtree(out)


def begin(out: Path) -> None:
    """Create `out` and mark it as being written."""
    out.mkdir(parents=True, exist_ok=True)
    (out / WRITING).write_text("a synth generator was writing this folder and did not finish; "
                               "`synth ... --force` replaces it\n")


def finish(out: Path) -> None:
    """The capture is complete: remove the marker."""
    (out / WRITING).unlink(missing_ok=True)
