"""PHYSINTERACT_CFL and PHYSINTERACT_GROUND (read by `simulation` at import), settings for measurements (#24): the
adaptive substep's CFL number (dev floor captures are far from step-converged at the default after a release) and
where the ground acts (the grid nodes, or the particles: docs/sim.md); docs/benchmarks/world_fits.md."""

from __future__ import annotations

import os

import pytest

from physinteract_usd import simulation as S


def test_the_cfl_setting_reads_a_number_in_0_1_and_refuses_others():
    assert S.cfl_number(None) == S.cfl_number("") == S.cfl_number("  ") == S.DEFAULT_CFL == 0.6
    assert S.cfl_number("0.3") == 0.3 and S.cfl_number(" 1 ") == 1.0
    for bad in ("fast", "0", "-0.3", "1.5", "nan"):
        with pytest.raises(ValueError, match="PHYSINTERACT_CFL"):
            S.cfl_number(bad)
    assert S.CFL == S.cfl_number(os.environ.get("PHYSINTERACT_CFL"))


def test_the_ground_setting_names_where_the_ground_acts_and_refuses_others():
    """PHYSINTERACT_GROUND: the ground effect at the grid nodes (unset: today's) or at the particles (#24)."""
    assert S.ground_contact(None) == S.ground_contact("") == S.ground_contact("nodes") == "nodes"
    assert S.ground_contact(" Penalty ") == "penalty"
    for bad in ("particles", "1"):
        with pytest.raises(ValueError, match="PHYSINTERACT_GROUND"):
            S.ground_contact(bad)
    assert S.GROUND_CONTACT == S.ground_contact(os.environ.get("PHYSINTERACT_GROUND"))


@pytest.mark.parametrize("name,value", [("PHYSINTERACT_CFL", "fast"), ("PHYSINTERACT_GROUND", "particles")])
def test_a_bad_setting_is_one_line_from_the_cli(tmp_path, name, value):
    import subprocess
    import sys

    env = dict(os.environ, **{name: value})
    r = subprocess.run([sys.executable, "-m", "physinteract_usd", "fit", str(tmp_path / "scene.usda")],
                       capture_output=True, text=True, env=env, timeout=300)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip() and "Warp" not in ln]
    assert r.returncode == 2 and len(lines) == 1 and name in lines[0] and repr(value) in lines[0], r.stderr
