"""Evidence a person understands, computed from the video and the model's frames: how the
silhouettes move (centroid speed after release), their rest shape before and after, their lowest
point, where the residual sits in time. One sentence per candidate (and the confusable effect and
what separates it), and for the non-physical causes the flag that fixes them."""

from __future__ import annotations

import numpy as np
import torch

from .core import CONFUSABLE, FIXES, separation


def _silhouettes(ctx) -> tuple[np.ndarray, np.ndarray]:
    """(video (T, H, W) bool, model (T, H, W) bool) silhouettes."""
    prob, x, F = ctx["prob"], ctx["x"], ctx["F"]
    model = []
    with torch.no_grad():
        for k in range(prob.T):
            model.append(prob.render_frame(k, x[k], F[k])["alpha"].cpu().numpy() > 0.5)
    model = np.stack(model)
    if prob.masks is not None:
        video = prob.masks.cpu().numpy() > 0.5
    else:
        bg = prob.background.cpu().numpy()
        video = np.abs(prob.frames.cpu().numpy() - bg[None]).max(-1) > 0.1
    if prob.weight is not None:
        hand = prob.weight.cpu().numpy() < 0.5
        video, model = video & ~hand, model & ~hand
    return video, model


def _centroids(sil: np.ndarray) -> np.ndarray:
    out = np.full((len(sil), 2), np.nan)
    for k, m in enumerate(sil):
        v, u = np.nonzero(m)
        if len(u):
            out[k] = (u.mean(), v.mean())
    return out


def _iou(a, b) -> float:
    u = (a | b).sum()
    return float((a & b).sum() / u) if u else 1.0


def release_frame(prob) -> int | None:
    rel = [int(c.release_frame) for c in prob.contacts if c.is_interaction and c.release_frame is not None
           and int(c.release_frame) < prob.T]
    return max(rel) if rel else None


def _settle(speed: np.ndarray, thr: float) -> int | None:
    """The first index from which the speed stays below thr."""
    for i in range(len(speed)):
        if np.all(speed[i:] < thr):
            return i
    return None


def _residual_by_frame(ctx) -> np.ndarray:
    res, r0 = ctx["res"], ctx["r0"]
    e = np.square(r0).reshape(res.shape).sum((1, 2, 3))
    return dict(zip(res.frames, e))


def _phases(ctx, R, video, model) -> str:
    """Where the residual sits: during the pull (frames before the release: the load held) or after the
    release (nothing held), and how the silhouettes' centroid speed falls after the release in the video
    and in the model: what separates damping (it slows every motion, most visibly after the release)
    from viscoelasticity (rate-dependent stress under the held load, a slow relaxation of the shape)."""
    if R is None:
        return ""
    byf = _residual_by_frame(ctx)
    tot = sum(byf.values())
    if tot <= 0:
        return ""
    after = sum(v for k, v in byf.items() if k >= R) / tot
    cv, cm = _centroids(video), _centroids(model)
    sv = np.linalg.norm(np.diff(cv, axis=0), axis=1)[R:]
    sm = np.linalg.norm(np.diff(cm, axis=0), axis=1)[R:]
    out = f"; {100 * after:.0f}% of the residual is after the release at frame {R}, {100 * (1 - after):.0f}% under the held load"
    if len(sv) >= 4 and np.isfinite(sv).all() and np.isfinite(sm).all():
        h = len(sv) // 2
        rv = float(np.mean(sv[h:]) / max(np.mean(sv[:h]), 1e-9))
        rm = float(np.mean(sm[h:]) / max(np.mean(sm[:h]), 1e-9))
        out += (f"; after the release the centroid's speed falls to {rv:.2f}x in the video and {rm:.2f}x in the model "
                "(second half against first)")
    return out


def describe(effect: str, cr, ctx) -> str:
    prob = ctx["prob"]
    video, model = _silhouettes(ctx)
    T = prob.T
    R = release_frame(prob)
    cv, cm = _centroids(video), _centroids(model)
    sv = np.linalg.norm(np.diff(cv, axis=0), axis=1)
    sm = np.linalg.norm(np.diff(cm, axis=0), axis=1)
    cam = prob.cameras[0]
    depth = float(np.linalg.norm(prob.x0.mean(0) - np.asarray(cam.position)))
    m_per_px = depth / float(cam.fx)
    est = cr.estimate
    parts = []
    if effect == "damping":
        k0 = R if R is not None else 1
        after_v, after_m = sv[k0:], sm[k0:]
        if len(after_v):
            thr = max(0.5, 0.1 * float(np.nanmax(np.r_[after_v, after_m, 1e-9])))
            sv_k, sm_k = _settle(np.nan_to_num(after_v), thr), _settle(np.nan_to_num(after_m), thr)
            where = f"after release at frame {R}" if R is not None else "over the clip"
            parts.append(f"{where} the model keeps moving ({np.nanmean(after_m[-3:]):.1f} px/frame over the last "
                         f"frames) while the video "
                         + (f"settles in {sv_k} frames" if sv_k is not None else "slows")
                         + f" ({np.nanmean(after_v[-3:]):.1f} px/frame); damping c ~ {est.get('coefficient', 0):.2g}/s"
                         + _phases(ctx, R, video, model))
    elif effect == "viscoelasticity":
        parts.append(f"the motion decays and the shape creeps in a way a single elastic material does not "
                     f"(E_v ~ {est.get('modulus', 0):.3g} Pa, tau ~ {est.get('relaxationTime', 0):.2g} s)"
                     + _return_to_rest(video, model, R) + _phases(ctx, R, video, model))
    elif effect == "plasticity":
        iv, im = _iou(video[-1], video[0]), _iou(model[-1], model[0])
        if im - iv >= 0.03:
            parts.append(f"the object's last shape in the video overlaps its rest shape by IoU {iv:.2f} while the "
                         f"model's returns to IoU {im:.2f}: permanent deformation (yield stress ~ "
                         f"{est.get('yieldStress', 0):.3g} Pa)" + _return_to_rest(video, model, R))
        else:   # the silhouettes do not show a permanent set: say so rather than claim one
            parts.append(f"a yield stress ~ {est.get('yieldStress', 0):.3g} Pa lowers the loss, but the last shapes "
                         f"overlap the rest shape alike in the video and the model (IoU {iv:.2f} / {im:.2f}): no "
                         "permanent set is visible, so this is weak evidence for plasticity"
                         + _return_to_rest(video, model, R))
    elif effect == "ground":
        def lowest(sil):
            rows = [np.nonzero(m.any(1))[0] for m in sil]
            return np.array([r.max() if len(r) else np.nan for r in rows])
        lv, lm = lowest(video), lowest(model)
        k = int(np.nanargmax(lm - lv)) if np.isfinite(lm - lv).any() else T - 1
        parts.append(f"the lowest points stop at image row {lv[k]:.0f} in the video but reach row {lm[k]:.0f} in the "
                     f"model at frame {k} (~{(lm[k] - lv[k]) * m_per_px * 1000:.0f} mm lower): a floor at "
                     f"y ~ {est.get('height', 0):.3f} m")
    elif effect == "heterogeneity":
        c = est.get("centre", [0, 0, 0])
        f = est.get("factor", 1.0)
        parts.append(f"the part of {est.get('particles')} particles around ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) m "
                     f"moves as if {'stiffer' if f > 1 else 'softer'} than the fitted field allows "
                     f"(x{f:.2f} in E): the material field needs more freedom")
    elif effect == "interaction:timing":
        byf = _residual_by_frame(ctx)
        kpk = max(byf, key=byf.get)
        parts.append(f"the residual peaks at frame {kpk}; the {est.get('what', 'release_frame').replace('_', ' ')} of "
                     f"{est.get('contact')} at frame {est.get('was')} fits better moved toward frame "
                     f"{est.get('frame')}: re-run `{est.get('fix')}` (then fit again)")
    elif effect == "interaction:contact":
        off = np.asarray(est.get("offset_m", [0, 0, 0])) * 1000
        parts.append(f"the contact {est.get('contact')} fits better moved by ({off[0]:.0f}, {off[1]:.0f}, "
                     f"{off[2]:.0f}) mm on the object: give it with `{est.get('fix', FIXES[effect])}` (then fit "
                     "again)")
    elif effect == "interaction:grasp_size":
        parts.append(f"a {'larger' if est.get('direction') == 'more' else 'smaller'} grasp on '{est.get('contact')}' "
                     f"({est.get('particles')} particles) fits better: set it with "
                     f"`{est.get('fix', FIXES[effect])}` (then fit again)")
    elif effect == "interaction:support":
        parts.append(f"a {'larger' if est.get('direction') == 'more' else 'smaller'} support '{est.get('contact')}' "
                     f"({est.get('particles')} particles) fits better: mark it with `{FIXES[effect]}`")
    elif effect == "camera:time_offset":
        parts.append(f"the video runs {est.get('frames', 0):+.2f} frames from the model throughout: "
                     f"{FIXES[effect]}")
    elif effect == "camera:depth_scale":
        parts.append(f"the motion looks as if the scene were x{est.get('scale', 1):.2f} its assumed size "
                     f"(gravity's pull in metres is off): {FIXES[effect]}")
    pair = _pair_sentence(cr)
    conf = CONFUSABLE.get(effect)
    if pair:
        parts.append(pair)
    elif conf:
        parts.append(f"(confusable with {conf[0]}: {conf[1]})")
    return " ".join(parts)


def _pair_sentence(cr) -> str:
    """The confusable pair the test found (`CandidateResult.rivals` / `rival_of`): who, how alike
    their columns are, what separates them, and what the refit on held-back frames said."""
    others = [r for r in getattr(cr, "rivals", [])]
    if not others:
        return ""
    bits = []
    for o in others:
        hb = ""
        if cr.held_back_drop is not None and o.held_back_drop is not None:
            hb = (f"; refitted on the same held-back frames, {cr.effect} lowers their loss by {cr.held_back_drop:.3g}, "
                  f"{o.effect} by {o.held_back_drop:.3g} (beyond the base refitted alike)")
        cos = f", |cos| {o.collinearity:.2f} of what the base cannot absorb" if o.collinearity is not None else ""
        pt = getattr(cr, "pair_test", None)
        nest = (f"; {pt['why']}" if pt and set(pt["pair"]) == {cr.effect, o.effect} else "")
        bits.append(f"(confusable with {o.effect}: it explains the same residual alone{cos}; "
                    f"{separation(cr.effect, o.effect)}{hb}{nest})")
    return " ".join(bits)


def _return_to_rest(video: np.ndarray, model: np.ndarray, R: int | None) -> str:
    """After release: the video's silhouette overlap with its rest shape, from the release to the last
    frame, against the model's. A permanent set stays short of the rest shape; a slow (viscoelastic)
    return keeps closing the gap."""
    if R is None or R >= len(video) - 2:
        return ""
    iv = [_iou(video[k], video[0]) for k in range(R, len(video))]
    im = [_iou(model[k], model[0]) for k in range(R, len(model))]
    h = max(2, len(iv) // 3)
    dv = float(np.mean(iv[-h:]) - np.mean(iv[-2 * h:-h])) if len(iv) >= 2 * h else float(iv[-1] - iv[0])
    return (f"; after release the video's overlap with the rest shape goes {iv[0]:.2f} -> {iv[-1]:.2f} "
            f"({'still rising' if dv > 0 else 'level or falling'} over the last {h} frames, {dv:+.3f}; the "
            f"model's {im[0]:.2f} -> {im[-1]:.2f}): a slow return points to viscoelasticity, a level gap to "
            "a permanent set")


__all__ = ["describe", "release_frame"]
