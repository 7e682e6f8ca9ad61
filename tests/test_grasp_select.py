"""The grasp's size chosen by what it renders (`fit.problem.grasp_variants`,
`fit.optimize.select_grasp`), on the tiny cantilever of tests/fit_scene.py whose frames were
rendered with a known grasp: the known grasp wins over one layer less or more, and a grasp one
layer too large or too small is brought back toward it."""

import dataclasses

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.fit import FitProblem, FitSettings
from physinteract_usd.fit.optimize import select_grasp
from physinteract_usd.fit.problem import grasp_variants


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    built = fs.build(tmp_path_factory.mktemp("grasp") / "base")
    sd = api.read_stage(built["stage"])
    obs = api.load_observations(sd)
    return sd, obs, fs.contacts(sd)


def _select(sd, obs, contacts):
    variants = grasp_variants(sd.particles_positions, sd.settings.particle_spacing, contacts, "hand")
    k, prob, e, losses = select_grasp(lambda cs: FitProblem(sd, obs, cs, device="cpu"), variants,
                                      FitSettings(search_evals=6))
    return variants, k, e, losses


def test_variants_are_one_layer_less_and_more():
    h = 0.01
    g = np.arange(6) * h
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    x0 = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    from physinteract_usd.fit import ContactSpec

    hand = np.where(x0[:, 0] >= 3.5 * h)[0]           # the two outer slabs x = 4h, 5h
    support = np.where(x0[:, 0] <= 0.5 * h)[0]        # slab x = 0
    cs = [ContactSpec("hand", "pointAdherent", hand, trajectory=np.zeros((2, 3))), ContactSpec("s", "fixed", support)]
    v = dict(grasp_variants(x0, h, cs, "hand"))
    assert set(np.round(x0[v["one layer less"][0].indices, 0] / h)) == {5}
    assert set(np.round(x0[v["one layer more"][0].indices, 0] / h)) == {3, 4, 5}
    # growing never takes another contact's particles
    cs2 = [cs[0], ContactSpec("s", "fixed", np.where(x0[:, 0] <= 3.5 * h)[0])]
    v2 = dict(grasp_variants(x0, h, cs2, "hand"))
    assert "one layer more" not in v2
    np.testing.assert_array_equal(v2["as found"][1].indices, cs2[1].indices)


def test_the_rendered_grasp_wins(case):
    sd, obs, contacts = case
    variants, k, e, losses = _select(sd, obs, contacts)
    assert variants[k][0] == "as found", losses
    assert abs(np.log(e / fs.E_TRUE)) < np.log(1.5)


def test_a_grasp_a_layer_too_large_is_made_smaller(case):
    sd, obs, contacts = case
    big = grasp_variants(sd.particles_positions, sd.settings.particle_spacing, contacts, "hand")
    big = dict(big)["one layer more"]
    variants, k, _, losses = _select(sd, obs, big)
    assert variants[k][0] == "one layer less", losses
    chosen = set(variants[k][1][0].indices.tolist())
    true = set(contacts[0].indices.tolist())
    assert len(chosen ^ true) < len(set(big[0].indices.tolist()) ^ true)
