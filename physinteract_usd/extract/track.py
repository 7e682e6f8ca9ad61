"""2D motion: dense optical flow between consecutive frames (OpenCV DIS, or Farneback where DIS
is missing) and point tracks chained through it with a forward-backward check.

Small frames are upsampled before the flow (the flow's patches need a few dozen pixels of
texture); flows come back in the frames' own pixel units. Any tracker with `flows(frames)` and
`track(flows, points, start)` (see `models.PointTracker`) can replace it, e.g. a learned point
tracker.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import sample


@dataclass
class Flows:
    forward: np.ndarray    # (T-1, H, W, 2): frame k -> k+1, (du, dv) in pixels
    backward: np.ndarray   # (T-1, H, W, 2): frame k+1 -> k
    images: np.ndarray | None = None  # (T, H, W, 3) 3x3-smoothed frames: the appearance check
    noise: float = 0.0     # per-channel noise of the smoothed frames (for the appearance check)
    grays: list | None = None  # the (upsampled) grey frames the flow was computed on
    scale: float = 1.0


@dataclass
class Tracks:
    uv: np.ndarray         # (T, N, 2) positions (nan before the start frame and once lost)
    valid: np.ndarray      # (T, N) bool
    start: int


def _gray(frame: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(frame, np.float32) @ np.array([0.299, 0.587, 0.114], np.float32) * 255 + 0.5,
                   0, 255).astype(np.uint8)


class DenseFlowTracker:
    """DIS optical flow (OpenCV) between consecutive frames, chained into point tracks."""

    name = "dis-flow"

    def __init__(self, min_width: int = 384, fb_tolerance: float = 1.0, appearance_tolerance: float = 0.12):
        self.min_width = min_width
        self.fb_tolerance = fb_tolerance
        self.appearance_tolerance = appearance_tolerance

    def _flow(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        import cv2

        if hasattr(cv2, "DISOpticalFlow_create"):
            dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
            dis.setUseSpatialPropagation(True)
            return dis.calc(a, b, None)
        return cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 4, 15, 5, 5, 1.1, 0)

    def flows(self, frames: np.ndarray) -> Flows:
        import cv2

        T, H, W = frames.shape[:3]
        s = max(1.0, self.min_width / W)
        size = (int(round(W * s)), int(round(H * s)))
        grays = []
        for f in frames:
            g = _gray(f)
            if s > 1:
                g = cv2.resize(g, size, interpolation=cv2.INTER_CUBIC)
            grays.append(g)
        fw, bw = [], []
        for k in range(T - 1):
            for dst, (a, b) in ((fw, (grays[k], grays[k + 1])), (bw, (grays[k + 1], grays[k]))):
                fl = self._flow(a, b)
                if s > 1:
                    fl = cv2.resize(fl, (W, H), interpolation=cv2.INTER_AREA) / s
                dst.append(fl.astype(np.float32))
        empty = np.zeros((0, H, W, 2), np.float32)
        smooth = np.stack([cv2.blur(np.asarray(f, np.float32), (3, 3)) for f in frames])
        if T > 1:
            d = (smooth[1:] - smooth[:-1]).reshape(-1, 3)
            noise = float(1.4826 * np.median(np.abs(d - np.median(d, 0))) / np.sqrt(2))
        else:
            noise = 0.0
        return Flows(np.stack(fw) if fw else empty, np.stack(bw) if bw else empty, smooth, noise, grays, s)

    def track(self, flows: Flows, points: np.ndarray, start: int = 0, stop: np.ndarray | None = None) -> Tracks:
        """Chain the flow from frame `start` forward and backward. `stop` (T, H, W) bool: a point
        that lands on a true pixel (e.g. the hand covering it) is lost from then on."""
        n_pairs = len(flows.forward)
        T = n_pairs + 1
        pts = np.asarray(points, np.float64).reshape(-1, 2)
        N = len(pts)
        uv = np.full((T, N, 2), np.nan)
        valid = np.zeros((T, N), bool)
        uv[start] = pts
        valid[start] = True
        if stop is not None:
            valid[start] &= ~sample(stop[start].astype(np.float32), pts, order=0).astype(bool)
        H, W = flows.forward.shape[1:3] if n_pairs else (1, 1)
        ref = sample(flows.images[start], pts) if flows.images is not None else None
        tol = self.appearance_tolerance + 4.0 * flows.noise
        for direction in (1, -1):
            cur = pts.copy()
            ok = valid[start].copy()
            k = start
            while 0 <= k + direction < T and ok.any():
                if direction == 1:
                    f_a, f_b = flows.forward[k], flows.backward[k]
                else:
                    f_a, f_b = flows.backward[k - 1], flows.forward[k - 1]
                d = sample(f_a, cur)
                nxt = cur + d
                back = sample(f_b, nxt)
                fb = np.linalg.norm(d + back, axis=1)
                inside = (nxt[:, 0] >= 0) & (nxt[:, 0] < W) & (nxt[:, 1] >= 0) & (nxt[:, 1] < H)
                ok = ok & inside & (fb < self.fb_tolerance + 0.1 * np.linalg.norm(d, axis=1))
                k += direction
                if stop is not None:
                    ok &= ~sample(stop[k].astype(np.float32), nxt, order=0).astype(bool)
                if ref is not None:
                    # the point should still look like itself: occluded points (by the hand or
                    # another part of the object) are lost
                    ok &= np.abs(sample(flows.images[k], np.clip(nxt, 0, [W - 1e-3, H - 1e-3])) - ref).max(1) <= tol
                cur = nxt
                uv[k][ok] = cur[ok]
                valid[k] = ok
        return Tracks(uv, valid, start)


def direct_displacements(tracker: DenseFlowTracker, flows: Flows, points: np.ndarray, start: int = 0,
                         stop: np.ndarray | None = None) -> Tracks:
    """Displacements of points from frame `start` straight to every frame (flow start -> k, no
    chaining, so no drift: the right measure of small motions), forward-backward and appearance
    checked; a point is invalid where the check fails (large motions: use the chained tracks)."""
    import cv2

    T = len(flows.grays)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    H, W = flows.images.shape[1:3]
    uv = np.full((T, len(pts), 2), np.nan)
    valid = np.zeros((T, len(pts)), bool)
    uv[start] = pts
    valid[start] = True
    ref = sample(flows.images[start], pts)
    tol = tracker.appearance_tolerance + 4.0 * flows.noise
    s = flows.scale
    for k in range(T):
        if k == start:
            continue
        f = tracker._flow(flows.grays[start], flows.grays[k])
        b = tracker._flow(flows.grays[k], flows.grays[start])
        if s > 1:
            f = cv2.resize(f, (W, H), interpolation=cv2.INTER_AREA) / s
            b = cv2.resize(b, (W, H), interpolation=cv2.INTER_AREA) / s
        d = sample(f, pts)
        nxt = pts + d
        fb = np.linalg.norm(d + sample(b, nxt), axis=1)
        ok = fb < tracker.fb_tolerance + 0.1 * np.linalg.norm(d, axis=1)
        ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] < W) & (nxt[:, 1] >= 0) & (nxt[:, 1] < H)
        ok &= np.abs(sample(flows.images[k], np.clip(nxt, 0, [W - 1e-3, H - 1e-3])) - ref).max(1) <= tol
        if stop is not None:
            ok &= ~sample(stop[k].astype(np.float32), nxt, order=0).astype(bool)
        uv[k][ok] = nxt[ok]
        valid[k] = ok
    return Tracks(uv, valid, start)


def median_flow(flow: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """The median (du, dv) of a flow field over a mask; None for an empty mask."""
    if not mask.any():
        return None
    return np.median(flow[mask], axis=0)


@dataclass
class MeasuredTracks:
    """Point tracks measured on a video (`measure_tracks`)."""

    uv: np.ndarray         # (T, N, 2) positions (nan where lost)
    valid: np.ndarray      # (T, N) bool
    fb_error: np.ndarray   # (T, N) forward-backward disagreement in pixels (nan where lost): the
                           # tracker's own inconsistency, a measure of its noise
    direct: np.ndarray     # (T, N) bool: measured by the flow start -> k itself (no chaining)
    start: int


def measure_tracks(frames: np.ndarray, points: np.ndarray, *, start: int = 0, stop: np.ndarray | None = None,
                   tracker: DenseFlowTracker | None = None, flows: Flows | None = None,
                   progress=None) -> MeasuredTracks:
    """Track `points` ((N, 2) pixel coordinates in frame `start`) through `frames` ((T, H, W, 3)
    float in [0, 1]): each point's position in frame k measured straight by the flow start -> k
    (no drift) where that passes the forward-backward and appearance checks, else by the flow
    chained through the frames between (`DenseFlowTracker.track`); lost points are nan / invalid.
    `stop` (T, H, W) bool: pixels that hide the object (the hand); a point on them is lost there.
    `progress`: a callable wrapping an iterable (e.g. tqdm) for the per-frame loop.

    The measurement the report compares the model's projected Gaussians with (and a fit may use
    as a loss term)."""
    import cv2

    tracker = tracker or DenseFlowTracker()
    flows = flows if flows is not None else tracker.flows(frames)
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    T = len(flows.grays)
    H, W = flows.images.shape[1:3]
    chained = tracker.track(flows, pts, start, stop)
    uv = np.full((T, len(pts), 2), np.nan)
    valid = np.zeros((T, len(pts)), bool)
    fb_err = np.full((T, len(pts)), np.nan)
    direct = np.zeros((T, len(pts)), bool)
    uv[start], valid[start], fb_err[start], direct[start] = pts, True, 0.0, True
    if stop is not None:
        valid[start] &= ~sample(stop[start].astype(np.float32), pts, order=0).astype(bool)
    ref = sample(flows.images[start], pts)
    tol = tracker.appearance_tolerance + 4.0 * flows.noise
    s = flows.scale
    ks = [k for k in range(T) if k != start]
    for k in (progress(ks) if progress else ks):
        f = tracker._flow(flows.grays[start], flows.grays[k])
        b = tracker._flow(flows.grays[k], flows.grays[start])
        if s > 1:
            f = cv2.resize(f, (W, H), interpolation=cv2.INTER_AREA) / s
            b = cv2.resize(b, (W, H), interpolation=cv2.INTER_AREA) / s
        d = sample(f, pts)
        nxt = pts + d
        fb = np.linalg.norm(d + sample(b, nxt), axis=1)
        ok = valid[start] & (fb < tracker.fb_tolerance + 0.1 * np.linalg.norm(d, axis=1))
        ok &= (nxt[:, 0] >= 0) & (nxt[:, 0] < W) & (nxt[:, 1] >= 0) & (nxt[:, 1] < H)
        ok &= np.abs(sample(flows.images[k], np.clip(nxt, 0, [W - 1e-3, H - 1e-3])) - ref).max(1) <= tol
        if stop is not None:
            ok &= ~sample(stop[k].astype(np.float32), nxt, order=0).astype(bool)
        uv[k][ok], fb_err[k][ok], direct[k][ok] = nxt[ok], fb[ok], True
        # where the straight flow fails (large motion, occlusion on the way back), the chain may hold
        ch = ~ok & chained.valid[k]
        if ch.any():
            cu = chained.uv[k][ch]
            fb_err[k][ch] = np.linalg.norm(cu + sample(b, cu) - pts[ch], axis=1)
            uv[k][ch] = cu
            ok = ok | ch
        valid[k] = ok
    return MeasuredTracks(uv, valid, fb_err, direct, start)
