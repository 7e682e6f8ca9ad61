"""A batch manifest: the captures or stages to process, one item each, with per-item overrides.

CSV (a header row; an empty cell is "the command's default"):

    source,name,iterations,effects,grasp_frame,release_frame,device,schedule
    captures/rope,,40,,,,,
    captures/glove,glove_b,40,damping,2,9,cuda,ladder
    stages/cap.usda,,,,,,,

JSON: a list of objects with the same keys, or {"defaults": {...}, "items": [...]} (an item's keys
win over "defaults"; lists are allowed where the CSV separates values with ';').

`source` is a capture folder (object, frames or video, transforms.json) or an existing stage
(.usda / .usdc / .usd), relative to the manifest's folder. The manifest is checked as a whole
before anything runs (a malformed value is an InputError naming the manifest, the row and the
column); a source that is missing or broken is that item's failure, found when it runs.

Layer 2: the standard library and errors only (the hints' syntax is checked by the application
layer, which knows the extraction's parser).
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError

STAGE_SUFFIXES = (".usda", ".usdc", ".usd")
EFFECTS = ("damping", "plasticity", "ground", "viscoelasticity")
SCHEDULES = ("bumps", "select", "ladder")
TYPES = ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent")

# key -> what it holds (the docs' table is built from this)
KEYS = {
    "source": "capture folder or stage file (required), relative to the manifest",
    "name": "the item's name (default: the source's folder or file stem); letters, digits, - and _",
    "iterations": "fit iterations (>= 1)",
    "seed": "the fit's random seed",
    "device": "cpu or cuda",
    "schedule": "the fit's schedule: bumps, select or ladder",
    "effects": "effects switched on before the fit: damping plasticity ground viscoelasticity (';' between)",
    "type": "interaction type: pointAdherent pointNonAdherent surfaceNonAdherent",
    "grasp_frame": "the hand takes hold at frame K",
    "release_frame": "the hand lets go at frame K, or never",
    "hint_pixel": "K,U,V: the contact is at pixel (U, V) of frame K",
    "hint_particles": "I,J,...: the contact holds these particles",
    "support_pixel": "K,U,V: the object is held still there (';' between several)",
    "support_particles": "I,J,...: these particles are held still",
    "grasp_radius": "metres the hand holds around the contact",
    "grid": "init: grid cells along the object's longest side, or auto (4 across its thinnest part)",
    "fps": "init: frames per second when the capture does not say",
    "youngs_range": "init: MIN,MAX Young's modulus in Pa",
    "sim_ready": "also export the sim-ready TetMesh asset (true / false)",
    "fit_settings": "the fit's other settings by name (JSON: an object; CSV: name=value;name=value)",
    "diagnose_settings": "the diagnosis's options by name, as fit_settings (refit, refit_iterations, candidates, ...)",
    "skip": "steps left out: report, diagnose, export (';' between)",
}
SKIPPABLE = ("report", "diagnose", "export")
HINT_KEYS = ("type", "grasp_frame", "release_frame", "hint_pixel", "hint_particles", "support_pixel",
             "support_particles", "grasp_radius")
INIT_KEYS = ("grid", "fps", "youngs_range")
FIT_KEYS = ("iterations", "seed", "device", "schedule", "effects", "fit_settings")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


@dataclass
class Item:
    """One manifest entry: `source` absolute, `kind` "capture" or "stage", `options` its validated
    overrides (only the keys it gives), `row` its 1-based row (CSV: the data row) for messages."""

    name: str
    source: Path
    kind: str
    row: int
    options: dict = field(default_factory=dict)


def read_manifest(path) -> list[Item]:
    """The manifest's items, checked (InputError naming the manifest, row and column)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "manifest not found" if not path.exists() else "manifest is not a file")
    suffix = path.suffix.lower()
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot be read as text ({exc})") from None
    if suffix == ".json":
        rows = _json_rows(path, text)
    elif suffix in (".csv", ".tsv", ".txt"):
        rows = _csv_rows(path, text, "\t" if suffix == ".tsv" else ",")
    else:
        raise InputError(path, f"manifest must be .csv or .json, not {suffix or 'no suffix'}")
    if not rows:
        raise InputError(path, "the manifest lists no items")
    items = [_item(path, i + 1, r) for i, r in enumerate(rows)]
    seen: dict[str, int] = {}
    for it in items:
        if it.name.lower() in seen:
            raise InputError(path, f"row {it.row}: name '{it.name}' is also row {seen[it.name.lower()]}'s "
                             "(give each item its own name)")
        seen[it.name.lower()] = it.row
    return items


def _json_rows(path: Path, text: str) -> list[dict]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    defaults = {}
    if isinstance(data, dict):
        unknown = set(data) - {"defaults", "items"}
        if unknown or "items" not in data:
            raise InputError(path, 'a JSON manifest is a list of items or {"defaults": {...}, "items": [...]}')
        defaults = data.get("defaults") or {}
        data = data["items"]
        if not isinstance(defaults, dict):
            raise InputError(path, '"defaults" must be an object')
        if "source" in defaults or "name" in defaults:
            raise InputError(path, '"defaults" cannot give a source or a name')
    if not isinstance(data, list):
        raise InputError(path, 'a JSON manifest is a list of items or {"defaults": {...}, "items": [...]}')
    rows = []
    for i, r in enumerate(data):
        if isinstance(r, str):
            r = {"source": r}
        if not isinstance(r, dict):
            raise InputError(path, f"item {i + 1}: must be an object with a \"source\" (or a path string)")
        rows.append({**defaults, **r})
    return rows


def _csv_rows(path: Path, text: str, delimiter: str) -> list[dict]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        return []
    reader = csv.DictReader(lines, delimiter=delimiter)
    header = [h.strip() for h in (reader.fieldnames or [])]
    if "source" not in header:
        if len(header) == 1 and not any(k in header for k in KEYS):   # a bare list of paths
            return [{"source": ln.strip()} for ln in lines]
        raise InputError(path, f"the header row has no 'source' column (got {', '.join(header)})")
    rows = []
    for r in reader:
        if None in r:
            raise InputError(path, f"row {len(rows) + 1}: more cells than the header has columns")
        rows.append({k.strip(): (v.strip() if isinstance(v, str) else v) for k, v in r.items()
                     if v is not None and (not isinstance(v, str) or v.strip() != "")})
    return rows


def _item(path: Path, row: int, r: dict) -> Item:
    def bad(key, problem):
        return InputError(path, f"row {row}, {key!r}: {problem}")

    unknown = sorted(set(r) - set(KEYS))
    if unknown:
        raise InputError(path, f"row {row}: unknown key {unknown[0]!r} (known: {', '.join(KEYS)})")
    src = r.get("source")
    if not isinstance(src, str) or not src.strip():
        raise bad("source", "a capture folder or stage file is required")
    source = Path(src).expanduser()
    if not source.is_absolute():
        source = path.parent.resolve() / source
    kind = "stage" if source.suffix.lower() in STAGE_SUFFIXES else "capture"
    name = r.get("name")
    if name is None:
        name = source.stem if kind == "stage" and source.stem != "scene" else source.name
        if kind == "stage" and source.stem == "scene":
            name = source.parent.name or "scene"
        name = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._-") or f"item{row}"
    elif not isinstance(name, str) or not _NAME.match(name):
        raise bad("name", "letters, digits, '.', '-' and '_' only, starting with a letter or digit")
    opts = {}
    for key, v in r.items():
        if key in ("source", "name"):
            continue
        opts[key] = _value(key, v, bad)
    return Item(name, source, kind, row, opts)


def _int(key, v, bad, lo=None):
    if isinstance(v, bool):
        raise bad(key, f"must be a whole number, got {v!r}")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise bad(key, f"must be a whole number, got {v!r}") from None
    if not math.isfinite(f) or f != int(f):
        raise bad(key, f"must be a whole number, got {v!r}")
    if lo is not None and f < lo:
        raise bad(key, f"must be >= {lo}, got {v!r}")
    return int(f)


def _float(key, v, bad, positive=True):
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise bad(key, f"must be a number, got {v!r}") from None
    if isinstance(v, bool) or not math.isfinite(f) or (positive and f <= 0):
        raise bad(key, f"must be a {'positive ' if positive else ''}number, got {v!r}")
    return f


def _list(v) -> list[str]:
    if isinstance(v, (list, tuple)):
        return [str(x).strip() for x in v if str(x).strip()]
    return [t.strip() for t in re.split(r"[;\s]+", str(v)) if t.strip()]


def _value(key, v, bad):
    if key == "iterations":
        return _int(key, v, bad, 1)
    if key == "seed":
        return _int(key, v, bad)
    if key == "grid":
        if isinstance(v, str) and v.strip().lower() == "auto":
            return "auto"
        return _int(key, v, bad, 4)
    if key == "grasp_frame":
        return _int(key, v, bad, 0)
    if key == "release_frame":
        if isinstance(v, str) and v.strip().lower() == "never":
            return "never"
        return _int(key, v, bad, 0)
    if key in ("fps", "grasp_radius"):
        return _float(key, v, bad)
    if key == "device":
        d = str(v).strip()
        if d != "cpu" and not re.match(r"^cuda(:\d+)?$", d):
            raise bad(key, f"must be cpu or cuda, got {v!r}")
        return d
    if key == "schedule":
        if v not in SCHEDULES:
            raise bad(key, f"must be one of {', '.join(SCHEDULES)}, got {v!r}")
        return v
    if key == "type":
        if v not in TYPES:
            raise bad(key, f"must be one of {', '.join(TYPES)}, got {v!r}")
        return v
    if key == "effects":
        names = _list(v)
        for n in names:
            if n not in EFFECTS:
                raise bad(key, f"unknown effect {n!r} (known: {', '.join(EFFECTS)})")
        return sorted(set(names), key=EFFECTS.index)
    if key == "youngs_range":
        parts = v if isinstance(v, (list, tuple)) else str(v).split(",")
        try:
            lo, hi = (float(x) for x in parts)
        except (TypeError, ValueError):
            raise bad(key, f"expected MIN,MAX in Pa, got {v!r}") from None
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo < hi):
            raise bad(key, f"needs 0 < MIN < MAX, got {v!r}")
        return [lo, hi]
    if key == "sim_ready":
        s = str(v).strip().lower()
        if s in ("1", "true", "yes", "y"):
            return True
        if s in ("0", "false", "no", "n", ""):
            return False
        raise bad(key, f"must be true or false, got {v!r}")
    if key == "support_pixel":
        return _list(v)
    if key == "skip":
        names = _list(v)
        for n in names:
            if n not in SKIPPABLE:
                raise bad(key, f"{n!r} cannot be skipped (only {', '.join(SKIPPABLE)})")
        return sorted(set(names), key=SKIPPABLE.index)
    if key in ("fit_settings", "diagnose_settings"):
        if isinstance(v, dict):
            return dict(v)
        out = {}
        for part in (t.strip() for t in str(v).split(";")):
            if not part:
                continue
            k, eq, val = part.partition("=")
            if not eq or not k.strip():
                raise bad(key, f"expected name=value;name=value, got {part!r}")
            try:
                out[k.strip()] = json.loads(val)
            except ValueError:
                out[k.strip()] = val.strip()
        return out
    # hint_pixel, hint_particles, support_particles: the extraction's parser checks them
    if isinstance(v, (list, tuple)):
        return ",".join(str(x) for x in v)
    return str(v)
