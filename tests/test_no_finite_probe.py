"""A fit whose every uniform-E probe fails says why where it can (#23: world dev_0510, a rope on a floor that extract
did not find, failed with "unstable or left the grid at every uniform E tried" and advice about the
E range): the probes' errors are kept, and where most fell out of the grid's bottom with no ground on, the error says
that nothing holds the object up and how to switch the ground on."""

from __future__ import annotations

import math

import pytest
import torch

from physinteract_usd.errors import SimulationError
from physinteract_usd.fit.search import UniformProbe, golden_section, has_ground, no_finite_uniform_probe

FELL = ("left the grid domain (40 particles past the edge of the grid's valid box by up to 1.20 cells (10.0 mm), "
        "e.g. particle 7, nearest the -y face; valid box [0, 0, 0] - [1, 1, 1] m)")
SIDE = FELL.replace("-y face", "+x face")


def _err(text, face):
    return SimulationError(text, frame=3, kind="domain", face=face)


def test_the_probes_keep_their_errors_and_the_search_says_the_object_fell():
    def loss_of(E):
        raise _err(FELL, "-y")

    f = UniformProbe(loss_of, 4, torch.float64, "cpu")
    golden_section(f, math.log(1e3), math.log(1e6), 4)
    assert len(f.errors) == len(f.cache) >= 3 and all(e.face == "-y" and "-y face" in str(e) for e in f.errors)
    err = no_finite_uniform_probe(f.errors, ground=False)
    msg = str(err)
    assert "fell out of its bottom" in msg and "no ground" in msg and "effects add SCENE ground" in msg


def test_the_message_names_the_ground_only_where_it_is_off_and_most_probes_fell():
    with_ground = str(no_finite_uniform_probe([_err(FELL, "-y"), _err(FELL, "-y"), _err(SIDE, "+x")], ground=True))
    assert "fell out of its bottom" in with_ground and "ground's height" in with_ground and "no ground" not in with_ground
    sideways = str(no_finite_uniform_probe([_err(SIDE, "+x"), _err(SIDE, "+x"), _err(FELL, "-y")], ground=False))
    assert "fell" not in sideways and "--youngs-range" in sideways
    assert "--youngs-range" in str(no_finite_uniform_probe())


@pytest.mark.parametrize("sim,expected", [(None, None), (type("S", (), {"effects": {"ground": {}}})(), True),
                                          (type("S", (), {"effects": {}})(), False)])
def test_has_ground(sim, expected):
    assert has_ground(type("P", (), {"sim": sim})()) is expected


UNSTABLE = "state became non-finite (40 particles, e.g. particle 7; none had walked out of the grid)"


def test_unstable_at_every_e_says_the_interaction_not_the_material_and_where_the_probes_failed():
    """dev_0568 (#23): a grasp whose path dived through the floor went unstable at every uniform E; the error said
    to check the E range. Now it says what the probes did and that soft and stiff alike point at the interaction."""
    errs = [SimulationError(UNSTABLE, frame=f, kind="unstable") for f in (16, 17, 17, 19)]
    msg = str(no_finite_uniform_probe(errs, ground=True))
    assert "4 of 4 unstable at frames 16-19" in msg
    assert "not for the material" in msg and "preview image" in msg and "--youngs-range" not in msg
    mixed = errs[:2] + [_err(SIDE, "+x")]
    msg = str(no_finite_uniform_probe(mixed, ground=True))
    assert "2 of 3 unstable at frames 16-17" in msg and "1 of 3 left the grid through its +x face at frame 3" in msg
    assert "--youngs-range" in msg and "not for the material" not in msg


def test_out_through_one_face_at_every_e_points_at_the_interaction():
    """validation_0009's kind (#23): 11 of 12 probes out through the grid's top at one frame, soft and stiff alike."""
    up = FELL.replace("-y face", "+y face")
    errs = [_err(up, "+y")] * 11 + [_err(SIDE, "+z")]
    msg = str(no_finite_uniform_probe(errs, ground=False))
    assert "11 of 12 left the grid through its +y face at frame 3" in msg
    assert "same (+y) face" in msg and "interaction carries it" in msg and "--youngs-range" not in msg
    split = [_err(up, "+y"), _err(up, "+y"), _err(SIDE, "+x"), _err(SIDE, "+x")]
    assert "--youngs-range" in str(no_finite_uniform_probe(split, ground=False))
