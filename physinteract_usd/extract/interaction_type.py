"""How the hand interacts: pointAdherent (a grasp that pulls), pointNonAdherent (a fingertip that
pushes) or surfaceNonAdherent (a palm). The evidence (`type_evidence`: which way the object moved
against the hand's body, how the hand came in, how long and straight the hand-object interface
is) and the default rules on it (`classify_interaction`, replaceable through `Models.classifier`)."""

from __future__ import annotations

import os
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .analysis import Analysis, disk_mask, median_flow, unit
from .geometry import pixel_centres
from .lifting import HandTrack, hand_scale, track_hand
from .segmentation import dilate, erode
from .timing import Timing, coupled_share

if TYPE_CHECKING:  # the models registry imports the default steps; only its type is needed here
    from .models import Models


def classify_interaction(evidence: dict, *, frames=None) -> tuple[str, float]:
    """The default rules (see `pipeline`'s doc, step 5). Returns (type, confidence in [0, 1])."""
    push = evidence.get("push_cos")
    moved = evidence.get("contact_motion_px", 0.0)
    surface = evidence.get("interface_span", 0.0)
    approach, ap_speed = evidence.get("approach_cos"), evidence.get("approach_speed_px", 0.0)
    brief = evidence.get("contact_frames")
    acting = evidence.get("acting_motion_px")
    still = acting is not None and acting < 2.0
    if is_ball(evidence.get("toucher_round")):
        # a ball touches a surface at a point, however long its seen interface with the object
        # (a plain sphere pressed into a ring or a bar: the interface is its arc)
        surface = 0.0
    if brief is not None and (brief <= 2 or still) and evidence.get("coupled_share", 1.0) < 0.5:
        # touched for a frame or two, or longer with the toucher moving less than 2 px while it
        # acts (a slow press into a sheet on a floor, dev_0009), and parted without the object
        # following: a knock or a press, not a grasp (a hand that takes hold pulls the object along)
        if flat(evidence, surface):
            return "surfaceNonAdherent", 0.5
        return "pointNonAdherent", 0.5
    along = depth_motion(evidence) if DEPTH_RULE else None
    if along is not None:
        # opt-in (PHYSINTERACT_TYPE_DEPTH=1, #23 fourteenth pass): the toucher moved mostly along the
        # camera's axis while it acted, toward it (a pinch pulling a hanging rope's end toward the
        # camera, dev_0311: 7.8% larger, truly 9.8%, read in the image as a press). Seen at the
        # contact, it touches the surface from the camera's side: toward the camera is out of the
        # surface, which only a hold takes the object along. Not the default: the apparent scale
        # fitted to the flow reads up to 10% where the truth moved 1-3% (an approach, a board
        # leaving), and "away, so a push" broke two grasps pulling away from the camera
        return "pointAdherent", 0.5
    tension = evidence.get("tension_px") or 0.0
    # it looks pushed away from the hand, but the hand came in and went back out the way it came: a
    # pull toward the camera, whose motion in depth the image does not show (below)
    in_depth = (push is not None and moved >= 1.0 and push < -0.6 and approach is not None and ap_speed >= 1.0
                and approach < 0.0)
    if not in_depth and tension < 0.7 and (pressed(evidence) or pressed(evidence, "approach_")):
        # the object next to the contact moved only along the inward normal (its largest displacement
        # from rest within 32 deg of it) and never followed the toucher out past its rest surface (by
        # more than 2 eps, the noise), though the toucher moved out (a grasp that only pushes looks
        # the same until it pulls: dev_9372, a glove dragging a rope across itself):
        # pushed, not held (a grasp drags the contact region along the surface with the toucher, or
        # holds it as the toucher moves away; dev_0007's stick, typed a grasp by its withdrawal).
        # Read against the silhouette's inward normal or, where that is ill-defined (a corner), the
        # way the toucher came in (#23, dev_0144: a palm pressing a block's corner)
        if flat(evidence, surface):
            return "surfaceNonAdherent", 0.6
        return "pointNonAdherent", 0.6
    face, into = evidence.get("face_normal_cos"), evidence.get("into_cos")
    if tension >= TENSION_PX and surface > 0.45:
        # a long straight interface, but the object followed the toucher out past its rest surface
        # (tension): a palm or a board cannot pull, a hand that holds can (a glove's flat side read
        # as a press)
        return "pointAdherent", 0.5
    if flat(evidence, surface) and surface > 0.45 and moved >= 1.0 and face is not None and face >= FACE_NORMAL_COS \
            and into is not None and into > 0:
        # a long straight interface (not a ball's) whose first main motion goes along its own normal
        # (closer to it than to the face) and into the object: a flat face pressed into it, a
        # palm or a board, which cannot hold. Its body lies beside the contact along the face, so
        # the push-away-from-the-body reading says nothing here (dev_9332: push_cos -0.13)
        return "surfaceNonAdherent", float(min(1.0, 0.5 + (surface - 0.45)))
    if push is None or moved < 1.0:
        return "pointAdherent", 0.3
    if in_depth:
        return "pointAdherent", 0.5
    if push < -0.6:
        # the object only moved away from the hand: pushed. A wide front (else a long flat
        # interface) is a palm.
        if flat(evidence, surface):
            return "surfaceNonAdherent", float(min(1.0, 0.5 + (surface - 0.45)))
        return "pointNonAdherent", float(min(1.0, -push))
    return "pointAdherent", float(min(1.0, 0.5 + 0.5 * (push + 0.6) / 1.6))


def depth_motion(evidence: dict) -> int | None:
    """+1 where the toucher moved mostly toward the camera while it acted (`toucher_depth`: its
    apparent scale grew by at least DEPTH_SCALE and the motion along the axis that implies is larger
    than its image motion), else None. (Away from the camera is not read: a grasp pulls that way as
    often as a push presses, dev_0157 / dev_0218.)"""
    S, along, across = (evidence.get(k) for k in ("depth_scale", "depth_px", "depth_image_px"))
    if S is None or along is None or across is None or S < 1.0 + DEPTH_SCALE or along <= across:
        return None
    return 1


def pressed(evidence: dict, prefix: str = "") -> bool:
    """The object next to the contact was pressed in (at least 1 px, its largest displacement
    within 32 deg of the inward direction) and never followed the toucher out past its rest
    surface (under 2 eps of tension) though the toucher moved out (at least 1 px): `normal_motion`'s
    evidence against the silhouette's inward normal (`prefix` "") or the toucher's approach
    ("approach_")."""
    return ((evidence.get(prefix + "press_cos") or 0.0) >= PRESS_COS
            and (evidence.get(prefix + "pressed_in_px") or 0.0) >= 1.0
            and (evidence.get(prefix + "tension_px") or 0.0) < 0.7
            and (evidence.get(prefix + "withdrawn_px") or 0.0) >= 1.0)


def flat(evidence: dict, surface: float) -> bool:
    """A surface contact: the toucher's front is wide (`wide_front`) where it was measured (#23: a
    contact is as wide as the front that makes it, whatever else of the toucher is seen over the
    object), else the hand-object interface's straight span is over 0.45 of the object (`surface`,
    0 for a ball)."""
    if evidence.get("front_width_m") is not None:
        return wide_front(evidence)
    return surface > 0.45


def wide_front(evidence: dict) -> bool:
    """The toucher pushes with a front wider than any fingertip, stick end or ball cap
    (`toucher_front_width` at least FRONT_WIDE_M 1 cm behind its leading point, or at least
    FRONT_DEEP_WIDE_M 3 cm behind it: a face seen obliquely leads with a corner, #23 fourteenth
    pass): a face (a palm, a board), unless it is a ball."""
    w, deep = evidence.get("front_width_m"), evidence.get("front_deep_m")
    wide = (w is not None and w >= FRONT_WIDE_M) or (deep is not None and deep >= FRONT_DEEP_WIDE_M)
    return wide and not is_ball(evidence.get("toucher_round"))


FACE_NORMAL_COS = float(np.cos(np.pi / 4))   # a motion closer to a face's normal than to the face
FRONT_WIDE_M = 0.06   # a front wider than this is a face: fingertips <= 2.8 cm, sticks <= 2 cm, palms >= 10 cm
FRONT_DEEP_AT_M = 0.03     # the front read again this far behind the leading point (`front_deep_m`)
FRONT_DEEP_WIDE_M = 0.08   # wider there: a face (a right-angle corner seen at 45 deg: 8.5 cm; a ball of
                           # radius 3.5 cm: 6.9; a pinch's two fingers: <= 5.7, a glove's 6.3; a finger 2.8)
PRESS_COS = 0.85      # the object's largest displacement within 32 deg of the inward normal: a press
TENSION_PX = 2.0      # px the object followed the toucher out past its rest surface: held
BALL_MAX_R_M = 0.05    # a round toucher wider than this is a face (a palm seen from above), not a ball
DEPTH_SCALE = 0.07    # an apparent scale change under 7% is no depth reading (seen: 5% on a push, dev_0201)
TRANSIT_RATIO = 3.0   # a toucher moving over 3x its acting pace is arriving or leaving (`acting_end`)


def inward_normal(silhouette: np.ndarray, c2, smooth: float = 1.5, min_grad: float = 0.5):
    """The surface's inward normal in the image at the contact `c2` (u, v): the gradient of the
    silhouette's signed distance (positive inside, smoothed by `smooth` px), unit; None where it is
    not defined (under `min_grad`: on the ridge of a thin object, a rope or a bar under the hand,
    where "inward" is across it both ways; along it the object is dragged, not pressed)."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    sil = np.asarray(silhouette, bool)
    if not sil.any() or sil.all():
        return None
    sd = gaussian_filter(distance_transform_edt(sil) - distance_transform_edt(~sil), smooth)
    gy, gx = np.gradient(sd)
    H, W = sil.shape
    u, v = int(np.clip(np.floor(c2[0]), 0, W - 1)), int(np.clip(np.floor(c2[1]), 0, H - 1))
    g = np.array([gx[v, u], gy[v, u]], float)
    n = float(np.linalg.norm(g))
    return g / n if n >= min_grad else None


def follow_rule(value: str | None, name: str = "PHYSINTERACT_TYPE_FOLLOW") -> bool:
    """The environment's PHYSINTERACT_TYPE_FOLLOW ("0" or unset: off, "1": on), read once at import:
    whether `normal_motion`'s tension counts only pairs in which the object keeps at most the
    toucher's pace (opt-in, #23: measured on the CPU dev halves only as the lever, not tried); the
    same reading of PHYSINTERACT_TYPE_DEPTH (`name`): whether `depth_motion` decides (opt-in)."""
    if value in (None, "", "0"):
        return False
    if value == "1":
        return True
    raise ValueError(f"{name}={value!r}: expected 0 or 1")


FOLLOW_ONLY = follow_rule(os.environ.get("PHYSINTERACT_TYPE_FOLLOW"))
DEPTH_RULE = follow_rule(os.environ.get("PHYSINTERACT_TYPE_DEPTH"), "PHYSINTERACT_TYPE_DEPTH")   # the in-depth pull (opt-in, `depth_motion`)


def normal_motion(vh: np.ndarray, vo: np.ndarray, into: np.ndarray, start: int, g: int, end: int,
                  eps: float = 0.35, follow_only: bool | None = None) -> dict:
    """How the object next to the contact moved against the surface's inward normal `into` (unit,
    image), from rest (`start`, the first frame of the contact period or the grasp, whichever is
    earlier) to `end` (the release; the last pair otherwise): `pressed_in_px` and `pulled_out_px`,
    its largest displacement into and out past its rest surface; `press_cos`, the cosine of its
    largest displacement with `into`; `tension_px`, its outward motion in the pairs from the grasp
    in which the toucher moves out (over `eps`) and the object follows it out while past its rest
    surface (summed, each pair's at most how far past it is). A press pushes along the inward
    normal and the object comes back at most to its rest surface; a grasp drags the contact region
    along the surface or holds it as the toucher moves away (the object follows it out: tension).
    `withdrawn_px`: the toucher's outward motion from the grasp to `end`, summed (the
    no-tension reading says something only where it moved out). `follow_only` (default
    FOLLOW_ONLY, off): a pair counts as tension only where the object's outward speed is at most
    the toucher's (+ eps): a held region is dragged, so it lags or keeps pace; an object that
    overtakes the toucher outward moves on its own (a plush swinging back past its rest as a
    stick withdraws, dev_0188: 4.4 vs 2.6 px a frame), which is no evidence of a hold."""
    follow_only = FOLLOW_ONLY if follow_only is None else follow_only
    d = np.asarray(into, float)
    X = np.zeros(2)
    big = np.zeros(2)
    out_max = in_max = tension = withdrawn = 0.0
    for k in range(max(0, start), min(end, len(vo))):
        if k >= g and np.isfinite(vh[k]).all():
            withdrawn += max(0.0, float(-vh[k] @ d))
        o = vo[k]
        if np.isfinite(o).all():
            X = X + o
        if np.linalg.norm(X) > np.linalg.norm(big):
            big = X.copy()
        out_max, in_max = max(out_max, float(-X @ d)), max(in_max, float(X @ d))
        if k >= g and np.isfinite(vh[k]).all() and np.isfinite(o).all():
            if float(-vh[k] @ d) > eps and float(-o @ d) > 0 and float(-X @ d) > 0 \
                    and (not follow_only or float(-o @ d) <= float(-vh[k] @ d) + eps):
                tension += min(float(-o @ d), float(-X @ d))
    nb = float(np.linalg.norm(big))
    return {"pressed_in_px": in_max, "pulled_out_px": out_max, "tension_px": tension, "withdrawn_px": withdrawn,
            "press_cos": float(big @ d / nb) if nb > 2 * eps else None}


def acting_end(vh: np.ndarray, coupled: np.ndarray, g: int, end: int, ratio: float = None,
               floor: float = 1.0) -> int:
    """The frame at which the toucher starts to leave at a transit's pace: the first pair from the
    grasp `g` (before `end`) in which it moves faster than `ratio` (TRANSIT_RATIO) times its pace
    while the object followed it (the median speed over the pairs coupled +1 in [g, end); all seen
    pairs where none) and over `floor` px; `end` where none does. A toucher that acts on an object
    moves at the pace the object follows (it drags or presses the material); one moving several
    times faster is arriving or leaving, and the flow of the object next to a fast toucher takes
    some of the toucher's (smeared across the motion boundary): that pair is no evidence of how
    the object follows."""
    fast = transit_pairs(vh, coupled, g, end, ratio, floor)
    return int(np.argmax(fast)) if fast.any() else end


def transit_pairs(vh: np.ndarray, coupled: np.ndarray, g: int, end: int, ratio: float = None,
                  floor: float = 1.0) -> np.ndarray:
    """(len(vh),) bool: the pairs in [g, end) in which the toucher moves at a transit's pace (over
    `ratio` times its pace while the object followed it, and over `floor` px; `acting_end`)."""
    ratio = TRANSIT_RATIO if ratio is None else ratio
    vh = np.asarray(vh, float)
    out = np.zeros(len(vh), bool)
    ks = [k for k in range(max(0, g), min(end, len(vh))) if np.isfinite(vh[k]).all()]
    if not ks:
        return out
    sp = np.linalg.norm(vh, axis=1)
    fol = [sp[k] for k in ks if coupled[k] == 1]
    pace = float(np.median(fol if fol else [sp[k] for k in ks]))
    for k in ks:
        out[k] = sp[k] > ratio * pace and sp[k] > floor
    return out


def is_ball(round_: list | None, residual: float = 0.1, size: tuple = (0.8, 1.25)) -> bool:
    """The toucher is a ball (`toucher_roundness`): its free outline is one circle (RMS residual
    under `residual` of its radius) whose radius is half its extent (within `size`: a disk's
    outline circle is exactly that; a palm's or a hand's outline arcs fit a smaller one), and no
    larger than BALL_MAX_R_M where its radius in metres was read (#23, fourteenth pass: a glove's
    palm seen from above fits a circle of 8 cm, dev_0322; a ball that large presses like a face:
    its cap 1 cm deep is 6 cm wide)."""
    if round_ is None or not (round_[0] < residual and size[0] <= round_[1] <= size[1]):
        return False
    return len(round_) < 3 or round_[2] is None or round_[2] <= BALL_MAX_R_M


# ------------------------------------------------------------------------------ step
def classify(an: Analysis, timing: Timing, c2, hand: HandTrack, evidence: dict, models: "Models",
             interaction_type: str | None = None, frames=None) -> tuple[str, float, str]:
    """Step 5: the type evidence into `evidence`, then the type: the user's (`interaction_type`)
    or the classifier's. Returns (type, confidence, source: "user" | "detected")."""
    evidence.update(type_evidence(an, timing, c2, hand))
    if interaction_type is not None:
        itype, conf, tsource = interaction_type, 1.0, "user"
    else:
        itype, conf = models.classifier(evidence, frames=frames)
        tsource = "detected"
    evidence["type_confidence"] = conf
    return itype, conf, tsource


def type_evidence(an: Analysis, timing: Timing, c2, hand: HandTrack) -> dict:
    """What the rules read: the first main motion against the direction to the hand's body
    (`push_cos`), the hand's approach against it (`approach_cos`, `approach_speed_px`), the
    interface's straight span (`interface_span`), the contact's motion and the coupled share."""
    g, p1 = timing.grasp, timing.period[1]
    motion = hand.motion
    # the toucher acts on the object until it starts to leave at a transit's pace (#23, thirteenth
    # pass): the pairs from there on are its departure, whose flow leaks into the object next to it
    # (dev_0266: a palm lifting off at 16-21 px a frame, the still bar next to it read moving out at
    # 7-13): the type reads the first main motion, the tension and the front up to there
    end_all = len(timing.object_velocity) if timing.release is None else timing.release
    end = acting_end(timing.hand_velocity, timing.coupled, g, end_all)
    act_hand = hand if end >= end_all else track_hand(replace(timing, release=end), c2)
    d2 = act_hand.first_move
    body = hand_body_direction(an, g, c2)
    push_cos = float(np.dot(unit(d2), body)) if motion > 0 and np.linalg.norm(body) > 0 else None
    span, face = interface_span(an, g, c2, p1, with_normal=True)
    v_app = approach_velocity(an, g, c2)
    app_speed = float(np.linalg.norm(v_app)) if v_app is not None else 0.0
    approach_cos = float(np.dot(unit(v_app), unit(d2))) if app_speed > 0 and motion > 0 else None
    into_cos = None
    # the direction from the contact into the object at rest (the surface's inward normal there)
    op = pixel_centres(an.rest.silhouette & disk_mask((an.H, an.W), c2, 3.0 * an.R))
    into = unit(op.mean(0) - np.asarray(c2, float)) if len(op) else np.zeros(2)
    if motion > 0:
        # the first main motion against it (a push goes into the object, a pull out of it, whatever
        # the toucher's body looks like)
        into_cos = float(np.dot(unit(d2), into)) if np.linalg.norm(into) > 0 else None
    normal = {}
    n_in = inward_normal(an.rest.silhouette, c2)
    # the way the toucher came in (#23): a toucher reaches the surface from outside, so its motion
    # in the frames before it first touches the object points into it, wherever the silhouette's
    # normal is ill-defined (a block's corner under a palm, dev_0144: 58 deg off the palm's press).
    # Before the first touch, not before the grasp: a grasp put later than the touch (the user's
    # --grasp-frame on a pull already under way) has the pull itself before it, not an approach
    first = min(timing.period[0], g)
    v_in = approach_velocity(an, first, c2)
    in_speed = float(np.linalg.norm(v_in)) if v_in is not None else 0.0
    if n_in is not None and in_speed >= 1.0 and float(np.dot(unit(v_in), n_in)) < 0.0:
        # the toucher came in from the side the silhouette calls inside: the silhouette's edge at
        # the contact is not the surface it touches (a palm pressing a bar's top from above, in
        # front of it in depth, its leading edge seen past the bar's lower outline: dev_0266)
        n_in = None
    if n_in is not None:
        normal = normal_motion(timing.hand_velocity, timing.object_velocity, n_in, first, g, end)
    if in_speed >= 1.0:
        ap = normal_motion(timing.hand_velocity, timing.object_velocity, unit(v_in), first, g, end)
        normal.update({f"approach_{k}": v for k, v in ap.items()})
    # the first main motion against the straight interface's normal: a flat face pushed into the
    # object moves along its own normal
    face_cos = float(abs(np.dot(unit(d2), face))) if face is not None and motion > 0 else None
    # how wide the toucher's front is where it pushes (its own shape, in metres): its leading edge
    # along its first main motion and along its approach (over 2 eps), the narrower: a flat face is
    # wide whichever way it comes in, a finger on a hand only along itself (a push 70 deg off
    # the finger reads the hand's side, 15 cm: dev_0204's glove finger on a ring)
    # Also 3 cm behind the leading point (`front_deep_m`, #23 fourteenth pass): a face seen obliquely
    # leads with a corner (a board turned to the camera) or a shallow arc at a few pixels a
    # centimetre (a palm at 128 px), whose first centimetre is narrow (dev_0312, dev_0339: 3-4.5 cm)
    # but which widens at least as fast as a right-angle corner seen at 45 deg (2.8 cm per cm of
    # depth: >= 8.5 cm at 3 cm); a finger's, a stick's, a pinch's stay at their own width there
    dirs = [d for d, ok in ((d2, motion > 0), (v_in, in_speed >= 2 * an.eps)) if ok]
    e_front = p1 if end >= end_all and timing.release is None else end
    fronts = [w for w in (toucher_front_width(an, g, c2, e_front, d) for d in dirs) if w is not None]
    front = min(fronts) if fronts else None
    deeps = [w for w in (toucher_front_width(an, g, c2, e_front, d, depth_m=FRONT_DEEP_AT_M) for d in dirs)
             if w is not None]
    deep = min(deeps) if deeps else None
    depth = toucher_depth(an, hand, g, min(end, p1))
    return {"approach_speed_px": app_speed, "into_cos": into_cos, "approach_cos": approach_cos,
            **depth,
            "face_normal_cos": face_cos, "front_width_m": front, "front_deep_m": deep,
            "toucher_round": toucher_roundness(an, g, c2, p1),
            "contact_uv": c2.tolist(), "contact_motion_px": motion, "acting_motion_px": float(hand.acting), "push_cos": push_cos,
            "hand_body_dir": body.tolist(), "interface_span": span,
            # the share of its motion in which the object followed, while it acted: not its arrival or
            # departure at a transit's pace (dev_0297: a board leaving a stiff sheet at 4.5 px a frame, the
            # sheet next to it read following at 1 px, 0.63 of the board's motion from the grasp to the
            # contact period's end)
            "coupled_share": coupled_share(timing.coupled, np.where(transit_pairs(timing.hand_velocity,
                                           timing.coupled, g, p1), 0.0, timing.speed), g, p1),
            "contact_frames": None if timing.release is None else int(timing.release - g),
            "acting_end": None if end >= end_all else int(end), **normal}


# ------------------------------------------------------------------------------ evidence
def toucher_depth(an: Analysis, hand: HandTrack, g: int, end: int) -> dict:
    """How far the toucher moved along the camera's axis against across it while it acted (#23,
    fourteenth pass): its apparent scale S (`lifting.hand_scale`, a similarity fitted to its flow)
    from the grasp to `end`, at the frame k of its largest change; a toucher at depth z that comes
    to z / S moved fx |1 - 1/S| px-equivalents (at the object's depth, the image's own units) along
    the axis, against its image motion from the grasp to k. `depth_scale`: S there (> 1: toward the
    camera); `depth_px`, `depth_image_px`; {} where it was not read (no camera, under 2 frames)."""
    cam = getattr(an, "cam0", None)
    if cam is None or end - g < 2:
        return {}
    S = hand_scale(an, g, end, hand.uv)
    k = g + int(np.argmax(np.abs(np.log(S[g:end + 1]))))
    along = float(cam.fx * abs(1.0 - 1.0 / S[k]))
    across = float(np.linalg.norm(hand.uv[k] - hand.uv[g]))
    return {"depth_scale": float(S[k]), "depth_px": along, "depth_image_px": across}


def touching_component(an: Analysis, k: int, c2) -> np.ndarray | None:
    """Frame k's hand mask reduced to its connected component that reaches within 1.5 R of the
    contact c2 (the toucher, not another hand part or a tool elsewhere); None where no hand pixel
    is that near."""
    import cv2

    hand = an.hand[k]
    if not hand.any():
        return None
    n, lab = cv2.connectedComponents(hand.astype(np.uint8), connectivity=8)
    near = lab[disk_mask(hand.shape, c2, 1.5 * an.R) & hand]
    if not (near > 0).any():
        return None
    return lab == np.bincount(near[near > 0], minlength=n).argmax()


def hand_body_direction(an: Analysis, k: int, c2: np.ndarray) -> np.ndarray:
    """Unit 2D vector from the contact to the hand's body (the centroid of the hand component
    that touches the object)."""
    hand = an.hand[k]
    if not hand.any():
        return np.zeros(2)
    m = touching_component(an, k, c2)
    pts = pixel_centres(hand if m is None else m)
    return unit(pts.mean(0) - c2)


def circle_fit(pts: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The least-squares circle through (N, 2) points (Kasa's algebraic fit): (centre, radius,
    RMS distance of the points from it)."""
    p = np.asarray(pts, np.float64)
    A = np.column_stack([2 * p, np.ones(len(p))])
    b = (p ** 2).sum(1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:2]
    r = float(np.sqrt(max(sol[2] + c @ c, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(p - c, axis=1) - r) ** 2)))
    return c, r, rms


def toucher_roundness(an: Analysis, g: int, c2, end: int, min_px: int = 12):
    """How much the toucher at the contact looks like a ball: per frame from the grasp to `end`,
    the outline of the hand component that touches the object, less where it meets the object (the
    object may hide part of it), fitted with a circle. Returns the median over the frames of
    (RMS residual / radius), of (radius / the component's half extent) and, where the analysis
    knows its scale (`px_per_m`), of the radius in metres at the object's depth; or None where no frame
    shows at least `min_px` free outline pixels. A ball's free outline is an arc of one circle
    whose radius is half its extent (about (0, 1)); a palm's, a finger on a hand or a tool's is
    not one circle (a large residual) or a much larger one."""
    import cv2

    res, size, rad = [], [], []
    for k in range(g, min(end, an.T - 1) + 1):
        m = touching_component(an, k, c2)
        if m is None:
            continue
        cont, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not cont:
            continue
        pts = np.concatenate([c.reshape(-1, 2) for c in cont]).astype(np.float64)
        touch = dilate(an.obj[k], 2)
        free = pts[~touch[pts[:, 1].astype(int), pts[:, 0].astype(int)]]
        if len(free) < min_px:
            continue
        _, r, rms = circle_fit(free + 0.5)
        comp = pixel_centres(m)
        ext = float(np.ptp(comp, axis=0).max()) + 1.0
        if r > 0:
            res.append(rms / r)
            size.append(r / (0.5 * ext))
            rad.append(r)
    if not res:
        return None
    ppm = getattr(an, "px_per_m", None)
    return [float(np.median(res)), float(np.median(size))] + ([float(np.median(rad)) / ppm] if ppm else [])


def approach_velocity(an: Analysis, g: int, c2, frames: int = 3):
    """The hand's mean image velocity (px / frame) over the frames before the contact starts,
    near the contact (None when the hand is not seen there)."""
    vs = []
    for k in range(max(0, g - frames), g):
        h = erode(an.hand[k], 1) & disk_mask((an.H, an.W), c2, 4.0 * an.R)
        v = median_flow(an.flows.forward[k], h)
        if v is not None:
            vs.append(v)
    return np.mean(vs, axis=0) if vs else None


def interface_span(an: Analysis, g: int, c2, end: int, with_normal: bool = False):
    """Length of the straight hand-object interface relative to the object's size along it
    (a palm on a ball: ~0.5+; fingertips: ~0.1-0.3), the largest over the grasp window; with
    `with_normal`, also that interface's unit normal in the image (None where none is straight)."""
    best, normal = 0.0, None
    for k in range(g, min(end, an.T - 1) + 1):
        a = an.hand[k] & dilate(an.obj[k], 2) & disk_mask((an.H, an.W), c2, 0.6 * an.obj_size_px)
        if a.sum() < 5:
            continue
        p = pixel_centres(a)
        mu = p.mean(0)
        w, V = np.linalg.eigh(np.cov((p - mu).T))
        axis = V[:, -1]
        proj = (p - mu) @ axis
        length = float(np.ptp(proj))
        thick = float(np.sqrt(max(w[0], 0)) * 4)
        op = pixel_centres(an.obj[k] | (an.rest.silhouette & ~an.hand[k]))
        size = float(np.ptp((op - mu) @ axis)) if len(op) else 1.0
        straight = length / max(thick, 1.0)
        if straight >= 3.0 and length / max(size, 1.0) > best:
            best, normal = length / max(size, 1.0), V[:, 0].copy()
    return (best, normal) if with_normal else best


def toucher_front_width(an: Analysis, g: int, c2, end: int, push, depth_m: float = 0.01,
                        min_px: int = 5) -> float | None:
    """How wide the toucher's front is where it pushes, in metres: per frame from the grasp to
    `end`, the toucher's component at the contact, its pixels within `depth_m` (at the object's
    depth; at least 1.5 px) of its leading edge along `push` (unit, image: the way it pushes), and
    their extent across `push`; the median over the frames. This is the toucher's own shape, not
    where it overlaps the object: a flat face (a palm, a board) is as wide at its front as it is
    (10-18 cm here), a fingertip, a stick's end or a ball's cap a few centimetres. None where
    `push` has no direction or no frame shows the toucher at the contact."""
    d = np.asarray(push, float)
    if not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
        return None
    d = d / np.linalg.norm(d)
    perp = np.array([-d[1], d[0]])
    band = max(1.5, depth_m * an.px_per_m)
    widths = []
    for k in range(g, min(end, an.T - 1) + 1):
        m = touching_component(an, k, c2)
        if m is None:
            continue
        p = pixel_centres(m)
        if len(p) < min_px:
            continue
        along = p @ d
        front = p[along >= along.max() - band]
        widths.append(float(np.ptp(front @ perp)) + 1.0)
    if not widths:
        return None
    return float(np.median(widths)) / an.px_per_m
