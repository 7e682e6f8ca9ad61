"""benchmarks/mismatch_probe.py's configurations (#24): the simulator choices it re-simulates the truth under are read
as written, and a typo is refused rather than silently run as the stage's own configuration."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from mismatch_probe import config_name, parse_configs  # noqa: E402


def test_configs_parse():
    cs = parse_configs("base;tau=0.05;cfl=0.3,grid=1.5; ;tau=0")
    assert cs == [{}, {"tau": 0.05}, {"cfl": 0.3, "grid": 1.5}, {"tau": 0.0}]
    assert [config_name(c) for c in cs] == ["base", "tau=0.05", "cfl=0.3,grid=1.5", "tau=0"]


@pytest.mark.parametrize("bad", ["cfll=0.3", "grid=0", "cfl=-1", "grid=x"])
def test_bad_configs_refused(bad):
    with pytest.raises(ValueError):
        parse_configs(bad)
