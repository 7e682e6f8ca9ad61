"""The type's physics on hand-made inputs (#23, the type class: palms and pushers typed as pulls):
a press read against the way the toucher came in where the silhouette's normal is ill-defined, and
point vs surface from the width of the toucher's front, not from where it overlaps the object."""

from types import SimpleNamespace

import numpy as np
import pytest

import physinteract_usd  # noqa: F401
from physinteract_usd.extract import classify_interaction
from physinteract_usd.extract.interaction_type import normal_motion, toucher_front_width


def _pairs(*runs):
    """Velocities per frame pair from (count, (vx, vy)) runs."""
    return np.array([v for n, v in runs for _ in range(n)], float)


# A palm pressing a block's top corner from above (dev_0144's kind): it comes down at 1.4 px a
# frame, presses on 5 pairs (the block gives 0.6 px a pair, straight down), rests 2, lifts off 5
# pairs (the block springs back 0.6 px a pair, to its rest surface, not past it) and leaves.
# The silhouette's inward normal at the corner points 58 deg off the press (down-left).
VH = _pairs((3, (0.0, 1.4)), (5, (0.0, 1.0)), (2, (0.0, 0.0)), (5, (0.0, -1.0)), (3, (0.0, -6.0)))
VO = _pairs((3, (0.0, 0.0)), (5, (0.0, 0.6)), (2, (0.0, 0.0)), (5, (0.0, -0.6)), (3, (0.0, 0.0)))
CORNER = np.array([-0.85, 0.53])
BASE = {"push_cos": -0.23, "contact_motion_px": 7.0, "interface_span": 0.31, "approach_cos": 1.0,
        "approach_speed_px": 1.4, "contact_frames": 12, "acting_motion_px": 5.0, "coupled_share": 0.4,
        "face_normal_cos": 0.6, "into_cos": 0.82, "toucher_round": [0.15, 0.83]}


def test_a_press_at_a_corner_is_read_against_the_way_the_toucher_came_in():
    """Against the corner's normal the press reads 58 deg off (press_cos 0.53 < 0.85), no rule
    fires and the default calls it a grasp; against the approach (a toucher reaches the surface from
    outside, so its approach points into the object) the block moved 3 px straight in and came back
    only to its rest surface while the palm moved out: a press."""
    n = normal_motion(VH, VO, CORNER, start=0, g=3, end=15)
    assert n["press_cos"] == pytest.approx(0.53, abs=0.01) and n["tension_px"] < 1e-9
    assert classify_interaction({**BASE, **n})[0] == "pointAdherent"            # as before
    a = normal_motion(VH, VO, np.array([0.0, 1.0]), start=0, g=3, end=15)
    assert a["press_cos"] == pytest.approx(1.0) and a["pressed_in_px"] == pytest.approx(3.0)
    assert a["pulled_out_px"] < 1e-9 and a["tension_px"] < 1e-9 and a["withdrawn_px"] == pytest.approx(5.0)
    ev = {**BASE, **n, **{f"approach_{k}": v for k, v in a.items()}}
    assert classify_interaction(ev)[0] == "pointNonAdherent"
    # its front as wide as a palm's: a surface
    assert classify_interaction({**ev, "front_width_m": 0.12})[0] == "surfaceNonAdherent"
    assert classify_interaction({**ev, "front_width_m": 0.02})[0] == "pointNonAdherent"
    # ... unless it is a ball (a plain sphere's outline is one circle of half its extent)
    assert classify_interaction({**ev, "front_width_m": 0.12, "toucher_round": [0.03, 0.97]})[0] == \
        "pointNonAdherent"


def test_a_grasp_that_came_in_and_pulls_back_out_is_no_press_against_its_approach():
    """A hand that came in along (0, 1), took hold and pulls back out the way it came, the object
    following out past its rest surface (tension against the approach): held, whatever the
    silhouette's normal reads; and one that came in and dragged the object sideways is no press."""
    vh = _pairs((3, (0.0, 1.4)), (2, (0.0, 0.0)), (6, (0.0, -1.0)), (3, (0.0, -5.0)))
    vo = _pairs((3, (0.0, 0.0)), (2, (0.0, 0.0)), (6, (0.0, -0.7)), (3, (0.0, 0.0)))
    a = normal_motion(vh, vo, np.array([0.0, 1.0]), start=0, g=3, end=11)
    assert a["tension_px"] == pytest.approx(4.2) and a["pressed_in_px"] == 0.0
    base = {"push_cos": 0.9, "contact_motion_px": 6.0, "interface_span": 0.1, "approach_cos": -1.0,
            "approach_speed_px": 1.4, "contact_frames": 8, "coupled_share": 0.9}
    assert classify_interaction({**base, **{f"approach_{k}": v for k, v in a.items()}})[0] == "pointAdherent"
    drag = normal_motion(_pairs((3, (0.0, 1.4)), (6, (1.0, 0.1)), (3, (-1.0, -0.3))),
                         _pairs((3, (0.0, 0.0)), (6, (0.8, 0.1)), (3, (-0.8, -0.1))),
                         np.array([0.0, 1.0]), start=0, g=3, end=12)
    assert abs(drag["press_cos"]) < 0.3
    assert classify_interaction({**base, "push_cos": 0.1, "approach_cos": 0.0,
                                 **{f"approach_{k}": v for k, v in drag.items()}})[0] == "pointAdherent"


def _analysis(masks, px_per_m):
    T, H, W = masks.shape
    return SimpleNamespace(hand=masks, T=T, H=H, W=W, px_per_m=px_per_m, R=6.0)


def test_the_toucher_front_width_is_its_own_shape_at_its_leading_edge():
    """At 500 px a metre (2 mm a pixel), pushing down (+v): a palm seen edge-on (a 140 x 16 px
    ellipse, 28 cm) has a front 1 cm deep as wide as a flat face's chord there; a fingertip on a
    hand (a 10 px wide finger under a big palm blob) has a front of its width, 2 cm; a ball of
    radius 3.5 cm has a cap of chord 2 sqrt(2 r d - d^2) = 4.9 cm. Whatever the object under them."""
    H, W = 120, 200
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    palm = ((xx - 100) / 70) ** 2 + ((yy - 60) / 8) ** 2 <= 1
    hand = (((xx - 100) / 40) ** 2 + ((yy - 30) / 20) ** 2 <= 1) | ((np.abs(xx - 100) <= 5) & (yy >= 30) & (yy <= 75))
    hand |= (np.abs(xx - 100) <= 5) & (yy <= 80) & ((xx - 100) ** 2 + (yy - 75) ** 2 <= 25)
    ball = (xx - 100) ** 2 + (yy - 60) ** 2 <= 17.5 ** 2
    down = np.array([0.0, 1.0])
    w_palm = toucher_front_width(_analysis(palm[None], 500.0), 0, (100.0, 68.0), 0, down)
    w_hand = toucher_front_width(_analysis(hand[None], 500.0), 0, (100.0, 80.0), 0, down)
    w_ball = toucher_front_width(_analysis(ball[None], 500.0), 0, (100.0, 77.5), 0, down)
    # the ellipse's chord 5 px (1 cm) above its lowest point: 2 * 70 * sqrt(1 - (3/8)^2) = 129.8 px
    assert w_palm == pytest.approx(2 * 70 * np.sqrt(1 - (3 / 8) ** 2) / 500, abs=0.006)
    assert w_hand == pytest.approx(0.02, abs=0.004)
    assert w_ball == pytest.approx(2 * np.sqrt(2 * 0.035 * 0.01 - 0.01 ** 2), abs=0.006)
    assert w_palm >= 0.06 > w_ball > w_hand
    # no push direction, or no toucher at the contact: nothing to say
    assert toucher_front_width(_analysis(palm[None], 500.0), 0, (100.0, 68.0), 0, np.zeros(2)) is None
    assert toucher_front_width(_analysis(palm[None], 500.0), 0, (10.0, 110.0), 0, down) is None


def test_an_object_overtaking_the_toucher_outward_is_no_hold_with_the_follow_rule():
    """PHYSINTERACT_TYPE_FOLLOW=1 (opt-in): tension counts only pairs in which the object keeps at
    most the toucher's outward pace. A stick pushes a plush in 2 px (1 px a pair) and withdraws at
    1 px a pair; the plush swings back out past its rest at 2 px a pair for 3 pairs (overtaking
    the stick: its own motion) - 6 px of tension by default, none with the rule. A held region
    dragged out at 0.6 of the toucher's pace keeps its tension either way."""
    into = np.array([1.0, 0.0])
    vh = _pairs((2, (1.0, 0.0)), (5, (-1.0, 0.0)))
    vo = _pairs((2, (1.0, 0.0)), (1, (-2.0, 0.0)), (3, (-2.0, 0.0)), (1, (0.0, 0.0)))
    swing = normal_motion(vh, vo, into, start=0, g=0, end=7, follow_only=False)
    assert swing["pulled_out_px"] == pytest.approx(6.0) and swing["tension_px"] == pytest.approx(6.0)
    assert normal_motion(vh, vo, into, start=0, g=0, end=7, follow_only=True)["tension_px"] == 0.0
    held = _pairs((2, (0.0, 0.0)), (5, (-0.6, 0.0)))
    a = normal_motion(vh, held, into, start=0, g=0, end=7, follow_only=False)
    b = normal_motion(vh, held, into, start=0, g=0, end=7, follow_only=True)
    assert a["tension_px"] == pytest.approx(3.0) and b["tension_px"] == pytest.approx(3.0)


def test_the_follow_rule_is_read_from_the_environment_as_0_or_1():
    from physinteract_usd.extract.interaction_type import FOLLOW_ONLY, follow_rule

    assert FOLLOW_ONLY is False or FOLLOW_ONLY is True
    assert follow_rule(None) is False and follow_rule("0") is False and follow_rule("1") is True
    with pytest.raises(ValueError, match="PHYSINTERACT_TYPE_FOLLOW"):
        follow_rule("yes")
