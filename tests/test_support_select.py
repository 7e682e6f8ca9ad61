"""A guessed support's size chosen by what it renders (`fit.problem.support_layer`,
`fit.optimize.select_supports`), on the tiny cantilever of tests/fit_scene.py whose frames were
rendered with a known support: the known support stays, and a support a layer too small or too
large is brought back toward it. Measured supports and sets from the user or the ground truth are
never resized, and a fit sizes a guess only on its first run."""

import dataclasses

import numpy as np
import pytest

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.contacts import ContactSet
from physinteract_usd.fit import FitProblem, FitSettings
from physinteract_usd.fit.optimize import select_supports
from physinteract_usd.fit.problem import support_layer


def _cube(n=6, h=0.01):
    g = np.arange(n) * h
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1), h


def _layers(x0, h, cs, name):
    c = next(c for c in cs if c.name == name)
    return set(np.round(x0[c.indices, 0] / h).astype(int).tolist())


def test_a_layer_more_or_less_is_one_slab_and_never_takes_the_hand():
    x0, h = _cube()
    hand = np.where(x0[:, 0] >= 4.5 * h)[0]                   # slab x = 5h
    support = np.where(x0[:, 0] <= 1.5 * h)[0]                # slabs x = 0, h
    cs = [ContactSet("hand", "pointAdherent", hand, trajectory=np.zeros((2, 3))),
          ContactSet("s", "fixed", support, guessed=True)]
    more = support_layer(x0, h, cs, "more")
    less = support_layer(x0, h, cs, "less")
    assert _layers(x0, h, more, "s") == {0, 1, 2} and _layers(x0, h, less, "s") == {0}
    # the hand's set is never changed, and growing stops at it
    for _ in range(3):
        more = support_layer(x0, h, more, "more") or more
    assert _layers(x0, h, more, "s") == {0, 1, 2, 3, 4}
    np.testing.assert_array_equal(more[0].indices, hand)


def test_measured_user_and_ground_truth_supports_stay_as_they_are():
    x0, h = _cube()
    support = np.where(x0[:, 0] <= 1.5 * h)[0]
    assert support_layer(x0, h, [ContactSet("s", "fixed", support)], "more") is None
    for source in ("user", "groundTruth"):
        cs = [ContactSet("s", "fixed", support, source=source, guessed=True)]
        assert support_layer(x0, h, cs, "more") is None
        assert support_layer(x0, h, cs, "less") is None
    with pytest.raises(ValueError):
        support_layer(x0, h, [ContactSet("s", "fixed", support)], "sideways")


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    built = fs.build(tmp_path_factory.mktemp("support") / "base")
    sd = api.read_scene(built["stage"])
    obs = api.load_observations(sd)
    return sd, obs, [dataclasses.replace(c, guessed=c.type == "fixed") for c in fs.contacts(sd)]


def _select(sd, obs, contacts):
    return select_supports(lambda cs: FitProblem(sd, obs, cs, device="cpu"), contacts, sd.particles_positions,
                           sd.settings.particle_spacing, FitSettings(search_evals=6))


def _support(cs):
    return set(next(c for c in cs if c.type == "fixed").indices.tolist())


def test_the_rendered_support_stays(case):
    sd, obs, contacts = case
    chosen, _, e, tried = _select(sd, obs, contacts)
    assert _support(chosen) == _support(contacts), tried
    assert [t[0] for t in tried] == ["as found", "1 layer more", "1 layer less"], tried
    assert abs(np.log(e / fs.E_TRUE)) < np.log(1.5)


@pytest.mark.parametrize("start", ["less", "more"])
def test_a_support_a_layer_off_is_brought_back(case, start):
    sd, obs, contacts = case
    x0, h = sd.particles_positions, sd.settings.particle_spacing
    off = support_layer(x0, h, contacts, start)
    true = _support(contacts)
    chosen, _, _, tried = _select(sd, obs, off)
    assert len(_support(chosen) ^ true) < len(_support(off) ^ true), tried
    assert tried[-1][2] >= min(t[2] for t in tried)       # the last one tried did not beat the chosen


def test_the_first_fit_sizes_a_guessed_support_on_the_stage_and_a_refit_keeps_it(tmp_path):
    """Through the API: an extraction that guessed the support a layer short; `fit` grows it, the
    fit layer records the size it chose, and a second fit keeps that size."""
    from physinteract_usd.usd.extract_io import write_extraction

    built = fs.build(tmp_path / "api")
    sd = api.read_scene(built["stage"])
    x0, h = sd.particles_positions, sd.settings.particle_spacing
    hand, support = fs.contacts(sd)
    short = support_layer(x0, h, [hand, dataclasses.replace(support, guessed=True)], "less")[1]
    write_extraction(built["stage"], sd, [
        ContactSet("hand", "pointAdherent", hand.indices, trajectory=hand.trajectory),
        ContactSet("support", "fixed", short.indices, guessed=True)],
        np.zeros((sd.n_frames, fs.HEIGHT, fs.WIDTH), bool))
    settings = {**fs.SMOKE_SETTINGS, "search_evals": 6}
    lines = []
    api.fit(built["stage"], iterations=1, progress=False, log=lines.append, settings_overrides=settings)
    after = {c.name: c for c in api.read_scene(built["stage"]).contacts}
    held = set(after["support"].indices.tolist())
    true = set(support.indices.tolist())
    assert len(held ^ true) < len(set(short.indices.tolist()) ^ true), lines
    assert after["support"].guessed and after["support"].source == "extracted"
    assert any(m.startswith("supports 1 layer more") for m in lines)
    lines.clear()
    api.fit(built["stage"], iterations=1, progress=False, log=lines.append, settings_overrides=settings)
    again = {c.name: c for c in api.read_scene(built["stage"]).contacts}
    assert set(again["support"].indices.tolist()) == held
    assert not any(m.startswith("supports") for m in lines)
