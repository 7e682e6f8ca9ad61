"""The package's layering (docs/ARCHITECTURE.md): no module imports one above it, no import cycles
between packages, and pxr only in usd/."""

from __future__ import annotations

import ast
import collections
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "physinteract_usd"

# lower imports nothing above it; a package may import itself freely
RANKS = {
    "errors": 0,
    "devices": 1, "gaussians": 1, "frames": 1, "camera": 1, "contacts": 1, "metrics": 1, "stopping": 1, "workers": 1,
    "thickness": 1,  # the thinnest part of a voxelised solid (numpy / scipy)
    "resolution": 1,  # the MPM's apparent stiffness by cells across a thin part (numpy)
    "fit_summary": 1,  # what a fit said about E, in short (pure Python: `info` reads it without torch, #26)
    "scene": 2, "fill": 2, "tetmesh": 2, "batch": 2,
    "refine": 2,  # the same scene on a finer grid (numpy: the resolution check, #22)
    "capture": 3, "sim": 3,
    "render": 4,
    "simulation": 5,
    "fit": 6, "extract": 6, "synth": 6,
    "compare": 6.5,   # the report's analysis: above the fit and extraction (it may use their types), below usd
    "diagnose": 6.5,  # what a fitted model lacks: score tests over the fit's problem (no USD)
    "usd": 7,
    "app": 8, "crosscheck": 8,
    "api": 9,
    "cli": 10, "__main__": 11,
}


def _module(p: Path) -> str:
    parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@functools.lru_cache(maxsize=1)
def _imports() -> dict[str, set[str]]:
    """{module: {imported physinteract_usd modules or names}}."""
    out = collections.defaultdict(set)
    for p in ROOT.rglob("*.py"):
        m = _module(p)
        pkg = m if p.name == "__init__.py" else m.rsplit(".", 1)[0]
        tree = ast.parse(p.read_text())
        typing_only = {id(n) for b in ast.walk(tree) if isinstance(b, ast.If) and "TYPE_CHECKING" in ast.dump(b.test)
                       for s in b.body for n in ast.walk(s)}
        for node in ast.walk(tree):
            if id(node) in typing_only:
                continue   # `if TYPE_CHECKING:` imports are for annotations: no import at run time
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    tgt = ".".join(base + ([node.module] if node.module else []))
                else:
                    tgt = node.module or ""
                if not tgt.startswith("physinteract_usd"):
                    continue
                if tgt == "physinteract_usd":   # `from .. import metrics`: the names are the modules
                    out[m].update(f"{tgt}.{a.name}" for a in node.names)
                else:
                    out[m].add(tgt)
            elif isinstance(node, ast.Import):
                out[m].update(a.name for a in node.names if a.name.startswith("physinteract_usd"))
    return out


def _top(m: str) -> str | None:
    parts = m.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_top_level_module_has_a_rank():
    tops = {p.stem if p.is_file() else p.name for p in ROOT.iterdir()
            if (p.suffix == ".py" and p.stem != "__init__") or (p.is_dir() and (p / "__init__.py").exists())}
    assert tops == set(RANKS), tops ^ set(RANKS)


def test_no_module_imports_one_above_it():
    bad = []
    for m, targets in _imports().items():
        a = _top(m)
        if a is None:
            continue   # the package's __init__ imports usd to register the schemas before any stage opens
        for t in targets:
            b = _top(t)
            if b is None or b == "__version__" or b == a:
                continue
            if RANKS[b] >= RANKS[a]:
                bad.append(f"{m} imports {t} ({b} is not below {a})")
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycles_between_modules():
    """Between modules (a package's __init__ re-exporting its own modules aside)."""
    mods = _imports()

    def resolve(t):
        return t if t in mods else (t.rsplit(".", 1)[0] if t.rsplit(".", 1)[0] in mods else None)

    graph = {}
    for m, ts in mods.items():
        graph[m] = set()
        for t in map(resolve, ts):
            if t is None or t == m or _top(t) is None:
                continue
            if m.startswith(t + "."):     # a module importing from its own package's __init__
                continue
            graph[m].add(t)
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                pytest.fail("import cycle: " + " -> ".join(path + [t]))
            if t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_pxr_only_in_the_usd_layer():
    users = sorted(_module(p) for p in ROOT.rglob("*.py")
                   if any(isinstance(n, (ast.Import, ast.ImportFrom))
                          and any((getattr(n, "module", None) or "").startswith("pxr") or a.name.startswith("pxr")
                                  for a in n.names)
                          for n in ast.walk(ast.parse(p.read_text()))))
    assert users and all(u.startswith("physinteract_usd.usd") for u in users), users
