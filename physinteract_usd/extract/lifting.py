"""How the contact moves: the hand's 2D track at the contact (`track_hand`), lifted to the 3D
initial trajectory T0 (`lift_trajectory`): a grasp at a depth that follows the hand's apparent
scale (`hand_scale`), a collider along its push direction (`push_direction`, `lift_along`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..contacts import ContactSet
from .analysis import Analysis, disk_mask, unit
from .contact import Contact3D, GraspContact, finger_radius, outward_normal
from .result import CONTACT_NAMES
from .segmentation import erode
from .timing import Timing


@dataclass
class HandTrack:
    """The hand's 2D track at the contact (`track_hand`)."""
    uv: np.ndarray          # (T, 2) px: the contact's centre up to the grasp, then the hand's flow integrated
    motion: float           # px: the track's largest extent from the grasp over the contact period
    first_main: int         # the frame the track first reaches half that extent (the first main motion)
    first_move: np.ndarray  # (2,) px: the displacement from the grasp to `first_main`
    acting: float = 0.0     # px: the largest extent from the grasp while the toucher acts (to the release)


@dataclass
class Lifted:
    """What `lift_trajectory` made."""
    contact: ContactSet                # the interaction contact, with its T0
    push_dir: np.ndarray | None        # (3,) a collider's push direction (None for a grasp)
    track_uv: np.ndarray               # (T, 2) the 2D track lifted (a grasp's held after its release)
    release: int | None                # the release frame: a grasp lets go, a collider leaves (None: never)
    # a grasp's path lifted at its grasp depth throughout (the apparent scale left out): what the
    # image alone says of its height (None for a collider)
    trajectory_flat: np.ndarray | None = None


def track_hand(timing: Timing, c2) -> HandTrack:
    """The hand's velocity at the contact (the object's next to it where the hand is not seen,
    within the contact period) integrated from the grasp frame."""
    vh, vo = timing.hand_velocity, timing.object_velocity
    g, p1 = timing.grasp, timing.period[1]
    T = len(vh) + 1
    hand_track = np.tile(c2, (T, 1)).astype(np.float64)
    for k in range(g, T - 1):
        v = vh[k] if not np.isnan(vh[k]).any() else (vo[k] if k < p1 and not np.isnan(vo[k]).any() else np.zeros(2))
        hand_track[k + 1] = hand_track[k] + v
    disp = hand_track - hand_track[g]
    ext = np.linalg.norm(disp[: p1 + 1], axis=1)
    far = int(np.argmax(ext))
    motion = float(ext[far])
    # the first main motion (half the largest extent) says push or pull: a poke is withdrawn
    # afterwards, a pull may end anywhere. Read while the toucher acts (to the release): a slow
    # press's few pixels are not its retreat's tens (dev_0010: a finger pressed a bar 2 px and
    # withdrew 14 px toward its body, which read as a pull)
    r = timing.release
    act = ext[: (min(p1, r) if r is not None and r > g + 1 else p1) + 1]
    m_act = float(act.max()) if len(act) else 0.0
    first_main = (int(np.argmax(act >= 0.5 * m_act)) if m_act >= 1.0 else
                  int(np.argmax(ext >= 0.5 * motion)) if motion > 0 else g)
    return HandTrack(hand_track, motion, first_main, disp[first_main], m_act)


def lift_trajectory(an: Analysis, hint, itype: str, timing: Timing, grasp: GraspContact, hand: HandTrack,
                    c3d: Contact3D, evidence: dict) -> Lifted:
    """Step 7: the interaction contact with its T0. A grasp holds the contact particles from the
    grasp to the release, its track held after it and lifted at a depth that follows the hand's
    apparent scale; a collider follows the hand over the whole video, lifted along its push
    direction, a sphere of the fingertip's radius starting just clear of the surface or a plane
    starting touching the object."""
    scene = an.scene
    T = an.T
    g, r = timing.grasp, timing.release
    c2, c3, idx, rest_g = grasp.uv, c3d.point, c3d.particles, c3d.rest
    motion, first_main = hand.motion, hand.first_main
    z_c = float(rest_g.camera.world_to_camera(c3[None])[0, 2])
    # adherent: the grasped particles follow the hand while grasped; colliders are the hand
    track = hand.uv.copy()
    if itype == "pointAdherent":
        end = (T - 1) if r is None else r
        track[end + 1:] = track[end]
    # depth: a hand coming toward the camera looks bigger; its apparent scale (a similarity fit to
    # its optical flow) gives the contact's depth over the grasp (pulls; colliders are lifted
    # along their push direction below)
    depth = np.full(T, z_c)
    if itype == "pointAdherent":
        scale = hand_scale(an, g, end, track)
        depth = z_c / scale
        evidence["hand_scale"] = np.round(scale, 4).tolist()
    base = scene.camera.at(g).unproject(c2[None], np.array([z_c]))[0]

    def lift(d):
        return np.stack([c3 + (scene.camera.at(k).unproject(track[k][None], np.array([d[k]]))[0] - base)
                         for k in range(T)])

    traj = lift(depth)
    # the simulation's domain bounds every lifted path (scene_bounds)
    bounds = scene_bounds(scene)
    flat = None
    if itype == "pointAdherent":
        kept = keep_on_ray_in_box(scene.camera, traj, bounds)
        moved = np.linalg.norm(kept - traj, axis=1)
        if moved.max() > 0:
            evidence["lift_kept_in_domain"] = {"frames": int((moved > 0).sum()), "max_m": round(float(moved.max()), 4)}
        traj = kept
        flat = keep_on_ray_in_box(scene.camera, lift(np.full(T, z_c)), bounds)
    users = hint is not None and (not hint.is_empty or hint.has_timing)
    contact = ContactSet(CONTACT_NAMES[itype], itype, np.zeros(0, np.int64), grasp_frame=g,
                         release_frame=r, trajectory=traj, contact_point=c3,
                         source="user" if users else "extracted")
    push3 = None
    if itype == "pointAdherent":
        contact.indices = idx
        contact.contact_point = an.x0[idx].mean(0)
        contact.trajectory = traj - c3 + contact.contact_point
        flat = flat - c3 + contact.contact_point
    else:
        outward = outward_normal(an, c3, idx)
        lateral = unit(traj[first_main] - traj[g])
        target = -outward
        fallbacks = ()
        if itype == "surfaceNonAdherent":
            gdir = unit(np.asarray(scene.settings.gravity, float))
            if np.linalg.norm(gdir) > 0 and np.dot(target, gdir) > np.cos(np.radians(40)):
                target = gdir  # a palm pressing down: along gravity
            elif np.linalg.norm(gdir) > 0:
                # the image refuses "into the surface" (the normal at an edge is a blend of two
                # faces): a palm then presses the object toward what holds it up, down
                fallbacks = (gdir,)
        push3 = (push_direction(lateral, c3, rest_g.camera, target, *fallbacks) if motion > 1.0
                 else unit(target))
        evidence.update({"outward_normal": outward.tolist(), "push_direction": push3.tolist()})
        if itype == "pointNonAdherent":
            radius = finger_radius(an, g, c2)
            evidence["finger_radius_source"] = "measured"
            if hint is not None and hint.grasp_radius is not None:
                radius = float(hint.grasp_radius)
                evidence["finger_radius_source"] = "user"
            evidence["finger_radius_m"] = radius
            contact.radius = radius
            # the sphere starts just clear of the object, on the outside of the contact
            start = c3 + outward * (radius + 0.5 * an.spacing)
            dmin = np.min(np.linalg.norm(an.x0 - start, axis=1))
            if dmin < radius + 0.25 * an.spacing:
                start = start + outward * (radius + 0.25 * an.spacing - dmin)
        else:
            normal = push3 if np.dot(push3, outward) < 0 else -push3
            contact.normal = tuple(map(float, normal))
            # the plane starts touching the object (no particle on its far side)
            s_min = float(np.min((an.x0 - c3) @ normal))
            start = c3 + normal * (s_min - 0.5 * an.spacing)
        contact.trajectory = lift_along(scene.camera, start, track, push3, g, bounds)
        contact.contact_point = c3
        # a collider acts wherever its trajectory puts it: on the stage it is active throughout
        # (the extraction's grasp and release, when it touches, are in the result and evidence)
        contact.grasp_frame = 0
        contact.release_frame = None
        if hint is not None and hint.has_timing:
            # the user says when the fingertip or palm touches: it acts only then
            if hint.grasp_frame is not None:
                contact.grasp_frame = g
            if hint.release_frame is not None:
                r = contact.release_frame = timing.release
    return Lifted(contact, push3, track, r, flat)


# ------------------------------------------------------------------------------ pieces
def scene_bounds(scene) -> tuple | None:
    """The box every lifted path stays in: the simulation's domain (None without one)."""
    st = getattr(scene, "settings", None)
    if st is None or getattr(st, "domain_min", None) is None:
        return None
    return np.asarray(st.domain_min, float), np.asarray(st.domain_max, float)


def hand_scale(an: Analysis, g: int, end: int, track: np.ndarray, max_step: float = 0.1) -> np.ndarray:
    """Cumulative apparent scale of the hand from frame g (1 up to g, held after `end`): per frame
    pair a similarity transform fitted (least median of squares) to the forward flow on the hand
    component at the contact. Scale s means the hand came 1/s closer: depth_k = depth_g / S_k."""
    import cv2

    T = an.T
    S = np.ones(T)
    for k in range(g, min(end, T - 1)):
        s = 1.0
        hand = an.hand[k]
        if hand.any():
            n, lab = cv2.connectedComponents(hand.astype(np.uint8), connectivity=8)
            near = lab[disk_mask(hand.shape, track[k], 2.0 * an.R) & hand]
            if (near > 0).any():
                comp = lab == np.bincount(near[near > 0]).argmax()
                m = erode(comp, 2)
                ys, xs = np.nonzero(m)
                if len(xs) >= 30:
                    p = np.stack([xs + 0.5, ys + 0.5], 1).astype(np.float32)
                    q = p + an.flows.forward[k][ys, xs]
                    A, _ = cv2.estimateAffinePartial2D(p, q, method=cv2.LMEDS)
                    if A is not None:
                        s = float(np.clip(np.sqrt(abs(np.linalg.det(A[:, :2]))), 1 - max_step, 1 + max_step))
        S[k + 1] = S[k] * s
    S[min(end, T - 1) + 1:] = S[min(end, T - 1)]
    return S


def push_direction(lateral: np.ndarray, c3: np.ndarray, cam, target: np.ndarray, *fallbacks) -> np.ndarray:
    """The 3D push direction: the image says only its component across the view ray (`lateral`,
    a direction at constant camera depth that moves the image the observed way); take the
    direction in the plane of `lateral` and the ray that is closest to `target` (into the surface,
    or gravity for a palm), as long as it moves the image the observed way, else `lateral`.
    "The observed way" is read in the image (the projection's derivative along the direction),
    not in 3D: a direction with a component along `lateral` but a larger one away from the camera
    moves the image toward its vanishing point, which may be the other way (dev_0181: a palm's
    press down the image lifted along a direction whose vanishing point was above it: the lift
    then went up while the palm pressed, and 12 m under the floor when it withdrew). `fallbacks`:
    further targets tried in turn where `target` fails that test."""
    ray = unit(c3 - cam.position)
    r2 = unit(ray - np.dot(ray, lateral) * lateral)
    seen = image_rate(cam, c3, lateral)
    for tg in (target, *fallbacks):
        t = np.dot(tg, lateral) * lateral + np.dot(tg, r2) * r2
        if np.linalg.norm(t) > 1e-9 and float(image_rate(cam, c3, t) @ seen) > 0:
            return unit(t)
    return lateral


def image_rate(cam, p: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(2,) px per metre: the derivative of p + s d's projection at s = 0 (pinhole, exact)."""
    x, y, z = cam.world_to_camera(np.asarray(p, float)[None])[0]
    R = cam.w2c_cv()[:3, :3]
    dx, dy, dz = R @ np.asarray(d, float)
    return np.array([cam.fx * (dx * z - x * dz) / z ** 2, cam.fy * (dy * z - y * dz) / z ** 2])


def lift_along(camera, start: np.ndarray, track: np.ndarray, direction: np.ndarray, g: int,
               bounds: tuple | None = None) -> np.ndarray:
    """Positions start + s_k direction whose projections follow the 2D track's displacement from
    frame g (s = 0 up to g), s_k in closed form: the line's image is a straight line through the
    start's projection, uv(s) = uv(0) + s / (1 + B s) * J (J: the image rate along the direction,
    B: the depth's relative rate), so the goal's position w along it gives s = w / (1 - B w).
    A goal at or beyond the line's vanishing point (1 - B w <= 0) is reached by no point of the
    line, however far: s is then as far as `bounds` allow that way. `bounds` (lo, hi): the box the
    path stays in (the simulation's domain: a toucher outside it acts on nothing, and a path that
    leaves the scene by metres is a lift that failed, never a motion); s is clipped to the
    segment of the line inside it (without bounds, an unreachable goal holds the last s)."""
    T = len(track)
    direction = np.asarray(direction, float)
    out = np.tile(start, (T, 1)).astype(np.float64)
    s_lo, s_hi = segment_in_box(start, direction, bounds)
    s_prev = 0.0
    for k in range(g + 1, T):
        cam = camera.at(k)
        uv0 = cam.project(np.asarray(start, float)[None])[0][0]
        goal = camera.at(g).project(np.asarray(start, float)[None])[0][0] + (track[k] - track[g])
        J = image_rate(cam, start, direction)
        jj = float(J @ J)
        if jj < 1e-12:
            continue   # the direction is the view ray: the image says nothing of s
        w = float((goal - uv0) @ J) / jj
        z0 = float(cam.world_to_camera(np.asarray(start, float)[None])[0, 2])
        B = float((cam.w2c_cv()[:3, :3] @ direction)[2]) / z0
        den = 1.0 - B * w
        s = w / den if den > 1e-9 else (np.inf if w > 0 else -np.inf)
        s = float(np.clip(s, s_lo, s_hi))
        if not np.isfinite(s):
            s = s_prev   # unbounded and unreachable: held where it last was
        out[k] = start + s * direction
        s_prev = s
    return out


def segment_in_box(p: np.ndarray, d: np.ndarray, bounds: tuple | None) -> tuple[float, float]:
    """The range of s for which p + s d lies in the box `bounds` = (lo, hi), grown to hold p (the
    whole line without bounds)."""
    if bounds is None:
        return -np.inf, np.inf
    p = np.asarray(p, float)
    lo, hi = (np.minimum(np.asarray(bounds[0], float), p), np.maximum(np.asarray(bounds[1], float), p))
    a, b = -np.inf, np.inf
    for i in range(3):
        if abs(d[i]) > 1e-12:
            t1, t2 = (lo[i] - p[i]) / d[i], (hi[i] - p[i]) / d[i]
            a, b = max(a, min(t1, t2)), min(b, max(t1, t2))
    return a, b


def keep_on_ray_in_box(camera, traj: np.ndarray, bounds: tuple | None) -> np.ndarray:
    """Each point of a path kept in the box `bounds` along its own view ray (its image unchanged,
    only its depth): to the nearest depth at which the ray is inside the box, or, where the ray
    misses the box, to the box's point nearest to it. A held contact lifted at a depth from the
    hand's apparent scale goes where that scale's drift puts it; the simulation's domain is where
    the object can be (a grasp outside it would pull the particles off the grid)."""
    if bounds is None:
        return traj
    lo, hi = (np.asarray(b, float) for b in bounds)
    out = np.array(traj, dtype=np.float64)
    for k in range(len(out)):
        p = out[k]
        if np.all(p >= lo) and np.all(p <= hi):
            continue
        o = camera.at(k).position
        a2, b2 = _ray_box(o, p - o, lo, hi)
        out[k] = o + float(np.clip(1.0, a2, b2)) * (p - o) if a2 <= b2 else np.clip(p, lo, hi)
    return out


def _ray_box(o, d, lo, hi) -> tuple[float, float]:
    """The range of t (> 0) for which o + t d lies in the box (empty: a > b)."""
    a, b = 1e-9, np.inf
    for i in range(3):
        if abs(d[i]) < 1e-12:
            if o[i] < lo[i] or o[i] > hi[i]:
                return 1.0, 0.0
            continue
        t1, t2 = (lo[i] - o[i]) / d[i], (hi[i] - o[i]) / d[i]
        a, b = max(a, min(t1, t2)), min(b, max(t1, t2))
    return a, b
