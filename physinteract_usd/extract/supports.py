"""What holds the object still: supports. Per particle its largest image motion over the video
(`particle_motion`, from object pixels tracked from frame 0), the still particles grouped into
connected regions (`components`), each cut to its core and shell (`support_core`, `log_split`)
(`find_supports`); the user's support hints (`hinted_supports`); the fixed contact sets
(`support_contacts`)."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from ..contacts import ContactSet
from ..errors import InputError
from .analysis import Analysis
from .geometry import back_project, particles_near, sample
from .lifting import keep_on_ray_in_box
from .segmentation import dilate

SUPPORT_HINT_RADIUS_M = 0.03  # a support the user points at where none was detected: a clamp's or a hand's size


# ------------------------------------------------------------------------------ step
def support_contacts(an: Analysis, hint, exclude, contact_motion_px: float, push_dir, evidence: dict,
                     notes: list, lowest_contact_y: float | None = None) -> tuple[list, np.ndarray]:
    """Step 8: the supports as `fixed` contact sets (the detected ones, or the user's hint's), none
    taking a particle of `exclude` (the hand's grasp). Returns (contact sets, motion per particle
    in px)."""
    fixed_sets, motion_p, sup_ev = find_supports(an, exclude=exclude, contact_motion_px=contact_motion_px,
                                                 push_dir=push_dir, lowest_contact_y=lowest_contact_y)
    evidence["supports"] = sup_ev
    sup_source = "extracted"
    floor = sup_ev.get("floor")
    if floor is not None and not (hint is not None and hint.has_support):
        evidence["floor"] = floor
        notes.append(f"the object rests on a floor at y = {floor['height']:.3f} m (nothing holds it: its lowest "
                     "part stays down and it stands on it), so no fixed support is set; the floor holds it by "
                     "friction, the `ground` effect: `physinteract-usd effects add STAGE ground` (height "
                     f"{floor['height']:.3f}); if something does hold it there, --support-pixel sets the support")
    cores = sup_ev.get("core_particles", [])
    shell = sum(len(s_) for s_ in fixed_sets) - sum(cores)
    if (fixed_sets and len(cores) == len(fixed_sets) and "fallback" not in sup_ev and shell > 0
            and not (hint is not None and hint.has_support)):
        notes.append(f"supports: {sum(len(s_) for s_ in fixed_sets)} particles held, {shell} of them the shell around "
                     "the stillest core (the video cannot tell whether a support's outer layer moves a little); if "
                     "the preview shows the support wrong, --support-pixel or --support-particles sets it")
    if hint is not None and hint.has_support:
        fixed_sets = hinted_supports(an, hint, fixed_sets, exclude)
        sup_source = "user"
        sup_ev["hint"] = [int(len(s)) for s in fixed_sets]
        if not fixed_sets:
            notes.append("the support hint leaves no particle outside the hand's grasp: no support is set")
    guessed = "fallback" in sup_ev and sup_source == "extracted"
    if guessed:
        notes.append(f"supports: a guess, {sup_ev['fallback']}; the first fit sizes it by what it renders; "
                     "--support-pixel or --support-particles sets it")
    contacts = []
    for i, s in enumerate(fixed_sets):
        contacts.append(ContactSet(f"support{i}" if len(fixed_sets) > 1 else "support", "fixed", s,
                                   contact_point=an.x0[s].mean(0), source=sup_source, guessed=guessed))
    return contacts, motion_p


# ------------------------------------------------------------------------------ detection
def find_supports(an: Analysis, exclude=np.zeros(0, np.int64), contact_motion_px: float = 0.0,
                  push_dir=None, rel_threshold: float = 0.08, abs_threshold: float = 0.6,
                  core_rel: float = 0.0, core_abs: float = 0.0, margin: float = 1.05,
                  shell_hidden_only: bool = True, lowest_contact_y: float | None = None,
                  grow_rel: float = 0.04, grow_noisy_px: float = 0.35):
    """Particles that stay put while the object moves: connected still regions -> fixed sets.

    Still: motion at most max(abs_threshold, rel_threshold x the contact's motion). Near a support
    the motion grows with the distance from it, so of each connected still region only its core
    (motion at most the split between the held particles' noise and their neighbours' small motion,
    `log_split`, or at most max(core_abs, core_rel x the contact's motion)) and `margin` spacings
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

    Each core is then grown (`grow_supports`) through its connected neighbours the camera does not
    see (with `shell_hidden_only`, as the shell) whose displacement stays at most `grow_rel` of the
    object's own (`relative_motion`: frame by frame against the 95th percentile of the particles',
    the median over the frames of large motion) and whose largest motion is within twice the
    stillness threshold: a held region's largest motion reads 1.5-20 px on the world suite's noisy,
    compressed videos, where a spike in one frame decides a maximum but not a median (#23, the 17
    dev captures: support recall 0.43 -> 0.49, precision 0.52 -> 0.51, none invented on the 7 free
    objects; growing through seen particles too gave 0.54 / 0.50 there but cost the named suite's
    precision 0.79 -> 0.70, hidden only 0.73). Only where the tracking is noisy: the core's split
    (`log_split`) at `grow_noisy_px` or more (the world suite's dev captures 0.25-3.1 px; the named
    synthetic suite's and the bundled sample's 0.04-0.33 px, where growing held 27 particles more of
    the sample, none of them truly held: precision 0.81 -> 0.71). 0 switches the growth off.

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
        floor = resting_base(x0, h, [], lowest_contact_y)
        if floor is not None:
            ev["floor"] = floor
        return [], motion, ev
    sets = components(x0[still], 1.8 * h, np.where(still)[0])
    sets = [s for s in sets if len(s) >= 2]
    # near a support the motion grows with the distance from it: keep each still region's core and
    # a margin around it. The core: the still particles' motions fall in two groups, the held ones
    # at the tracking noise (~0.01-0.1 px) and their neighbours that move a little (0.2-1 px); the
    # split is where the two groups of log motion are best separated (Otsu). Measured against
    # the synthetic suite's true supports (docs/benchmarks/extract.md) it beats a fixed share of each
    # region's motion (F1 0.72 vs 0.57 mean).
    low = max(core_abs, core_rel * moving)
    split = log_split(motion[np.concatenate(sets)]) if sets else 0.0
    cores, n_core = [], []
    for s_ in sets:
        keep, nc = support_core(x0, s_, motion[s_], max(low, split), h, margin,
                                rest.particle_visible[s_] if shell_hidden_only else None)
        cores.append(keep)
        n_core.append(nc)
    sets = cores
    ev["core_particles"] = n_core   # the rest of each set is the shell around its core (uncertain)
    ev["core_threshold_px"] = max(low, split)
    if grow_rel > 0 and sets and ev["core_threshold_px"] >= grow_noisy_px:
        # a held region's largest motion reads 1.5-20 px on noisy, compressed videos (a spike in a
        # frame or two, the toucher passing by): grown from each core through the neighbours that
        # stay still against the object's own motion frame by frame (`relative_motion`)
        rel = relative_motion(x0, S3, D, h)
        rel[motion > 2.0 * thr] = np.inf      # and never a particle whose largest motion is far from still
        n_before = sum(len(s_) for s_ in sets)
        sets = grow_supports(x0, sets, rel, h, grow_rel, exclude,
                             visible=rest.particle_visible if shell_hidden_only else None)
        ev["grown_particles"] = int(sum(len(s_) for s_ in sets) - n_before)
        ev["grow_rel"] = grow_rel
    # a floor is not a support: still regions at the object's bottom, on which it can stand, are
    # where it rests (held by friction, not pinned)
    floor = resting_base(x0, h, sets, lowest_contact_y)
    if floor is not None:
        ev["floor"] = floor
        ev["sets_on_floor"] = [int(len(s_)) for s_ in sets]
        ev["sets"] = []
        return [], motion, ev
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


def lowest_toucher_y(trajectory, radius: float, itype: str, base_y: float, acting=None) -> float | None:
    """The lowest height at which the toucher acts on the object (resting_base's (c)): its
    trajectory's lowest point, less a pusher's radius only when its centre goes below the object's
    base `base_y` (it acts on the underside, holding the object up). A round collider pushing a thin
    object sideways reaches below its base with its radius (a radius more than half the object's
    height) while it pushes along the floor, not up (#23: dev_0184, a bar 2.8 cm tall on a floor
    pushed sideways by a 2.1 cm fingertip whose centre stayed 0.6 cm above the base, was given a
    support). `acting` ((T,) bool, `toucher_acting`): only those frames count; None when none
    does (a toucher that never reaches the object holds nothing up)."""
    tr = np.asarray(trajectory, np.float64)
    if acting is not None:
        tr = tr[np.asarray(acting, bool)]
        if not len(tr):
            return None
    low = float(tr[:, 1].min())
    if itype == "pointNonAdherent" and low < base_y:
        low -= float(radius)
    return low


def toucher_low(trajectory, flat, radius: float, itype: str, base_y: float, acting, evidence=None) -> float | None:
    """`lowest_toucher_y` of a grasp's path read both ways, the higher of the two: its depth follows
    the hand's apparent scale, which a tool leaving the frame or turning misreads (#23: dev_0510's
    tongs lifting a rope off its floor read 13% smaller, the path put 9 cm away and 4 mm under the
    rope's base, the true lift 5 cm up), so it is below the base only where its path at the grasp
    depth (`flat`, the image alone; None for a collider) says so too. `evidence` gets both."""
    low = lowest_toucher_y(trajectory, radius, itype, base_y, acting)
    if flat is None or low is None:
        return low
    low_flat = lowest_toucher_y(flat, radius, itype, base_y, acting)
    if evidence is not None:
        evidence["toucher_low_m"] = {"scaled": round(low, 4), "at_grasp_depth": round(low_flat, 4)}
    return max(low, low_flat)


def toucher_acting(trajectory, itype: str, radius: float, x0: np.ndarray, h: float, grasp: int,
                   release: int | None) -> np.ndarray:
    """(T,) bool: the frames in which the toucher acts on the object, the only ones whose T0 says
    anything about what holds the object up (resting_base's (c), `lowest_toucher_y`). A grasp acts
    from its grasp frame to its release (the held particles follow it then, not before or after);
    a fingertip's sphere while its surface is within a spacing of the object at rest (before it
    arrives and after it leaves it is elsewhere, and may pass under the object's base level beside
    it: #23, dev_0390's glove finger going down and away after its release, its T0 2.3 cm under a
    plush's base, the truth's too; dev_0402's sphere put 1.5 cm clear under a ring on its floor,
    which it never reached); a palm's plane every frame, as before (it is not a point)."""
    tr = np.asarray(trajectory, np.float64)
    T = len(tr)
    if itype == "pointAdherent":
        act = np.zeros(T, bool)
        act[max(int(grasp), 0): T if release is None else min(int(release) + 1, T)] = True
        return act
    if itype == "pointNonAdherent" and radius > 0:
        from scipy.spatial import cKDTree

        return cKDTree(np.asarray(x0, np.float64)).query(tr)[0] <= float(radius) + h
    return np.ones(T, bool)


def resting_base(x0: np.ndarray, h: float, sets: list, lowest_contact_y: float | None = None,
                 tip_margin: float = 0.15, flat: float = 0.6, hold_share: float = 0.06):
    """Whether the object rests on a floor (a dict: the floor's height, the base's particles) or
    not (None). A floor holds an object from below, by friction: it rests there when
    (a) it can stand on its base (the particles within 1.5 spacings of its lowest point, the 1st
    percentile of the heights: a few deep troughs of a wavy sheet are not what it lies on): the
    centre of mass lies over the base's footprint with a margin of at least `tip_margin` x its
    height above it (a thin stem or a hanging end cannot stand on its tip);
    (b) every still region found (`sets`, specks aside) touches the floor (holds 3 base particles
    or more) and is flat, as a contact patch is (its height at most max(1.5 spacings, `flat` x its
    width): the still foot of a leg or a stem, or a clamped end as thick as it is wide, is held);
    still regions at two places or more are held there unless the object's underside joins them
    on the floor's plane (`one_underside`: a block pressed on a floor is still at two corners of its
    bottom); a strap on its anchors or a toy on its feet, off the plane between them, stays held;
    (c) the contact is not pushed below it (`lowest_contact_y`, the lowest point of the toucher's
    T0 while it acts on the object, `toucher_acting`, more than a spacing under the base:
    something holds the object above the ground).
    With no still region at all, (a) and (c) decide (the whole object moved: it slid or tipped on
    something that does not hold it).
    A still region smaller than `hold_share` of the object's size (its area n h^2 under
    hold_share x V^(2/3), V = P h^3) holds nothing up, wherever it is: a hold
    carries the object's weight through the material at it, at a stress of the weight over its
    area, V^(1/3) / (hold_share x L) times the stress the weight puts on the object's own
    cross-sections (L: its length); an object that keeps its shape under its own weight (strain
    rho g L / E up to ~0.15, the suite's softest) would stretch off a hold of a few particles by
    more than its own size (~2.5x at 0.06) rather than hang still from it. Such a speck reads
    still for other reasons (tracking noise, a hand passing next to it: dev_0204, 0206, 0218, a
    4-8 particle speck of 1500-5500 at 0.018-0.045 of V^(2/3)), or, on the base, is a small patch
    of where it touches the floor (dev_0206: 14 particles, 0.045, 2 spacings tall); the holds of
    held objects on the world suite read 0.11-0.8 (seeds 140-164). It is left out of the floor's
    test (b), not of the supports when the object is held."""
    from scipy.spatial import ConvexHull, QhullError

    y = x0[:, 1]
    ymin = float(y.min())
    if lowest_contact_y is not None and lowest_contact_y < ymin - h:
        return None
    # the base from the underside's 1st percentile, not its single lowest particle: a wavy sheet's
    # few deepest troughs (or particles the fill put under the surface) are not what it lies on
    ylow = max(ymin, float(np.percentile(y, 1)))
    base = y <= ylow + 1.5 * h
    big = max((len(s_) for s_ in sets), default=0)
    real = [np.asarray(s_, np.int64) for s_ in sets if len(s_) >= max(4, 0.05 * big)]   # specks aside
    size = hold_share * len(x0) ** (2.0 / 3.0)         # in particles: hold_share x V^(2/3) / h^2
    real = [s_ for s_ in real if len(s_) >= size]      # too small to hold it up
    if len(real) > 1 and not one_underside(x0, h, base, real):
        return None         # still at two places with the object off the floor between: held there (anchors)
    for s_ in real:
        if base[s_].sum() < 3:
            return None
        # in whole spacings: the particles sit on a lattice, so a patch 3 spacings tall and 5 wide
        # is flat at 0.6 exactly (rounding decided dev_0144's corner either way)
        height = round(float(np.ptp(y[s_])) / h)
        width = round(float(max(np.ptp(x0[s_, 0]), np.ptp(x0[s_, 2]))) / h)
        if height > max(1.5, flat * width):
            return None
    com = x0.mean(0)
    pts = x0[base][:, [0, 2]]
    c = com[[0, 2]]
    try:
        hull = ConvexHull(pts)
        # signed distance of the centre of mass's projection to the footprint's edges (> 0 inside)
        eq = hull.equations                               # n . p + d <= 0 inside
        inside = float(np.min(-(eq[:, :2] @ c + eq[:, 2])))
    except (QhullError, ValueError):
        inside = -float(np.min(np.linalg.norm(pts - c, axis=1))) if len(pts) else -np.inf
    inside += 0.5 * h                                     # the particles sit half a spacing in from the edge
    lift = float(com[1] - ylow)
    if inside < tip_margin * max(lift, h):
        return None
    return {"height": float(ymin - 0.5 * h), "friction": 0.5, "base_particles": int(base.sum()),
            "stance_margin_m": inside, "com_height_m": lift}


def one_underside(x0: np.ndarray, h: float, base: np.ndarray, regions: list) -> bool:
    """Whether still `regions` at two places or more are contacts of one floor: each holds base
    particles (the lowest plane, `base`) and the object's underside joins them along that plane
    (the base particles, linked within 1.8 spacings, form one piece through every region). An
    object on a floor lies on it between its contacts; one held at two places (a strap on its
    anchors, a bridge on its piers) hangs off the plane between them, or sags below its anchors, so
    its lowest points are not at the anchors at all (#23: dev_0144, a block pressed on a floor,
    still at two corners of its bottom, was given two supports)."""
    ids = np.flatnonzero(base)
    if len(ids) < 3:
        return False
    lab = np.full(len(x0), -1)
    for k, comp in enumerate(components(x0[ids], 1.8 * h, ids)):
        lab[comp] = k
    pieces = set()
    for s_ in regions:
        on = lab[np.asarray(s_, np.int64)]
        on = on[on >= 0]
        if len(on) < 3:
            return False
        pieces.add(int(np.bincount(on).argmax()))
    return len(pieces) == 1


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


def log_split(motion: np.ndarray, floor_px: float = 0.02) -> float:
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

    valid = np.isfinite(D).all(-1)                # (T, S)
    dist, nn = cKDTree(seeds3).query(x0, k=min(k_local, D.shape[1]))
    dist, nn = dist.reshape(len(x0), -1), nn.reshape(len(x0), -1)
    motion = np.zeros(len(x0))
    near = dist[:, 0] <= 1.5 * h
    # visible: the seeds within 1.5 spacings, frame by frame (`frame_displacements`), their largest
    if near.any():
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # a particle whose seeds are all lost: nan
            motion[near] = np.nanmax(frame_displacements(x0[near], seeds3, D, h, k_local), axis=1)
    far = ~near
    if far.any():
        # hidden: the nearest seeds' largest motions, inverse-distance weighted
        with np.errstate(invalid="ignore"):
            smax = np.nan_to_num(np.nanmax(np.where(valid, np.linalg.norm(np.where(valid[..., None], D, 0.0), axis=-1),
                                                    np.nan), axis=0))
        w = 1.0 / (dist[far] + 0.5 * h)
        motion[far] = np.sum(w * smax[nn[far]], 1) / np.sum(w, 1)
    return np.nan_to_num(motion, nan=0.0)


def frame_displacements(x0: np.ndarray, seeds3: np.ndarray, D: np.ndarray, h: float, k_local: int = 6) -> np.ndarray:
    """(P, T) image displacement (px) per particle and frame from tracked seeds (as
    `particle_motion`): the inverse-distance average of the seeds within 1.5 spacings, or, for a
    particle the camera does not see, of its `k_local` nearest seeds; nan where none is tracked."""
    from scipy.spatial import cKDTree

    T, S, _ = D.shape
    valid = np.isfinite(D).all(-1)
    Dz = np.where(valid[..., None], D, 0.0)
    k = min(k_local, S)
    dist, nn = cKDTree(seeds3).query(x0, k=k)
    dist, nn = dist.reshape(len(x0), k), nn.reshape(len(x0), k)
    far = dist[:, :1] > 1.5 * h
    w = np.where((dist <= 1.5 * h) | far, 1.0 / (dist + 0.5 * h), 0.0)            # (P, k)
    wv = w[:, None, :] * valid[:, nn].transpose(1, 0, 2)                          # (P, T, k)
    num = np.einsum("ptk,tpkc->ptc", wv, Dz[:, nn])
    den = wv.sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.linalg.norm(num / den[..., None], axis=-1)


def relative_motion(x0: np.ndarray, seeds3: np.ndarray, D: np.ndarray, h: float, big: float = 0.5) -> np.ndarray:
    """Per particle, its image displacement against the object's own, frame by frame (the 95th
    percentile of the particles' displacements), the median over the frames where the object's
    reaches `big` of its largest: ~0 for a held particle, whatever its few noisy frames read;
    1 where nothing is known."""
    disp = frame_displacements(x0, seeds3, D, h)
    with np.errstate(invalid="ignore"):
        ref = np.nanpercentile(disp, 95, axis=0) if np.isfinite(disp).any() else np.zeros(disp.shape[1])
    ref = np.nan_to_num(ref)
    frames = ref >= big * max(float(ref.max()), 1e-9)
    if not frames.any() or ref.max() <= 0:
        return np.ones(len(x0))
    with np.errstate(invalid="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            rel = np.nanmedian(disp[:, frames] / ref[frames], axis=1)
    return np.nan_to_num(rel, nan=1.0)


def grow_supports(x0: np.ndarray, sets: list, rel: np.ndarray, h: float, limit: float,
                  exclude=np.zeros(0, np.int64), radius: float = 1.05, visible: np.ndarray | None = None) -> list:
    """Each support set grown through the particles within `radius` spacings, step by step, whose
    `rel` (`relative_motion`) is at most `limit`, never into `exclude` (the grasp) or another set;
    with `visible` ((P,) bool), only through the particles the camera does not see (as the shell
    in `support_core`: a seen particle is measured where it is, a hidden one takes its nearest
    seeds' motion)."""
    from scipy.spatial import cKDTree

    P = len(x0)
    ok = np.asarray(rel) <= limit
    if visible is not None:
        ok &= ~np.asarray(visible, bool)
    ok[np.asarray(exclude, np.int64)] = False
    taken = np.zeros(P, bool)
    for s_ in sets:
        taken[np.asarray(s_, np.int64)] = True
    tree = cKDTree(x0)
    out = []
    for s_ in sets:
        cur = np.zeros(P, bool)
        cur[np.asarray(s_, np.int64)] = True
        front = cur.copy()
        while front.any():
            nb = np.zeros(P, bool)
            for lst in tree.query_ball_point(x0[front], radius * h):
                nb[lst] = True
            front = nb & ok & ~cur & ~taken
            cur |= front
            taken |= front
        out.append(np.where(cur)[0].astype(np.int64))
    return out


def components(points, radius, ids):
    """Connected groups of `points` (pairs within `radius`), as sorted `ids`."""
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


# ------------------------------------------------------------------------------ the user's word
def hinted_supports(an: Analysis, hint, detected: list, exclude) -> list:
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
        rest_k = an.rest_at(k)
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


# ------------------------------------------------------------------------------ sanity
def unpin(x0: np.ndarray, h: float, contact: ContactSet, supports: list, notes: list, evidence: dict,
          max_stretch: float = 1.0) -> list:
    """Supports that would pin the object against the interaction itself, shrunk or dropped, and
    said so (a fit on them goes unstable or leaves its grid at every E, #23): of each support,
    the particles (a) the grasp holds too or that lie within two spacings of them (held by two
    hands at once), (b) a collider's sphere sweeps through along its T0 (a fixed particle inside a
    moving sphere), and (c) for a grasp, a whole support that its T0 would stretch the object
    away from by more than `max_stretch` x the rest distance between them (the video shows no
    such stretch: the hand would tear the object off it). Returns the supports left."""
    if not supports:
        return supports
    tr = None if contact.trajectory is None else np.asarray(contact.trajectory, np.float64)
    out, said = [], []
    for s in supports:
        idx = np.asarray(s.indices, np.int64)
        keep = np.ones(len(idx), bool)
        why = []
        if contact.type == "pointAdherent" and len(contact.indices):
            held = x0[np.asarray(contact.indices, np.int64)]
            d = np.min(np.linalg.norm(x0[idx][:, None, :] - held[None], axis=2), axis=1)
            near = d <= 2.0 * h
            if near.any():
                keep &= ~near
                why.append(f"{int(near.sum())} next to the grasp")
            if keep.any() and tr is not None:
                c = held.mean(0)
                pts = x0[idx[keep]]
                d0 = float(np.min(np.linalg.norm(pts - c, axis=1)))
                moved = tr - tr[0] + c
                dt = np.min(np.linalg.norm(moved[:, None, :] - pts[None], axis=2), axis=1)
                stretch = float((dt.max() - d0) / max(d0, h))
                if stretch > max_stretch:
                    keep[:] = False
                    why.append(f"the grasp's path would stretch the object {stretch:.1f}x the "
                               f"{100 * d0:.1f} cm between them")
        elif contact.type == "pointNonAdherent" and tr is not None and contact.radius > 0:
            d = np.min(np.linalg.norm(x0[idx][:, None, :] - tr[None], axis=2), axis=1)
            inside = d < contact.radius - 0.5 * h
            if inside.any():
                keep &= ~inside
                why.append(f"{int(inside.sum())} inside the fingertip's path")
        if why:
            left = int(keep.sum())
            said.append(f"{s.name}: {len(idx)} -> {left if left >= 3 else 0} particles ({'; '.join(why)})")
        if keep.sum() >= 3:
            s.indices = idx[keep]
            out.append(s)
    if said:
        evidence["supports_unpinned"] = said
        notes.append("supports that would pin the object against the interaction were shrunk or dropped ("
                     + "; ".join(said) + "): a fit on them goes unstable; if the object is held there, "
                     "--support-pixel or --support-particles sets it")
    return out


def above_floor(x0: np.ndarray, contact: ContactSet, floor: dict | None, notes: list, evidence: dict,
                camera=None) -> ContactSet:
    """The toucher's T0 kept from going through the floor the object rests on, and said so. Its depth is read from
    the hand's apparent scale, which a fingertip pressing down and toward the camera misreads as a dive (#23:
    dev_0568, a poke on a sheet on its floor read as a grasp whose path went 5.5 cm down: the held particles were
    dragged 3.7 cm under the floor and the fit went unstable at every uniform E). A grasp's held particles stay on or
    above the object's base (they follow T0's displacement from the grasp frame); a collider's sphere, or a plane
    pressing from above, stays on or above the floor (`floor["height"]`; how far a press may squeeze the object
    against it is not bounded here: a sphere beside the object may go as low as the floor). What the image says is
    kept: a point too low is moved along its camera ray (`camera`, a `Camera`: its depth alone was wrong) up to that
    level; straight up where the ray does not reach it (or no camera is given). The frames before a grasp, and a
    collider's frames above that level, are left as read. No floor: unchanged."""
    if floor is None or contact.trajectory is None:
        return contact
    tr = np.asarray(contact.trajectory, np.float64).copy()
    x0 = np.asarray(x0, np.float64)
    base = float(x0[:, 1].min())
    if contact.type == "pointAdherent":
        if not len(contact.indices):
            return contact
        g = min(max(int(contact.grasp_frame), 0), len(tr) - 1)
        lowest = tr[g, 1] + base - float(x0[contact.indices, 1].min())   # T0's height that puts them on the base
        sl = slice(g, len(tr))
    else:
        if contact.type == "pointNonAdherent":
            lowest = float(floor["height"]) + float(contact.radius)
        elif float(np.asarray(contact.normal, float)[1]) < -0.7:   # a plane whose object side is below it: a press
            lowest = float(floor["height"])
        else:
            return contact
        sl = slice(0, len(tr))
    under = tr[sl, 1] < lowest
    if not under.any():
        return contact
    depth = float(lowest - tr[sl, 1].min())
    above = (np.array([-np.inf, lowest, -np.inf]), np.full(3, np.inf))    # the half-space the path is kept in
    if camera is not None:
        kept = keep_on_ray_in_box(camera, tr, above)                          # along each frame's ray
    else:
        kept = np.clip(tr, *above)                                            # straight up
    tr[sl] = kept[sl]
    evidence["path_above_floor"] = {"frames": int(under.sum()), "raised_m": round(depth, 4)}
    notes.append(f"the {contact.name}'s path went {100 * depth:.1f} cm under what the floor allows on "
                 f"{int(under.sum())} frames (its depth is read from the hand's apparent size): kept on the floor "
                 "there; if the hand really goes that low, the object is not resting on a floor (--support-pixel)")
    return replace(contact, trajectory=tr)
