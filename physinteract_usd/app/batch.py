"""`batch`: init -> extract -> fit -> report -> diagnose -> export over a manifest of captures or
stages, in a local process pool (default) or on a Ray cluster (one task per item); a summary table
(CSV + HTML) and a catalogue stage referencing every fitted asset (docs/batch.md).

```
OUT/                              default: <manifest stem>.batch/ beside the manifest
  summary.csv, summary.html       one row per manifest item (rewritten as items finish)
  catalogue.usda                  references every finished item's asset
  items/<name>/batch.json         the item's record: status, one-line error, step keys, numbers
  items/<name>/log.txt            what its steps said
  items/<name>/scene.usda ...     a capture's stage (a stage item is fitted where it is)
  items/<name>/report.html, report.json, diagnose.json, asset.usdc [, asset.sim.usda]
```

Idempotent: every step has a key (batch/keys.py: the inputs' fingerprint and the settings up to
that step); an item whose recorded keys all match is reused without running, and an item runs
from its first stale step (a failed fit re-runs from the fit, a changed hint from extraction).
One item's failure is its record's one-line error; the rest go on. SIGINT / SIGTERM stop cleanly:
items not started stay to do, running fits keep their best iterate (an `interrupted` version), and
finished items are kept.

The core (manifest parsing, keys, schedulers, summary) is `physinteract_usd.batch`; this module
is what an item runs, through the application layer's verbs (no subprocess of our CLI).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import os
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from .. import __version__
from ..batch.keys import STEPS, first_stale_step, fingerprint, step_keys
from ..batch.manifest import HINT_KEYS, KEYS, Item, read_manifest
from ..batch.runner import Events, run_pool
from ..batch.summary import atomic_write_text, write_csv, write_html
from ..errors import InputError, SimulationError

MARKER = ".physinteract-batch.json"
RECORD = "batch.json"
DEFAULT_ITERATIONS = 60


# ------------------------------------------------------------------------------ the manifest
def load_manifest(manifest) -> list[Item]:
    """The manifest's items, their hints checked by the extraction's own parser (InputError naming
    the manifest and row)."""
    from ..extract import parse_hint

    from ..fit import FitSettings

    known = {f.name for f in dataclasses.fields(FitSettings)} - {"iterations", "seed", "schedule", "joint"}
    diag = diagnose_function()
    diag_known = set()
    if diag is not None:
        diag_known = {n for n, prm in inspect.signature(diag).parameters.items()
                      if prm.kind is prm.KEYWORD_ONLY} - {"device", "progress", "log", "write_stage"}
    items = read_manifest(manifest)
    for it in items:
        try:
            _hint(it.options, parse_hint)
        except InputError as exc:
            raise InputError(manifest, f"row {it.row}: {exc.oneline()}") from None
        for k in it.options.get("fit_settings") or {}:
            if k not in known:
                raise InputError(manifest, f"row {it.row}, 'fit_settings': unknown setting {k!r} (known: "
                                 f"{', '.join(sorted(known))})")
        for k in it.options.get("diagnose_settings") or {}:
            if diag is not None and k not in diag_known:
                raise InputError(manifest, f"row {it.row}, 'diagnose_settings': unknown option {k!r} (known: "
                                 f"{', '.join(sorted(diag_known))})")
    return items


def _hint(s: dict, parse_hint):
    return parse_hint(s.get("hint_pixel"), s.get("hint_particles"), s.get("support_pixel") or None,
                      s.get("support_particles"), s.get("grasp_radius"), grasp_frame=s.get("grasp_frame"),
                      release_frame=s.get("release_frame"))


def resolve_settings(item: Item, defaults: dict) -> dict:
    """Every setting of the item: its own, else the command's, else None (the verb's default)."""
    s = {k: None for k in KEYS if k not in ("source", "name")}
    s.update({k: v for k, v in defaults.items() if v is not None})
    s.update(item.options)
    s["effects"] = list(s.get("effects") or [])
    s["sim_ready"] = bool(s.get("sim_ready"))
    s["skip"] = list(s.get("skip") or [])
    return s


def diagnose_function():
    """`app.diagnose.diagnose` when this build has the verb (it is looked up when a batch runs)."""
    try:
        mod = importlib.import_module(f"{__package__}.diagnose")
    except ImportError:
        return None
    return getattr(mod, "diagnose", None)


# ------------------------------------------------------------------------------ one item (in a worker)
def _call(fn, *args, **kw):
    """`fn(*args, **kw)` without the keywords it does not take (verbs that land later may differ)."""
    try:
        params = inspect.signature(fn).parameters
    except (TypeError, ValueError):
        return fn(*args, **kw)
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return fn(*args, **kw)
    return fn(*args, **{k: v for k, v in kw.items() if k in params})


class _Interrupted(KeyboardInterrupt):
    pass


def _first_line(exc: BaseException) -> str:
    if isinstance(exc, InputError):
        return exc.oneline()
    if isinstance(exc, SimulationError):
        return exc.message()
    text = [ln for ln in str(exc).strip().splitlines() if ln.strip()]
    return f"{type(exc).__name__}: {text[0].strip()}" if text else type(exc).__name__


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:
        pass
    return str(o)


class _StopWatcher:
    """On Ray, the driver asks running items to stop by creating a stop file beside the outputs
    (a signal cannot reach a task, and Ray's own cancel interrupts it wherever it stands): while
    the file exists a thread asks this process's run to stop, as a signal would (`stopping`), so
    a fit writes its best iterate; the steps check `seen` between them."""

    def __init__(self, path):
        import threading

        self.path, self.seen = path, bool(path) and os.path.exists(path)
        self._done = threading.Event()
        if path:
            threading.Thread(target=self._watch, daemon=True).start()

    def _watch(self):
        from .. import stopping

        while not self._done.wait(0.5):
            if os.path.exists(self.path):
                self.seen = True
                stopping.request("SIGTERM")   # again after a fit's graceful() starts afresh

    def close(self):
        from .. import stopping

        self._done.set()
        if self.seen:   # a reused worker process must not carry the request into its next item
            stopping._STATE.reset()


def run_item(p: dict) -> dict:
    """Run one item's steps from `p["start"]` (the earlier ones are reused); returns its record.
    Never raises for the item's own failures: they are the record's one-line `error`."""
    t0 = time.perf_counter()
    work = Path(p["work"])
    work.mkdir(parents=True, exist_ok=True)
    s = p["settings"]
    device = s.get("device") or "cpu"
    prev = p.get("previous") or {}
    kind, source = p["kind"], Path(p["source"])
    stage = source if kind == "stage" else work / "scene.usda"
    rec = {"name": p["name"], "source": str(source), "kind": kind, "status": "failed", "error": None,
           "failed_step": None, "settings": s, "steps": {}, "keys": {},
           "metrics": dict(prev.get("metrics") or {}), "outputs": dict(prev.get("outputs") or {}),
           "notes": [], "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "version": __version__}
    rec["outputs"].update({"stage": str(stage), "log": str(work / "log.txt")})
    logf = open(work / "log.txt", "a", encoding="utf-8")

    def log(*parts):
        logf.write(" ".join(str(x) for x in parts) + "\n")
        logf.flush()

    log(f"=== {time.strftime('%Y-%m-%d %H:%M:%S')} batch item {p['name']} ({kind} {source}), from step {p['start']}")
    start = STEPS.index(p["start"])
    step = STEPS[0]
    watcher = _StopWatcher(p.get("stop_file"))
    try:
        from ..devices import cpu_threads, quiet_warp_init

        quiet_warp_init(device)
        cpu_threads(device)   # one torch thread on the CPU: Warp is single-threaded, the ops are small
        if os.environ.get("OMP_NUM_THREADS", "").isdigit():   # a pool's share of the cores (OpenCV's own pool too)
            import cv2

            cv2.setNumThreads(int(os.environ["OMP_NUM_THREADS"]))
        for i, step in enumerate(STEPS):
            if watcher.seen:
                raise KeyboardInterrupt("stop requested")
            if i < start:
                rec["steps"][step] = {"status": "reused"}
                continue
            ts = time.perf_counter()
            log(f"--- {step}")
            if step in (s.get("skip") or []):
                status, note = "skipped", "left out as asked"
                for k in _STEP_METRICS.get(step, ()):   # nothing of an earlier run's step stays as if current
                    rec["metrics"].pop(k, None)
                    rec["outputs"].pop(k, None)
            else:
                status, note = _STEP[step](p, s, stage, work, rec, log)
            rec["steps"][step] = {"status": status, "seconds": round(time.perf_counter() - ts, 3)}
            if note:
                rec["steps"][step]["note"] = note
                rec["notes"].append(f"{step}: {note}")
                log(f"{step}: {note}")
        rec["status"], step = "done", None
    except KeyboardInterrupt as exc:
        rec["status"], rec["error"] = "interrupted", f"{step}: interrupted" + (f" ({exc})" if str(exc) else "")
    except Exception as exc:  # noqa: BLE001  (one item's failure is its record, whatever it is)
        rec["error"] = f"{step}: {_first_line(exc)}"
        log(traceback.format_exc())
    finally:
        watcher.close()
    if step is not None:
        rec["failed_step"] = step
        rec["steps"].setdefault(step, {"status": "interrupted" if rec["status"] == "interrupted" else "failed"})
    # the keys of the steps that hold (a stage's are taken after the run: its root has our effects)
    keys = p["keys"] if kind == "capture" else step_keys(s, fingerprint(source, kind), __version__)
    ok = [st for st in STEPS if rec["steps"].get(st, {}).get("status") in ("ran", "reused", "skipped")]
    for st in STEPS:
        if st not in ok:
            break
        if (st == "diagnose" and rec["steps"][st]["status"] == "skipped"
                and "diagnose" not in (s.get("skip") or [])):
            continue   # a diagnosis skipped for want of the verb runs once the verb is there
        rec["keys"][st] = keys[st]
    rec["seconds"] = round(time.perf_counter() - t0, 2)
    log(f"=== {rec['status']}" + (f": {rec['error']}" if rec["error"] else "") + f" ({rec['seconds']} s)")
    logf.close()
    return json.loads(json.dumps(rec, default=_json_default))


def _step_init(p, s, stage, work, rec, log):
    from .adapters import read_scene
    from .init import init

    if p["kind"] == "stage":
        if not stage.is_file():
            raise InputError(stage, "stage not found")
        read_scene(stage)   # checked: a stage with bad authored values fails here
        return "skipped", "an existing stage: fitted where it is"
    kw = {k: s[k] for k in ("grid", "fps") if s.get(k) is not None}
    if s.get("youngs_range"):
        kw["youngs_range"] = tuple(s["youngs_range"])
    redo = stage.exists()
    init(stage, p["source"], force=redo, discard_fits=redo, yes=True, **kw)
    return "ran", ("re-initialised (the capture or init settings changed)" if redo else "")


def _step_extract(p, s, stage, work, rec, log):
    from ..extract import parse_hint
    from .adapters import read_scene, stage_contacts
    from .extract import extract

    hint = _hint(s, parse_hint)
    if p["kind"] == "stage" and hint is None and s.get("type") is None and stage_contacts(read_scene(stage)):
        return "skipped", "the stage's own contacts"
    r = extract(stage, hint=hint, interaction_type=s.get("type"), log=log, device=s.get("device") or "cpu")
    prev = Path(str(stage)[: -len(stage.suffix)] + ".extract") / "preview.png"
    if prev.exists():
        rec["outputs"]["preview"] = str(prev)
    summ = r.summary() if hasattr(r, "summary") else {}
    rec["metrics"]["interaction"] = summ.get("interaction_type") or summ.get("type") or ""
    return "ran", ""


def _apply_effects(p, s, stage, log) -> str:
    """Switch on the item's effects (and, on a capture's own stage, off the ones it no longer
    lists) through the `effects` verb; a note of what changed."""
    from .adapters import read_scene, stage_effects

    want = list(s.get("effects") or [])
    have = set(stage_effects(read_scene(stage)))
    add = [e for e in want if e not in have]
    drop = sorted(have - set(want)) if p["kind"] == "capture" else []
    if not add and not drop:
        return ""
    try:
        mod = importlib.import_module(f"{__package__}.effects")
    except ImportError:
        mod = None
    fn_add = getattr(mod, "add", None) or getattr(mod, "add_effect", None)
    fn_drop = getattr(mod, "remove", None) or getattr(mod, "remove_effect", None)
    if (add and fn_add is None) or (drop and fn_drop is None):
        raise InputError("effects", "this build has no `effects` verb to switch effects on or off: author "
                         "them in the stage, or leave the manifest's effects empty")
    for e in add:
        _call(fn_add, stage, e, log=log)
    for e in drop:
        _call(fn_drop, stage, e, log=log)
    return ", ".join([f"+{e}" for e in add] + [f"-{e}" for e in drop])


def _step_fit(p, s, stage, work, rec, log):
    from .fit import fit

    note = _apply_effects(p, s, stage, log)
    over = dict(s.get("fit_settings") or {})
    if s.get("schedule"):
        over["schedule"] = s["schedule"]
    for k, v in over.items():   # a tuple setting (levels, level_share) arrives from JSON as a list
        if isinstance(v, list):
            over[k] = tuple(v)
    out = fit(stage, iterations=s.get("iterations") or DEFAULT_ITERATIONS, device=s.get("device") or "cpu",
              seed=int(s.get("seed") or 0), progress=False, log=log, settings_overrides=over or None,
              yes=True)
    summ = out.summary()
    m = rec["metrics"]
    m.update({"version": summ["version"], "current_version": summ["current_version"],
              "final_loss": summ["final_loss"], "fit_psnr": summ["psnr"], "fit_seconds": summ["runtime_s"],
              "iterations": summ["iterations"], "youngs_median_pa": summ["youngs_modulus_pa"]["median"],
              "youngs_min_pa": summ["youngs_modulus_pa"]["min"], "youngs_max_pa": summ["youngs_modulus_pa"]["max"],
              "device": summ["device"]})
    (work / "fit.json").write_text(json.dumps(summ, indent=1, default=_json_default))
    rec["outputs"]["fit_json"] = str(work / "fit.json")
    if summ["stopped_by"] or summ["interrupted"]:
        raise _Interrupted(f"stopped by {summ['stopped_by'] or 'a signal'}: v{summ['version']} holds the best iterate")
    if not summ["is_current"]:
        note = (note + "; " if note else "") + (f"v{summ['version']} kept as a version, v{summ['current_version']} "
                                                f"stays current ({summ['current_reason']})")
    return "ran", note


def _step_report(p, s, stage, work, rec, log):
    from .report import report

    html, js = work / "report.html", work / "report.json"
    data = report(stage, html=html, force=True, device=s.get("device") or "cpu", progress=False, log=log)
    atomic_write_text(js, json.dumps(data, indent=1, default=_json_default))
    rec["outputs"].update({"report_html": str(html), "report_json": str(js)})
    m = rec["metrics"]
    for k in ("psnr", "psnr_masked", "ssim", "iou", "track_error_px", "verdict", "headline"):
        if k in data:
            m[k] = data[k]
    m["frames_psnr"] = [f.get("psnr") for f in data.get("frames") or []]
    if data.get("version") is not None:
        m["reported_version"] = data["version"]
    return "ran", ""


def _step_diagnose(p, s, stage, work, rec, log):
    fn = diagnose_function()
    m = rec["metrics"]
    if fn is None:
        for k in ("diagnosis", "diagnosis_reason", "top_candidate"):
            m.pop(k, None)
        return "skipped", "this build has no diagnose verb yet"
    opts = dict(s.get("diagnose_settings") or {})
    data = _call(fn, stage, device=s.get("device") or "cpu", progress=False, log=log, **opts)
    if hasattr(data, "summary") and callable(data.summary):
        data = data.summary()
    if not isinstance(data, dict):
        data = {"verdict": str(data)}
    js = work / "diagnose.json"
    atomic_write_text(js, json.dumps(data, indent=1, default=_json_default))
    rec["outputs"]["diagnose_json"] = str(js)
    m["diagnosis"] = data.get("verdict", "")
    m["diagnosis_reason"] = data.get("reason", "")
    cands = data.get("candidates") or []
    m["top_candidate"] = cands[0].get("effect", "") if cands and isinstance(cands[0], dict) else ""
    return "ran", ""


def _step_export(p, s, stage, work, rec, log):
    from .export import export

    asset = work / "asset.usdc"
    export(stage, asset, force=True)
    rec["outputs"]["asset"] = str(asset)
    if s.get("sim_ready"):
        sim = work / "asset.sim.usda"
        export(stage, sim, force=True, sim_ready=True)
        rec["outputs"]["sim_ready"] = str(sim)
    else:
        rec["outputs"].pop("sim_ready", None)
    return "ran", ""


_STEP_METRICS = {"report": ("psnr", "psnr_masked", "ssim", "iou", "track_error_px", "verdict", "headline",
                             "frames_psnr", "reported_version", "report_html", "report_json"),
                 "diagnose": ("diagnosis", "diagnosis_reason", "top_candidate", "diagnose_json"),
                 "export": ("asset", "sim_ready")}

_STEP = {"init": _step_init, "extract": _step_extract, "fit": _step_fit, "report": _step_report,
         "diagnose": _step_diagnose, "export": _step_export}


# ------------------------------------------------------------------------------ the driver
@dataclass
class _Plan:
    item: Item
    work: Path
    settings: dict
    keys: dict
    previous: dict | None
    start: str | None          # None: reused as it is


@dataclass
class BatchResult:
    out: Path
    records: dict = field(default_factory=dict)      # name -> record (manifest order)
    reused: list = field(default_factory=list)
    ran: list = field(default_factory=list)
    failed: list = field(default_factory=list)
    interrupted: list = field(default_factory=list)
    not_started: list = field(default_factory=list)
    outputs: dict = field(default_factory=dict)
    seconds: float = 0.0

    def summary(self) -> dict:
        """The JSON `batch --json` prints."""
        return {"out": str(self.out), "items": len(self.records), "ran": self.ran, "reused": self.reused,
                "failed": {n: self.records[n].get("error") for n in self.failed}, "interrupted": self.interrupted,
                "not_started": self.not_started, "outputs": self.outputs, "seconds": round(self.seconds, 2),
                "records": [{k: r.get(k) for k in ("name", "status", "error", "seconds", "metrics", "outputs", "notes")}
                            for r in self.records.values()]}


def _prepare_out(out: Path, manifest: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).exists():
        raise InputError(out, "exists, is not empty and was not written by `batch`: choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    from ..usd.layout import check_writable_dir

    check_writable_dir(out)
    (out / "items").mkdir(exist_ok=True)
    atomic_write_text(out / MARKER, json.dumps({"generator": f"physinteract-usd {__version__}",
                                                "manifest": str(manifest.resolve())}, indent=1))


def _acquire_lock(out: Path) -> Path:
    """OUT/.lock holding this process's id; InputError while another live `batch` holds it."""
    lock = out / ".lock"
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            try:
                pid = int(lock.read_text().strip() or 0)
                os.kill(pid, 0)
            except (ValueError, ProcessLookupError, FileNotFoundError):
                lock.unlink(missing_ok=True)      # left by a batch that is gone
                continue
            except PermissionError:
                pass
            raise InputError(out, f"another batch (process {pid}) is writing this folder; wait for it or "
                             "choose another --out") from None
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        return lock
    raise InputError(lock, "cannot take the output folder's lock")


def _read_record(work: Path) -> dict | None:
    try:
        r = json.loads((work / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return r if isinstance(r, dict) else None


def _cores() -> int:
    """The CPU cores this process may use (its affinity: a container's share, not the host's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


class _Progress(Events):
    def __init__(self, result: BatchResult, plans: dict, total: int, progress: bool, log, write_summary):
        self.result, self.plans, self.log, self.write_summary = result, plans, log, write_summary
        self.running: set[str] = set()
        self.bar = None
        if progress and total:
            from tqdm import tqdm

            import sys

            tty = sys.stderr.isatty()
            self.bar = tqdm(total=total, unit="item", desc="batch", dynamic_ncols=True, mininterval=0.5 if tty else 30.0)
        self._post()

    def _say(self, msg):
        if self.bar is not None:
            self.bar.write(msg)
        else:
            self.log(msg)

    def _post(self):
        if self.bar is not None:
            r = self.result
            self.bar.set_postfix_str(f"done {len(r.ran)}, running {len(self.running)}, failed {len(r.failed)}"
                                     + (f", reused {len(r.reused)}" if r.reused else ""), refresh=False)
            self.bar.update(0)

    def _record(self, name: str, rec: dict) -> None:
        plan = self.plans[name]
        plan.work.mkdir(parents=True, exist_ok=True)
        atomic_write_text(plan.work / RECORD, json.dumps(rec, indent=1, default=_json_default))
        self.result.records[name] = rec
        self.running.discard(name)
        st = rec.get("status")
        (self.result.ran if st == "done" else self.result.interrupted if st == "interrupted"
         else self.result.failed).append(name)
        if self.bar is not None:
            self.bar.update(1)
        m = rec.get("metrics") or {}
        if st == "done":
            extra = ", ".join(x for x in (
                f"v{m['version']}" if m.get("version") is not None else "",
                f"PSNR {m['psnr']:.2f} dB" if isinstance(m.get("psnr"), (int, float)) else "",
                str(m.get("verdict") or ""), f"diagnosis {m['diagnosis']}" if m.get("diagnosis") else "") if x)
            self._say(f"{name}: done in {rec.get('seconds', 0):.0f} s" + (f" ({extra})" if extra else ""))
        else:
            self._say(f"{name}: {st.upper()}: {rec.get('error')}")
        self._post()
        self.write_summary()

    def started(self, name):
        self.running.add(name)
        self._post()

    def finished(self, name, record):
        self._record(name, record)

    def _synthetic(self, name, status, error):
        plan = self.plans[name]
        return {"name": name, "source": str(plan.item.source), "kind": plan.item.kind, "status": status,
                "error": error, "settings": plan.settings, "steps": {}, "keys": {},
                "metrics": dict((plan.previous or {}).get("metrics") or {}),
                "outputs": dict((plan.previous or {}).get("outputs") or {}), "notes": [], "version": __version__}

    def failed(self, name, error):
        self._record(name, self._synthetic(name, "failed", error))

    def interrupted(self, name):
        self._record(name, self._synthetic(name, "interrupted", "interrupted before it finished"))

    def tick(self):
        if self.bar is not None:
            self.bar.update(0)   # refreshes the elapsed time and ETA at most every mininterval

    def close(self):
        if self.bar is not None:
            self.bar.close()


def batch(manifest, *, out=None, workers=None, ray=None, device=None, iterations=None, schedule=None, seed=None,
          grid=None, skip=None, gpus_per_item=1.0, retries=2, force=False, progress=True, log=print) -> BatchResult:
    """Run every manifest item (module doc). `ray`: None for the local process pool of `workers`
    processes (default: one per CPU core, one in all when an item uses CUDA); "" or an address for
    Ray (one task per item, `gpus_per_item` GPUs each when it uses CUDA, `retries` when its worker
    dies). `device`, `iterations`, `schedule`, `seed`, `grid`, `skip` (steps left out: report,
    diagnose, export): the defaults an item's own columns override. `force`: run every item from its first step. Returns a BatchResult; items that fail
    are in `.failed` (with their one-line errors in `.records`), not raised."""
    t0 = time.perf_counter()
    manifest = Path(manifest)
    items = load_manifest(manifest)
    if workers is not None and (isinstance(workers, bool) or int(workers) < 1):
        raise InputError("--workers", f"must be at least 1, got {workers}")
    if ray is not None and workers is not None:
        raise InputError("--workers", "is the local pool's size: with --ray the cluster's CPUs and GPUs decide "
                         "how many items run at once")
    if retries is None or int(retries) < 0:
        raise InputError("--retries", f"must be >= 0, got {retries}")
    if not (float(gpus_per_item) > 0):
        raise InputError("--gpus-per-item", f"must be positive, got {gpus_per_item}")
    if skip:
        from ..batch.manifest import SKIPPABLE

        skip = [x.strip() for x in (skip.split(",") if isinstance(skip, str) else skip) if x.strip()]
        bad = [x for x in skip if x not in SKIPPABLE]
        if bad:
            raise InputError("--skip", f"{bad[0]!r} cannot be skipped (only {', '.join(SKIPPABLE)})")
    defaults = {"device": device, "iterations": iterations, "schedule": schedule, "seed": seed, "grid": grid,
                "skip": skip or None}
    if ray is not None:
        from ..batch.ray_runner import import_ray

        import_ray()   # without Ray: one line saying how to get it, before anything is written
    else:
        from ..devices import check_device

        for d in sorted({(it.options.get("device") or device or "cpu") for it in items}):
            check_device(d)
    out = Path(out) if out is not None else manifest.with_name(f"{manifest.stem}.batch")
    _prepare_out(out, manifest)
    lock = _acquire_lock(out)
    try:
        diag = diagnose_function() is not None
        result = BatchResult(out=out)
        plans: dict[str, _Plan] = {}
        for it in items:
            s = resolve_settings(it, defaults)
            s["diagnose_available"] = diag
            work = out / "items" / it.name
            prev = _read_record(work)
            if work.exists() and prev is None and any(work.iterdir()):
                raise InputError(work, "exists and holds no batch record: not written by `batch`; move it away")
            keys = step_keys(s, fingerprint(it.source, it.kind), __version__)
            start = "init" if force or prev is None else first_stale_step(prev.get("keys"), keys)
            if start is None and prev.get("status") != "done":
                start = "init"
            plans[it.name] = _Plan(it, work, s, keys, prev, start)
        for name, plan in plans.items():
            if plan.start is None:
                result.records[name] = plan.previous
                result.reused.append(name)
        paths = {"summary_csv": out / "summary.csv", "summary_html": out / "summary.html",
                 "catalogue": out / "catalogue.usda"}

        def ordered():
            return [result.records[n] if n in result.records else
                    {"name": n, "source": str(plans[n].item.source), "status": "not run", "error": None}
                    for n in plans]

        def write_summary():
            recs = []
            for r in ordered():
                r = dict(r)
                if r["name"] in result.reused:
                    r["status"] = "reused"
                recs.append(r)
            totals = {"items": len(plans), "ran": len(result.ran), "reused": len(result.reused),
                      "failed": len(result.failed), "interrupted": len(result.interrupted)}
            write_csv(paths["summary_csv"], recs, out)
            write_html(paths["summary_html"], recs, out, title=f"physinteract-usd batch: {manifest.name}", totals=totals)

        tasks = [(name, {"name": name, "source": str(pl.item.source), "kind": pl.item.kind, "work": str(pl.work),
                         "settings": pl.settings, "keys": pl.keys, "start": pl.start, "previous": pl.previous})
                 for name, pl in plans.items() if pl.start is not None]
        if result.reused:
            log(f"{len(result.reused)} of {len(plans)} items done earlier with the same inputs and settings: reused "
                f"({', '.join(result.reused[:5])}{', ...' if len(result.reused) > 5 else ''})")
        ev = _Progress(result, plans, len(tasks), progress, log, write_summary)
        try:
            if tasks:
                if ray is not None:
                    from ..batch.ray_runner import run_ray

                    stop_file = out / f".stop-{os.getpid()}-{int(time.time())}"
                    for _, pl in tasks:
                        pl["stop_file"] = str(stop_file)
                    result.not_started = run_ray(
                        tasks, run_item, address=ray or None, events=ev, retries=int(retries), stop_file=stop_file,
                        gpus=lambda pl: float(gpus_per_item) if str(pl["settings"].get("device") or "cpu").startswith("cuda")
                        else 0.0)
                else:
                    uses_cuda = any(str(pl["settings"].get("device") or "cpu").startswith("cuda") for _, pl in tasks)
                    n = int(workers) if workers is not None else (1 if uses_cuda else _cores())
                    n = min(n, len(tasks))
                    # the workers' native thread pools (OpenMP, OpenCV) share the cores instead of
                    # each spinning on all of them
                    threads = str(max(1, _cores() // n))
                    env = {k: threads for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
                    # ... and a diagnosis's worker processes too (`workers.fork_map`), unless the user set them
                    env.setdefault("PHYSINTERACT_WORKERS", os.environ.get("PHYSINTERACT_WORKERS") or threads)
                    result.not_started = run_pool(tasks, run_item, workers=n, events=ev, retries=int(retries),
                                                  env=env)
        finally:
            ev.close()
            write_summary()
            from ..usd.catalogue import write_catalogue

            entries = []
            for r in ordered():
                if r.get("status") == "done" and (r.get("outputs") or {}).get("asset"):
                    m = r.get("metrics") or {}
                    data = {k: m[k] for k in ("version", "psnr", "psnr_masked", "ssim", "iou", "verdict", "diagnosis",
                                              "top_candidate", "youngs_median_pa") if m.get(k) not in (None, "")}
                    data["source"] = str(r.get("source", ""))
                    entries.append({"name": r["name"], "asset": r["outputs"]["asset"], "data": data})
            write_catalogue(paths["catalogue"], entries)
    finally:
        lock.unlink(missing_ok=True)
    result.records = {n: result.records[n] for n in plans if n in result.records}
    result.outputs = {k: str(v) for k, v in paths.items()}
    result.seconds = time.perf_counter() - t0
    return result
