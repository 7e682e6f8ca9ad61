"""Contact sheet of a synthetic capture: frames with the silhouette outline, the hand mask, the
contact trajectory and the unseen supports drawn on them."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def contact_sheet(out_dir, rgb, masks, hand_masks, cam, gt, path, n_tiles: int = 8, scale: int = 2) -> Path:
    import cv2

    T = len(rgb)
    ks = np.unique(np.linspace(0, T - 1, min(n_tiles, T)).round().astype(int))
    tiles = []
    traj_uv, _ = cam.project(gt.trajectory)
    sup_uv, _ = cam.project(gt.x0[gt.fixed_indices])
    for k in ks:
        img = (np.clip(rgb[k], 0, 1) * 255).astype(np.uint8)[:, :, ::-1].copy()
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        for m, colour in ((masks[k], (255, 255, 0)), (hand_masks[k], (0, 0, 255))):
            mm = cv2.resize(m.astype(np.uint8), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            cnts, _ = cv2.findContours(mm, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
            cv2.drawContours(img, cnts, -1, colour, 1)
        for u, v in sup_uv[:: max(1, len(sup_uv) // 30)]:
            cv2.circle(img, (int(u * scale), int(v * scale)), 1, (255, 0, 255), -1)
        pts = (traj_uv * scale).astype(np.int32)
        cv2.polylines(img, [pts[: k + 1]], False, (0, 255, 0), 1)
        cv2.circle(img, tuple(int(c) for c in pts[min(k, len(pts) - 1)]), 3, (0, 255, 0), 1)
        cv2.putText(img, f"{k}", (3, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1)
        tiles.append(img)
    cols = 4
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + cols], 1) for i in range(0, len(tiles), cols)]
    sheet = np.concatenate(rows, 0)
    cv2.imwrite(str(path), sheet)
    return Path(path)
