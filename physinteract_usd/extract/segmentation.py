"""Hand (or tool) segmentation with classical computer vision.

The default `ColourMotionSegmenter` separates each frame into background, object and hand:

1. background: the per-pixel median of the video over the frames in which the pixel is free of
   the object (`render.estimate_background`), re-estimated once with the hand left out as well;
2. foreground: pixels that differ from the background by more than a threshold set from the
   noise level (a robust MAD estimate over the whole video);
3. hand candidates: foreground pixels outside the object's silhouette (visible-only masks), or,
   with amodal masks or no masks at all, foreground pixels whose colour is more likely under the
   hand's colour model than under the object's;
4. colour models: 3D RGB histograms (16 bins a channel, smoothed) of the hand (learned from the
   candidates outside the object), of the object (its silhouette pixels and the colours of its
   Gaussians) and of the background image. A candidate is kept where the hand's likelihood wins;
   this removes anti-aliased silhouette fringes, shadows and noise;
5. clean-up: morphological opening and closing, small connected components dropped.

Any segmenter with the same call signature (see `models.HandSegmenter`) can replace it, e.g. a
SAM / grounding-model pipeline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BINS = 16


@dataclass
class Segmentation:
    hand: np.ndarray          # (T, H, W) bool: hand / tool pixels (the loss leaves them out)
    object: np.ndarray        # (T, H, W) bool: visible object pixels
    background: np.ndarray    # (H, W, 3) float32
    foreground: np.ndarray    # (T, H, W) bool: anything that is not background
    noise_sigma: float        # robust per-channel noise estimate of frame - background
    threshold: float          # the foreground threshold used


def _cv2():
    import cv2

    return cv2


def _disk(r: int):
    cv2 = _cv2()
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))


def dilate(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask.astype(bool)
    return _cv2().dilate(mask.astype(np.uint8), _disk(r)) > 0


def erode(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask.astype(bool)
    return _cv2().erode(mask.astype(np.uint8), _disk(r)) > 0


def open_close(mask: np.ndarray, r_open: int = 1, r_close: int = 1) -> np.ndarray:
    cv2 = _cv2()
    m = mask.astype(np.uint8)
    if r_open > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, _disk(r_open))
    if r_close > 0:
        m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, _disk(r_close))
    return m > 0


def drop_small(mask: np.ndarray, min_area: int) -> np.ndarray:
    cv2 = _cv2()
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area
    return keep[lab]


# ------------------------------------------------------------------------------ colour models
def _bin_index(rgb: np.ndarray) -> np.ndarray:
    q = np.clip((np.asarray(rgb, np.float32) * BINS).astype(np.int32), 0, BINS - 1)
    return (q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]


def colour_histogram(rgb: np.ndarray, weights=None, smooth: float = 1.0) -> np.ndarray:
    """A normalised, smoothed (BINS^3,) colour histogram of (N, 3) colours in [0, 1]."""
    from scipy.ndimage import gaussian_filter

    idx = _bin_index(np.asarray(rgb).reshape(-1, 3))
    h = np.bincount(idx, weights=None if weights is None else np.asarray(weights).reshape(-1),
                    minlength=BINS ** 3).astype(np.float64).reshape(BINS, BINS, BINS)
    if smooth > 0:
        h = gaussian_filter(h, smooth, mode="constant")
    s = h.sum()
    return (h / s if s > 0 else np.full_like(h, 1.0 / h.size)).reshape(-1)


def likelihood(hist: np.ndarray, rgb: np.ndarray) -> np.ndarray:
    return hist[_bin_index(rgb)]


def skin_prior(rgb: np.ndarray) -> np.ndarray:
    """A generic skin test in YCrCb (the classical Cr 135..180, Cb 85..135 box), for bootstrapping
    the hand's colour model when nothing else tells the hand apart. rgb (..., 3) in [0, 1]."""
    r, g, b = (np.asarray(rgb, np.float32)[..., i] for i in range(3))
    y = 0.299 * r + 0.587 * g + 0.114 * b
    cr = (r - y) * 0.713 + 0.5
    cb = (b - y) * 0.564 + 0.5
    return (cr > 135 / 255) & (cr < 180 / 255) & (cb > 85 / 255) & (cb < 135 / 255) & (y > 0.15)


# ------------------------------------------------------------------------------ the segmenter
class ColourMotionSegmenter:
    """Background subtraction + learned colour models (see the module's doc)."""

    name = "colour-motion"

    def __init__(self, min_area_fraction: float = 8e-4, min_threshold: float = 0.05,
                 noise_factor: float = 5.0):
        self.min_area_fraction = min_area_fraction
        self.min_threshold = min_threshold
        self.noise_factor = noise_factor

    def __call__(self, frames: np.ndarray, masks: np.ndarray | None, *, masks_amodal: bool = False,
                 rest_alpha: np.ndarray | None = None, object_colors: np.ndarray | None = None) -> Segmentation:
        from ..render import estimate_background

        f = np.asarray(frames, np.float32)
        T, H, W, _ = f.shape
        min_area = max(6, int(round(self.min_area_fraction * H * W)))
        have_masks = masks is not None
        M = np.asarray(masks, bool) if have_masks else np.zeros((T, H, W), bool)
        if have_masks:
            cover = M
        elif rest_alpha is not None:
            cover = np.repeat(dilate(rest_alpha > 0.05, 2)[None], T, 0)
        else:
            cover = np.zeros((T, H, W), bool)
        # where the hand may be: outside the visible silhouette (inside too with amodal or no masks)
        outside = ~dilate_all(M, 1) if (have_masks and not masks_amodal) else np.ones((T, H, W), bool)
        skin = skin_prior(f)
        eps = 1e-6
        obj_px = [f[M]] if have_masks and M.any() else []
        if object_colors is not None and len(object_colors):
            obj_px.append(np.asarray(object_colors, np.float32).reshape(-1, 3))
        h_obj = colour_histogram(np.concatenate(obj_px)) if obj_px else None
        l_obj = np.log(likelihood(h_obj, f) + eps) if h_obj is not None else None

        # pass 0: background with the object left out; motion + a generic skin prior seed the
        # hand's colour model; pass 1: background with the hand left out too (pixels the hand
        # never leaves are inpainted from their surroundings), then motion + learned colours
        bg = estimate_background(f, cover, dilate=2)
        hand = np.zeros((T, H, W), bool)
        sigma, thr = 0.0, self.min_threshold
        for _pass in range(2):
            fg, sigma, thr = self._foreground(f, bg, cover | hand)
            seeds = fg & outside & ~dilate_all(cover, 1) if masks_amodal or not have_masks else fg & outside
            seeds = np.stack([drop_small(open_close(c, 1, 0), min_area) for c in seeds])
            core = np.stack([erode(m, 1) for m in seeds])
            if core.sum() >= max(30, 3 * min_area):
                boot = core  # the moving hand teaches its own colours
            else:
                boot = core | (outside & skin & ~dilate_all(cover, 1))  # too little motion: a skin prior
            if boot.sum() < min_area:
                hand = np.zeros((T, H, W), bool)
                break
            h_hand = colour_histogram(f[boot])
            # background colours, less the background estimate's skin-like pixels next to the
            # moving hand (where a hand that stays put has leaked into the median)
            near_hand = dilate(seeds.any(0), max(2, int(0.1 * max(H, W))))
            leak = (skin_prior(bg) & near_hand).reshape(-1)
            bg_px = bg.reshape(-1, 3)[~leak]
            h_bg = colour_histogram(bg_px if len(bg_px) else bg.reshape(-1, 3))
            lh = np.log(likelihood(h_hand, f) + eps)
            l_bg = np.log(likelihood(h_bg, f) + eps)
            # with visible masks the object is inside them: outside, a pixel is hand or background
            # (an object colour there says nothing: a fingertip as beige as the coil it presses)
            l_rest = l_bg if l_obj is None or (have_masks and not masks_amodal) else np.maximum(l_bg, l_obj)
            # motion and colour agree, or colour alone is decisive next to such pixels
            sure = outside & fg & (lh > l_rest)
            strong = outside & (lh > l_rest + 2.0)
            if l_obj is not None and (masks_amodal or not have_masks):
                strong &= lh > l_obj + 1.0
            hand = np.stack([_connected_to(sure[k] | strong[k], sure[k]) if sure[k].any() else sure[k]
                             for k in range(T)])
            hand = np.stack([drop_small(open_close(h, 1, 1), min_area) for h in hand])
            if masks_amodal or not have_masks:
                # the toucher comes in from outside the object: a blob of "hand" wholly inside the
                # object's region is the object's own colour (a pale sheet under a white glove)
                free = ~dilate_all(cover, 1)
                hand = np.stack([_connected_to(hand[k], free[k]) if hand[k].any() else hand[k] for k in range(T)])
            hand = drop_still_props(hand, seeds)
            if _pass == 1:
                # (the hand left out of the background, a hand at rest differs from it too: the
                # toucher's pieces in a frame hold pixels that differ there)
                hand = np.stack([_connected_to(hand[k], seeds[k]) for k in range(T)])
            if _pass == 0:
                bg, seen = estimate_background(f, cover | hand, dilate=2, return_seen=True)
                bg = _inpaint(bg, seen == 0)
                # a toucher that arrives and then sits still is what the median shows where it sits:
                # the background there is the side of the pixel's one lasting change that looks like
                # the background, not like the toucher or the object (what it showed before the
                # toucher arrived, or after it left)
                bg = background_across_changes(f, ~dilate_all(cover, 2), bg, thr, h_hand, h_obj, min_area=min_area)
        if have_masks:
            obj = M & ~hand
        else:
            # without silhouettes the object is the foreground that is not the hand, near where it
            # rests (the hand's own rim, its shadow or a prop elsewhere are not the object)
            obj = fg & ~hand
            if rest_alpha is not None and (rest_alpha > 0.05).any():
                ys, xs = np.nonzero(rest_alpha > 0.05)
                reach = max(3, int(round(0.2 * max(np.ptp(xs), np.ptp(ys)))))
                obj &= dilate(rest_alpha > 0.05, reach)[None]
        return Segmentation(hand=hand, object=obj, background=bg, foreground=fg, noise_sigma=sigma,
                            threshold=thr)

    def _foreground(self, f, bg, cover):
        """Foreground by a noise-scaled distance to the background (3x3 box-averaged)."""
        cv2 = _cv2()
        raw = f - bg[None]
        d = np.stack([cv2.blur(x, (3, 3)) for x in raw])
        free = ~dilate_all(cover, 2)
        vals = d[free] if free.any() else d.reshape(-1, 3)
        sig = 1.4826 * np.median(np.abs(vals - np.median(vals, 0)), 0) + 1e-4
        dist = np.abs(d).max(-1)
        thr = max(self.min_threshold, self.noise_factor * float(sig.max()))
        # the 3x3 average spreads a difference by a pixel: the pixel itself must differ too
        fg = (dist > thr) & (np.abs(raw).max(-1) > 0.5 * thr)
        fg = np.stack([open_close(x, 0, 1) for x in fg])
        return fg, float(sig.max()), thr


def step_changes(f: np.ndarray, free: np.ndarray, min_frames: int = 2):
    """Per pixel, the one lasting change of its colour over the frames in which it is `free`: the
    split (frames before t, frames from t on) that best fits its colours with two constant ones
    (least squares), each side holding at least `min_frames` free frames. f (T, H, W, 3), free
    (T, H, W) bool. Returns (before, after, step, rms): the two sides' mean colours (H, W, 3), the
    largest channel difference between them and the RMS residual of the two-colour fit (H, W);
    step 0 where no split has `min_frames` on both sides."""
    T, H, W, _ = f.shape
    w = free.astype(np.float64)[..., None]
    fw = f.astype(np.float64) * w
    S_all, Q_all, N_all = fw.sum(0), (fw * f).sum((0, 3)), w[..., 0].sum(0)
    s1 = np.zeros((H, W, 3))
    q1 = np.zeros((H, W))
    n1 = np.zeros((H, W))
    best = np.full((H, W), np.inf)
    before = np.zeros((H, W, 3))
    after = np.zeros((H, W, 3))
    for t in range(1, T):
        s1 += fw[t - 1]
        q1 += (fw[t - 1] * f[t - 1]).sum(-1)
        n1 += w[t - 1, ..., 0]
        n2 = N_all - n1
        ok = (n1 >= min_frames) & (n2 >= min_frames)
        if not ok.any():
            continue
        s2 = S_all - s1
        with np.errstate(all="ignore"):
            m1, m2 = s1 / n1[..., None], s2 / n2[..., None]
            sse = (q1 - (s1 * m1).sum(-1)) + ((Q_all - q1) - (s2 * m2).sum(-1))
        better = ok & (sse < best)
        best = np.where(better, sse, best)
        before = np.where(better[..., None], m1, before)
        after = np.where(better[..., None], m2, after)
    found = np.isfinite(best)
    step = np.where(found, np.abs(before - after).max(-1), 0.0)
    with np.errstate(all="ignore"):
        rms = np.where(found, np.sqrt(np.maximum(best, 0.0) / np.maximum(3 * N_all, 1)), np.inf)
    return before.astype(np.float32), after.astype(np.float32), step, rms


def background_across_changes(f: np.ndarray, free: np.ndarray, bg: np.ndarray, thr: float,
                              h_hand: np.ndarray, h_obj: np.ndarray | None, consistent: float = 0.25,
                              margin: float = 2.0, min_area: int = 6, eps: float = 1e-6) -> np.ndarray:
    """`bg` corrected where a pixel's colour changes once and lasts (`step_changes`: a step over the
    foreground threshold `thr`, both sides steady: RMS residual under `consistent` x the step): a
    toucher that arrives and sits still for most of the video, or one that sat still and left, is
    what the per-pixel median shows there. Of the two sides, the background is the one that looks
    more like the background's colours where nothing changes (the pixels without such a step) than
    like the toucher's (`h_hand`) or the object's (`h_obj`) colours, by at least `margin` in log
    likelihood ratio (as decisive as a colour must be to make a pixel hand alone); where the colours
    do not decide (a glove the colour of the floor, dev_9372) the median stands. Pixels whose
    background so chosen differs from `bg` by under `thr` are left as they are, and so are the
    pieces of such pixels smaller than `min_area` (a toucher that sits still covers a blob; scattered
    pixels are noise deciding: dev_0014's fingertip, whose flow at the contact they turned)."""
    before, after, step, rms = step_changes(f, free)
    changed = (step > thr) & (rms < consistent * step)
    if not changed.any():
        return bg
    steady = (~changed) & free.any(0)
    if steady.sum() < 16:
        return bg
    h_bg = colour_histogram(bg[steady])

    def score(c):
        other = likelihood(h_hand, c)
        if h_obj is not None:
            other = np.maximum(other, likelihood(h_obj, c))
        return np.log(likelihood(h_bg, c) + eps) - np.log(other + eps)

    b, a = before[changed], after[changed]
    d = score(b) - score(a)
    pick = np.where((d >= 0)[:, None], b, a)
    out = bg.copy()
    cur = out[changed]
    move = (np.abs(d) >= margin) & (np.abs(pick - cur).max(-1) > thr)
    where = np.zeros(changed.shape, bool)
    where[changed] = move
    where = drop_small(open_close(where, 1, 0), min_area)
    move &= where[changed]
    cur[move] = pick[move]
    out[changed] = cur
    return out.astype(np.float32)


def drop_still_props(hand: np.ndarray, seeds: np.ndarray, share: float = 0.5) -> np.ndarray:
    """`hand` (T, H, W) less the places that are "hand" in most frames (`share`) but never
    meet the moving toucher (`seeds`, its moving pixels, in any frame): a prop of the hand's colour
    that stays put (a brown post the object hangs on, joined to the hand through the object's
    moving rim) is background. A hand that rests in one place is kept: it moved there, next to
    where it rests. `fixed_pieces` are dropped too (a fixed thing the toucher passes over later)."""
    cv2 = _cv2()
    still = hand.mean(0) >= share
    if not still.any():
        return hand
    n, lab = cv2.connectedComponents(still.astype(np.uint8), connectivity=8)
    met = np.unique(lab[dilate(seeds.any(0), 2) & still])
    drop = still & ~np.isin(lab, met)
    drop |= fixed_pieces(hand)
    return hand & ~drop[None] if drop.any() else hand


def fixed_pieces(hand: np.ndarray, presence: float = 0.9) -> np.ndarray:
    """(H, W) the pieces of the first frame's "hand" that are not its largest piece and are "hand" in nearly every
    frame (`presence`): a fixed thing of the hand's colour apart from the toucher when the video starts (#23: dev_0542's
    drawn support's foot beside the ring, which the toucher passes over later, so `drop_still_props` kept it and the
    grasp was read at frame 0). A hand resting from the first frame is its largest piece and stays."""
    cv2 = _cv2()
    n0, lab0 = cv2.connectedComponents(hand[0].astype(np.uint8), connectivity=8)
    out = np.zeros(hand.shape[1:], bool)
    if n0 <= 2:
        return out
    area = np.bincount(lab0.ravel(), minlength=n0)
    main = 1 + int(np.argmax(area[1:]))
    here = hand.mean(0)
    for q in range(1, n0):
        piece = lab0 == q
        if q != main and here[piece].mean() >= presence:
            out |= piece
    return out


def _inpaint(img: np.ndarray, holes: np.ndarray) -> np.ndarray:
    if not holes.any():
        return img
    cv2 = _cv2()
    u8 = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    out = cv2.inpaint(u8, holes.astype(np.uint8), 5, cv2.INPAINT_TELEA).astype(np.float32) / 255.0
    return np.where(holes[..., None], out, img).astype(np.float32)


def dilate_all(masks: np.ndarray | None, r: int) -> np.ndarray | None:
    if masks is None:
        return None
    return np.stack([dilate(m, r) for m in masks])


def _connected_to(mask: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The components of `mask` that contain a pixel of `seed`."""
    cv2 = _cv2()
    n, lab = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, bool)
    keep[np.unique(lab[seed & mask])] = True
    keep[0] = False
    return keep[lab]
