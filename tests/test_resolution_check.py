"""The fitted model's own resolution error (`refine.refine_scene`, `diagnose.resolution`,
`diagnose --resolution`; issue #22): the finer scene keeps the coarse one's mass and contacts, Richardson's
extrapolation recovers a power law exactly and predicts the next refinement's change on the tiny bar, and the
verdict weighs the estimate."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

import diagnose_scene as ds
from physinteract_usd.errors import InputError


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return ds.build(tmp_path_factory.mktemp("resbar") / "ctl", noise=0.015, seed=0)


def _problem(stage):
    from physinteract_usd.app.adapters import effects_with_fitted, read_scene
    from physinteract_usd.app.diagnose import problem_and_base
    from physinteract_usd.diagnose.core import rest_frames
    from physinteract_usd.diagnose.residual import ImageResidual

    sd = read_scene(stage)
    prob, base = problem_and_base(sd, effects_with_fitted(sd))
    res = ImageResidual(prob, max_pixels=3000)
    with torch.no_grad():
        x, F = prob.sim.simulate(base.E, base.nu, None, effects=base.effects)
    res.set_photometric(x, F)
    res.set_noise_weights(x, F, rest_frames(prob))
    return sd, prob, base, res, res(x, F)


@pytest.mark.parametrize("split", [2, 3])
def test_the_finer_scene_keeps_each_cells_mass_centre_values_and_contacts(bar, split):
    from physinteract_usd.app.adapters import read_scene
    from physinteract_usd.refine import refine_scene

    sd = read_scene(bar["stage"])
    fine, cs, parent = refine_scene(sd, split)
    n, m3 = len(sd.particles_positions), split ** 3
    assert len(fine.particles_positions) == n * m3
    np.testing.assert_array_equal(parent, np.repeat(np.arange(n), m3))
    # the same mass (volume) and centre of mass in every coarse particle's cell, the finer points inside it
    v = fine.particles_volumes.reshape(n, m3)
    np.testing.assert_allclose(v.sum(1), sd.particles_volumes, rtol=1e-12)
    x = fine.particles_positions.reshape(n, m3, 3)
    np.testing.assert_allclose(x.mean(1), sd.particles_positions, atol=1e-9)
    h = sd.settings.particle_spacing
    assert np.abs(x - sd.particles_positions[:, None]).max() <= 0.5 * h * (1 - 1.0 / split) + 1e-9
    # the finer lattice's own spacing between neighbours
    d = np.sort(np.linalg.norm(x[0, 1:] - x[0, :1], axis=1))[0]
    assert math.isclose(d, h / split, rel_tol=1e-9)
    # the grid: every coarse node a finer one (same corner), cell / split, substeps x split
    st, fs = sd.settings, fine.settings
    np.testing.assert_array_equal(fs.domain_min, st.domain_min)
    assert math.isclose(fs.cell_size, st.cell_size / split) and math.isclose(fs.particle_spacing, h / split)
    assert tuple(fs.grid_resolution) == tuple(r * split for r in st.grid_resolution)
    assert fs.substeps == st.substeps * split
    # values and contact membership from the parent
    np.testing.assert_array_equal(fine.youngs_modulus, sd.youngs_modulus[parent])
    np.testing.assert_array_equal(fine.poisson_ratio, sd.poisson_ratio[parent])
    for c, f in zip(sd.contacts, cs):
        assert f.name == c.name and f.type == c.type
        np.testing.assert_array_equal(np.sort(f.indices), np.sort(np.flatnonzero(np.isin(parent, c.indices))))
    with pytest.raises(ValueError, match="2, 3 or 4"):
        refine_scene(sd, 1)


def test_richardson_recovers_a_power_law_and_clips_outside_its_range():
    from physinteract_usd.diagnose.resolution import richardson

    for p in (0.8, 1.0, 1.7, 3.0):
        e = 2.5e-3                             # the coarse model's error, a mean square
        c = {a: e * (1 - a ** -p) ** 2 for a in (2, 3)}
        got = richardson(c)
        assert got["order"] == pytest.approx(p, rel=1e-6) and not got["clipped"]
        assert got["error"] == pytest.approx(e, rel=1e-6)
    # a finer change no larger than the first: beyond the asymptotic range, the order clipped at 4
    got = richardson({2: 1e-3, 3: 0.9e-3})
    assert got["clipped"] and got["order"] == 4.0 and got["error"] == pytest.approx(1e-3 / (1 - 2 ** -4) ** 2)
    # the finer change larger than p -> 0 allows: clipped at 1/2
    got = richardson({2: 1e-3, 3: 1e-3 * 1.7 ** 2})
    assert got["clipped"] and got["order"] == 0.5
    assert richardson({2: 0.0, 3: 0.0})["error"] == 0.0


def test_the_extrapolated_error_predicts_the_next_refinements_change(bar):
    """Richardson from cell / 2 and / 3 predicts the change to cell / 4, which a converging model's error
    approaches (the tiny bar: 2.2 cells across its thickness, far from resolved)."""
    from physinteract_usd.diagnose.resolution import resolution_change, resolution_error

    _, prob, base, res, r0 = _problem(bar["stage"])
    est = resolution_error(prob, base, res, r0, splits=(2, 3))
    assert est["error"] is not None and est["error"] > 0 and est["cos"] > 0.8
    c4 = resolution_change(prob, base, res, r0, split=4)["change"]
    p = est["order"]
    predicted = est["error"] * (1 - 4.0 ** -p) ** 2
    assert predicted == pytest.approx(c4, rel=0.15)
    # and the changes grow toward it: the model converges (each finer grid moves the frames further, less each time)
    lv = est["levels"]
    assert lv[0]["change"] < lv[1]["change"] < c4 < est["error"] * 1.0001
    assert lv[0]["particles"] == [len(prob.x0), 8 * len(prob.x0)]
    # one refinement at the assumed order (the CPU's default) errs toward the grid: at least the change a
    # finer grid (cell / 4) makes, and exactly the change over (1 - 2^-p)^2 at the assumed order
    from physinteract_usd.diagnose.resolution import ASSUMED_ORDER, one_level

    one = resolution_error(prob, base, res, r0, splits=(2,))
    assert one["assumed"] and one["cos"] is None and one["order"] == ASSUMED_ORDER
    assert one["error"] == pytest.approx(lv[0]["change"] / (1 - 2 ** -ASSUMED_ORDER) ** 2, rel=1e-9)
    assert one["error"] == pytest.approx(one_level(lv[0]["change"], 2)["error"])
    assert one["error"] >= c4


def test_the_verdict_weighs_the_resolution_error():
    from physinteract_usd.diagnose.core import Diagnosis, conclude

    def diag(res_err):
        d = Diagnosis("adequate", "", [], loss=2.8e-3, floor=1.0e-3)
        if res_err is not None:
            d.noise = {"resolution": {"error": res_err, "order": 1.5,
                                      "levels": [{"split": 2, "change": 0.3 * res_err}]}}
        return conclude(d)

    assert diag(None).verdict == "unexplained"               # 2.8x the floor, nothing explains it
    assert diag(0.1e-3).verdict == "unexplained"             # 2.8 > 2 x 1.1
    d = diag(0.5e-3)                                         # 2.8 < 2 x 1.5
    assert d.verdict == "adequate"
    assert "resolution error" in d.reason and "cell / 2" in d.reason


def test_diagnose_with_the_resolution_check(bar):
    from physinteract_usd import api

    d = api.diagnose(bar["stage"], refit=0, starts=1, progress=False, log=lambda *a: None, write_stage=False,
                     resolution="2,3", candidates="damping,camera:depth_scale")
    rz = d["noise"]["resolution"]
    assert [lv["split"] for lv in rz["levels"]] == [2, 3] and rz["error"] > 0
    assert d["verdict"] == "adequate" and "resolution error" in d["reason"]
    json.dumps(d, allow_nan=False)
    for bad in ("5,6", "1", "2,2", "a,b", "2,3,4"):
        with pytest.raises(InputError, match="--resolution"):
            api.diagnose(bar["stage"], refit=0, starts=1, progress=False, log=lambda *a: None, write_stage=False,
                          resolution=bad)


def test_a_failed_or_empty_resolution_check_leaves_the_verdict_to_the_floor():
    from physinteract_usd.diagnose.core import Diagnosis, conclude

    d = Diagnosis("adequate", "", [], loss=2.8e-3, floor=1.0e-3)
    d.noise = {"resolution": {"levels": [], "order": None, "error": None, "failed": "CUDA out of memory"}}
    d = conclude(d)
    assert d.verdict == "unexplained" and "Richardson" not in d.reason
    d = Diagnosis("adequate", "", [], loss=1.5e-3, floor=1.0e-3)         # the finer grids moved nothing: order None
    d.noise = {"resolution": {"levels": [{"split": 2, "change": 0.0}], "order": None, "error": 0.0}}
    d = conclude(d)
    assert d.verdict == "adequate" and "order -" in d.reason


def test_the_cpu_default_is_one_refinement_and_the_reason_says_the_order_was_assumed():
    from physinteract_usd.app.diagnose import parse_resolution
    from physinteract_usd.diagnose.core import Diagnosis, conclude
    from physinteract_usd.diagnose.resolution import one_level

    assert parse_resolution(None, "cpu") == (2,) and parse_resolution(None, "cuda") == (2, 3)
    assert parse_resolution("3", "cpu") == (3,) and parse_resolution("off", "cuda") == ()
    d = Diagnosis("adequate", "", [], loss=2.8e-3, floor=1.0e-3)
    rz = one_level(0.2e-3, 2)                                 # error 0.2e-3 / (1 - 2^-1)^2 = 0.8e-3
    d.noise = {"resolution": {**rz, "levels": [{"split": 2, "change": 0.2e-3}], "cos": None}}
    d = conclude(d)
    assert d.verdict == "adequate" and "assumed: one refinement" in d.reason
