"""When: the contact period, the grasp (the contact's start, past the approach) and the release,
from the hand's and the object's velocities next to the contact and whether the object follows
the hand (coupling)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .analysis import Analysis, disk_mask, median_flow
from .contact import ContactSeen
from .segmentation import dilate, erode


@dataclass
class Timing:
    """What `find_timing` measured (frame pairs k -> k+1 index the velocities)."""
    hand_velocity: np.ndarray      # (T-1, 2) px / frame, nan where unseen
    object_velocity: np.ndarray    # (T-1, 2) px / frame, nan where unseen
    coupled: np.ndarray            # (T-1,) +1 follows, 0 still, -1 not (`coupling`)
    near: np.ndarray               # (T,) bool: the hand at the contact
    period: tuple[int, int]        # the contact period (first, last frame)
    speed: np.ndarray              # (T-1,) the hand's speed, px / frame
    grasp: int                     # the frame the contact starts
    release: int | None            # None: held to the end
    share: float = 0.0             # the share of the toucher's speed the object kept in contact (`contact_share`)


def find_timing(an: Analysis, seen: ContactSeen, evidence: dict) -> Timing:
    """Step 4: velocities and coupling next to the contact, the contact period, the grasp and the
    release (recorded in `evidence`).

    The grasp: the toucher comes to (near) rest on the object before it moves it (`contact_start`,
    the last of its stillest frames before the motion). The release: the end of the contact from
    there on (`release`): the toucher moves apart from the object (it moves and the object next to
    it does not follow, or follows at less than half the share of its speed it kept while they
    touched: `part_by_ratio`), or stops touching it. Both read the object's own motion and the
    toucher's, whatever the toucher looks like."""
    vh, vo = velocities(an, seen.centres)
    coupled = coupling(vh, vo, an.eps)
    near = seen.touching | (np.array([c is not None for c in seen.centres]) & (seen.hint_uv is not None))
    near = bridge_faint(near, evidence.get("touch_px"))
    p0, p1 = contact_period(near)
    if METHOD == "model":
        return model_timing(vh, vo, coupled, near, (p0, p1), an.eps, evidence)
    before = motion_before(an, seen.centres, p0)
    own = carried_on(coupled, vo, p0, before, an.eps)
    if own:
        coupled[own] = 0
        evidence["moving_before_contact_px"] = np.round(before, 3).tolist()
    speed = np.linalg.norm(vh, axis=1)
    g = contact_start(speed, near, p0, p1, coupled, vh)
    run = contact_run(coupled, near, vh, vo, an.eps)
    g = not_after_the_motion(g, coupled, vo, run)
    g = past_the_approach(g, coupled, speed, run, an.eps)
    g_hand = g
    g = following_onset(g, coupled, vo, an.eps)
    if METHOD == "hybrid":
        # the model's grasp (better on both halves of the ninth pass's dev captures), the rules'
        # release from it (the model's was worse on the held-out half): untried, for a GPU A/B
        hw = held_window(vh, vo, near, an.eps)
        if hw is not None:
            g = g_hand = hw[0]
    share = 0.0
    if run is not None:
        coupled = part_by_ratio(coupled, vh, vo, run, an.eps)
        share = contact_share(coupled, vh, vo, run, an.eps)
    r = release(coupled, near, g, speed, vh=vh, vo=vo, share=share, eps=an.eps)
    evidence["timing_cues"] = {
        "grasp": "the object starts to follow the toucher" if g != g_hand or (g < len(coupled) and coupled[g] > 0)
                 else "the toucher's onset from rest (the object's motion does not show it)",
        "release": "held to the end" if r is None else ("the toucher leaves the object" if r < len(near) and not near[r]
                                                        else "the toucher moves off and the object does not follow")}
    evidence.update({"contact_period": [p0, p1], "coupling": coupled.tolist(),
                     "hand_velocity_px": np.round(vh, 3).tolist(),
                     "object_velocity_px": np.round(vo, 3).tolist(), "grasp_frame": g, "release_frame": r})
    return Timing(vh, vo, coupled, near, (p0, p1), speed, g, r, share)


def contact_run(coupled: np.ndarray, near: np.ndarray, vh: np.ndarray, vo: np.ndarray, eps: float):
    """The contact as frame pairs (first, last): of the runs of pairs in which the toucher touches
    the object (`near` at the pair's first frame) and is not seen moving apart from it (coupling
    >= 0; a single pair apart between two in contact is noise), the one with the most evidence of
    contact: the object's motion that follows the toucher, plus a little for each pair in which both
    are seen still. Pairs where the object next to the contact is unseen are trimmed from the ends.
    None when no run holds a pair of evidence."""
    T1 = len(coupled)
    seen_o = np.isfinite(vo).all(1)
    so = np.nan_to_num(np.linalg.norm(vo, axis=1))
    sh = np.nan_to_num(np.linalg.norm(vh, axis=1))
    ok = np.array([bool(near[k]) and coupled[k] >= 0 for k in range(T1)])
    for k in range(1, T1 - 1):
        # one pair apart between two in contact is noise, unless the toucher moved fast in it
        if not ok[k] and near[k] and ok[k - 1] and ok[k + 1] and not sh[k] >= 3 * eps:
            ok[k] = True
    # evidence per pair: a pair in which the object follows counts 1 (more when the motion is well
    # above the noise, at most 2: one fast pair, e.g. a mis-segmented hand, must not outweigh a
    # whole pull), a seen still pair 1/4
    ev = np.where(coupled > 0, 1.0 + np.clip(np.minimum(np.where(np.isfinite(vh).all(1), sh, so), so) / eps - 1, 0, 1), 0.0)
    ev = np.where((coupled == 0) & seen_o & ok, 0.25, ev)
    ev = np.where(seen_o, ev, 0.0)
    best = None
    k = 0
    while k < T1:
        if not ok[k]:
            k += 1
            continue
        j = k
        while j + 1 < T1 and ok[j + 1]:
            j += 1
        a, b = k, j
        while a <= b and not seen_o[a]:
            a += 1
        while b >= a and not seen_o[b]:
            b -= 1
        if a <= b:
            score = float(ev[a:b + 1].sum())
            if score > 0 and (best is None or score > best[2] + 1e-9):
                best = (a, b if j < T1 - 1 else j, score)
        k = j + 1
    if best is None:
        return None
    return best[0], best[1]


def apply_overrides(timing: Timing, hint, evidence: dict, notes: list) -> Timing:
    """The user's grasp and release frames (`--grasp-frame`, `--release-frame`) win over the
    detected ones; a grasp given alone re-measures the release from it (the detected release is
    kept when it still comes after the grasp). Recorded in `evidence["timing_source"]` and the
    notes."""
    src = {"grasp": "extracted", "release": "extracted"}
    if hint is None or not hint.has_timing:
        evidence["timing_source"] = src
        return timing
    g, r = timing.grasp, timing.release
    if hint.grasp_frame is not None:
        g_user = int(hint.grasp_frame)
        if g_user != g:
            notes.append(f"grasp at frame {g_user} as given (--grasp-frame; the video suggested {g})")
        g = g_user
        src["grasp"] = "user"
        if hint.release_frame is None and (r is None or r <= g or g < timing.grasp):
            r = release_after(timing, g)
    if hint.release_frame is not None:
        r_user = None if hint.release_frame == hint.NEVER else int(hint.release_frame)
        if r_user != r:
            said = "never" if r is None else str(r)
            notes.append(f"release {'never' if r_user is None else 'at frame %d' % r_user} as given "
                         f"(--release-frame; the video suggested {said})")
        if r_user is not None and r_user <= g:
            from ..errors import InputError

            raise InputError("--release-frame", f"frame {r_user} is not after the grasp frame {g}"
                             f"{' (detected: give --grasp-frame too)' if src['grasp'] != 'user' else ''}")
        r = r_user
        src["release"] = "user"
    evidence.update({"timing_source": src, "grasp_frame": g, "release_frame": r})
    return Timing(timing.hand_velocity, timing.object_velocity, timing.coupled, timing.near, timing.period,
                  timing.speed, g, r, timing.share)


def timing_confidence(timing: Timing, eps: float, evidence: dict, notes: list) -> str:
    """A plain statement of how sure the timing is: "high", "medium" or "low" into
    `evidence["timing_confidence"]`, with the reasons as notes (each naming the flag that fixes it).
    User-given frames are not judged."""
    src = evidence.get("timing_source", {})
    g, r = timing.grasp, timing.release
    T1 = len(timing.coupled)
    end = T1 if r is None else min(T1, r)
    so = np.linalg.norm(timing.object_velocity, axis=1)
    sh = timing.speed
    reasons = []
    if src.get("grasp") != "user":
        # how far back the toucher rests on the object before the motion (a grasp may be anywhere in it)
        a = g
        while a - 1 >= timing.period[0] and np.isfinite(sh[a - 1]) and sh[a - 1] < eps and timing.near[a - 1]:
            a -= 1
        moved = [k for k in range(g, end) if np.isfinite(so[k]) and so[k] >= eps]
        if not moved:
            peak = float(np.nanmax(so[g:end])) if end > g and np.isfinite(so[g:end]).any() else 0.0
            reasons.append(f"timing uncertain: the object next to the contact moves little (at most {peak:.2f} px a "
                           f"frame) while the hand touches it, frames {g}..{'end' if r is None else r}; "
                           "--grasp-frame / --release-frame set them")
        elif moved[0] - g >= 3:
            reasons.append(f"grasp uncertain: the hand is on the object from frame {g}, the object moves little "
                           f"before frame {moved[0]}; --grasp-frame sets it")
        if g - a >= 2:
            reasons.append(f"grasp uncertain: the hand rests on the object from frame {a} and starts to move it "
                           f"after frame {g} (the grasp is put there); --grasp-frame sets it")
        if g <= timing.period[0] and timing.near[0]:
            reasons.append("grasp uncertain: the hand already touches the object in the first frame (the grasp may "
                           "come before the video); --grasp-frame sets it")
    if src.get("release") != "user":
        if r is None and T1 > 0 and timing.near[-1]:
            reasons.append("no release seen: the hand holds on to the end of the video; --release-frame sets it")
        elif r is not None and contact_seen(timing.coupled, timing.hand_velocity, timing.object_velocity, g) is None:
            reasons.append(f"release uncertain: the video never shows the object moving with the hand or resting "
                           f"under it (frames {g}..{r}); the release is where the hand leaves it, frame {r}; "
                           "--release-frame sets it")
        elif r is not None and r < len(timing.near) and not timing.near[r] and (r == 0 or timing.coupled[r - 1] >= 0):
            reasons.append(f"release from the hand leaving the object at frame {r}, not from the object's motion; "
                           "--release-frame sets it")
        if r is not None and 0 < r < T1:
            # what the object next to the contact shows around the release
            before = [k for k in range(max(g, r - 3), r) if timing.near[k]]
            hidden = [k for k in before if not np.isfinite(so[k])]
            around = [k for k in range(max(g, r - 2), min(T1, r + 2)) if timing.near[k] and np.isfinite(so[k])]
            if before and len(hidden) >= max(2, len(before) - 1):
                reasons.append(f"release uncertain: the object next to the contact is hidden in frames "
                               f"{hidden[0]}..{hidden[-1] + 1} before the release at frame {r}; --release-frame sets it")
            elif around and float(np.max(so[around])) < eps and not any("moves little (at most" in x for x in reasons):
                reasons.append(f"release uncertain: the object next to the contact barely moves around frame {r} (at "
                               f"most {float(np.max(so[around])):.2f} px a frame): the release is read from the hand "
                               "moving away alone; --release-frame sets it")
        own = moved_alone(timing, eps)
        if own is not None:
            a, b, peak = own
            reasons.append(f"release uncertain: the object next to the contact moves on its own (up to {peak:.1f} px "
                           f"a frame) while the hand rests on it in frames {a}..{b + 1}, before the hand moves off "
                           f"at frame {r}: it may have let go at frame {a}; --release-frame sets it")
    hidden = [k for k in range(g, end) if not np.isfinite(sh[k])]
    if len(hidden) >= max(2, 0.3 * max(end - g, 1)):
        reasons.append(f"the hand is hidden near the contact in {len(hidden)} of frames {g}..{end}: its motion "
                       "there is the object's")
    level = "high" if not reasons else ("low" if len(reasons) >= 2 or "moves little (at most" in reasons[0]
                                        else "medium")
    evidence["timing_confidence"] = level
    evidence["timing_uncertain"] = reasons
    notes.extend(reasons)
    return level


def moved_alone(timing: Timing, eps: float):
    """Where the two cues of the release disagree: the pairs before the release (after the object
    last followed the toucher) in which the object next to the contact moves clearly (>= 2 `eps`)
    and not with the toucher (decoupled) while the toucher rests on it (slower than 2 `eps`, or
    hidden: no evidence either way, `moves_off`). The release is put where the toucher moves off;
    an object that moved away from a resting hand may have been let go there. Returns (first pair,
    last pair, the fastest such motion in px a frame) of the first run of them, or None."""
    g, r = timing.grasp, timing.release
    if r is None:
        return None
    so = np.linalg.norm(timing.object_velocity, axis=1)
    sh = np.linalg.norm(timing.hand_velocity, axis=1)
    # after the object last followed the toucher (before it, the pull had not yet taken the object
    # along: a slow start, not a letting go)
    last = max([k for k in range(g, min(r, len(so))) if timing.coupled[k] > 0], default=g)
    ks = [k for k in range(last + 1, min(r, len(so))) if timing.near[k] and timing.coupled[k] < 0
          and np.isfinite(so[k]) and so[k] >= 2 * eps and not (np.isfinite(sh[k]) and sh[k] >= 2 * eps)]
    if not ks:
        return None
    run = [ks[0]]
    for k in ks[1:]:
        if k != run[-1] + 1:
            break
        run.append(k)
    return run[0], run[-1], float(max(so[k] for k in run))


def collider_start(timing: Timing, eps: float = 0.35, reach: int = 3, back: int = 2) -> int:
    """A fingertip's or a palm's grasp: the first pair (within `reach` of the toucher's stillest
    frame) in which the object follows it: a collider acts from when the object starts to give (it
    may rest on the surface before, acting on nothing). From there back over at most `back` pairs
    in which the object already follows the toucher's way (`coupling` +1: its way within ~45 deg, at
    >= 20% of its speed), while the toucher is at the contact: a push starting as the toucher
    arrives moves the object next to the contact by less than `eps` in its first pair, which
    `following_onset` (two pairs >= `eps` running, a pull's rule) steps over (#23, 33rd session:
    dev_0539, a sphere arriving at 0.46 px a frame at 48 fps, the object following at 0.25 px in
    the arrival's pair: the grasp 2 frames late)."""
    c, g = timing.coupled, timing.grasp
    vh, vo = timing.hand_velocity, timing.object_velocity
    near = timing.near
    end = len(c) if timing.release is None else min(len(c), timing.release)
    for k in range(g, min(end, g + reach + 1)):
        if c[k] > 0 or gives(vh[k], vo[k], eps):
            lo = k - int(back)
            while k - 1 >= max(lo, 0) and c[k - 1] > 0 and near[k - 1]:
                k -= 1
            return k
    return g


def gives(vh_k: np.ndarray, vo_k: np.ndarray, eps: float = 0.35) -> bool:
    """Whether the object next to the contact gives to a pushing toucher in a frame pair: both move (>= `eps`) and
    the object's way is within 90 deg of the toucher's (`coupling` asks ~45 deg to call it following) (#23, 28th
    session: dev_0545, a fingertip pressing a rope on its floor from above and aside, the rope squeezed out sideways
    at 0.5-0.8 px a frame while the fingertip goes down at 1 px: read decoupled, the grasp 3 frames late)."""
    if not (np.isfinite(vh_k).all() and np.isfinite(vo_k).all()):
        return False
    na, nb = float(np.linalg.norm(vh_k)), float(np.linalg.norm(vo_k))
    return na >= eps and nb >= eps and float(np.dot(vh_k, vo_k)) > 0.0


def ramp_start(timing: Timing, eps: float = 0.35, rest: float = 0.25) -> int:
    """The grasp moved back to where the toucher's motion leaves its rest (#23, tenth pass): a
    motion from rest starts smoothly (a hand's speed grows from zero, it cannot jump), so where the
    grasp's pair is already moving (its toucher faster than the noise `eps`) the toucher began to
    act earlier, at the foot of its speed ramp, below the level at which the object's following or
    the onset can be seen. Going back from the grasp's pair while the toucher touches the object
    and moves more slowly pair by pair, the foot is the first pair at rest (at most `rest` x eps:
    the trackers' noise on a still hand, 0.01-0.1 px a frame on the world suite's captures; the
    walk never wanders on into the rest's noise) or the slowest pair; the grasp is the frame after
    it, the first frame of the first moving pair. A grasp at rest, or a toucher not seen, stays."""
    g, sp, near = timing.grasp, timing.speed, timing.near
    if g is None or g >= len(sp) or not np.isfinite(sp[g]) or sp[g] <= eps:
        return g
    k = g
    while (k - 1 >= 0 and np.isfinite(sp[k - 1]) and near[k - 1] and sp[k - 1] < sp[k]
           and sp[k] > rest * eps):
        k -= 1
    return k + 1 if k < g else g


BACK_OUT_PX = 1.0   # a collider this far back out past where it first touched (along its push) presses nothing


def collider_release(timing: Timing, push_uv, eps: float = 0.35) -> int | None:
    """A collider's release (a fingertip, a sphere, a palm pushes; it cannot pull): a pair in which
    it moves on into the object (within 60 deg of its push `push_uv`, the first main motion in the
    image) faster than the object next to the contact gives way along the push cannot part them
    (it would pass through the object: it presses a stiff one that barely gives, dev_9301: a
    sphere pressing a 6e5 Pa sheet, moving 0.8 px a frame into it against the sheet's 0.2). Such
    pairs are no evidence of parting; the release is read again without them (`release`). A
    toucher that moves into the object slower than the object moves away along the push has lost
    it (a knocked block that flies off, dev_0012)."""
    d = np.asarray(push_uv, float)
    nd = float(np.linalg.norm(d))
    if nd < 1e-9:
        return timing.release
    d = d / nd
    vh, vo, c = timing.hand_velocity, timing.object_velocity, timing.coupled.copy()
    a = approach(timing, eps)
    if a is not None and float(a @ d) < 0:
        # (#23, fifteenth pass) a collider comes into contact moving into the object: a "push"
        # against its approach is its leaving (a palm that rests on the object, its press a pixel,
        # reads its departure as its first main motion once the release is read late), and a
        # leaving is no pressing on (dev_0322: released at 24, truly 23..24, read held to the end)
        d = a / float(np.linalg.norm(a))
    depth = 0.0      # how far the toucher has gone into the object along the push since the grasp, in pixels
    for k in range(timing.grasp, len(c)):
        if not np.isfinite(vh[k]).all():
            continue
        ih = float(vh[k] @ d)
        # (#23, 28th session) a toucher already back out past where it first touched (it came back more than it
        # pushed in) presses nothing: its next move along the push is no pressing on (dev_0543: a fingertip's press
        # and its way back out, then a pair down and aside as it left read as pressing, the release 18 -> 21)
        inside = depth > -BACK_OUT_PX
        depth += ih
        if c[k] >= 0 or not np.isfinite(vo[k]).all() or not inside:
            continue
        io = float(vo[k] @ d)
        if ih > max(eps, 0.5 * float(np.linalg.norm(vh[k]))) and io < ih:
            c[k] = 0
    return release(c, timing.near, timing.grasp, timing.speed, vh=vh, vo=vo, share=timing.share, eps=eps)


def approach(timing: Timing, eps: float = 0.35) -> np.ndarray | None:
    """The toucher's approach in the image: its summed motion over the pairs of the contact period
    before the grasp in which it is seen touching and moving (faster than `eps`); None where it
    is not seen coming in (or its motion sums to under 2 `eps`)."""
    vh, near = timing.hand_velocity, timing.near
    p0, g = timing.period[0], timing.grasp
    ks = [k for k in range(max(0, p0), min(g, len(vh))) if near[k] and np.isfinite(vh[k]).all()
          and float(np.linalg.norm(vh[k])) > eps]
    if not ks:
        return None
    a = np.sum([vh[k] for k in ks], axis=0)
    return a if float(np.linalg.norm(a)) >= 2 * eps else None


def part_by_ratio(coupled: np.ndarray, vh: np.ndarray, vo: np.ndarray, run, eps: float) -> np.ndarray:
    """`coupled` with the pairs in which the object follows at less than half its usual share of the
    toucher's speed (the median over the run's pairs where the toucher moves at >= 2 eps; at least
    3 of them) set to -1 (apart)."""
    sh = np.linalg.norm(vh, axis=1)
    so = np.linalg.norm(vo, axis=1)
    share = contact_share(coupled, vh, vo, run, eps)
    out = coupled.copy()
    for k in range(len(coupled)):
        if out[k] > 0 and np.isfinite(sh[k]) and np.isfinite(so[k]) and sh[k] >= 2 * eps and so[k] < 0.5 * share * sh[k]:
            out[k] = -1
        # the object next to a held point does not outrun the hand: moving at 2.5x its speed, it
        # moves by itself (springs back after the release, while the hand drifts the same way)
        if out[k] > 0 and np.isfinite(sh[k]) and np.isfinite(so[k]) and so[k] >= 2 * eps and so[k] > 2.5 * max(sh[k], eps):
            out[k] = -1
    return out


def contact_share(coupled: np.ndarray, vh: np.ndarray, vo: np.ndarray, run, eps: float) -> float:
    """The share of the toucher's speed the object next to the contact keeps while they touch: the
    70th percentile of the object's speed over the toucher's over the run's pairs in which it
    follows and the toucher moves at >= 2 `eps` (at least 3 of them; else 0: not measured)."""
    sh = np.linalg.norm(vh, axis=1)
    so = np.linalg.norm(vo, axis=1)
    a, b = run
    fast = [k for k in range(a, b + 1) if coupled[k] > 0 and np.isfinite(sh[k]) and np.isfinite(so[k])
            and sh[k] >= 2 * eps]
    return float(np.percentile([so[k] / sh[k] for k in fast], 70)) if len(fast) >= 3 else 0.0


def release_after(timing: Timing, g: int):
    """The release after a grasp at frame g (the user's): the end of the contact run from g (the
    first pair from which the toucher moves apart from the object, or stops touching it)."""
    c, near = timing.coupled, timing.near
    T1 = len(c)
    k = g
    while k < T1:
        apart = not near[k] or (c[k] < 0 and (k + 1 >= T1 or c[k + 1] < 0 or not near[k + 1]))
        if apart and k > g:
            return k
        k += 1
    return None


def velocities(an: Analysis, centres: list):
    """Per frame pair k -> k+1 the hand's and the object's median flow near the contact."""
    T = an.T
    vh = np.full((T - 1, 2), np.nan)
    vo = np.full((T - 1, 2), np.nan)
    for k in range(T - 1):
        c = centres[k]
        if c is None:
            continue
        disk = disk_mask((an.H, an.W), c, an.R)
        big = disk_mask((an.H, an.W), c, 2.0 * an.R)
        fl = an.flows.forward[k]
        h_in = erode(an.hand[k], 1)
        v = median_flow(fl, h_in & disk, h_in & big)
        if v is not None:
            vh[k] = v
        # object pixels clear of the hand in both frames of the pair: the flow smears a few pixels
        # across motion boundaries, and an object pixel the hand moves onto in frame k+1 is hidden
        # there, so its flow is the hand's (a toucher withdrawing over the object it let go of
        # read as the object following it)
        o_in = erode(an.obj[k], 1) & ~dilate(an.hand[k] | an.hand[k + 1], an.clear)
        v = median_flow(fl, o_in & big, o_in & disk_mask((an.H, an.W), c, 3.0 * an.R))
        if v is not None:
            vo[k] = v
    return vh, vo


def motion_before(an: Analysis, centres: list, p0: int) -> np.ndarray | None:
    """The object's own image motion (px / frame) where the contact will be, in the frame pair just
    before the toucher reaches it (p0 - 1 -> p0): its median flow within 2 R of the contact's
    first centre, clear of the toucher. None where there is no such pair or nothing is seen."""
    c = centres[p0] if 0 <= p0 < len(centres) else None
    if c is None or p0 < 1:
        return None
    k = p0 - 1
    o_in = erode(an.obj[k], 1) & ~dilate(an.hand[k] | an.hand[k + 1], an.clear)
    v = median_flow(an.flows.forward[k], o_in & disk_mask((an.H, an.W), c, 2.0 * an.R))
    return None if v is None else np.asarray(v, float)


def carried_on(coupled: np.ndarray, vo: np.ndarray, p0: int, before, eps: float) -> list:
    """The first pairs of the contact in which the object next to it only carries on moving as it
    did before the toucher came (`before`, at least 2 `eps`: an object settling or sliding on its
    own): its way (within 60 deg) and no faster than 1.5x. Its following there is no evidence the
    toucher moves it (dev_9331: a plush toy still sliding sideways at 2 px a frame on the floor as
    a palm lands on it read as a grasp pulling it sideways)."""
    if before is None:
        return []
    nb = float(np.linalg.norm(before))
    if nb < 2 * eps:
        return []
    out = []
    for k in range(p0, len(coupled)):
        v = vo[k]
        if coupled[k] <= 0 or not np.isfinite(v).all():
            break
        n = float(np.linalg.norm(v))
        if n > 1.5 * nb or float(np.dot(v, before)) < 0.5 * n * nb:
            break
        out.append(k)
    return out


def coupling(vh: np.ndarray, vo: np.ndarray, eps: float, floor: float = 0.05) -> np.ndarray:
    """+1: the object near the contact moves with the hand (its way, at >= 20% of its speed: the
    object next to a grasp stretches and lags, a stiff one pushed barely gives); 0: both (about)
    still, or the object near the contact unseen; -1: not (the hand moves and the object does not
    follow, or the object moves without the hand). Below `floor` px a motion has no direction."""
    out = np.full(len(vh), -1, np.int8)
    for k in range(len(vh)):
        a, b = vh[k], vo[k]
        if np.isnan(b).any():
            out[k] = 0      # the object near the contact unseen: no evidence either way
            continue
        if np.isnan(a).any():
            a = np.zeros(2)  # the hand hidden (e.g. behind the object): no evidence of its motion
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        if max(na, nb) < eps:
            out[k] = 0
        elif nb >= max(floor, 0.2 * na) and na >= floor and np.dot(a, b) >= 0.7 * na * nb:
            out[k] = 1
        else:
            out[k] = -1
    return out


FAINT_GAP = 2   # frames: a gap in the touching this short, the hand still seen at the contact throughout, is no parting


def bridge_faint(near: np.ndarray, touch, gap: int = FAINT_GAP) -> np.ndarray:
    """`near` with its gaps of at most `gap` frames between two touching frames filled where the hand is still seen at
    the contact in every frame of the gap (`touch` > 0 px, under the touching's 3 px floor): a hand turning at the
    contact, or half hidden by the object, for a frame or two has not let go (#23, 33rd session: dev_0530, a pull out
    and back whose hand shows 2 px at the contact in frames 19-20 of a hold to 24: the contact period ended at 18, the
    release read at 19)."""
    near = np.asarray(near, bool).copy()
    if touch is None:
        return near
    touch = np.asarray(touch, float)
    T = len(near)
    k = 1
    while k < T:
        if not near[k] and near[k - 1]:
            j = k
            while j < T and not near[j]:
                j += 1
            if j < T and j - k <= gap and np.all(touch[k:j] > 0):
                near[k:j] = True
            k = j
        else:
            k += 1
    return near


def contact_period(near: np.ndarray) -> tuple[int, int]:
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


def contact_start(speed: np.ndarray, near: np.ndarray, p0: int, p1: int, coupled: np.ndarray, vh: np.ndarray) -> int:
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
    on = rest_onset(speed, vh, p0, p1, coupled)
    if on is not None:
        return on
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
            return skip_approach(ks[pick], coupled, speed, p1)
    win = grasp_window(near, coupled, vh)
    return skip_approach(win[0], coupled, speed, p1) if win is not None else p0


def rest_onset(speed: np.ndarray, vh: np.ndarray, p0: int, p1: int, coupled: np.ndarray | None = None,
               eps: float = 0.35, noise: float = 0.1, window: int = 4) -> int | None:
    """The grasp as the onset of the toucher's motion after it comes to rest on the object,
    judged against its own noise floor, not against its peak (a slow press at 0.3-0.5 px a frame
    followed by a fast retreat is all 'slow' next to the retreat). The rest: the first two frames
    running of the contact period slower than `eps` (one slow frame is the approach's start or
    end), or one where the toucher is first seen (unseen in the frame before: it is already there),
    or one slower than 2 `eps` and than the pairs either side where it turns (the pairs either
    side over 60 deg apart, the object not following the pair before: a sphere that comes in and
    pulls back out stops for an instant; a pull that reverses mid-way is no rest);
    its floor the mean of the 2 stillest of its first 6 slow frames running (the median of 3 was
    the rest's last slow frame where it has only 3: glove 2 frames late). The onset: the
    first frame pair, within `window` frames of the first frame at the floor (+`noise` px), from
    which the toucher moves above that level in two pairs running, the same way (cos >= 0.5:
    noise has no direction). The grasp is the frame before it (the last one at rest). None where
    the video shows no such onset soon after the rest (a hand holding a stiff object barely
    moves; the caller's rule decides)."""
    T1 = len(speed)
    hi = min(p1, T1 - 1)

    def slow(k):
        return 0 <= k < T1 and np.isfinite(speed[k]) and speed[k] < eps

    def turn(k):
        # one frame between an approach and a motion the other way (within 60 deg of reversed, or
        # across): the toucher stops there for an instant
        if not (0 < k < T1 - 1 and np.isfinite(vh[k - 1]).all() and np.isfinite(vh[k + 1]).all()
                and np.isfinite(speed[k]) and speed[k] < 2 * eps):
            return False
        if coupled is not None and coupled[k - 1] > 0:
            return False
        a, b = vh[k - 1], vh[k + 1]
        na, nb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
        return speed[k] < min(na, nb) and float(np.dot(a, b)) < 0.5 * na * nb

    def arrival(k):
        # one frame slower than eps where the toucher, coming in at 3 eps or more within the 3
        # pairs before, slows to its least speed and then moves on: it arrived there (a sphere
        # that comes down onto a sheet and presses on at once, dev_9301: 1.3, 0.9, 0.4, 0.27, 0.4,
        # 0.5 px; a hand's grasp with no dwell)
        if not (slow(k) and 3 <= k < T1 - 1 and np.isfinite(speed[k - 1]) and np.isfinite(speed[k + 1])):
            return False
        before = [speed[j] for j in range(k - 3, k) if np.isfinite(speed[j])]
        if not (speed[k - 1] > speed[k] and before and max(before) >= 3 * eps and k + 2 < T1):
            return False
        # ... and moves on from there: the next two pairs above its speed there (+ `noise`), the
        # same way (the onset below); a toucher that settles after it came in (tongs, dev_9205:
        # 3.7, 0.12, 0.6, 0.21, 0.19, 0 px) has not arrived at its first slow frame
        u, v = vh[k + 1], vh[k + 2]
        if not (np.isfinite(u).all() and np.isfinite(v).all()):
            return False
        nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        return min(nu, nv) > speed[k] + noise and float(np.dot(u, v)) >= 0.5 * nu * nv

    s = next((k for k in range(p0, hi + 1) if (slow(k) and (slow(k + 1) or (k > 0 and not np.isfinite(speed[k - 1]))))
              or turn(k) or arrival(k)), None)
    if s is None:
        return None
    w = [speed[s]]
    for k in range(s + 1, min(hi, s + 5) + 1):
        if not slow(k):
            break
        w.append(speed[k])
    thr = float(np.mean(np.sort(w)[:2])) + noise
    a = next(k for k in range(s, hi + 1) if np.isfinite(speed[k]) and speed[k] <= thr)
    for k in range(a + 1, min(hi - 1, a + window) + 1):
        u, v = vh[k], vh[k + 1]
        if not (np.isfinite(u).all() and np.isfinite(v).all()):
            continue
        nu, nv = float(np.linalg.norm(u)), float(np.linalg.norm(v))
        if nu > thr and nv > thr and float(np.dot(u, v)) >= 0.5 * nu * nv:
            return k - 1
    return None


def following_onset(g: int, coupled: np.ndarray, vo: np.ndarray, eps: float, reach: int = 2) -> int:
    """The grasp from the object's own motion: the first frame pair k within `reach` pairs from
    the toucher's rest onset g from which the object next to the contact follows the toucher
    (`coupling` +1) and moves (>= `eps`) in two pairs running; the grasp is frame k, the last one
    before the object moves. The toucher's onset (read against its own noise floor) comes first
    and the object's visible motion up to two pairs later: a pull starting smoothly from rest moves
    the object next to the contact by less than `eps` in its first pair or two, and the object
    takes up the toucher's motion only once it has hold (on the fresh dev captures the toucher's
    onset alone put the grasp a frame early on 5 of 12 captures, 2 on one). Past `reach` the two
    onsets are not the same event (the object was already moving, or moves by itself): g stands.
    Where the object next to the contact does not visibly follow (a stiff object, the contact
    hidden), or is not seen at rest before it does, from the pair before the toucher's onset on (it
    moves on its own: a plush toy still sliding as a palm lands on it, dev_9331, whose grasp this
    put 2 frames late), the toucher's onset stands."""
    so = np.linalg.norm(vo, axis=1)
    T1 = len(coupled)
    if g >= 1 and np.isfinite(so[g - 1]) and so[g - 1] >= eps:
        return g      # the object was moving (on its own) into the toucher's onset: no onset of its own
    for k in range(g, min(T1 - 1, g + reach + 1)):
        if coupled[k] > 0 and coupled[k + 1] > 0 and so[k] >= eps and so[k + 1] >= eps:
            return k
        if not (np.isfinite(so[k]) and so[k] < eps):
            break     # an onset starts from rest: the object seen moving (on its own) or unseen here has none
    return g


def not_after_the_motion(g: int, coupled: np.ndarray, vo: np.ndarray, run) -> int:
    """A grasp comes before the object moves with the toucher: where the object next to the contact
    has already made most of its following motion over the contact run (`contact_run`) before the
    grasp frame g, g is the end of that motion (a hold, then the release: dev_9224, a pull straight
    from the approach with no rest before it, its hold's onset read as the grasp), and the grasp is
    the first frame pair of the run in which the object follows."""
    if run is None:
        return g
    a, b = run
    m = np.array([float(np.linalg.norm(vo[k])) if coupled[k] > 0 and np.isfinite(vo[k]).all() else 0.0
                  for k in range(a, b + 1)])
    if m.sum() <= 0 or g <= a or m[: g - a].sum() <= 0.5 * m.sum():
        return g
    return a + int(np.argmax(m > 0))


def past_the_approach(g: int, coupled: np.ndarray, speed: np.ndarray, run, eps: float = 0.35) -> int:
    """A grasp read on the toucher's approach: where every pair from g to the contact run's first
    pair in which the object follows has the toucher moving (faster than `eps`) with the object not
    following, and at least one of them fast (3 `eps`: coming in, not a slow press), those pairs
    are its approach, and the grasp is that first following pair (dev_9229: a glove that comes in
    over the bar, touching it in the image from the first frame, and pulls with no rest: grasp
    0 -> 5, truly 4)."""
    if run is None:
        return g
    a, b = run
    first = next((k for k in range(max(a, g), b + 1) if coupled[k] > 0), None)
    if first is None or first <= g:
        return g
    pairs = range(g, first)
    if all(coupled[k] < 0 and np.isfinite(speed[k]) and speed[k] > eps for k in pairs) and \
            max(speed[k] for k in pairs) >= 3 * eps:
        return first
    return g


def skip_approach(g: int, coupled: np.ndarray, speed: np.ndarray, p1: int, eps: float = 0.35) -> int:
    """A start frame in which the hand still moves and the object does not follow, followed by
    one in which it does, is the end of the approach: start one later (at most twice)."""
    for _ in range(2):
        if g + 1 <= min(p1, len(coupled) - 1) and coupled[g] < 0 and coupled[g + 1] > 0 and speed[g] > eps:
            g += 1
    return g


def release(coupled: np.ndarray, near: np.ndarray, g: int, speed: np.ndarray | None = None,
            vh: np.ndarray | None = None, vo: np.ndarray | None = None, share: float = 0.0, eps: float = 0.35,
            window: int = 3):
    """The release: the object stops following the hand at some frame r_c (the hand no longer
    touching it, or a decoupled frame pair after which they stay apart); None: held to the end. A
    slow pull may leave the object behind for a frame or two after the grasp: decoupling counts
    only once the object has followed (bow_tie). A hand slows down before it lets go and moves off
    after: with `speed`, when the hand was still moving in the pair before r_c (the decoupling
    seen a pair late), the release is the frame after the slowest of the pairs just before r_c in
    which it still moved (ties to the earlier); pairs in which both were still (a hold before
    letting go) are not searched (the release would land at the hold's start).

    Whether they stay apart: with the velocities (`vh`, `vo`; `parted`), over the decoupled pair
    and the next ones (`window` pairs in all) the object's motion next to the contact, summed, is
    no longer the share of the toucher's summed motion it kept while they touched (`share`,
    `contact_share`): after a release it springs back, stays, or moves on by itself while the
    toucher goes its own way, and their relative motion grows; a pair's flow that disagrees for
    one pair (noise, the toucher's flow smeared onto the object next to it) is summed away. Without
    them, two decoupled pairs in a row, or one in which the hand moves fast.

    (Eighth pass) With the velocities, only a pair in which the toucher makes a motion of its own
    that the object does not follow can part them (`moves_off`): a still toucher, or one carrying
    on (slowing) its motion, says nothing about the hold, and the release is not walked back into
    a rest of the toucher (it starts moving off at r_c). On the fresh dev captures (data/world_dev7,
    the study half) the release within a frame went 8 -> 10 of 15 with this alone: the object
    moving alone next to a still hand (a ball rolling on, a there-and-back pull turning) had been
    read as the release, 3-5 frames early."""
    T1 = len(coupled)
    r_c = None
    first = next((k for k in range(g + 1, T1) if coupled[k] > 0), g)
    motion = vh is not None and vo is not None
    start = first + 1 if first > g else g + 1
    if motion and first == g:
        # nothing followed: the contact is seen from the first pair in which both rest on each
        # other (seen, still); a toucher seen only moving apart before that is still coming in
        # (dev_0002: its approach read as the release). Never seen: only its leaving ends it.
        seen = contact_seen(coupled, vh, vo, g)
        if seen is None:
            return next((k for k in range(g + 1, T1) if not near[k]), None)
        start = max(start, seen + 1)
    for k in range(start, T1):
        if not near[k]:
            r_c = k
            break
        if motion:
            # parting needs the toucher's own motion, not followed (`moves_off`): while it rests
            # or carries on, the object falling behind or moving alone is the held material
            if coupled[k] < 0 and moves_off(k, vh, eps, vo) and parted(k, near, vh, vo, share, eps, window, coupled):
                r_c = k
                break
            continue
        fast = speed is not None and np.isfinite(speed[k]) and speed[k] >= 3 * 0.35
        if coupled[k] < 0 and (fast or k + 1 >= T1 or coupled[k + 1] < 0 or not near[k + 1]):
            # the object catching up again (a lagging pull round a bend) was not a release
            ahead = [j for j in range(k + 1, min(T1, k + 5)) if near[j] and coupled[j] > 0]
            if len(ahead) >= 2 and not fast:
                continue
            r_c = k
            break
    if r_c is None or speed is None:
        return r_c
    if motion and r_c - 1 > g and np.isfinite(speed[r_c - 1]) and speed[r_c - 1] < eps:
        # the toucher rested in the pair before (below eps): its moving off starts at r_c, not a
        # pair late; walking back would put the release into the hold
        return r_c
    ks = []
    for k in range(r_c - 1, max(g, r_c - 3), -1):
        if not np.isfinite(speed[k]) or coupled[k] == 0:
            break
        ks.append(k)
    if not ks:
        return r_c
    best = min(speed[k] for k in ks)
    if best >= speed[r_c]:
        return r_c
    k_min = min(k for k in ks if speed[k] <= best + 0.1)
    return k_min + 1


def moves_off(k: int, vh: np.ndarray, eps: float, vo: np.ndarray | None = None) -> bool:
    """Whether frame pair k can show the toucher parting from the object: the toucher is seen
    moving at >= 2 `eps` (twice the level below which nothing is "moving") in a new motion, not
    carrying on the one before. While it is still (or hidden) the video says nothing about the
    hold: a held elastic object swings, settles or springs about a still hand (dev_0104: a glove
    holding a ball still for 4 frames while the ball rolled on at 1.5-2.8 px a frame, released 4
    frames early). While it carries on its motion (the pair before moved at >= 2 `eps`, this one
    within 60 deg of it and no faster than it by more than `eps`, the noise: a pull slowing to its
    end) the object next to the contact falling behind is the held material stretching or
    swinging back, not a letting go (dev_0136: a hanging ball's side stopped while the glove
    finished its pull over 3 frames). Letting go is a new motion of the toucher: it starts from
    rest, speeds up or turns away, and the object does not follow it. Or, with the object's
    velocity `vo`, the object next to the contact does more than lag behind a toucher carrying on:
    it outruns it along its motion (by more than `eps`: nothing held or pushed can, a block knocked
    away), or springs back or turns away from it."""
    if not np.isfinite(vh[k]).all():
        return False
    s = float(np.linalg.norm(vh[k]))
    if s < 2 * eps:
        return False
    if k >= 1 and np.isfinite(vh[k - 1]).all():
        p = vh[k - 1]
        sp = float(np.linalg.norm(p))
        if sp >= 2 * eps and float(np.dot(p, vh[k])) >= 0.5 * sp * s and s <= sp + eps:
            if vo is None or not np.isfinite(vo[k]).all():
                return False
            # carrying on: parting only where the object next to the contact does not merely lag
            # (its velocity within half the toucher's speed, and eps, of the segment 0..vh: a held
            # point moves with the toucher, its surroundings by less): it outruns the toucher, or
            # springs back or turns away from it (the hemp rope let go mid-stroke: the hand moves on
            # at 4 px a frame, the rope next to it swings back at 3.2 px)
            u = vh[k] / s
            along = float(vo[k] @ u)
            off = float(np.linalg.norm(vo[k] - min(max(along, 0.0), s) * u))
            return bool(along > s + eps or off > max(eps, 0.5 * s))
    return True


def contact_seen(coupled: np.ndarray, vh: np.ndarray, vo: np.ndarray, g: int) -> int | None:
    """The first frame pair from g in which the video shows the toucher in contact with the object:
    the object next to the contact follows it, or both are seen resting (still); None: never."""
    for k in range(g, len(coupled)):
        if coupled[k] > 0 or (coupled[k] == 0 and np.isfinite(vh[k]).all() and np.isfinite(vo[k]).all()):
            return k
    return None


def parted(k: int, near: np.ndarray, vh: np.ndarray, vo: np.ndarray, share: float, eps: float = 0.35,
           window: int = 3, coupled: np.ndarray | None = None) -> bool:
    """Whether the toucher and the object next to the contact move apart from frame pair k on:
    over pairs k .. k + window - 1 (those in which the object there is seen; a hidden toucher
    counts as still) the object's summed motion differs from `share` x the toucher's by more than
    half of that (it falls behind, springs back, runs ahead or turns away); or, with no share
    measured, the summed motions are decoupled as a single pair would be (`coupling`). The
    toucher leaving the object within the window parts them; both about still (under `eps` summed)
    does not."""
    T1 = len(vh)
    js = range(k, min(T1, k + window))
    if any(not near[j] for j in js):
        return True
    seen = [j for j in js if np.isfinite(vo[j]).all()]
    if not seen:
        return False
    if coupled is not None:
        # they stay apart: more of the window's pairs decoupled than coupled or still
        apart = sum(int(coupled[j] < 0) for j in seen)
        if apart <= len(seen) - apart:
            return False
    Vh = np.sum([np.nan_to_num(vh[j]) for j in seen], axis=0)
    Vo = np.sum([vo[j] for j in seen], axis=0)
    nh, no = float(np.linalg.norm(Vh)), float(np.linalg.norm(Vo))
    if max(nh, no) < eps:
        return False
    apart = (float(np.linalg.norm(Vo - share * Vh)) > 0.5 * share * nh if share > 0
             else bool(coupling(Vh[None], Vo[None], eps)[0] < 0))
    return apart and not lags_behind(k, vh, [vh[j] for j in seen], Vo / len(seen), eps)


def lags_behind(k: int, vh: np.ndarray, after: list, o_after: np.ndarray, eps: float = 0.35) -> bool:
    """The object next to the contact only lags behind a toucher that keeps moving as it did: in
    no pair of the window (`after`, the toucher's velocities; a hidden toucher: no evidence) does
    the toucher speed up, turn or reverse by more than half its speed (at least `eps`) against its
    mean over the (seen) pairs k-3 .. k-1, in which it moved at >= 2 `eps` (slowing down along it,
    as a pull ends before the hand lets go, is not moving off), and the object's mean motion over
    the window (`o_after`) has not turned back against that motion by more than `eps` in all nor
    outrun it.
    That is no release: a toucher that lets go moves off (turns or speeds up) and a released
    elastic end springs back; what lags is the measurement (a plain object's flow next to the
    hand, dev_9217: a stiff anchored bar still held by a glove that kept pulling at 2 px a frame
    read 0.0-0.4 px next to it for 8 frames, released 11 frames early) or the material stretching."""
    prev = [vh[j] for j in range(max(0, k - 3), k) if np.isfinite(vh[j]).all()]
    if not prev or not after or not all(np.isfinite(v).all() for v in after):
        return False
    v_prev = np.mean(prev, axis=0)
    s_prev = float(np.linalg.norm(v_prev))
    if s_prev < 2 * eps:
        return False
    u = v_prev / s_prev
    tol = max(eps, 0.5 * s_prev)
    for v in after:
        along = float(v @ u)
        if along > s_prev + tol or abs(float(v[0] * u[1] - v[1] * u[0])) > tol or along < -eps:
            return False     # it speeds up, turns or reverses: it moves off (slowing down is not)
    v_after = np.mean(after, axis=0)
    return float(o_after @ u) * len(after) >= -eps and float(np.linalg.norm(o_after)) <= float(np.linalg.norm(v_after))


def coupled_share(coupled: np.ndarray, speed: np.ndarray, g: int, p1: int) -> float:
    """Share of the hand's motion over the contact in which the object next to it follows."""
    sl = slice(g, min(p1, len(coupled)))
    sp = np.nan_to_num(speed[sl])
    tot = float(sp.sum())
    return float(sp[coupled[sl] > 0].sum() / tot) if tot > 0 else 0.0


def grasp_window(touch: np.ndarray, coupled: np.ndarray, vh: np.ndarray):
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
    end = None if j >= T - 1 else j
    return g, end, score


# ------------------------------------------------------------------ the ninth pass: one model (#23)
# "rules": the passes' cascade (contact_start ... release, the default); "model": the ninth pass's
# `held_window` (opt-in until a GPU read on fresh dev seeds decides: docs/benchmarks/world.md);
# "hybrid": the model's grasp, the rules' release from it (and the rules' collider steps)
METHOD = "rules"


def held_evidence(vh: np.ndarray, vo: np.ndarray, near: np.ndarray, eps: float = 0.35,
                  share: float = 0.0) -> np.ndarray:
    """Per frame pair k -> k+1, the evidence that the toucher acts on the object there, in [-1, 1]:
    the sign says whether the object next to the contact moves with the toucher (`coupling`: its
    way within 45 deg, at >= 20% of its speed: the object next to a grasp stretches and lags, a
    stiff one pushed barely gives) or not; the size is how much the pair can tell, the toucher's
    speed over the noise: (|vh| - eps) / eps, clipped to [0, 1] (a toucher at the noise level is
    still, and a still toucher says nothing about a hold: the held object may swing, roll or
    settle about it; a pair of full weight moves at 2 eps or more). 0 where either is unseen; -1
    where the pair's first frame shows no toucher at the object (nothing holds it there).

    With the contact's `share` (the part of the toucher's motion the object next to it takes up
    while they touch, `contact_share_of`), a pair follows only where the object's motion along the
    toucher's is over half that share: between "it moves with the toucher at its share" and "it
    stays", whichever is nearer (the sign of the log-likelihood ratio of the two under isotropic
    flow noise); an object that springs back slower than a toucher moving off the same way keeps a
    fifth of its speed but not its share."""
    T1 = len(vh)
    out = np.zeros(T1)
    c = coupling(vh, vo, eps)
    seen = np.isfinite(vh).all(1) & np.isfinite(vo).all(1)
    a0 = np.where(seen[:, None], vh, 0.0)
    sh = np.linalg.norm(a0, axis=1)
    if share > 0:
        p = (a0 * np.where(seen[:, None], vo, 0.0)).sum(1) / np.maximum(sh ** 2, 1e-12)
        c = np.where((c > 0) & (p < 0.5 * share) & (sh >= eps), -1, c)
    w = np.clip((sh - eps) / eps, 0.0, 1.0)
    out[seen] = (np.where(c > 0, 1.0, -1.0) * w)[seen]
    out[~np.asarray(near[:T1], bool)] = -1.0
    return out


def held_window(vh: np.ndarray, vo: np.ndarray, near: np.ndarray, eps: float = 0.35):
    """When the toucher acts: the run of frame pairs [a, b] with the most `held_evidence` (summed;
    a pair apart inside a long run of following ones is outweighed, a long approach or a lasting
    parting is not). The grasp is a, the first pair of the run in which the object follows (pairs
    of no evidence before it, a toucher resting on the object, are not yet its action: the grasp
    is the last frame before the object moves with it). The release is the first pair after b with
    evidence against the hold in which the toucher makes a motion of its own (`moves_off`: from
    rest, faster or turned; letting go is the toucher moving off, and the object falling behind a
    toucher that carries on its motion is the material stretching or a plain texture's flow), or
    in which it no longer touches the object: pairs of no evidence after b, a toucher resting,
    still hold it. None: held to the end. Returns (grasp, release or None, score), or None when no
    pair shows the object following the toucher."""
    lk = held_evidence(vh, vo, near, eps)
    run = best_run(lk)
    if run is None:
        return None
    share = contact_share_of(vh, vo, lk, run)
    if share > 0:
        lk = held_evidence(vh, vo, near, eps, share)
        run = best_run(lk) or run
    a, b, score = run
    while a < b and lk[a] <= 0.0:
        a += 1
    a = after_arrival(a, b, lk, vh, eps)
    a = motion_onset(a, vh, eps)
    near = np.asarray(near, bool)
    r = next((j for j in range(b + 1, len(lk)) if not near[j] or (lk[j] < 0.0 and moves_off(j, vh, eps, vo))), None)
    return a, r, score


def best_run(lk: np.ndarray):
    """The run of pairs [a, b] with the largest sum of `lk` (> 0), as (a, b, sum); None if none."""
    run, acc, start = None, 0.0, 0
    for k in range(len(lk)):
        if acc <= 0.0:
            acc, start = 0.0, k
        acc += lk[k]
        if acc > 0 and (run is None or acc > run[2] + 1e-9):
            run = (start, k, acc)
    return run


def contact_share_of(vh: np.ndarray, vo: np.ndarray, lk: np.ndarray, run) -> float:
    """The share of the toucher's motion the object next to the contact takes up while they touch:
    the median, over the run's pairs of full evidence for the hold (the toucher moving at 2 eps or
    more, the object following), of the object's motion along the toucher's over the toucher's
    speed; 0 (not measured) with fewer than 3 such pairs."""
    a, b = run[0], run[1]
    ks = [k for k in range(a, b + 1) if lk[k] >= 1.0]
    if len(ks) < 3:
        return 0.0
    p = [float(vo[k] @ vh[k]) / float(vh[k] @ vh[k]) for k in ks]
    return float(np.median(p))


def after_arrival(a: int, b: int, lk: np.ndarray, vh: np.ndarray, eps: float = 0.35) -> int:
    """A toucher arrives at the object and comes to rest there before it acts (a hand closes on
    the object, a fingertip settles on the surface): where the run [a, b] holds a rest of the
    toucher (pairs slower than `eps`) with less evidence of the object following before the rest
    than after it, the pairs before it were the approach (the object settling under gravity, or
    its flow smeared by the toucher coming in, can read as following), and the action starts at
    the first pair after the rest with evidence for it. A rest inside the main motion (a pull that
    turns back) has the larger part of the motion before it and stays in."""
    sp = np.linalg.norm(vh, axis=1)
    rest = [k for k in range(a, b + 1) if np.isfinite(sp[k]) and sp[k] < eps]
    if not rest:
        return a
    r0 = rest[0]
    r1 = r0
    while r1 + 1 <= b and np.isfinite(sp[r1 + 1]) and sp[r1 + 1] < eps:
        r1 += 1
    if r0 > a and float(lk[a:r0].sum()) < float(lk[r1 + 1:b + 1].sum()):
        return next((k for k in range(r1 + 1, b + 1) if lk[k] > 0.0), a)
    return a


def motion_onset(a: int, vh: np.ndarray, eps: float = 0.35, reach: int = 3) -> int:
    """The start of the toucher's motion that the object follows from pair a: a motion from rest
    starts smoothly (its speed grows from zero), so its first pairs are slower than the level at
    which the object's following can be seen. Going back from a (at most `reach` pairs) while the
    toucher moves the same way (within 45 deg of its motion at a) and more slowly pair by pair, the
    onset is the first pair of that ramp; the rest before it (the toucher's noise: no direction, no
    ramp) stops it. The grasp is that pair's first frame, the last one before the motion."""
    if not np.isfinite(vh[a]).all():
        return a
    sp = np.linalg.norm(vh, axis=1)
    u = vh[a]
    k = a
    while k - 1 >= max(0, a - reach) and np.isfinite(vh[k - 1]).all():
        nv = float(sp[k - 1])
        if not (1e-9 < nv < sp[k] and float(vh[k - 1] @ u) >= 0.7 * nv * float(sp[a])):
            break
        k -= 1
    return k


def collider_back_out(g: int, r, vh: np.ndarray, near: np.ndarray, share: float = 0.1):
    """A collider's release (a fingertip, a stick, a palm: it pushes and cannot pull): it touches the
    object only where it is in at or inside the object's surface, so a press ends where the toucher,
    withdrawing, is back where it touched it first: the first frame after its deepest point at
    which its image track from the grasp frame g (the toucher's velocities integrated; a hidden
    pair counts as still) has come back along the push to within `share` of the push's depth, or
    where it leaves the object first. The object left behind by a faster withdrawal (it springs
    back slower than the toucher retreats) is no release before that: the toucher still moves
    through where the surface was. Returns `r` (the held window's) where the track shows no push
    (under 1 px) or no return (a knocked object, a toucher that never withdraws)."""
    T1 = len(vh)
    if g >= T1:
        return r
    v = np.where(np.isfinite(vh).all(1)[:, None], vh, 0.0)
    track = np.zeros((T1 + 1, 2))
    track[g + 1:] = np.cumsum(v[g:], axis=0)
    d = np.linalg.norm(track, axis=1)
    k_max = int(np.argmax(d[: (r + 1) if r is not None else T1 + 1]))
    depth = float(d[k_max])
    if depth < 1.0:
        return r
    u = track[k_max] / depth
    along = track @ u
    for k in range(k_max + 1, T1 + 1):
        if k < len(near) and not near[k]:
            return k
        if along[k] <= share * depth:
            return k
    return r


def model_timing(vh, vo, coupled, near, period, eps: float, evidence: dict) -> Timing:
    """The grasp and release from `held_window` (one likelihood model, the same for every toucher);
    where no pair shows the object following the toucher, the contact period's first frame and the
    frame the toucher leaves (a note in `timing_confidence` says the video shows no contact)."""
    speed = np.linalg.norm(vh, axis=1)
    hw = held_window(vh, vo, near, eps)
    if hw is not None:
        g, r, score = hw
        share = 0.0
        cue_g = "the object starts to follow the toucher"
        cue_r = ("held to the end" if r is None else "the toucher leaves the object" if not near[r]
                 else "the toucher moves off and the object does not follow")
    else:
        g, share, score = period[0], 0.0, 0.0
        r = next((k for k in range(g + 1, len(near)) if not near[k]), None)
        cue_g, cue_r = "the toucher reaches the object (the object is never seen to follow it)", \
            ("held to the end" if r is None else "the toucher leaves the object")
    evidence["timing_cues"] = {"grasp": cue_g, "release": cue_r, "share": share, "score": round(float(score), 3)}
    evidence.update({"contact_period": list(period), "coupling": coupled.tolist(),
                     "hand_velocity_px": np.round(vh, 3).tolist(),
                     "object_velocity_px": np.round(vo, 3).tolist(), "grasp_frame": g, "release_frame": r})
    return Timing(vh, vo, coupled, near, period, speed, g, r, share)
