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


# ------------------------------------------------------------------ thirteenth pass (#23)
def test_the_toucher_acts_until_it_leaves_at_a_transit_pace():
    """`acting_end`: a palm that presses at 1 px a frame and lifts off at 15 px a frame acts until
    its first departure pair (the still object next to a fast toucher reads some of its flow);
    a held pull on a smooth ramp (0.5 -> 4 -> 0.5 px a frame) acts to its release: no pair is over
    3x its pace; a toucher seen nowhere acts to the end."""
    from physinteract_usd.extract.interaction_type import acting_end

    vh = _pairs((4, (0.0, 0.0)), (5, (0.0, 1.0)), (5, (0.0, -1.0)), (3, (0.0, -15.0)))
    co = np.array([0] * 4 + [1] * 10 + [1] * 3)
    assert acting_end(vh, co, 4, 17) == 14
    # the departure's smeared flow read as the object following it out past its rest: gone with it
    vo = _pairs((4, (0.0, 0.0)), (5, (0.0, 0.6)), (5, (0.0, -0.6)), (3, (0.0, -6.0)))
    down = np.array([0.0, 1.0])   # into the object
    assert normal_motion(vh, vo, down, start=4, g=4, end=17)["tension_px"] > 2.0
    assert normal_motion(vh, vo, down, start=4, g=4, end=14)["tension_px"] < 1e-9
    ramp = np.sin(np.linspace(0.15, np.pi - 0.15, 12)) * 4.0
    pull = np.column_stack([ramp, -0.3 * ramp])
    assert acting_end(pull, np.ones(12, int), 0, 12) == 12
    assert acting_end(np.full((5, 2), np.nan), np.zeros(5, int), 0, 5) == 5


def _palm_over_a_bar(T=24):
    """A palm 80 px wide coming down (+v) onto a bar (rows 40-55) seen from above: in front of the
    bar in depth, its leading edge is seen past the bar's lower outline. It comes in at 4 px a
    frame (frames 0-3), touches from frame 4, presses 1 px a frame (pairs 8-12: the bar gives 0.6
    px a pair), lifts 1 px a frame (13-17: the bar springs back to rest) and leaves at 15 px a frame
    (18-20), the bar next to it read moving up at 6 px a frame (the palm's flow smeared onto it)."""
    from physinteract_usd.extract.timing import Timing

    H, W = 80, 120
    b = [36, 40, 44, 48] + [52] * 5 + [53, 54, 55, 56, 57] + [56, 55, 54, 53, 52] + [37, 22, 7] + [-100] * (T - 22)
    yy, xx = np.mgrid[0:H, 0:W]
    hand = np.stack([(xx >= 20) & (xx < 100) & (yy <= bk) & (yy > bk - 30) for bk in b])
    bar = (yy >= 40) & (yy <= 55) & (xx >= 10) & (xx < 110)
    flow = np.zeros((T - 1, H, W, 2), np.float32)
    for k in range(T - 1):
        flow[k][hand[k]] = (0.0, b[k + 1] - b[k])
    vh = np.full((T - 1, 2), np.nan)
    vo = np.full((T - 1, 2), np.nan)
    for k in range(4, 21):
        vh[k] = (0.0, b[k + 1] - b[k])
    vo[4:21] = _pairs((4, (0.0, 0.0)), (5, (0.0, 0.6)), (5, (0.0, -0.6)), (3, (0.0, -6.0)))
    coupled = np.zeros(T - 1, int)
    coupled[8:21] = 1
    near = np.zeros(T, bool)
    near[4:22] = True
    timing = Timing(vh, vo, coupled, near, (4, 21), np.linalg.norm(np.nan_to_num(vh), axis=1), 8, 21)
    an = SimpleNamespace(hand=hand, obj=np.repeat(bar[None], T, 0), T=T, H=H, W=W, R=6.0, eps=0.35,
                         obj_size_px=100.0, px_per_m=500.0, flows=SimpleNamespace(forward=flow),
                         rest=SimpleNamespace(silhouette=bar))
    return an, timing, np.array([60.0, 52.0])


def test_a_palm_pressing_a_bar_from_above_is_a_surface_not_a_grasp():
    """dev_0266's kind (glove palm on a bar, typed a grasp): the silhouette's inward normal at the
    contact points up (the palm's leading edge is seen near the bar's lower outline), against the
    way the palm came in (down): a toucher reaches a surface from outside, so that edge is not the
    surface it touches and its 'tension' (the press read as a pull out) is no evidence; and the
    first main motion is read while the palm acts, not its 45 px departure. What is left: pressed
    3 px in along its approach, back to rest, never past it, while the palm lifted 5 px: a press,
    by a 16 cm front: a surface."""
    from physinteract_usd.extract.interaction_type import inward_normal, type_evidence
    from physinteract_usd.extract.lifting import track_hand

    an, timing, c2 = _palm_over_a_bar()
    assert inward_normal(an.rest.silhouette, c2) @ np.array([0.0, 1.0]) < -0.9   # "inward" is up
    ev = type_evidence(an, timing, c2, track_hand(timing, c2))
    assert ev["acting_end"] == 18 and "tension_px" not in ev
    assert ev["approach_press_cos"] == pytest.approx(1.0) and ev["approach_pressed_in_px"] == pytest.approx(3.0)
    assert ev["approach_tension_px"] < 1e-9 and ev["approach_withdrawn_px"] == pytest.approx(5.0)
    assert ev["push_cos"] < -0.9 and ev["front_width_m"] >= 0.06
    assert classify_interaction(ev)[0] == "surfaceNonAdherent"


def test_a_board_that_leaves_fast_is_not_followed_while_it_acted():
    """dev_0297's kind (a board on a stiff clamped sheet, typed a grasp): the board comes to rest,
    presses 2.4 px, lifts 2.1 px and leaves at 1 and 4.5 px a frame; the sheet next to it moves
    only within the noise, but the departure's smeared flow reads as following (4.5 of its 9.8 px).
    Over the contact the share it followed is 0.63 (a grasp's); without the departure pair (over
    3x the pace) 0.32: touched two frames and parted, not followed: a press, by an 18 cm front."""
    from physinteract_usd.extract.interaction_type import transit_pairs
    from physinteract_usd.extract.timing import coupled_share

    sp = np.array([0.1, 0.58, 0.65, 0.77, 0.1, 0.37, 0.71, 0.81, 0.23, 1.05, 4.46])
    vh = np.column_stack([np.zeros_like(sp), sp])
    co = np.array([0, -1, 1, -1, 0, -1, -1, -1, 0, 1, 1])
    fast = transit_pairs(vh, co, 0, len(sp))
    assert fast.tolist() == [False] * 10 + [True]
    before = coupled_share(co, sp, 0, len(sp))
    after = coupled_share(co, np.where(fast, 0.0, sp), 0, len(sp))
    assert before == pytest.approx(0.63, abs=0.01) and after == pytest.approx(0.32, abs=0.01)
    ev = {"push_cos": 0.51, "contact_motion_px": 5.55, "interface_span": 0.85, "approach_cos": -1.0,
          "approach_speed_px": 1.54, "contact_frames": 2, "acting_motion_px": 0.63, "face_normal_cos": 0.99,
          "into_cos": -0.27, "front_width_m": 0.18, "toucher_round": [0.2, 0.7]}
    assert classify_interaction({**ev, "coupled_share": before})[0] == "pointAdherent"
    assert classify_interaction({**ev, "coupled_share": after})[0] == "surfaceNonAdherent"


# ------------------------------------------------------------------ fourteenth pass (#23)
def _board_mask(H, W, corner, px_per_m, az_deg=30.0, el_deg=40.0, size=(0.18, 0.14)):
    """A flat board (`size`, m) lying face down, seen from azimuth `az_deg` and elevation `el_deg`
    (orthographic, `px_per_m`): a parallelogram whose nearest corner (its lowest point in the
    image, +v down) is at `corner` (u, v)."""
    import cv2

    a, e = np.radians(az_deg), np.radians(el_deg)
    X, Z = size[0] / 2, size[1] / 2
    pts = np.array([[x * np.cos(a) + z * np.sin(a), (-x * np.sin(a) + z * np.cos(a)) * np.sin(e)]
                    for x, z in ((-X, -Z), (X, -Z), (X, Z), (-X, Z))]) * px_per_m
    pts += np.asarray(corner, float) - pts[np.argmax(pts[:, 1])]
    m = np.zeros((H, W), np.uint8)
    cv2.fillPoly(m, [np.round(pts * 16).astype(np.int32)], 1, shift=4)
    return m.astype(bool)


def test_a_face_seen_obliquely_is_wide_behind_its_leading_corner():
    """A board 18 x 14 cm turned 30 deg to the camera, seen 40 deg from above (dev_0312's kind, at
    its 250 px a metre) leads with a corner: 1 cm behind it the board is 2 / (sin 40 sin 60) = 3.6 cm
    wide (a fingertip's, under the 6 cm of a face), 3 cm behind it 10.8 cm. A fingertip on a hand
    stays 2 cm there, a ball of radius 3.5 cm 2 sqrt(2 r d - d^2) = 6.9 cm, a pinch's two fingers
    (1 cm thick, 2.4 cm apart at their tips, 5 cm 6 cm back) 4.7 cm: only the face reaches 8 cm."""
    down = np.array([0.0, 1.0])
    H, W = 160, 240
    board = _board_mask(H, W, (120.0, 120.0), 250.0)
    an = _analysis(board[None], 250.0)
    w1 = toucher_front_width(an, 0, (120.0, 119.0), 0, down)
    w3 = toucher_front_width(an, 0, (120.0, 119.0), 0, down, depth_m=0.03)
    assert w1 == pytest.approx(0.02 / (np.sin(np.radians(40)) * np.sin(np.radians(60))), abs=0.008) and w1 < 0.06
    assert w3 == pytest.approx(0.03 * 2 / (np.sin(np.radians(40)) * np.sin(np.radians(60))), abs=0.008) and w3 >= 0.08
    # at 500 px a metre (the shapes of test_the_toucher_front_width_is_its_own_shape_at_its_leading_edge)
    yy, xx = np.mgrid[0:120, 0:200] + 0.5
    hand = (((xx - 100) / 40) ** 2 + ((yy - 30) / 20) ** 2 <= 1) | ((np.abs(xx - 100) <= 5) & (yy >= 30) & (yy <= 75))
    hand |= (np.abs(xx - 100) <= 5) & (yy <= 80) & ((xx - 100) ** 2 + (yy - 75) ** 2 <= 25)
    ball = (xx - 100) ** 2 + (yy - 60) ** 2 <= 17.5 ** 2
    # a pinch: two 1 cm thick fingers (5 px), their tips 2.4 cm apart (12 px) at v = 100, 5 cm apart 6 cm up,
    # joined by the hand further up
    pinch = ((xx - 100) / 25) ** 2 + ((yy - 55) / 15) ** 2 <= 1
    for x0, x1 in ((94.0, 87.5), (106.0, 112.5)):
        for t in np.linspace(0, 1, 200):
            pinch |= (xx - (x0 + t * (x1 - x0))) ** 2 + (yy - (100 - 30 * t)) ** 2 <= 2.5 ** 2
    deep = {n: toucher_front_width(_analysis(m[None], 500.0), 0, c, 0, down, depth_m=0.03)
            for n, m, c in (("hand", hand, (100.0, 80.0)), ("ball", ball, (100.0, 77.5)), ("pinch", pinch, (100.0, 102.0)))}
    assert deep["hand"] == pytest.approx(0.022, abs=0.004)
    assert deep["ball"] == pytest.approx(2 * np.sqrt(2 * 0.035 * 0.03 - 0.03 ** 2), abs=0.006)
    assert deep["pinch"] == pytest.approx(0.047, abs=0.004)
    assert max(deep.values()) < 0.08 <= w3


def test_a_board_pressing_with_a_corner_first_is_a_surface():
    """The rules on dev_0339's evidence (a board pressing a plush on a floor at 128 px, typed a
    fingertip by 7df5970): its front 1 cm behind the leading point 4.5 cm, 3 cm behind it 20 cm:
    a face. Its front alone, or a ball's 7 cm, stays a point."""
    ev = {"push_cos": -0.95, "contact_motion_px": 5.67, "interface_span": 0.8, "approach_cos": 0.99,
          "approach_speed_px": 3.66, "contact_frames": 23, "acting_motion_px": 5.67, "coupled_share": 0.46,
          "face_normal_cos": 0.97, "into_cos": 0.96, "tension_px": 0.0, "press_cos": 0.69, "pressed_in_px": 1.75,
          "toucher_round": [0.17, 0.86], "front_width_m": 0.045}
    assert classify_interaction(ev)[0] == "pointNonAdherent"
    assert classify_interaction({**ev, "front_deep_m": 0.20})[0] == "surfaceNonAdherent"
    assert classify_interaction({**ev, "front_deep_m": 0.069})[0] == "pointNonAdherent"
    assert classify_interaction({**ev, "front_deep_m": 0.20, "toucher_round": [0.03, 0.97]})[0] == "pointNonAdherent"


def test_a_round_toucher_as_wide_as_a_palm_is_no_ball():
    """dev_0322's kind (a glove's palm seen from above, typed a fingertip): its free outline fits one
    circle (RMS 3% of its radius) of half its extent, as a ball's does, but of radius 8 cm; a ball that
    large presses like a face (its cap 1 cm deep is 6 cm wide). At 400 px a metre: a disk of radius
    32 px (8 cm) over an object is no ball, one of 12 px (3 cm) is; without a scale both are."""
    from physinteract_usd.extract.analysis import disk_mask
    from physinteract_usd.extract.interaction_type import is_ball, toucher_roundness

    H, W = 120, 160
    obj = np.zeros((H, W), bool)
    obj[70:, 10:150] = True
    rounds = {}
    for r in (32.0, 12.0):
        hand = disk_mask((H, W), (80.0, 70.0 - r + 4.0), r) & ~obj     # sunk 4 px into the object
        an = SimpleNamespace(hand=hand[None], obj=obj[None], R=4.0, T=1, H=H, W=W, px_per_m=400.0)
        rounds[r] = toucher_roundness(an, 0, np.array([80.0, 70.0]), 0)
    big, small = rounds[32.0], rounds[12.0]
    assert big[0] < 0.1 and 0.8 <= big[1] <= 1.25 and big[2] == pytest.approx(0.08, abs=0.004)
    assert small[2] == pytest.approx(0.03, abs=0.003)
    assert not is_ball(big) and is_ball(small)
    assert is_ball(big[:2]) and is_ball(small[:2])
    ev = {"push_cos": 0.27, "contact_motion_px": 31.0, "interface_span": 0.46, "approach_cos": 1.0,
          "approach_speed_px": 0.95, "contact_frames": 2, "acting_motion_px": 4.3, "coupled_share": 0.33,
          "face_normal_cos": 0.97, "into_cos": -0.81, "front_width_m": 0.07}
    assert classify_interaction({**ev, "toucher_round": big})[0] == "surfaceNonAdherent"
    assert classify_interaction({**ev, "toucher_round": small})[0] == "pointNonAdherent"


def test_a_toucher_coming_toward_the_camera_reads_as_a_pull_when_the_depth_rule_is_on(monkeypatch):
    """`toucher_depth`: a toucher whose flow spreads 2% a frame about its centre for 5 frames grows
    1.02^5 = 1.104x: at fx 400 px it came 400 (1 - 1/1.104) = 37.7 px-equivalents toward the camera
    while it stayed in place in the image. With PHYSINTERACT_TYPE_DEPTH=1 (opt-in) a toucher that came
    mostly toward the camera by over 7% holds what it moves (dev_0311: a pinch pulling a hanging rope
    toward the camera, pressed-in by the image's reading); off, the image's reading stands."""
    from physinteract_usd.extract import interaction_type as it
    from physinteract_usd.extract.analysis import disk_mask
    from physinteract_usd.extract.lifting import HandTrack

    T, H, W = 7, 80, 80
    hand = np.repeat(disk_mask((H, W), (40.0, 40.0), 15.0)[None], T, 0)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    flow = np.repeat(np.stack([(xx - 40.0) * 0.02, (yy - 40.0) * 0.02], -1)[None].astype(np.float32), T - 1, 0)
    an = SimpleNamespace(hand=hand, T=T, H=H, W=W, R=4.0, flows=SimpleNamespace(forward=flow),
                         cam0=SimpleNamespace(fx=400.0))
    track = HandTrack(np.tile([40.0, 40.0], (T, 1)), 0.0, 0, np.zeros(2), 0.0)
    d = it.toucher_depth(an, track, 0, 5)
    assert d["depth_scale"] == pytest.approx(1.02 ** 5, rel=2e-3)
    assert d["depth_px"] == pytest.approx(400 * (1 - 1.02 ** -5), rel=0.01) and d["depth_image_px"] == 0.0
    ev = {"push_cos": -0.6, "contact_motion_px": 18.8, "interface_span": 0.13, "approach_cos": 0.85,
          "approach_speed_px": 2.9, "contact_frames": 7, "acting_motion_px": 18.8, "coupled_share": 0.99,
          "tension_px": 0.0, "press_cos": 0.96, "pressed_in_px": 18.6, "withdrawn_px": 2.1, "front_width_m": 0.025}
    monkeypatch.setattr(it, "DEPTH_RULE", False)
    assert classify_interaction({**ev, **d})[0] == "pointNonAdherent"
    monkeypatch.setattr(it, "DEPTH_RULE", True)
    assert classify_interaction({**ev, **d})[0] == "pointAdherent"
    assert classify_interaction({**ev, **d, "depth_scale": 1.05})[0] == "pointNonAdherent"       # under 7%
    assert classify_interaction({**ev, **d, "depth_image_px": 40.0})[0] == "pointNonAdherent"    # mostly across
    assert classify_interaction({**ev, **d, "depth_scale": 1 / 1.104})[0] == "pointNonAdherent"  # away: not read
