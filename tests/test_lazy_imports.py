"""A verb imports what it needs: the package, the CLI and `api` load neither torch nor Warp until a
verb that simulates or renders uses them; Warp, once loaded, is quiet (the package's log level)."""

import subprocess
import sys

import pytest

CODE = r"""
import sys
import physinteract_usd.cli as cli
from physinteract_usd import api
cli.build_parser()
api.list_versions, api.use_version, api.export
print("BARE", sorted(m for m in ("torch", "warp", "trimesh") if m in sys.modules))
import physinteract_usd.sim.effects, physinteract_usd.sim.cfl
heavy = sorted(m for m in ("torch", "warp", "trimesh") if m in sys.modules)
print("HEAVY", heavy)
from physinteract_usd.sim import Rollout      # the torch entry points load on use
import warp as wp
print("WARP", wp.config.log_level == wp.LOG_ERROR, "torch" in sys.modules)
print("API", api.fit.__module__, sorted(set(api.__all__) - set(dir(api))))
"""


def test_the_cli_and_api_load_no_torch_or_warp_until_used():
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=120,
                         env={"PHYSINTERACT_WARP_LOG": "", **__import__("os").environ})
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if " " in line)
    assert lines["BARE"] == "[]", lines["BARE"]
    assert lines["HEAVY"] in ("[]", "['warp']"), lines["HEAVY"]    # the simulator's tables: Warp, not torch
    assert lines["WARP"] == "True True"
    assert lines["API"] == "physinteract_usd.app.fit []"


def test_a_verbs_help_loads_neither_torch_nor_warp():
    code = ("import sys\nfrom physinteract_usd.cli import _main\n"
            "try:\n    _main(['fit', '--help'])\nexcept SystemExit:\n    pass\n"
            "print('LOADED', sorted(m for m in ('torch', 'warp') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "LOADED []" in out.stdout, out.stdout[-500:]


@pytest.mark.parametrize("name", ["nonexistent_thing"])
def test_api_unknown_name_is_an_attribute_error(name):
    from physinteract_usd import api

    with pytest.raises(AttributeError):
        getattr(api, name)
