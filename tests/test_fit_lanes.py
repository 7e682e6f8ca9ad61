"""A fit whose rollouts run on two lanes (sim/lanes.py) ends where the one-lane fit does: tests/fit_scene.py's
tiny bar, the smoke settings, the same loss history and fitted E within float32 summation order's reach (the
lanes sum the grid in another order; nothing else differs)."""

from __future__ import annotations

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.sim import lanes as lanes_mod

QUIET = dict(progress=False, log=lambda *a: None)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return fs.build(tmp_path_factory.mktemp("lanes") / "base")


def _fit(scene, where, n, monkeypatch):
    made = []

    class Counted(lanes_mod.Lanes):
        def __init__(self, sol):
            super().__init__(sol)
            made.append(self)

    monkeypatch.setattr(lanes_mod, "LANES", n)
    monkeypatch.setattr(lanes_mod, "MIN_PARTICLES", 0)
    monkeypatch.setattr(lanes_mod, "Lanes", Counted)
    stage = fs.copy_scene(scene["root"], where)
    out = api.fit(stage, iterations=fs.SMOKE_ITERATIONS, contact_from=scene["gt"],
                  settings_overrides=fs.SMOKE_SETTINGS, **QUIET)
    return out.result, len(made)


def test_a_fit_on_two_lanes_ends_where_the_one_lane_fit_does(scene, tmp_path, monkeypatch):
    r1, n1 = _fit(scene, tmp_path / "one", 1, monkeypatch)
    r2, n2 = _fit(scene, tmp_path / "two", 2, monkeypatch)
    assert n1 == 0 and n2 > 0                       # the second fit's rollouts ran on two lanes
    h1, h2 = np.asarray(r1.loss_history), np.asarray(r2.loss_history)
    assert len(h1) == len(h2) == fs.SMOKE_ITERATIONS
    assert np.allclose(h2, h1, rtol=1e-3, atol=0.0)
    assert r2.final_loss == pytest.approx(r1.final_loss, rel=1e-3)
    E1, E2 = np.asarray(r1.youngs), np.asarray(r2.youngs)
    assert np.allclose(E2, E1, rtol=1e-2)
    assert np.median(np.abs(E2 / E1 - 1.0)) < 1e-3
