"""The extraction preview: frames with the detected hand, the contact, the supports and the track
drawn on them (a BGR uint8 image; `usd.extract_io` writes it as <stem>.extract/preview.png)."""

from __future__ import annotations

import numpy as np

COL_HAND = (60, 60, 255)      # BGR
COL_OBJECT = (255, 255, 0)
COL_CONTACT = (0, 255, 0)
COL_SUPPORT = (255, 0, 255)
COL_TRACK = (0, 220, 255)


def preview_image(result, scene, n_tiles: int = 8, cols: int = 4) -> np.ndarray:
    import cv2

    frames = result.frames
    T, H, W = frames.shape[:3]
    s = max(1, int(np.ceil(256 / W)))
    key = [0, result.grasp_frame, result.release_frame if result.release_frame is not None else T - 1, T - 1]
    ks = sorted(set([int(k) for k in np.linspace(0, T - 1, n_tiles).round()] + [k for k in key if 0 <= k < T]))
    while len(ks) > n_tiles:  # drop evenly spaced frames that are not key frames
        extra = [k for k in ks if k not in key]
        if not extra:
            break
        ks.remove(extra[len(extra) // 2])
    x0 = scene.particles_positions
    inter = result.interaction[0] if result.interaction else None
    sup_idx = np.concatenate([c.indices for c in result.supports]) if result.supports else np.zeros(0, int)
    tiles = []
    for k in ks:
        cam = scene.camera.at(k)
        img = (np.clip(frames[k], 0, 1) * 255 + 0.5).astype(np.uint8)[:, :, ::-1].copy()
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
        for m, col in ((result.object_masks[k] if result.object_masks is not None else None, COL_OBJECT),
                       (result.hand_masks[k], COL_HAND)):
            if m is None or not m.any():
                continue
            mm = cv2.resize(m.astype(np.uint8), None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
            cnts, _ = cv2.findContours(mm, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, cnts, -1, col, 1)
        if len(sup_idx):
            uv, _ = cam.project(x0[sup_idx])
            for u, v in uv[:: max(1, len(uv) // 60)]:
                if np.isfinite(u) and np.isfinite(v):
                    cv2.circle(img, (int(u * s), int(v * s)), max(1, s // 2), COL_SUPPORT, -1)
        if inter is not None:
            if len(inter.indices) and k <= result.grasp_frame:
                uv, _ = cam.project(x0[inter.indices])
                for u, v in uv:
                    cv2.circle(img, (int(u * s), int(v * s)), max(1, s // 2), COL_CONTACT, -1)
            if result.track_uv is not None:
                pts = (result.track_uv[: k + 1] * s).astype(np.int32)
                if len(pts) > 1:
                    cv2.polylines(img, [pts], False, COL_TRACK, 1)
                cv2.circle(img, tuple(int(c) for c in pts[-1]), 2 * s, COL_CONTACT, 1)
            if inter.trajectory is not None:
                uv, _ = cam.project(inter.trajectory[k][None])
                if np.isfinite(uv).all():
                    cv2.drawMarker(img, (int(uv[0, 0] * s), int(uv[0, 1] * s)), COL_TRACK, cv2.MARKER_CROSS, 3 * s, 1)
        label = f"{k}"
        if k == result.grasp_frame:
            label += " grasp"
        if result.release_frame is not None and k == result.release_frame:
            label += " release"
        cv2.putText(img, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3)
        cv2.putText(img, label, (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
        tiles.append(img)
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    sheet = np.concatenate([np.concatenate(tiles[i:i + cols], 1) for i in range(0, len(tiles), cols)], 0)
    head = np.full((40, sheet.shape[1], 3), 32, np.uint8)
    rel = "none" if result.release_frame is None else str(result.release_frame)
    n_sup = sum(len(c.indices) for c in result.supports)
    line1 = (f"{result.interaction_type} ({result.type_source}), grasp {result.grasp_frame}, release {rel}; "
             f"{len(result.supports)} support set(s), {n_sup} particles")
    line2 = "red: hand   cyan: object   green: contact   yellow: track / T0   magenta: supports"
    cv2.putText(head, line1, (4, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (255, 255, 255), 1)
    cv2.putText(head, line2, (4, 33), cv2.FONT_HERSHEY_SIMPLEX, 0.38, (200, 200, 200), 1)
    return np.concatenate([head, sheet], 0)
