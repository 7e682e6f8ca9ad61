"""A synthetic capture's ground truth, `DIR/gt/` (never read by init, extract or fit): its writer and
its readers, side by side.

```
gt/gt.json                 scene, sizes, interaction (type, contact point and radius, grasp and
                           release frames, trajectory per frame, collider radius, plane normal,
                           friction), supports (centre, radius), hidden effect, noise, suggested init
gt/youngs_modulus.npy      (N,) E per Gaussian, input PLY order
gt/poisson_ratio.npy       (N,)
gt/gaussian_positions.npy  (T, N, 3) the Gaussians' centres per frame
gt/particles.npz           the ground-truth simulation's particles (rest, E, nu, volume, positions)
gt/hand_masks/, gt/amodal_masks/   per-frame PNGs
```
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..contacts import ContactSet
from ..errors import InputError
from ..frames import write_mask


def write_ground_truth(out_dir, info: dict, youngs: np.ndarray, poisson: np.ndarray, gaussian_positions: np.ndarray,
                       particles: dict, hand_masks, amodal_masks) -> None:
    """Write `out_dir/gt/` (see the module doc)."""
    gt = Path(out_dir) / "gt"
    for sub in ("hand_masks", "amodal_masks"):
        (gt / sub).mkdir(parents=True, exist_ok=True)
    for k in range(len(hand_masks)):
        write_mask(gt / "hand_masks" / f"{k:06d}.png", hand_masks[k])
        write_mask(gt / "amodal_masks" / f"{k:06d}.png", amodal_masks[k])
    np.save(gt / "youngs_modulus.npy", np.asarray(youngs, np.float32))
    np.save(gt / "poisson_ratio.npy", np.asarray(poisson, np.float32))
    np.save(gt / "gaussian_positions.npy", np.asarray(gaussian_positions, np.float32))
    np.savez_compressed(gt / "particles.npz", **particles)
    (gt / "gt.json").write_text(json.dumps(info, indent=1))


def read_ground_truth(gt_dir) -> dict:
    """gt/gt.json as a dict (InputError naming the file when it is not a synth capture's gt/)."""
    p = Path(gt_dir) / "gt.json"
    if not p.exists():
        raise InputError(p, "file not found (is this a synth capture's gt/ folder?)")
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(p, f"not valid JSON ({exc})") from None


def read_gt_array(gt_dir, name: str) -> np.ndarray:
    """One of the gt/*.npy arrays, float64 (InputError naming the file when missing)."""
    p = Path(gt_dir) / name
    if not p.exists():
        raise InputError(p, "file not found (is this a synth capture's gt/ folder?)")
    try:
        a = np.load(p, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(p, f"not a readable .npy array ({str(exc).split('.')[0]})") from None
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(p, f"holds {a.dtype} values, not numbers")
    return a.astype(np.float64)


def read_gt_contacts(gt_dir, x0: np.ndarray, n_frames: int) -> list[ContactSet]:
    """The true interaction, supports and T0 as contact sets over the stage's particles `x0`: the
    grasp holds the particles within the true contact radius (at least 3), the supports the
    particles inside their spheres (less the grasped ones). Source "groundTruth"."""
    g = read_ground_truth(gt_dir)
    it = g["interaction"]
    x0 = np.asarray(x0, np.float64)
    traj = np.asarray(it["trajectory"], np.float64)
    if len(traj) != n_frames:
        raise InputError(Path(gt_dir) / "gt.json", f"trajectory has {len(traj)} frames, the stage {n_frames}")
    cp = np.asarray(it["contact_point"], np.float64)
    src = "groundTruth"
    if it["type"] == "pointAdherent":
        d = np.linalg.norm(x0 - cp, axis=1)
        idx = np.where(d < it["contact_radius"])[0]
        if len(idx) < 3:
            idx = np.argsort(d)[:3]
        inter = ContactSet("hand", "pointAdherent", idx, it["grasp_frame"], it["release_frame"], traj, source=src)
    elif it["type"] == "pointNonAdherent":
        inter = ContactSet("finger", "pointNonAdherent", grasp_frame=it["grasp_frame"],
                           release_frame=it.get("release_frame"), trajectory=traj, radius=it["collider_radius"],
                           friction=it.get("friction", 0.5), contact_point=cp, source=src)
    else:
        inter = ContactSet("palm", "surfaceNonAdherent", grasp_frame=it["grasp_frame"],
                           release_frame=it.get("release_frame"), trajectory=traj, normal=tuple(it["plane_normal"]),
                           friction=it.get("friction", 0.5), contact_point=cp, source=src)
    fixed = np.zeros(len(x0), bool)
    for s in g["supports"]:
        fixed |= np.linalg.norm(x0 - np.asarray(s["centre"]), axis=1) < s["radius"]
    if inter.type == "pointAdherent":
        fixed[inter.indices] = False
    out = [inter]
    if fixed.any():
        out.append(ContactSet("support", "fixed", np.where(fixed)[0], source=src))
    return out
