"""Running the `physinteract-usd` CLI without blocking Blender: no bpy here (testable anywhere).

A `Job` is a list of steps run in order: `CliStep`s are subprocesses of the CLI (stdout and stderr
go to temp files, so a chatty verb can never fill a pipe and hang), `PyStep`s are callables run
in-process when their turn comes (the USD import, which must run on Blender's main thread).
The owner calls `poll()` from a timer (modal operator) or in a loop (background mode); `poll()`
never blocks on a subprocess.

On failure `Job.error` holds one line: the CLI's own error line from stderr (every verb prints
`physinteract-usd VERB: error: FILE: problem` on bad input), else a description of the exit.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from typing import Callable

CLI_NAME = "physinteract-usd"
EXIT_MEANING = {2: "bad input", 3: "simulation unstable", 130: "interrupted"}
KILL_AFTER = 5.0   # seconds between a forced stop's SIGTERM and SIGKILL
# variables Blender (or its bundled USD / MaterialX) sets that must not leak into the CLI's Python
_STRIP_ENV_PREFIXES = ("PXR_",)
_STRIP_ENV = ("PYTHONPATH", "PYTHONHOME", "MATERIALX_SEARCH_PATH", "PYTHONEXECUTABLE")


class CliNotFound(RuntimeError):
    pass


def resolve_cli(setting: str | None) -> list[str]:
    """The CLI as an argv prefix: the preference (an executable, or a command line such as
    `/path/python -m physinteract_usd`), else `physinteract-usd` on PATH."""
    setting = (setting or "").strip()
    if setting:
        if os.path.isfile(setting):
            if not os.access(setting, os.X_OK):
                raise CliNotFound(f"{setting}: is not executable")
            return [setting]
        parts = shlex.split(setting)
        exe = parts[0] if os.path.isabs(parts[0]) else shutil.which(parts[0])
        if exe is None or not os.path.isfile(exe):
            raise CliNotFound(f"{parts[0]}: not found (set the path of {CLI_NAME} in the add-on preferences)")
        return [exe, *parts[1:]]
    exe = shutil.which(CLI_NAME)
    if exe is None:
        raise CliNotFound(f"{CLI_NAME} not found on PATH: set its path in the add-on preferences "
                          "(Edit > Preferences > Add-ons > PhysInteract USD)")
    return [exe]


def cli_env(base: dict | None = None) -> dict:
    env = dict(os.environ if base is None else base)
    for k in list(env):
        if k in _STRIP_ENV or k.startswith(_STRIP_ENV_PREFIXES):
            del env[k]
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def last_line(text: str) -> str:
    """The last non-empty line, where carriage returns (progress bars) also end lines."""
    for line in reversed(text.replace("\r", "\n").split("\n")):
        if line.strip():
            return line.strip()
    return ""


def error_line(stderr: str) -> str:
    """The CLI's one-line error: the last stderr line that says error (argparse's included)."""
    lines = [ln.strip() for ln in stderr.replace("\r", "\n").split("\n") if ln.strip()]
    for ln in reversed(lines):
        if "error" in ln.lower():
            return ln
    return lines[-1] if lines else ""


@dataclass
class CliStep:
    label: str
    argv: list
    on_done: Callable[[str], None] | None = None  # called with stdout on success
    optional: bool = False        # a failure becomes a note in Job.notes and the job goes on


@dataclass
class PyStep:
    label: str
    fn: Callable[[], None]  # raises on failure; str(exc) becomes the error


@dataclass
class Job:
    steps: list
    cwd: str | None = None
    env: dict | None = None
    state: str = "idle"            # idle | running | done | failed | cancelled
    index: int = 0
    error: str = ""
    started: float = 0.0
    step_started: float = 0.0
    outputs: dict = field(default_factory=dict)   # label -> (returncode, stdout, stderr)
    notes: list = field(default_factory=list)     # one-line notes for the user (what was skipped)
    stopping: str = ""             # "" | "graceful" (SIGINT sent) | "forced" (SIGTERM sent)
    stop_requested: float = 0.0
    _proc: subprocess.Popen | None = None
    _out: object = None
    _err: object = None

    # ------------------------------------------------------------------ public
    @property
    def current(self):
        return self.steps[self.index] if self.index < len(self.steps) else None

    @property
    def finished(self) -> bool:
        return self.state in ("done", "failed", "cancelled")

    def start(self) -> "Job":
        self.state = "running"
        self.started = time.monotonic()
        self._begin()
        return self

    def poll(self) -> str:
        """Advance without blocking on a subprocess; returns the state."""
        while self.state == "running":
            step = self.current
            if step is None:
                self.state = "done"
                break
            if isinstance(step, PyStep):
                try:
                    step.fn()
                except Exception as exc:  # noqa: BLE001 - shown to the user as one line
                    self._fail(f"{step.label}: {last_line(str(exc)) or exc.__class__.__name__}")
                    break
                self._next()
                continue
            if self._proc.poll() is None:
                if self.stopping == "forced" and time.monotonic() - self.stop_requested > KILL_AFTER:
                    self._proc.kill()
                break
            self._finish_cli(step)
        return self.state

    def wait(self, interval: float = 0.05, timeout: float | None = None) -> str:
        """Blocking loop over poll() (background mode and tests)."""
        t0 = time.monotonic()
        while self.poll() == "running":
            if timeout is not None and time.monotonic() - t0 > timeout:
                self.kill()
                self.error = f"timed out after {timeout:.0f} s"
                break
            time.sleep(interval)
        return self.state

    def cancel(self, force: bool = False) -> None:
        """Ask the running step to stop; returns at once.

        First request: SIGINT, the CLI's own clean stop (a fit keeps its best iterate and writes
        it; that can take a while on the CPU): the job stays `running` with `stopping` set, and
        ends `cancelled` when the CLI exits. A second request (or force=True): SIGTERM (to the CLI
        a second signal: it quits at once, removing its temp files), then SIGKILL if it is still
        there `KILL_AFTER` seconds later. A PyStep or a job between steps stops at once."""
        proc = self._proc
        if proc is None or proc.poll() is not None or os.name != "posix":
            if proc is not None and proc.poll() is None:
                proc.kill()
                proc.wait()
            self._close()
            self._mark_cancelled()
            return
        now = time.monotonic()
        if not self.stopping and not force:
            self.stopping = "graceful"
            self.stop_requested = now
            proc.send_signal(signal.SIGINT)
        elif self.stopping != "forced":
            self.stopping = "forced"
            self.stop_requested = now
            proc.terminate()
        else:  # a third request: no more waiting
            proc.kill()

    def kill(self, timeout: float = 5.0) -> None:
        """Stop now and wait for the process (unregister, Blender quitting, timeouts)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            for stop in ([lambda: proc.send_signal(signal.SIGINT)] if os.name == "posix" else []) + \
                    [proc.terminate, proc.kill]:
                stop()
                try:
                    proc.wait(timeout / 3)
                    break
                except subprocess.TimeoutExpired:
                    continue
        self._close()
        self._mark_cancelled()

    def _mark_cancelled(self) -> None:
        if not self.finished:
            label = self.current.label if self.current else ""
            self.state = "cancelled"
            self.error = f"{label}: cancelled" if label else "cancelled"

    def progress(self) -> str:
        """One line for the panel: step k/n, its name, seconds, and what the CLI is doing (its
        latest meaningful output line, see `describe_output`)."""
        return self.progress_info()[0]

    def progress_info(self) -> tuple[str, float | None]:
        """(the panel's line, the step's completed share in [0, 1] or None when the CLI gives
        none, e.g. during the fit's start search)."""
        step = self.current
        if step is None:
            return "", None
        secs = time.monotonic() - self.step_started
        text = f"[{self.index + 1}/{len(self.steps)}] {step.label}  {secs:.0f} s"
        frac = None
        if isinstance(step, CliStep) and self._out is not None:
            what, frac = describe_output(self._tail(self._out, 16384), self._tail(self._err, 16384),
                                         stderr_newer=_mtime(self._err) > _mtime(self._out))
            if what:
                text += f"  {what[:120]}"
        if self.stopping == "graceful":
            text += f"  (stopping: waiting for the CLI's clean stop, {time.monotonic() - self.stop_requested:.0f} s; " \
                    "Cancel again to force)"
        elif self.stopping == "forced":
            text += "  (forcing the stop)"
        return text, frac

    # --------------------------------------------------------------- internals
    def _begin(self) -> None:
        self.step_started = time.monotonic()
        step = self.current
        if step is None or isinstance(step, PyStep):
            return
        self._out = tempfile.TemporaryFile(mode="w+b")
        self._err = tempfile.TemporaryFile(mode="w+b")
        try:
            self._proc = subprocess.Popen([str(a) for a in step.argv], stdout=self._out, stderr=self._err,
                                          stdin=subprocess.DEVNULL, cwd=self.cwd,
                                          env=self.env if self.env is not None else cli_env())
        except OSError as exc:
            self._close()
            self._fail(f"{step.label}: cannot run {step.argv[0]} ({exc.strerror or exc})")

    def _finish_cli(self, step: CliStep) -> None:
        rc = self._proc.returncode
        out, err = self._read(self._out), self._read(self._err)
        self._close()
        self.outputs[step.label] = (rc, out, err)
        if self.stopping:
            self.state = "cancelled"
            kept = "best iterate so far" in (out + err) or "interrupted" in last_line(out)
            how = "stopped" if self.stopping == "graceful" and rc in (0, 130) else "cancelled"
            self.error = f"{step.label}: {how}" + ("; the CLI kept its best iterate" if kept and how == "stopped" else "")
            return
        if rc != 0:
            line = error_line(err)
            what = EXIT_MEANING.get(rc, "failed") if rc >= 0 else f"killed by signal {-rc}"
            msg = line or f"{step.label}: {CLI_NAME} exited with code {rc} ({what})"
            if step.optional:
                self.notes.append(f"{step.label} skipped: {msg}")
                self._next()
                return
            self._fail(msg)
            return
        if step.on_done is not None:
            try:
                step.on_done(out)
            except Exception as exc:  # noqa: BLE001
                self._fail(f"{step.label}: {last_line(str(exc)) or exc.__class__.__name__}")
                return
        self._next()

    def _next(self) -> None:
        self.index += 1
        if self.index >= len(self.steps):
            self.state = "done"
        else:
            self._begin()

    def _fail(self, msg: str) -> None:
        self.state = "failed"
        self.error = msg

    def _close(self) -> None:
        for f in (self._out, self._err):
            if f is not None:
                f.close()
        self._out = self._err = None
        self._proc = None

    @staticmethod
    def _read(f) -> str:
        f.seek(0)
        return f.read().decode("utf-8", "replace")

    @staticmethod
    def _tail(f, n: int = 4096) -> str:
        if f is None:
            return ""
        try:
            size = os.fstat(f.fileno()).st_size
            f.seek(max(0, size - n))
            return f.read().decode("utf-8", "replace")
        except (OSError, ValueError):
            return ""


# ------------------------------------------------------------------------------- progress
# lines that say nothing about the verb's progress: Warp's banner and warnings, Python warnings
_NOISE = re.compile(r"^(Warp\b|Module \S+ \S+ load|\s*warnings\.warn|\S*Warning\b|.*\bUserWarning\b|"
                    r"\s*(Devices|Kernel cache|CUDA|Driver)\b|\s*\"(cpu|cuda)[:\"]|\s+\S.*:\s*$)", re.I)
# tqdm: "fit:  50%|#####     | 1/2 [00:16<00:16, 16.11s/it, E=2.29e+05, K=8, best=0.0914, loss=0.0914]"
_TQDM = re.compile(r"^(?P<desc>[^:|]*?):?\s*(?P<pct>\d+)%\|[^|]*\|\s*(?P<n>\d+)/(?P<total>\d+)\s*"
                   r"\[(?P<elapsed>[^<\]]*)<(?P<eta>[^,\]]*)(?:,\s*(?P<rate>[^,\]]*))?(?:,\s*(?P<post>[^\]]*))?\]")
_SEARCH = re.compile(r"^uniform E (?P<e>\S+) Pa: loss (?P<loss>\S+)")


def _lines(text: str) -> list[str]:
    return [ln.strip() for ln in text.replace("\r", "\n").split("\n") if ln.strip() and not _NOISE.match(ln)]


def _mtime(f) -> int:
    try:
        return os.fstat(f.fileno()).st_mtime_ns if f is not None else 0
    except (OSError, ValueError):
        return 0


def describe_output(stdout: str, stderr: str, stderr_newer: bool = True) -> tuple[str, float | None]:
    """What a running verb is doing, from the tails of its stdout and stderr: (one line, the share
    done or None). Skips Warp's banner and warnings; a tqdm bar becomes `fit 50% (1/2, 16.11s/it,
    ETA 00:16) loss=...`; the fit's start search (`uniform E ... Pa: loss ...` lines, before its
    bar exists) becomes `start search: 3 uniform E tried, best loss ...`. The newer of the two
    streams wins (the CLI logs to stdout and draws its bar on stderr)."""
    out, err = _lines(stdout), _lines(stderr)
    order = (err, out) if stderr_newer else (out, err)
    line = next((ls[-1] for ls in order if ls), "")
    if not line:
        return "", None
    m = _TQDM.match(line)
    if m:
        n, total = int(m["n"]), int(m["total"])
        rate = (m["rate"] or "").strip()
        bits = [f"{n}/{total}"] + ([rate] if rate and "?" not in rate else []) + \
            ([f"ETA {m['eta'].strip()}"] if m["eta"] and "?" not in m["eta"] else [])
        desc = m["desc"].strip() or "progress"
        text = f"{desc} {int(m['pct'])}% ({', '.join(bits)})"
        if m["post"]:
            text += " " + " ".join(p.strip() for p in m["post"].split(","))
        return text, (n / total if total else None)
    if _SEARCH.match(line):
        tried = [float(s["loss"]) for s in map(_SEARCH.match, out) if s]
        best = min(tried) if tried else float(_SEARCH.match(line)["loss"])
        return f"start search: {len(tried)} uniform E tried, best loss {best:.5g} (last: {line})", None
    return line, None


# ------------------------------------------------------------------------- argv of each verb
def init_argv(cli: list, stage: str, *, capture: str | None = None, object: str | None = None,
              video: str | None = None, camera: str | None = None, masks: str | None = None,
              masks_amodal: bool = False, fps: float | None = None, grid: int | None = None,
              force: bool = False, padding: float | None = None, youngs_range=None,
              poisson: float | None = None, max_poisson: float | None = None, density: float | None = None,
              spacing: float | None = None, model: str | None = None) -> list:
    """`init`'s argv; a setting left None (or 0) is not passed: the CLI's default applies."""
    argv = [*cli, "init", stage]
    for flag, value in (("--capture", capture), ("--object", object), ("--video", video),
                        ("--camera", camera), ("--masks", masks)):
        if value:
            argv += [flag, value]
    if masks_amodal:
        argv.append("--masks-amodal")
    if fps:
        argv += ["--fps", repr(float(fps))]
    if grid:
        argv += ["--grid", str(int(grid))]
    for flag, value in (("--padding", padding), ("--poisson", poisson), ("--max-poisson", max_poisson),
                        ("--density", density), ("--spacing", spacing)):
        if value:
            argv += [flag, f"{float(value):g}"]
    if youngs_range and all(youngs_range):
        argv += ["--youngs-range", f"{float(youngs_range[0]):g},{float(youngs_range[1]):g}"]
    if model:
        argv += ["--model", model]
    if force:
        argv.append("--force")
    return argv


_SUGGESTED_FLAGS = {"--grid": "grid", "--padding": "padding", "--youngs-range": "youngs_range",
                    "--poisson": "poisson", "--max-poisson": "max_poisson", "--density": "density",
                    "--spacing": "spacing", "--model": "model"}


def suggested_init(text: str) -> dict:
    """init's settings from a capture's README (`physinteract-usd synth` writes a `Suggested:` init
    command line): {"grid": 24, "padding": 0.3, "youngs_range": (1e3, 6e4), ..., "preload": "STRESS_FREE"}
    (the panel's Scan item for --preload / --no-preload); {} when none."""
    for line in text.splitlines():
        if " init " not in f" {line} " and not line.strip().startswith("physinteract-usd init"):
            continue
        try:
            words = shlex.split(line)
        except ValueError:
            continue
        out = {}
        for i, w in enumerate(words[:-1]):
            key = _SUGGESTED_FLAGS.get(w)
            if key is None:
                continue
            v = words[i + 1]
            try:
                if key == "youngs_range":
                    lo, hi = (float(x) for x in v.split(","))
                    out[key] = (lo, hi)
                elif key == "grid":
                    out[key] = int(v)
                elif key == "model":
                    out[key] = v
                else:
                    out[key] = float(v)
            except ValueError:
                continue
        for w, v in (("--preload", "PRELOAD"), ("--no-preload", "STRESS_FREE")):   # the scan's preload, a bare flag
            if w in words:
                out["preload"] = v
        if out:
            return out
    return {}


def verb_argv(cli: list, verb: str, stage: str, *rest) -> list:
    return [*cli, verb, stage, *map(str, rest)]
