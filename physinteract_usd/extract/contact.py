"""Where the hand touches the object: the contact region's centre per frame (`find_contact`), the
contact at the grasp frame (`contact_at_grasp`), and in 3D the contact point and the particles the
hand holds (`contact_particles`); for colliders the fingertip's radius and the surface's outward
normal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .analysis import Analysis, disk_mask, unit
from .geometry import back_project, particles_near, pixel_centres
from .hints import hint_location
from .segmentation import dilate

RADIUS_SHARE = 0.35  # grasp radius as a share of the contact region's extent
GRASP_RADIUS_M = 0.03   # a hand's grasp (thumb and fingertips, ~6 cm across; the median of the suite's hands): the least it holds
GRASP_MAX_SHARE = 0.3   # ... and at most this share of the object's extent (something stays free)


@dataclass
class ContactSeen:
    """Where the hand touches the object, frame by frame (`find_contact`)."""
    touching: np.ndarray               # (T,) bool: the hand touches the object (at least 3 px)
    centres: list                      # per frame the contact region's centre (u, v), or None
    hint_uv: np.ndarray | None         # the hint's location in the image (None without a hint)
    hint_particles: np.ndarray | None  # the hint's particles (a `--hint-particles` hint)
    hint_frame: int | None             # the frame the hint's pixel is in


@dataclass
class GraspContact:
    """The contact at the grasp frame (`contact_at_grasp`)."""
    uv: np.ndarray       # (2,) its centre in the image
    region: np.ndarray   # (H, W) bool: its pixels (none when the hint gives particles)


@dataclass
class Contact3D:
    """The contact in 3D (`contact_particles`)."""
    point: np.ndarray            # (3,) world metres: the contact's centre
    particles: np.ndarray        # the particles within the grasp radius (or the hint's)
    pixels: np.ndarray | None    # (N, 2) the contact pixels back-projected (None for hinted particles)
    radius: float | None         # the grasp radius [m] (None for hinted particles)
    rest: object                 # the object at rest seen from the grasp frame (`geometry.render_rest`)


# ------------------------------------------------------------------------------ steps
def find_contact(an: Analysis, hint, evidence: dict) -> ContactSeen:
    """Step 3 (where, over time): the hand touching the object per frame and the contact region's
    centre, next to the hint's location when there is one. InputError when no hand touches the
    object and no hint says where."""
    touch = np.array([an.touching(k) for k in range(an.T)])
    evidence["touch_px"] = touch.tolist()
    hint_c2, hint_idx, hint_frame = hint_location(an, hint)
    touching = touch >= 3
    if hint_c2 is None and not touching.any():
        raise InputError(an.scene.path, "no hand touching the object was found in the video; give a hint "
                         "(--hint-pixel K,U,V or --hint-particles) or author a contact set")
    centres = contact_centres(an, touching, hint_c2, hint_frame)
    return ContactSeen(touching, centres, hint_c2, hint_idx, hint_frame)


def contact_at_grasp(an: Analysis, seen: ContactSeen, g: int) -> GraspContact:
    """The contact at the grasp frame g: the hand over the object at rest, next to the first
    location (a hint's pixel of a later frame is carried back to g through the flow)."""
    centres, hint_c2, hint_frame = seen.centres, seen.hint_uv, seen.hint_frame
    c2 = centres[g] if centres[g] is not None else (hint_c2 if hint_c2 is not None else centres[int(np.argmax(seen.touching))])
    if hint_c2 is not None:
        c2 = hint_c2 if hint_frame is None or hint_frame <= g else track_back_to(an, hint_c2, hint_frame, g)
    region = an.contact_region(g, c2) if seen.hint_particles is None else np.zeros((an.H, an.W), bool)
    if hint_c2 is not None and seen.hint_particles is None:
        region = disk_mask((an.H, an.W), c2, max(2.0, 0.75 * an.R)) & (an.rest.alpha > 0.05)
        if not region.any():
            region = disk_mask((an.H, an.W), c2, 1.0)
    return GraspContact(c2, region)


def contact_particles(an: Analysis, hint, itype: str, seen: ContactSeen, grasp: GraspContact, g: int,
                      evidence: dict, notes: list) -> Contact3D:
    """Step 6: the contact pixels at the grasp frame back-projected with the rendered depth, their
    robust centre (a grasp's moved onto the material) and the particles within the grasp radius
    (`contact_radius_m`, or the hint's `grasp_radius`); a hint's particles as they are."""
    rest_g = an.rest_at(g)
    radius = None
    if seen.hint_particles is not None:
        idx = seen.hint_particles
        c3 = an.x0[idx].mean(0)
        pix = None
    else:
        region, c2 = grasp.region, grasp.uv
        pix = pixel_centres(region) if region.any() else c2[None]
        pts3 = back_project(rest_g, pix)
        radius, radius_why = contact_radius_m(an, region, with_reason=True)
        if hint is not None and hint.grasp_radius is not None:
            radius, radius_why = float(hint.grasp_radius), "user"
        if itype == "pointAdherent":
            evidence.update({"grasp_radius_m": radius, "grasp_radius_source": radius_why})
        c3 = robust_centre(pts3)
        if itype == "pointAdherent":
            c3 = onto_particles(c3, an.x0, an.spacing)
        idx = particles_near(c3[None], an.x0, radius, min_count=3)
    if itype == "pointAdherent" and seen.hint_particles is None and evidence.get("grasp_radius_source") == "pinch":
        notes.append(f"grasp: {len(idx)} particles within {100 * radius:.1f} cm of the contact, the least a pinch "
                     "holds (the video shows where the hand grasps, not how much it holds); --grasp-radius "
                     "sets it")
    return Contact3D(c3, idx, pix, radius, rest_g)


# ------------------------------------------------------------------------------ pieces
def contact_centres(an: Analysis, touching, hint_c2, hint_frame):
    """Per frame, the centre of the hand-object contact region (None where the hand does not
    touch). With a hint, the region next to the hint's location."""
    centres = []
    prev = hint_c2
    for k in range(an.T):
        if not touching[k] and hint_c2 is None:
            centres.append(None)
            continue
        if hint_c2 is None:
            # the toucher's leading part: a hand in front of the object overlaps it far from where
            # it touches
            full = leading_part(an, k, an.contact_region(k))
            region = full if prev is None else full & disk_mask((an.H, an.W), prev, 1.5 * an.R)
            if not region.any() and prev is not None:
                region = full & disk_mask((an.H, an.W), prev, 3 * an.R)
        else:
            region = an.contact_region(k, prev)
            if not region.any() and prev is not None:
                region = an.contact_region(k) & disk_mask((an.H, an.W), prev, 3 * an.R)
        if not region.any():
            centres.append(prev if hint_c2 is not None else None)
            continue
        c = pixel_centres(region).mean(0)
        if hint_c2 is not None:
            c = 0.5 * (c + prev)
        centres.append(c)
        prev = c
    return centres


def leading_part(an: Analysis, k: int, region: np.ndarray) -> np.ndarray:
    """Of a contact region wider than 4 R, the toucher's leading part: the pixels within R of
    its farthest reach from the toucher's body (the centroid of the hand component it belongs to)
    toward the region. A fingertip, a stick's end, a sphere's front and a pinch's fingertips touch
    with their leading part; the rest of a hand in front of the object only hides it. Only where
    the region is at most half the hand component (its body seen beside the object)."""
    import cv2

    if not region.any():
        return region
    ys, xs = np.nonzero(region)
    if max(np.ptp(xs), np.ptp(ys)) + 1 <= 4.0 * an.R:
        return region
    n, lab = cv2.connectedComponents(an.hand[k].astype(np.uint8), connectivity=8)
    labs = lab[region]
    labs = labs[labs > 0]
    if not len(labs):
        return region
    comp = lab == np.bincount(labs).argmax()
    if region.sum() > 0.5 * comp.sum():
        return region    # the hand mostly over the object: its body is not seen apart from where it touches
    body = pixel_centres(comp).mean(0)
    pix = pixel_centres(region)
    u = unit(pix.mean(0) - body)
    if not np.any(u):
        return region
    proj = (pix - body) @ u
    keep = proj >= proj.max() - an.R
    out = np.zeros_like(region)
    out[ys[keep], xs[keep]] = True
    return out


def track_back_to(an: Analysis, c, k_from, k_to):
    """A pixel of frame k_from carried back to frame k_to through the flow."""
    tr = an.tracker.track(an.flows, np.asarray(c, np.float64)[None], start=k_from)
    p = tr.uv[k_to, 0]
    return p if np.isfinite(p).all() else np.asarray(c, np.float64)


def onto_particles(c3: np.ndarray, x0: np.ndarray, spacing: float) -> np.ndarray:
    """A hand holds material: a grasp centre more than a particle spacing from every particle (the
    rendered surface it was back-projected from is the splats' edge, which lies well outside the
    particles of a fuzzy or thin object, and at a silhouette's rim the depth is the background's
    fill) moves straight toward its nearest particle until it is one spacing away."""
    d = np.linalg.norm(x0 - c3, axis=1)
    j = int(np.argmin(d))
    if d[j] <= spacing:
        return c3
    return x0[j] + (c3 - x0[j]) * (spacing / d[j])


def robust_centre(pts: np.ndarray) -> np.ndarray:
    """The mean of the 80% of the points nearest their median."""
    med = np.median(pts, 0)
    d = np.linalg.norm(pts - med, axis=1)
    keep = d <= np.percentile(d, 80) + 1e-12
    return pts[keep].mean(0)


def contact_radius_m(an: Analysis, region, with_reason: bool = False):
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


def finger_radius(an: Analysis, g: int, c2) -> float:
    """The fingertip's half-width at the contact (distance transform of the hand mask), in metres."""
    import cv2

    hand = an.hand[g].astype(np.uint8)
    if not hand.any():
        return 1.5 * an.spacing
    dt = cv2.distanceTransform(hand, cv2.DIST_L2, 3)
    disk = disk_mask(hand.shape, c2, 2 * an.R) & (hand > 0)
    r_px = float(np.percentile(dt[disk], 75)) if disk.any() else float(dt.max())
    return float(np.clip(r_px / an.px_per_m, 0.5 * an.spacing, 6 * an.spacing))


def outward_normal(an: Analysis, c3, idx) -> np.ndarray:
    """Outward surface normal at a contact point: away from the particles within a few spacings,
    flipped toward the camera's side if it is ambiguous."""
    d = np.linalg.norm(an.x0 - c3, axis=1)
    near = an.x0[d < max(4 * an.spacing, np.sort(d)[min(len(d) - 1, 20)])]
    n = unit(c3 - near.mean(0))
    if np.linalg.norm(n) == 0:
        n = unit(an.cam0.position - c3)
    return n


def pushing_edge(an: Analysis, grasp: GraspContact, direction, g: int | None = None) -> GraspContact:
    """A collider's contact at the grasp frame cut to its pushing edge: of the contact region, the
    pixels within half a contact radius of its farthest reach along the toucher's push in the
    image (`direction`). A fingertip or a sphere touches the surface with its front; the rest of
    the region is the toucher seen over the object behind that point, whose depth is elsewhere
    (#23: dev_0014, dev_0011, dev_0001 put 6-17 px behind the front, 3-9 cm off along the view)."""
    d = unit(np.asarray(direction, np.float64))
    if not np.any(d):
        return grasp
    region = grasp.region
    if g is not None:
        # the toucher next to the contact (where the frame's contact region is empty, a noisy
        # silhouette covering it: its pixels near the contact's location)
        seed = region if region.any() else an.hand[g] & disk_mask((an.H, an.W), grasp.uv, 1.5 * an.R)
        front = hidden_front(an, g, seed, d) if seed.any() else seed
        region = region | (front if region.any() or not front.any() else front | seed)
    if not region.any():
        return grasp
    ys, xs = np.nonzero(region)
    pix = pixel_centres(region)
    proj = pix @ d
    keep = proj >= proj.max() - 0.5 * an.R
    out = np.zeros_like(region)
    out[ys[keep], xs[keep]] = True
    return GraspContact(pix[keep].mean(0), out)


def hidden_front(an: Analysis, g: int, region: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The toucher's front where the video shows it only as a notch in the object's silhouette:
    with visible silhouettes, the pixels of the object at rest that frame g's silhouette does not
    show, ahead of the contact region along the push `d` (within 2 R), as wide as the region's
    front, with the object seen on both sides of them (a notch cut into the silhouette; a band
    along its edge is the object that moved), joined to the region. A fingertip over a sheet of a
    similar colour (dev_0014) is segmented only down to where it enters the silhouette (the
    background there is estimated from the frames the finger covers it); the notch it cuts into
    the silhouette reaches its tip. Nothing without visible masks."""
    import cv2

    out = np.zeros_like(region)
    if not getattr(an, "visible_masks", False) or not region.any():
        return out
    notch = an.rest.silhouette & ~an.obj[g] & ~region
    if not notch.any():
        return out
    e = np.array([-d[1], d[0]])
    pix_r = pixel_centres(region)
    proj_r = pix_r @ d
    reach = float(proj_r.max())
    front = pix_r[proj_r >= reach - 0.5 * an.R]
    lo, hi = float((front @ e).min()) - 1.0, float((front @ e).max()) + 1.0
    ys, xs = np.nonzero(notch)
    pix = pixel_centres(notch)
    a, lat = pix @ d, pix @ e
    ok = (a > reach) & (a <= reach + 2.0 * an.R) & (lat >= lo) & (lat <= hi)
    obj = an.obj[g]
    H, W = obj.shape
    steps = np.arange(1.0, max(2.0, an.R, hi - lo) + 1.0)     # the object within the front's width either side
    for i in np.nonzero(ok)[0]:
        sides = []
        for sgn in (1.0, -1.0):
            q = pix[i][None] + sgn * steps[:, None] * e[None]
            u, v = np.floor(q[:, 0]).astype(int), np.floor(q[:, 1]).astype(int)
            inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
            sides.append(bool(obj[v[inside], u[inside]].any()))
        ok[i] = sides[0] and sides[1]
    cand = np.zeros_like(region)
    cand[ys[ok], xs[ok]] = True
    # a toucher's front is a solid piece: the silhouette's speckles (a segmenter's ragged masks,
    # dev_0010 at 128 px) are opened away
    cand = cv2.morphologyEx(cand.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)).astype(bool)
    if not cand.any():
        return out
    # joined to the region across a pixel or two (the toucher's anti-aliased rim is in neither)
    near = dilate(region, 2)
    n, lab = cv2.connectedComponents((cand | near).astype(np.uint8), connectivity=8)
    labs = np.unique(lab[region])
    return np.isin(lab, labs[labs > 0]) & cand
