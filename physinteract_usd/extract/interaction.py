"""Interaction extraction from a video: where the hand touches the object, when it grasps and lets
go, how (interaction type), how it moves (the initial trajectory T0), and what holds the object
still (supports). numpy / OpenCV / scipy only; no USD (the stage I/O is `usd.extract_io`).

The method (docs/extract.md has the full account):

1. render the object at rest through the camera (silhouette, depth, particle visibility);
2. segment the hand in every frame (`models.segmenter`) and compute optical flow (`models.tracker`);
3. per frame, the contact region = hand pixels over the object at rest or next to its visible
   silhouette; per frame pair, the hand's and the object's velocities near it;
4. timing: the contact period = the longest run of frames in which the hand touches the object;
   the grasp is where the hand comes to (near) rest on the object before its main motion; the
   release is the hand's slowest frame before the object stops following it;
5. type: a contact whose first main motion moves the object away from the hand's body is a push
   (non-adherent), unless the hand went back the way it came in (a pull in depth); a long,
   straight hand-object interface is a surface (a palm); else adherent;
6. contact particles: the contact pixels at the grasp frame back-projected with the rendered depth
   (X = T_c^-1 pi^-1(x, d)) and mapped to the particles within a radius;
7. T0: the hand's velocity at the contact integrated from the grasp, lifted to 3D (at the
   contact's depth for a pull, along the push direction for a collider);
8. supports: particles that do not move while the rest does (tracked, interpolated to the ones
   the camera does not see), grouped into connected regions; gravity says a still object that
   would otherwise fall is held somewhere, so the stillest particles are taken when no region is.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from .geometry import back_project, particles_near, pixel_centres, render_rest, sample
from .models import Models
from .result import CONTACT_NAMES, INTERACTION_TYPES, ExtractedContact, ExtractionResult, Hint
from .segment import dilate, erode


RADIUS_SHARE = 0.35  # grasp radius as a share of the contact region's extent
GRASP_RADIUS_M = 0.03   # a hand's grasp (thumb and fingertips, ~6 cm across; the median of the suite's hands): the least it holds
GRASP_MAX_SHARE = 0.3   # ... and at most this share of the object's extent (something stays free)
SUPPORT_HINT_RADIUS_M = 0.03  # a support the user points at where none was detected: a clamp's or a hand's size


# ------------------------------------------------------------------------------ small helpers
def _disk_mask(shape, centre, radius) -> np.ndarray:
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W]
    return (xx + 0.5 - centre[0]) ** 2 + (yy + 0.5 - centre[1]) ** 2 <= radius ** 2


def _median_flow(flow: np.ndarray, mask: np.ndarray, fallback: np.ndarray | None = None):
    m = mask if mask.sum() >= 3 else fallback
    if m is None or not m.any():
        return None
    return np.median(flow[m], axis=0)


def _unit(v):
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.zeros_like(v)


def classify_interaction(evidence: dict, *, frames=None) -> tuple[str, float]:
    """The default rules (see the module doc). Returns (type, confidence in [0, 1])."""
    push = evidence.get("push_cos")
    moved = evidence.get("contact_motion_px", 0.0)
    surface = evidence.get("interface_span", 0.0)
    approach, ap_speed = evidence.get("approach_cos"), evidence.get("approach_speed_px", 0.0)
    if push is None or moved < 1.0:
        return "pointAdherent", 0.3
    if push < -0.6 and approach is not None and ap_speed >= 1.0 and approach < 0.0:
        # it looks pushed away from the hand, but the hand came in and went back out the way it
        # came: a pull toward the camera (depth is not seen)
        return "pointAdherent", 0.5
    if push < -0.6:
        # the object only moved away from the hand: pushed. A long flat interface is a palm.
        if surface > 0.45:
            return "surfaceNonAdherent", float(min(1.0, 0.5 + (surface - 0.45)))
        return "pointNonAdherent", float(min(1.0, -push))
    return "pointAdherent", float(min(1.0, 0.5 + 0.5 * (push + 0.6) / 1.6))


# ------------------------------------------------------------------------------ the analysis
class _Analysis:
    """Per-frame quantities shared by the steps."""

    def __init__(self, scene, frames, masks, masks_amodal, models: Models, device: str = "cpu"):
        self.scene = scene
        self.device = device
        self.frames = np.asarray(frames, np.float32)
        self.T, self.H, self.W = self.frames.shape[:3]
        cam = scene.camera
        self.static_camera = cam.is_static or np.allclose(cam.c2w, cam.c2w[0:1], atol=1e-9)
        self.cam0 = cam.at(0)
        self.x0 = np.asarray(scene.particles_positions, np.float64)
        self.spacing = float(scene.settings.particle_spacing)
        self.rest = render_rest(scene.gaussians, self.cam0, self.x0, self.spacing, device)
        if not self.rest.silhouette.any():
            raise InputError(scene.path, "the object is not in the camera's view at frame 0 (its rendered "
                             "silhouette is empty): check the camera")
        z = self.rest.depth[self.rest.silhouette]
        self.z_obj = float(np.median(z))
        self.px_per_m = float(self.cam0.fx / self.z_obj)
        self.spacing_px = self.spacing * self.px_per_m
        self.seg = models.segmenter(self.frames, masks, masks_amodal=masks_amodal, rest_alpha=self.rest.alpha,
                                    object_colors=scene.gaussians.colors)
        self.hand = self.seg.hand
        self.obj = self.seg.object
        self.flows = models.tracker.flows(self.frames)
        self.tracker = models.tracker
        ys, xs = np.nonzero(self.rest.silhouette)
        self.obj_size_px = float(max(np.ptp(xs), np.ptp(ys)) + 1)
        self.R = float(np.clip(2.5 * self.spacing_px, 4.0, 0.25 * self.obj_size_px + 4.0))
        self.eps = 0.35  # px per frame: below this, "not moving"
        self.clear = max(2, int(round(0.4 * self.R)))  # px kept clear of the hand when measuring the object

    # ---- contact region per frame
    def contact_region(self, k: int, centre=None) -> np.ndarray:
        hand = self.hand[k]
        region = hand & (self.rest.silhouette | dilate(self.obj[k], 2))
        if centre is not None:
            region &= _disk_mask((self.H, self.W), centre, 1.5 * self.R)
        return region

    def touching(self, k: int) -> int:
        return int((self.hand[k] & dilate(self.obj[k], 2)).sum())


def _hand_body_direction(an: _Analysis, k: int, c2: np.ndarray) -> np.ndarray:
    """Unit 2D vector from the contact to the hand's body (the centroid of the hand component
    that touches the object)."""
    import cv2

    hand = an.hand[k]
    if not hand.any():
        return np.zeros(2)
    n, lab = cv2.connectedComponents(hand.astype(np.uint8), connectivity=8)
    near = lab[_disk_mask(hand.shape, c2, 1.5 * an.R) & hand]
    comp = np.bincount(near[near > 0], minlength=n).argmax() if (near > 0).any() else 0
    m = lab == comp if comp > 0 else hand
    pts = pixel_centres(m)
    return _unit(pts.mean(0) - c2)


def _velocities(an: _Analysis, centres: list):
    """Per frame pair k -> k+1 the hand's and the object's median flow near the contact."""
    T = an.T
    vh = np.full((T - 1, 2), np.nan)
    vo = np.full((T - 1, 2), np.nan)
    for k in range(T - 1):
        c = centres[k]
        if c is None:
            continue
        disk = _disk_mask((an.H, an.W), c, an.R)
        big = _disk_mask((an.H, an.W), c, 2.0 * an.R)
        fl = an.flows.forward[k]
        h_in = erode(an.hand[k], 1)
        v = _median_flow(fl, h_in & disk, h_in & big)
        if v is not None:
            vh[k] = v
        # object pixels clear of the hand: the flow smears a few pixels across motion boundaries
        o_in = erode(an.obj[k], 1) & ~dilate(an.hand[k], an.clear)
        v = _median_flow(fl, o_in & big, o_in & _disk_mask((an.H, an.W), c, 3.0 * an.R))
        if v is not None:
            vo[k] = v
    return vh, vo


def _coupling(vh: np.ndarray, vo: np.ndarray, eps: float) -> np.ndarray:
    """+1: the object near the contact moves with the hand; 0: both (about) still; -1: not."""
    out = np.full(len(vh), -1, np.int8)
    for k in range(len(vh)):
        a, b = vh[k], vo[k]
        if np.isnan(a).any() and np.isnan(b).any():
            out[k] = 0
            continue
        if np.isnan(a).any():
            a = np.zeros(2)  # the hand hidden (e.g. behind the object): no evidence of its motion
        if np.isnan(b).any():
            out[k] = 0 if np.linalg.norm(a) < eps else 1  # the object near the contact all covered
            continue
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if max(na, nb) < eps:
            out[k] = 0
        elif nb >= eps and nb >= 0.2 * na and np.dot(a, b) >= 0.7 * na * nb:
            # the object next to the contact moves the hand's way (slower: it stretches)
            out[k] = 1
        else:
            out[k] = -1
    return out


def _hand_scale(an: _Analysis, g: int, end: int, track: np.ndarray, max_step: float = 0.1) -> np.ndarray:
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
            near = lab[_disk_mask(hand.shape, track[k], 2.0 * an.R) & hand]
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


def _approach_velocity(an: _Analysis, g: int, c2, frames: int = 3):
    """The hand's mean image velocity (px / frame) over the frames before the contact starts,
    near the contact (None when the hand is not seen there)."""
    vs = []
    for k in range(max(0, g - frames), g):
        h = erode(an.hand[k], 1) & _disk_mask((an.H, an.W), c2, 4.0 * an.R)
        v = _median_flow(an.flows.forward[k], h)
        if v is not None:
            vs.append(v)
    return np.mean(vs, axis=0) if vs else None


def _contact_period(near: np.ndarray) -> tuple[int, int]:
    """The longest run of frames in which the hand touches the object (one-frame gaps bridged)."""
    T = len(near)
    n = near.copy()
    for k in range(1, T - 1):
        if not n[k] and near[k - 1] and near[k + 1]:
            n[k] = True
    best, k = (0, T - 1, -1), 0
    while k < T:
        if n[k]:
            j = k
            while j + 1 < T and n[j + 1]:
                j += 1
            if j - k > best[2]:
                best = (k, j, j - k)
            k = j + 1
        else:
            k += 1
    return best[0], best[1]


def _contact_start(speed: np.ndarray, near: np.ndarray, p0: int, p1: int, coupled: np.ndarray, vh: np.ndarray) -> int:
    """The frame the contact starts: a hand comes to (near) rest on the object before it pulls or
    pushes. Within the contact period, the slowest frame of the first run of slow frames (speed at
    most 30% of the period's peak); ties (within 0.1 px, the tracking noise) go to the later frame
    (a late start misses only the first, slow motion; an early one would put the approach into T0).
    A wider tie (0.25 px) chained through the slowly starting pull and put balloon's and
    knit_cap's grasp 2 frames late (grasp error over the suite 0.69 -> 0.46 frames with 0.1). Where
    the hand never slows before most of its motion, the start of the run in which the object
    follows the hand."""
    T1 = len(speed)
    ks = [k for k in range(p0, min(p1, T1 - 1) + 1) if np.isfinite(speed[k])]
    if not ks:
        return p0
    sp = np.array([speed[k] for k in ks])
    peak = float(sp.max())
    slow = sp <= max(0.35, 0.3 * peak)
    path = np.cumsum(sp)
    if slow.any():
        i = int(np.argmax(slow))
        j = i
        while j + 1 < len(ks) and slow[j + 1]:
            j += 1
        run = list(range(i, j + 1))
        # the stillest frame, then later frames as long as they stay as still (a run of "slow"
        # frames may hold the whole slow pull: jumping to its last near-tie put toy_rope's and
        # knit_cap's grasp 8 frames late)
        pick = run[int(np.argmin(sp[run]))]
        best = sp[pick]
        while pick + 1 <= run[-1] and sp[pick + 1] <= best + 0.1:
            pick += 1
        if path[pick] - sp[pick] <= 0.5 * path[-1]:
            return _skip_approach(ks[pick], coupled, speed, p1)
    win = _grasp_window(near, coupled, vh)
    return _skip_approach(win[0], coupled, speed, p1) if win is not None else p0


def _skip_approach(g: int, coupled: np.ndarray, speed: np.ndarray, p1: int, eps: float = 0.35) -> int:
    """A start frame in which the hand still moves and the object does not follow, followed by
    one in which it does, is the end of the approach: start one later (at most twice)."""
    for _ in range(2):
        if g + 1 <= min(p1, len(coupled) - 1) and coupled[g] < 0 and coupled[g + 1] > 0 and speed[g] > eps:
            g += 1
    return g


def _release(coupled: np.ndarray, near: np.ndarray, g: int, speed: np.ndarray | None = None):
    """The release: the object stops following the hand (two decoupled frame pairs in a row, or
    the hand no longer touching) at some frame r_c; None: held to the end. A hand slows down
    before it lets go and moves off after: with `speed`, the release is the frame after the
    slowest of the frame pairs just before r_c (ties to the earlier: a late release would drag
    the object along the hand's retreat)."""
    T1 = len(coupled)
    r_c = None
    # a slow pull may leave the object behind for a frame or two after the grasp: decoupling only
    # counts once the object has followed the hand (bow_tie: released 2 frames after its grasp)
    first = next((k for k in range(g + 1, T1) if coupled[k] > 0), g)
    for k in range(first + 1 if first > g else g + 1, T1):
        if not near[k]:
            r_c = k
            break
        if coupled[k] < 0 and (k + 1 >= T1 or coupled[k + 1] < 0 or not near[k + 1]):
            r_c = k
            break
    if r_c is None or speed is None:
        return r_c
    ks = [k for k in range(max(g + 1, r_c - 3), min(r_c, T1 - 1) + 1) if np.isfinite(speed[k])]
    if not ks:
        return r_c
    best = min(speed[k] for k in ks)
    k_min = min(k for k in ks if speed[k] <= best + 0.1)
    return k_min + 1


def _coupled_share(coupled: np.ndarray, speed: np.ndarray, g: int, p1: int) -> float:
    """Share of the hand's motion over the contact in which the object next to it follows."""
    sl = slice(g, min(p1, len(coupled)))
    sp = np.nan_to_num(speed[sl])
    tot = float(sp.sum())
    return float(sp[coupled[sl] > 0].sum() / tot) if tot > 0 else 0.0


def _grasp_window(touch: np.ndarray, coupled: np.ndarray, vh: np.ndarray):
    """The run of touching frames with coupled (or still) motion that carries the most motion.
    Returns (grasp, release or None, motion in px)."""
    T = len(touch)
    best = None
    k = 0
    speed = np.nan_to_num(np.linalg.norm(vh, axis=1))
    while k < T - 1:
        if touch[k] and coupled[k] >= 0:
            j = k
            while j < T - 1 and touch[j] and coupled[j] >= 0:
                j += 1
            # frames k .. j-1 are pairs inside the window; the window holds from k to j
            score = float(np.sum(speed[k:j][coupled[k:j] > 0]))
            if best is None or score > best[2]:
                best = (k, j, score)
            k = j + 1
        else:
            k += 1
    if best is None:
        return None
    g, j, score = best
    release = None if j >= T - 1 else j
    return g, release, score


# ------------------------------------------------------------------------------ main entry
def extract_interaction(scene, frames, masks=None, *, masks_amodal: bool = False, hint: Hint | None = None,
                        interaction_type: str | None = None, models: Models | None = None,
                        log=print, device: str = "cpu") -> ExtractionResult:
    """Extract the interaction from a video of the stage's object.

    scene: a `SceneData` (read_stage); frames (T, H, W, 3) float in [0, 1]; masks (T, H, W) bool
    object silhouettes or None. `hint` and `interaction_type` win over detection. Returns an
    `ExtractionResult` (contacts with the fit's fields, hand masks, evidence). `device` (cpu or
    cuda) is where the object at rest is rendered for depth; the rest runs on the CPU."""
    models = models or Models()
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise InputError(scene.path, "frames must be (T, H, W, 3)")
    T = len(frames)
    if T < 3:
        raise InputError(scene.path, f"extraction needs at least 3 frames, the stage has {T}")
    if (frames.shape[2], frames.shape[1]) != (scene.camera.width, scene.camera.height):
        raise InputError(scene.path, f"frames are {frames.shape[2]}x{frames.shape[1]}, the camera "
                         f"{scene.camera.width}x{scene.camera.height}")
    if interaction_type is not None and interaction_type not in INTERACTION_TYPES:
        raise InputError("--type", f"must be one of {', '.join(INTERACTION_TYPES)}, not {interaction_type!r}")
    hint = _check_hint(hint, scene, T)
    notes = []
    an = _Analysis(scene, frames, masks, masks_amodal, models, device)
    if not an.static_camera:
        notes.append("the camera moves: image-space motion cues (timing, supports) assume a static camera "
                     "and are unreliable")
    evidence = {"spacing_px": an.spacing_px, "object_size_px": an.obj_size_px, "radius_px": an.R,
                "hand_pixels": int(an.hand.sum()), "models": models.describe()}
    touch = np.array([an.touching(k) for k in range(T)])
    evidence["touch_px"] = touch.tolist()

    # ---- where: a first contact location (hint or detection), refined at the grasp frame
    hint_c2, hint_idx, hint_frame = _hint_location(an, hint)
    touching = touch >= 3
    if hint_c2 is None and not touching.any():
        raise InputError(scene.path, "no hand touching the object was found in the video; give a hint "
                         "(--hint-pixel K,U,V or --hint-particles) or author a contact set")
    centres = _contact_centres(an, touching, hint_c2, hint_frame)
    vh, vo = _velocities(an, centres)
    coupled = _coupling(vh, vo, an.eps)
    near = touching | (np.array([c is not None for c in centres]) & (hint_c2 is not None))
    p0, p1 = _contact_period(near)
    speed = np.linalg.norm(vh, axis=1)
    g = _contact_start(speed, near, p0, p1, coupled, vh)
    r = _release(coupled, near, g, speed)
    evidence.update({"contact_period": [p0, p1], "coupling": coupled.tolist(),
                     "hand_velocity_px": np.round(vh, 3).tolist(),
                     "object_velocity_px": np.round(vo, 3).tolist(), "grasp_frame": g, "release_frame": r})

    # contact at the grasp frame: the hand over the object at rest, next to the first location
    c2 = centres[g] if centres[g] is not None else (hint_c2 if hint_c2 is not None else centres[int(np.argmax(touching))])
    if hint_c2 is not None:
        c2 = hint_c2 if hint_frame is None or hint_frame <= g else _track_back_to(an, hint_c2, hint_frame, g)
    region = an.contact_region(g, c2) if hint_idx is None else np.zeros((an.H, an.W), bool)
    if hint_c2 is not None and hint_idx is None:
        region = _disk_mask((an.H, an.W), c2, max(2.0, 0.75 * an.R)) & (an.rest.alpha > 0.05)
        if not region.any():
            region = _disk_mask((an.H, an.W), c2, 1.0)

    # ---- how it moved: the hand's 2D track at the contact, from the contact's start on
    hand_track = np.tile(c2, (T, 1)).astype(np.float64)
    for k in range(g, T - 1):
        v = vh[k] if not np.isnan(vh[k]).any() else (vo[k] if k < p1 and not np.isnan(vo[k]).any() else np.zeros(2))
        hand_track[k + 1] = hand_track[k] + v
    disp = hand_track - hand_track[g]
    ext = np.linalg.norm(disp[: p1 + 1], axis=1)
    far = int(np.argmax(ext))
    motion = float(ext[far])
    # the first main motion (half the largest extent) says push or pull: a poke is withdrawn
    # afterwards, a pull may end anywhere
    first_main = int(np.argmax(ext >= 0.5 * motion)) if motion > 0 else g
    d2 = disp[first_main]
    body = _hand_body_direction(an, g, c2)
    push_cos = float(np.dot(_unit(d2), body)) if motion > 0 and np.linalg.norm(body) > 0 else None
    span = _interface_span(an, g, c2, p1)
    v_app = _approach_velocity(an, g, c2)
    app_speed = float(np.linalg.norm(v_app)) if v_app is not None else 0.0
    approach_cos = float(np.dot(_unit(v_app), _unit(d2))) if app_speed > 0 and motion > 0 else None
    evidence.update({"approach_speed_px": app_speed, "approach_cos": approach_cos})
    evidence.update({"contact_uv": c2.tolist(), "contact_motion_px": motion, "push_cos": push_cos,
                     "hand_body_dir": body.tolist(), "interface_span": span,
                     "coupled_share": _coupled_share(coupled, speed, g, p1)})

    # ---- type
    if interaction_type is not None:
        itype, conf, tsource = interaction_type, 1.0, "user"
    else:
        itype, conf = models.classifier(evidence, frames=frames)
        tsource = "detected"
    evidence["type_confidence"] = conf

    # ---- 3D: contact particles, T0
    cam_g = scene.camera.at(g)
    rest_g = an.rest if an.static_camera else render_rest(scene.gaussians, cam_g, an.x0, an.spacing, an.device)
    if hint_idx is not None:
        idx = hint_idx
        c3 = an.x0[idx].mean(0)
        pix = None
    else:
        pix = pixel_centres(region) if region.any() else c2[None]
        pts3 = back_project(rest_g, pix)
        radius, radius_why = _contact_radius_m(an, region, with_reason=True)
        if hint is not None and hint.grasp_radius is not None:
            radius, radius_why = float(hint.grasp_radius), "user"
        if itype == "pointAdherent":
            evidence.update({"grasp_radius_m": radius, "grasp_radius_source": radius_why})
        c3 = _robust_centre(pts3)
        if itype == "pointAdherent":
            c3 = _onto_particles(c3, an.x0, an.spacing)
        idx = particles_near(c3[None], an.x0, radius, min_count=3)
    z_c = float(rest_g.camera.world_to_camera(c3[None])[0, 2])
    # adherent: the grasped particles follow the hand while grasped; colliders are the hand
    track = hand_track.copy()
    if itype == "pointAdherent":
        end = (T - 1) if r is None else r
        track[end + 1:] = track[end]
    else:
        r = None
    # depth: a hand coming toward the camera looks bigger; its apparent scale (a similarity fit to
    # its optical flow) gives the contact's depth over the grasp (pulls; colliders are lifted
    # along their push direction below)
    depth = np.full(T, z_c)
    if itype == "pointAdherent":
        scale = _hand_scale(an, g, end, track)
        depth = z_c / scale
        evidence["hand_scale"] = np.round(scale, 4).tolist()
    traj = np.empty((T, 3))
    base = scene.camera.at(g).unproject(c2[None], np.array([z_c]))[0]
    for k in range(T):
        traj[k] = c3 + (scene.camera.at(k).unproject(track[k][None], np.array([depth[k]]))[0] - base)
    contact = ExtractedContact(CONTACT_NAMES[itype], itype, np.zeros(0, np.int64), grasp_frame=g,
                               release_frame=r, trajectory=traj, contact_point=c3, track_uv=track,
                               pixels=pix, pixels_frame=g, confidence=conf,
                               source="hint" if not (hint is None or hint.is_empty) else "extracted",
                               label=f"{itype} ({tsource})")
    push3 = None
    if itype == "pointAdherent":
        if hint_idx is None and evidence.get("grasp_radius_source") == "pinch":
            notes.append(f"grasp: {len(idx)} particles within {100 * radius:.1f} cm of the contact, the least a pinch "
                         "holds (the video shows where the hand grasps, not how much it holds); --grasp-radius "
                         "sets it")
        contact.indices = idx
        contact.contact_point = an.x0[idx].mean(0)
        contact.trajectory = traj - c3 + contact.contact_point
    else:
        outward = _outward_normal(an, c3, idx)
        lateral = _unit(traj[first_main] - traj[g])
        target = -outward
        if itype == "surfaceNonAdherent":
            gdir = _unit(np.asarray(scene.settings.gravity, float))
            if np.linalg.norm(gdir) > 0 and np.dot(target, gdir) > np.cos(np.radians(40)):
                target = gdir  # a palm pressing down: along gravity
        push3 = _push_direction(lateral, c3, rest_g.camera, target) if motion > 1.0 else _unit(target)
        evidence.update({"outward_normal": outward.tolist(), "push_direction": push3.tolist()})
        if itype == "pointNonAdherent":
            radius = _finger_radius(an, g, c2)
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
        contact.trajectory = _lift_along(scene.camera, start, track, push3, g)
        contact.contact_point = c3
        contact.grasp_frame = 0
        contact.release_frame = None
    contacts = [contact]

    # ---- supports
    fixed_sets, motion_p, sup_ev = find_supports(an, exclude=idx if itype == "pointAdherent" else np.zeros(0, np.int64),
                                                 contact_motion_px=motion, push_dir=push3)
    evidence["supports"] = sup_ev
    sup_source = "extracted"
    cores = sup_ev.get("core_particles", [])
    shell = sum(len(s_) for s_ in fixed_sets) - sum(cores)
    if (fixed_sets and len(cores) == len(fixed_sets) and "fallback" not in sup_ev and shell > 0
            and not (hint is not None and hint.has_support)):
        notes.append(f"supports: {sum(len(s_) for s_ in fixed_sets)} particles held, {shell} of them the shell around "
                     "the stillest core (the video cannot tell whether a support's outer layer moves a little); if "
                     "the preview shows the support wrong, --support-pixel or --support-particles sets it")
    if hint is not None and hint.has_support:
        fixed_sets = _hinted_supports(an, scene, hint, fixed_sets,
                                      idx if itype == "pointAdherent" else np.zeros(0, np.int64))
        sup_source = "hint"
        sup_ev["hint"] = [int(len(s)) for s in fixed_sets]
        if not fixed_sets:
            notes.append("the support hint leaves no particle outside the hand's grasp: no support is set")
    guessed = "fallback" in sup_ev and sup_source == "extracted"
    if guessed:
        notes.append(f"supports: a guess, {sup_ev['fallback']}; the first fit sizes it by what it renders; "
                     "--support-pixel or --support-particles sets it")
    for i, s in enumerate(fixed_sets):
        contacts.append(ExtractedContact(f"support{i}" if len(fixed_sets) > 1 else "support", "fixed", s,
                                         contact_point=an.x0[s].mean(0), source=sup_source, label="support",
                                         guessed=guessed))
    return ExtractionResult(contacts=contacts, hand_masks=an.hand, interaction_type=itype, type_source=tsource,
                            grasp_frame=int(contact.grasp_frame) if itype == "pointAdherent" else g,
                            release_frame=r, evidence=evidence, notes=notes, frames=frames,
                            object_masks=an.obj, support_motion=motion_p)


# ------------------------------------------------------------------------------ pieces
def _check_pixel(k, uv, scene, T, flag):
    if not (0 <= int(k) < T):
        raise InputError(flag, f"frame {k} is outside the video (0..{T - 1})")
    u, v = map(float, uv)
    W, H = scene.camera.width, scene.camera.height
    if not (0 <= u < W and 0 <= v < H):
        raise InputError(flag, f"pixel ({u - 0.5:g}, {v - 0.5:g}) is outside the {W}x{H} frame")


def _check_hint(hint, scene, T):
    if hint is None:
        return hint
    P = len(scene.particles_positions)
    if hint.support_particles is not None and len(hint.support_particles):
        idx = np.asarray(hint.support_particles)
        if not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= P:
            raise InputError("--support-particles", f"particle indices must be integers in [0, {P}) (the stage "
                             f"has {P} simulation particles)")
        hint.support_particles = np.unique(idx.astype(np.int64))
    for k, uv in hint.support_pixels or []:
        _check_pixel(k, uv, scene, T, "--support-pixel")
    if hint.grasp_radius is not None:
        ext = float(np.max(np.ptp(np.asarray(scene.particles_positions, float), axis=0)))
        if not 0 < hint.grasp_radius <= ext:  # nan fails the comparison too
            raise InputError("--grasp-radius", f"must be a length in metres in (0, {ext:.3g}] (the object's "
                             f"extent), got {hint.grasp_radius}")
    if hint.is_empty:
        return hint
    if hint.particles is not None and len(hint.particles):
        idx = np.asarray(hint.particles)
        if not np.issubdtype(idx.dtype, np.integer):
            raise InputError("--hint-particles", "particle indices must be integers")
        if idx.min() < 0 or idx.max() >= P:
            raise InputError("--hint-particles", f"particle indices must lie in [0, {P}) (the stage has {P} "
                             "simulation particles)")
        hint.particles = np.unique(idx.astype(np.int64))
    if hint.pixel is not None:
        k = 0 if hint.frame is None else hint.frame
        _check_pixel(k, hint.pixel, scene, T, "--hint-pixel")
        hint.frame = int(k)
    return hint


def _hinted_supports(an: _Analysis, scene, hint, detected: list, exclude) -> list:
    """The supports the user's hint asks for (see `Hint`): their particles as they are, or per
    support pixel the detected still region there (within 2 spacings of the pixel's surface point)
    or else the particles within SUPPORT_HINT_RADIUS_M of it. Detected regions no pixel points at
    are dropped."""
    exclude = np.asarray(exclude, np.int64)
    if hint.support_particles is not None and len(hint.support_particles):
        held = np.setdiff1d(hint.support_particles, exclude)
        return [held] if len(held) else []
    sets, used = [], set()
    for k, uv in hint.support_pixels:
        rest_k = an.rest if an.static_camera else render_rest(scene.gaussians, scene.camera.at(k), an.x0,
                                                                an.spacing, an.device)
        c = np.asarray(uv, np.float64)[None]
        if not sample(dilate(rest_k.silhouette, 1).astype(np.float32), c, order=0)[0]:
            raise InputError("--support-pixel", f"pixel ({c[0, 0] - 0.5:g}, {c[0, 1] - 0.5:g}) is not on the "
                             "object at rest")
        p3 = back_project(rest_k, c)[0]
        near = [i for i, s_ in enumerate(detected)
                if np.min(np.linalg.norm(an.x0[s_] - p3, axis=1)) <= 2.0 * an.spacing]
        if near:
            for i in near:
                if i not in used:
                    used.add(i)
                    sets.append(detected[i])
            continue
        idx = particles_near(p3[None], an.x0, max(SUPPORT_HINT_RADIUS_M, 1.6 * an.spacing), min_count=3)
        sets.append(np.setdiff1d(idx, exclude))
    return [s_ for s_ in sets if len(s_)]


def _hint_location(an: _Analysis, hint):
    """(2D location, particle indices, frame) of the hint; Nones without one."""
    if hint is None or hint.is_empty:
        return None, None, None
    if hint.particles is not None and len(hint.particles):
        uv, _ = an.cam0.project(an.x0[hint.particles].mean(0)[None])
        return uv[0], hint.particles, hint.frame
    c = np.asarray(hint.pixel, np.float64)
    k = hint.frame
    on_obj = dilate(an.obj[k] | an.rest.silhouette | an.hand[k], max(2, int(round(an.R))))
    if not sample(on_obj.astype(np.float32), c[None], order=0)[0]:
        raise InputError("--hint-pixel", f"pixel ({c[0]:g}, {c[1]:g}) in frame {k} is not on or next to the "
                         "object")
    return c, None, k


def _contact_centres(an: _Analysis, touching, hint_c2, hint_frame):
    """Per frame, the centre of the hand-object contact region (None where the hand does not
    touch). With a hint, the region next to the hint's location."""
    centres = []
    prev = hint_c2
    for k in range(an.T):
        if not touching[k] and hint_c2 is None:
            centres.append(None)
            continue
        region = an.contact_region(k, prev)
        if not region.any() and prev is not None:
            region = an.contact_region(k) & _disk_mask((an.H, an.W), prev, 3 * an.R)
        if not region.any():
            centres.append(prev if hint_c2 is not None else None)
            continue
        c = pixel_centres(region).mean(0)
        if hint_c2 is not None:
            c = 0.5 * (c + prev)
        centres.append(c)
        prev = c
    return centres


def _track_back_to(an: _Analysis, c, k_from, k_to):
    """A pixel of frame k_from carried back to frame k_to through the flow."""
    tr = an.tracker.track(an.flows, np.asarray(c, np.float64)[None], start=k_from)
    p = tr.uv[k_to, 0]
    return p if np.isfinite(p).all() else np.asarray(c, np.float64)


def _onto_particles(c3: np.ndarray, x0: np.ndarray, spacing: float) -> np.ndarray:
    """A hand holds material: a grasp centre more than a particle spacing from every particle (the
    rendered surface it was back-projected from is the splats' edge, which lies well outside the
    particles of a fuzzy or thin object, and at a silhouette's rim the depth is the background's
    fill) moves straight toward its nearest particle until it is one spacing away."""
    d = np.linalg.norm(x0 - c3, axis=1)
    j = int(np.argmin(d))
    if d[j] <= spacing:
        return c3
    return x0[j] + (c3 - x0[j]) * (spacing / d[j])


def _robust_centre(pts: np.ndarray) -> np.ndarray:
    med = np.median(pts, 0)
    d = np.linalg.norm(pts - med, axis=1)
    keep = d <= np.percentile(d, 80) + 1e-12
    return pts[keep].mean(0)


def _contact_radius_m(an: _Analysis, region, with_reason: bool = False):
    """The grasp's radius in metres: a hand holds a region of physical size, not of pixels, so at
    least GRASP_RADIUS_M (a pinch), more when the contact region seen is larger (RADIUS_SHARE of
    its extent), at most GRASP_MAX_SHARE of the object's extent and never under 1.6 particle
    spacings. (At low resolution the region the hand covers is a few pixels and says little:
    sized from pixels, the foam_bar sample's grasp held 11 particles for the truth's 47, and the
    fit stiffened the soft half to carry the pull.) With `with_reason`, (radius, what decided it:
    "pinch" | "contact region" | "object size" | "spacing")."""
    ext_obj = float(np.max(np.ptp(an.x0, axis=0)))
    r, why = GRASP_RADIUS_M, "pinch"
    if region.any():
        ys, xs = np.nonzero(region)
        ext_px = float(max(np.ptp(xs), np.ptp(ys)) + 1)
        if RADIUS_SHARE * ext_px / an.px_per_m > r:
            r, why = RADIUS_SHARE * ext_px / an.px_per_m, "contact region"
    if r > GRASP_MAX_SHARE * ext_obj:
        r, why = GRASP_MAX_SHARE * ext_obj, "object size"
    if r < 1.6 * an.spacing:
        r, why = 1.6 * an.spacing, "spacing"
    return (float(r), why) if with_reason else float(r)


def _interface_span(an: _Analysis, g: int, c2, end: int) -> float:
    """Length of the straight hand-object interface relative to the object's size along it
    (a palm on a ball: ~0.5+; fingertips: ~0.1-0.3), the largest over the grasp window."""
    best = 0.0
    for k in range(g, min(end, an.T - 1) + 1):
        a = an.hand[k] & dilate(an.obj[k], 2) & _disk_mask((an.H, an.W), c2, 0.6 * an.obj_size_px)
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
        if straight >= 3.0:
            best = max(best, length / max(size, 1.0))
    return best


def _push_direction(lateral: np.ndarray, c3: np.ndarray, cam, target: np.ndarray) -> np.ndarray:
    """The 3D push direction: the image says only its component across the view ray (`lateral`);
    take the direction in the plane of `lateral` and the ray that is closest to `target` (into
    the surface, or gravity for a palm), as long as it moves the image the observed way."""
    ray = _unit(c3 - cam.position)
    r2 = _unit(ray - np.dot(ray, lateral) * lateral)
    t = np.dot(target, lateral) * lateral + np.dot(target, r2) * r2
    if np.dot(t, lateral) <= 0 or np.linalg.norm(t) < 1e-9:
        return lateral
    return _unit(t)


def _lift_along(camera, start: np.ndarray, track: np.ndarray, direction: np.ndarray, g: int) -> np.ndarray:
    """Positions start + s_k direction whose projections follow the 2D track's displacement from
    frame g (s_k by Gauss-Newton on the reprojection; s = 0 up to g)."""
    T = len(track)
    out = np.tile(start, (T, 1)).astype(np.float64)
    uv0, _ = camera.at(g).project(start[None])
    s = 0.0
    for k in range(T):
        if k <= g:
            continue
        cam = camera.at(k)
        goal = uv0[0] + (track[k] - track[g])
        for _ in range(6):
            p = start + s * direction
            uv, _ = cam.project(p[None])
            eps = 1e-4
            uv2, _ = cam.project((p + eps * direction)[None])
            J = (uv2[0] - uv[0]) / eps
            jj = float(J @ J)
            if jj < 1e-12:
                break
            s -= float(J @ (uv[0] - goal)) / jj
        out[k] = start + s * direction
    return out


def _outward_normal(an: _Analysis, c3, idx) -> np.ndarray:
    """Outward surface normal at a contact point: away from the particles within a few spacings,
    flipped toward the camera's side if it is ambiguous."""
    d = np.linalg.norm(an.x0 - c3, axis=1)
    near = an.x0[d < max(4 * an.spacing, np.sort(d)[min(len(d) - 1, 20)])]
    n = _unit(c3 - near.mean(0))
    if np.linalg.norm(n) == 0:
        n = _unit(an.cam0.position - c3)
    return n


def _finger_radius(an: _Analysis, g: int, c2) -> float:
    """The fingertip's half-width at the contact (distance transform of the hand mask), in metres."""
    import cv2

    hand = an.hand[g].astype(np.uint8)
    if not hand.any():
        return 1.5 * an.spacing
    dt = cv2.distanceTransform(hand, cv2.DIST_L2, 3)
    disk = _disk_mask(hand.shape, c2, 2 * an.R) & (hand > 0)
    r_px = float(np.percentile(dt[disk], 75)) if disk.any() else float(dt.max())
    return float(np.clip(r_px / an.px_per_m, 0.5 * an.spacing, 6 * an.spacing))


# ------------------------------------------------------------------------------ supports
def find_supports(an: _Analysis, exclude=np.zeros(0, np.int64), contact_motion_px: float = 0.0,
                  push_dir=None, rel_threshold: float = 0.08, abs_threshold: float = 0.6,
                  core_rel: float = 0.0, core_abs: float = 0.0, margin: float = 1.05,
                  shell_hidden_only: bool = True):
    """Particles that stay put while the object moves: connected still regions -> fixed sets.

    Still: motion at most max(abs_threshold, rel_threshold x the contact's motion). Near a support
    the motion grows with the distance from it, so of each connected still region only its core
    (motion at most the split between the held particles' noise and their neighbours' small motion,
    `_log_split`, or at most max(core_abs, core_rel x the contact's motion)) and `margin` spacings
    around it are kept: fixing particles that do move a little would hide the material there from
    the fit. The default margin (1.05 spacings) keeps the core and the one shell of neighbours around
    it that is still too: the motion is interpolated from tracked seeds up to 1.5 spacings away (and
    hidden particles from the nearest seeds), which blurs a support's boundary by about a spacing, so
    the core alone misses the support's outer shell. Measured on the synthetic suite (docs/benchmarks/
    extract.md): support recall 0.67 -> 0.82, precision 0.79 -> 0.74, and the fit from extracted
    contacts within 0.05 of the true-contact fit on 7 scenes instead of 6; the two ropes hung from a
    sharp hook (hemp_rope, toy_rope) lose by the extra shell, which holds particles that move.
    `shell_hidden_only` (default): of the shell, only the particles the camera does not see are
    kept (`support_core`): the blur is the hidden particles', whose motion comes from the nearest
    seeds, while a seen particle is measured where it is. Fit bar on 8 of 13 scenes instead of 7
    (toy_rope passes, glove 0.315 -> 0.367, tow_rope 0.563 -> 0.502, the rest within 0.03; H100,
    2026-11-24).

    Motion per particle (px): `particle_motion` from object pixels tracked from frame 0."""
    x0, h = an.x0, an.spacing
    rest = an.rest
    step = max(1, int(round(0.5 * an.spacing_px)))
    sil = rest.silhouette & ~dilate(an.hand[0], 1)
    ys, xs = np.nonzero(sil)
    sel = (ys % step == 0) & (xs % step == 0)
    seeds = np.stack([xs[sel] + 0.5, ys[sel] + 0.5], 1).astype(np.float64)
    stop = np.stack([dilate(m, 1) for m in an.hand])
    tr = an.tracker.track(an.flows, seeds, start=0, stop=stop)
    if an.flows.grays is not None and hasattr(an.tracker, "_flow"):
        # small motions from direct flows (no drift) where they pass their checks
        from .track import direct_displacements

        dr = direct_displacements(an.tracker, an.flows, seeds, 0, stop)
        use = dr.valid & (~tr.valid | (np.linalg.norm(dr.uv - tr.uv, axis=2) < 3.0))
        tr.uv = np.where(use[..., None], dr.uv, tr.uv)
        tr.valid = tr.valid | dr.valid
    seeds3 = back_project(rest, seeds)
    # a seed is informative when it was watched while the object moved: tracked through the
    # frames in which the object's motion reached half its largest (a seed lost early, when
    # nothing had moved yet, tells nothing about stillness)
    disp = np.linalg.norm(tr.uv - seeds[None], axis=2)
    with np.errstate(invalid="ignore"):
        M = np.array([np.nanpercentile(d[v], 90) if v.sum() >= 3 else 0.0 for d, v in zip(disp, tr.valid)])
    seen_motion = np.array([M[tr.valid[:, i]].max() if tr.valid[:, i].any() else 0.0 for i in range(len(seeds))])
    good = (seen_motion >= 0.5 * max(M.max(), 1e-9)) & (tr.valid.sum(0) >= 2)
    ev = {"seeds": int(len(seeds)), "seeds_tracked": int(good.sum())}
    P = len(x0)
    if good.sum() < 6:
        return [], np.full(P, np.nan), ev
    D = (tr.uv - seeds[None])[:, good]          # (T, S, 2), nan where lost
    S3 = seeds3[good]
    motion = particle_motion(x0, S3, D, h)
    moving = max(contact_motion_px, float(np.nanpercentile(motion, 95)))
    thr = max(abs_threshold, rel_threshold * moving)
    ev.update({"threshold_px": thr, "reference_motion_px": moving})
    still = motion <= thr
    still[np.asarray(exclude, np.int64)] = False
    if moving < 3 * abs_threshold:
        ev["note"] = "the object hardly moves: no support can be told from the motion"
        return [], motion, ev
    sets = _components(x0[still], 1.8 * h, np.where(still)[0])
    sets = [s for s in sets if len(s) >= 2]
    # near a support the motion grows with the distance from it: keep each still region's core and
    # a margin around it. The core: the still particles' motions fall in two groups, the held ones
    # at the tracking noise (~0.01-0.1 px) and their neighbours that move a little (0.2-1 px); the
    # split is where the two groups of log motion are best separated (Otsu). Measured against
    # the synthetic suite's true supports (docs/benchmarks/extract.md) it beats a fixed share of each
    # region's motion (F1 0.72 vs 0.57 mean).
    low = max(core_abs, core_rel * moving)
    split = _log_split(motion[np.concatenate(sets)]) if sets else 0.0
    cores, n_core = [], []
    for s_ in sets:
        keep, nc = support_core(x0, s_, motion[s_], max(low, split), h, margin,
                                rest.particle_visible[s_] if shell_hidden_only else None)
        cores.append(keep)
        n_core.append(nc)
    sets = cores
    ev["core_particles"] = n_core   # the rest of each set is the shell around its core (uncertain)
    ev["core_threshold_px"] = max(low, split)
    if not sets and push_dir is not None and np.linalg.norm(push_dir) > 0:
        # pushed and not driven away: held on the far side along the push (a ball pressed onto
        # an unseen stand)
        d = np.asarray(push_dir, float) / np.linalg.norm(push_dir)
        proj = x0 @ d
        tip = x0[np.argmax(proj)]
        lateral = np.linalg.norm((x0 - tip) - np.outer((x0 - tip) @ d, d), axis=1)
        extent = float(np.max(np.ptp(x0, axis=0)))
        sel = (proj >= proj.max() - 1.5 * h) & (lateral <= 0.3 * extent)
        sel[np.asarray(exclude, np.int64)] = False
        if sel.sum() >= 2:
            sets = [np.where(sel)[0]]
            ev["fallback"] = "far side along the push (no still region in view)"
    if not sets:
        # gravity: a still-standing object is held somewhere; take the stillest particles
        order = np.argsort(motion)
        order = order[~np.isin(order, exclude)]
        sets = [order[: max(3, P // 50)]]
        ev["fallback"] = "stillest particles (no still region)"
    ev["sets"] = [int(len(s)) for s in sets]
    return sets, motion, ev


def support_core(x0: np.ndarray, ids: np.ndarray, motion: np.ndarray, limit: float, h: float,
                 margin: float = 1.05, visible: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Of one still region (particle `ids`, their `motion` in px): the core (motion <= `limit`; the
    stillest quarter if fewer than 2 are) and its shell (within `margin` spacings of the core).
    With `visible` ((len(ids),) bool), only the shell particles the camera does not see are kept:
    a seen particle's motion comes from seeds on it, a hidden one's from the nearest seeds, which
    blurs the support's hidden boundary. Returns (kept ids, core size); at least 3 are kept."""
    ids = np.asarray(ids, np.int64)
    core = ids[motion <= limit]
    if len(core) < 2:
        core = ids[motion <= np.percentile(motion, 25)]
    d = np.min(np.linalg.norm(x0[ids][:, None, :] - x0[core][None, :, :], axis=2), axis=1)
    keep_mask = d <= margin * h
    if visible is not None:
        keep_mask &= np.isin(ids, core) | ~np.asarray(visible, bool)
    keep = ids[keep_mask]
    if len(keep) < 3:
        keep = ids[np.argsort(motion)[:3]]
    return keep, int(min(len(core), len(keep)))


def _log_split(motion: np.ndarray, floor_px: float = 0.02) -> float:
    """Otsu's threshold on log(motion + floor_px): the motion (px) that best separates two groups
    of particles by between-group variance of their log motion. floor_px keeps the particles at
    the tracking noise from spreading over decades of log."""
    v = np.sort(np.log(np.asarray(motion, np.float64) + floor_px))
    n = len(v)
    if n < 4:
        return float(np.max(motion)) if n else 0.0
    c = np.cumsum(v)
    i = np.arange(1, n)
    mean_lo = c[:-1] / i
    mean_hi = (c[-1] - c[:-1]) / (n - i)
    between = i * (n - i) * (mean_lo - mean_hi) ** 2
    k = int(np.argmax(between))
    return float(np.exp(0.5 * (v[k] + v[k + 1])) - floor_px)


def particle_motion(x0: np.ndarray, seeds3: np.ndarray, D: np.ndarray, h: float, k_local: int = 6) -> np.ndarray:
    """Largest image displacement over the video per particle (px), from tracked seed points
    (rest positions seeds3 (S, 3), displacements D (T, S, 2), nan once lost).

    A particle with seeds within 1.5 spacings takes their inverse-distance average frame by frame;
    one the camera does not see (the far side, the inside, a part out of view) takes the
    inverse-distance average of its nearest seeds' largest motions (a guess: see the gravity and
    push rules in `find_supports`)."""
    from scipy.spatial import cKDTree

    T, S, _ = D.shape
    valid = np.isfinite(D).all(-1)                # (T, S)
    Dz = np.where(valid[..., None], D, 0.0)
    tree = cKDTree(seeds3)
    k = min(k_local, S)
    dist, nn = tree.query(x0, k=k)
    dist = dist.reshape(len(x0), k)
    nn = nn.reshape(len(x0), k)
    motion = np.zeros(len(x0))
    near = dist[:, 0] <= 1.5 * h
    # visible: inverse-distance weights over the seeds within 1.5 spacings, frame by frame
    w = np.where(dist <= 1.5 * h, 1.0 / (dist + 0.5 * h), 0.0)           # (P, k)
    wv = w[near][:, None, :] * valid[:, nn[near]].transpose(1, 0, 2)      # (Pn, T, k)
    num = np.einsum("ptk,tpkc->ptc", wv, Dz[:, nn[near]])                 # (Pn, T, 2)
    den = wv.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        disp = num / den[..., None]
    motion[near] = np.nanmax(np.where(den[..., None] > 0, np.linalg.norm(disp, axis=-1)[..., None], np.nan)[..., 0], axis=1)
    far = ~near
    if far.any():
        # hidden: the nearest seeds' largest motions, inverse-distance weighted
        with np.errstate(invalid="ignore"):
            smax = np.nan_to_num(np.nanmax(np.where(valid, np.linalg.norm(Dz, axis=-1), np.nan), axis=0))
        w = 1.0 / (dist[far] + 0.5 * h)
        motion[far] = np.sum(w * smax[nn[far]], 1) / np.sum(w, 1)
    return np.nan_to_num(motion, nan=0.0)


def _components(points, radius, ids):
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if not len(points):
        return []
    tree = cKDTree(points)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    from scipy.sparse import coo_matrix

    n = len(points)
    A = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else coo_matrix((n, n))
    nc, lab = connected_components(A, directed=False)
    return [np.sort(ids[lab == i]).astype(np.int64) for i in range(nc)]
