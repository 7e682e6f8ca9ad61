"""What the installed `physinteract-usd` offers: its verbs and each verb's flags, read from its own
`-h` (about 0.7 s a call: the CLI imports its heavy modules lazily). No bpy here.

The panel shows a feature (report, diagnose, effects, versions, `export --sim-ready`, the grasp
and release hints) only when the CLI has it, and says so in one line when it does not, so the
add-on works with an older CLI and picks new verbs up without an update.
"""

from __future__ import annotations

import re
import subprocess
import threading

from .runner import cli_env

_CACHE: dict = {}            # (argv tuple, verb or "") -> set of names, or None while probing
_LOCK = threading.Lock()
_VERB_LINE = re.compile(r"^\s{2,}([a-z][a-z0-9-]*)\s{2,}\S|^\s{2,}([a-z][a-z0-9-]*)\s*$")
_FLAG = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")


def _help(cli: list, *verb: str, timeout: float = 60.0) -> str:
    try:
        proc = subprocess.run([*cli, *verb, "-h"], capture_output=True, text=True, timeout=timeout,
                              env=cli_env(), stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return proc.stdout if proc.returncode == 0 else ""


def parse_verbs(help_text: str) -> set:
    """The verbs listed under `positional arguments:` / `VERB` in `physinteract-usd -h`, or in its
    usage line's `{a,b,c}`."""
    m = re.search(r"\{([a-z0-9_,-]+)\}", help_text)
    if m:
        return set(m.group(1).split(","))
    verbs, inside = set(), False
    for line in help_text.splitlines():
        if line.strip() == "VERB":
            inside = True
            continue
        if inside:
            if line and not line.startswith(" "):
                break
            mm = _VERB_LINE.match(line)
            if mm and line.startswith("    ") and not line.startswith("      "):
                verbs.add(mm.group(1) or mm.group(2))
    return verbs


def parse_flags(help_text: str) -> set:
    return set(_FLAG.findall(help_text))


def verbs(cli: list, refresh: bool = False) -> set:
    """The CLI's verbs (empty if it cannot be run). Blocks the first time (one `-h`)."""
    return _get(cli, "", refresh)


def flags(cli: list, verb: str, refresh: bool = False) -> set:
    """A verb's `--flags` (empty if the verb is absent)."""
    if verb not in verbs(cli, refresh):
        return set()
    return _get(cli, verb, refresh)


def has(cli: list, verb: str, flag: str | None = None) -> bool:
    return verb in verbs(cli) and (flag is None or flag in flags(cli, verb))


def _get(cli, verb, refresh):
    key = (tuple(cli), verb)
    with _LOCK:
        known = _CACHE.get(key)
    if known is not None and not refresh:
        return known
    text = _help(cli, verb) if verb else _help(cli)
    value = parse_flags(text) if verb else parse_verbs(text)
    with _LOCK:
        _CACHE[key] = value
    return value


def cached(cli: list, verb: str = "") -> set | None:
    """What is known without running anything (None: not probed yet): for the panel's draw()."""
    with _LOCK:
        return _CACHE.get((tuple(cli), verb))


def probe_in_background(cli: list, verb_list=("extract", "export", "report", "diagnose", "effects",
                                                "versions", "simulate", "init", "fit")) -> threading.Thread:
    """Fill the cache off Blender's main thread (the panel draws from `cached`)."""
    def work():
        vs = verbs(cli)
        for v in verb_list:
            if v in vs:
                _get(cli, v, False)

    t = threading.Thread(target=work, daemon=True, name="physinteract-cli-probe")
    t.start()
    return t


def clear() -> None:
    with _LOCK:
        _CACHE.clear()
