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
                break
            self._finish_cli(step)
        return self.state

    def wait(self, interval: float = 0.05, timeout: float | None = None) -> str:
        """Blocking loop over poll() (background mode and tests)."""
        t0 = time.monotonic()
        while self.poll() == "running":
            if timeout is not None and time.monotonic() - t0 > timeout:
                self.cancel()
                self.error = f"timed out after {timeout:.0f} s"
                break
            time.sleep(interval)
        return self.state

    def cancel(self) -> None:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            # SIGINT first: the CLI turns it into KeyboardInterrupt, removes its temp files and
            # exits 130; then SIGTERM, then SIGKILL
            stops = ([lambda: proc.send_signal(signal.SIGINT)] if os.name == "posix" else []) + \
                [proc.terminate, proc.kill]
            for stop in stops:
                stop()
                try:
                    proc.wait(3)
                    break
                except subprocess.TimeoutExpired:
                    continue
        self._close()
        if not self.finished:
            self.state = "cancelled"
            self.error = f"{self.current.label}: cancelled" if self.current else "cancelled"

    def progress(self) -> str:
        """One line for the panel: step k/n, its name, seconds, and the CLI's latest output line."""
        step = self.current
        if step is None:
            return ""
        text = f"[{self.index + 1}/{len(self.steps)}] {step.label}  {time.monotonic() - self.step_started:.0f} s"
        if isinstance(step, CliStep) and self._out is not None:
            tail = last_line(self._tail(self._err)) or last_line(self._tail(self._out))
            if tail:
                text += f"  {tail[:120]}"
        return text

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
        if rc != 0:
            line = error_line(err)
            what = EXIT_MEANING.get(rc, "failed") if rc >= 0 else f"killed by signal {-rc}"
            self._fail(line or f"{step.label}: {CLI_NAME} exited with code {rc} ({what})")
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


# ------------------------------------------------------------------------- argv of each verb
def init_argv(cli: list, stage: str, *, capture: str | None = None, object: str | None = None,
              video: str | None = None, camera: str | None = None, masks: str | None = None,
              masks_amodal: bool = False, fps: float | None = None, grid: int | None = None,
              force: bool = False) -> list:
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
    if force:
        argv.append("--force")
    return argv


def verb_argv(cli: list, verb: str, stage: str, *rest) -> list:
    return [*cli, verb, stage, *map(str, rest)]
