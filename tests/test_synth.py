"""The synthetic suite (physinteract_usd.synth): every scene generates a complete capture folder,
its ground truth projects into its own masks through transforms.json alone (cv2, not our camera
code), the material fields vary in space, hidden effects are recorded and change the frames, and
generation is repeatable. `-m slow` adds the paper-size smoke test (every scene, 3 frames)."""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from physinteract_usd.synth import SCENES, generate, list_scenes
from physinteract_usd.synth.outdir import WRITING

SMALL_FRAMES = 3          # frames per scene in the fast tests (rest frame + 2 simulated)
PROJECTION_MIN_SHARE = 0.98
ALL = sorted(SCENES)


# ------------------------------------------------------------------------------ helpers
def read_mask(path: Path) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert m is not None, path
    if m.ndim == 3:
        m = m[..., 0]
    return m > 127


def project_transforms(points: np.ndarray, transforms: dict) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) and camera depths (N,) of world points, from transforms.json only
    (nerfstudio: camera-to-world with OpenGL axes x right, y up, z back), through cv2.projectPoints."""
    c2w = np.asarray(transforms["transform_matrix"], dtype=np.float64)
    c2w_cv = c2w @ np.diag([1.0, -1.0, -1.0, 1.0])          # OpenGL -> OpenCV camera axes
    w2c = np.linalg.inv(c2w_cv)
    R, t = w2c[:3, :3], w2c[:3, 3]
    K = np.array([[transforms["fl_x"], 0.0, transforms["cx"]],
                  [0.0, transforms["fl_y"], transforms["cy"]],
                  [0.0, 0.0, 1.0]])
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(np.asarray(points, np.float64).reshape(-1, 1, 3), rvec, t, K, np.zeros(5))
    depth = np.asarray(points, np.float64) @ R.T[:, 2] + t[2]
    return uv.reshape(-1, 2), depth


def share_in_mask(points: np.ndarray, transforms: dict, mask: np.ndarray, ignore: np.ndarray | None = None) -> float:
    """The share of points in front of the camera whose pixel (through transforms.json) is in
    `mask`; points whose pixel is in `ignore` (and not in `mask`) are left out."""
    H, W = mask.shape
    uv, z = project_transforms(points, transforms)
    # pixel (i, j) covers [i, i+1) x [j, j+1): its centre is at (i + 0.5, j + 0.5)
    col = np.floor(uv[:, 0]).astype(int)
    row = np.floor(uv[:, 1]).astype(int)
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    c, r = np.clip(col, 0, W - 1), np.clip(row, 0, H - 1)
    hit = inside & mask[r, c]
    counted = np.ones(len(hit), bool) if ignore is None else ~(inside & ~mask[r, c] & ignore[r, c])
    return float(hit[counted].mean()) if counted.any() else 1.0


def projection_shares(out: Path, amodal: bool = False) -> list[float]:
    """Per frame: the share of ground-truth Gaussian centres (gt/gaussian_positions.npy) that land,
    through transforms.json, in the object's mask dilated by a pixel, leaving out those the hand
    hides (gt/hand_masks: masks/ holds visible silhouettes, so the hand's pixels are not object).
    amodal: against gt/amodal_masks (the object's whole silhouette), every point counted."""
    tr = json.loads((out / "transforms.json").read_text())
    W, H = int(tr["w"]), int(tr["h"])
    pos = np.load(out / "gt" / "gaussian_positions.npy")
    kernel = np.ones((3, 3), np.uint8)
    shares = []
    for k in range(len(pos)):
        obj = read_mask(out / ("gt/amodal_masks" if amodal else "masks") / f"{k:06d}.png")
        hand = None if amodal else read_mask(out / "gt" / "hand_masks" / f"{k:06d}.png")
        assert obj.shape == (H, W)
        _, z = project_transforms(pos[k], tr)
        assert np.all(z > 0), f"frame {k}: ground-truth points behind the camera"
        obj = cv2.dilate(obj.astype(np.uint8), kernel) > 0
        shares.append(share_in_mask(pos[k], tr, obj, hand))
    return shares


def check_capture_folder(out: Path, name: str, n_frames: int) -> dict:
    for f in ("object.ply", "transforms.json", "README.txt", "preview.png", "gt/gt.json",
              "gt/youngs_modulus.npy", "gt/poisson_ratio.npy", "gt/gaussian_positions.npy", "gt/particles.npz"):
        assert (out / f).is_file(), f"{name}: {f} missing"
    for sub in ("frames", "masks", "gt/hand_masks", "gt/amodal_masks"):
        files = sorted((out / sub).glob("*.png"))
        assert [p.name for p in files] == [f"{k:06d}.png" for k in range(n_frames)], f"{name}: {sub}"
    assert not (out / WRITING).exists(), f"{name}: the generator's writing marker left behind"
    info = json.loads((out / "gt" / "gt.json").read_text())
    assert info["scene"] == name and info["n_frames"] == n_frames
    tr = json.loads((out / "transforms.json").read_text())
    for key in ("fl_x", "fl_y", "cx", "cy", "w", "h", "fps", "transform_matrix"):
        assert key in tr, f"{name}: transforms.json lacks {key}"
    frame0 = cv2.imread(str(out / "frames" / "000000.png"))
    assert frame0.shape == (tr["h"], tr["w"], 3)
    assert cv2.imread(str(out / "preview.png")) is not None

    from physinteract_usd.gaussians import read_ply

    g = read_ply(out / "object.ply")
    E = np.load(out / "gt" / "youngs_modulus.npy")
    nu = np.load(out / "gt" / "poisson_ratio.npy")
    pos = np.load(out / "gt" / "gaussian_positions.npy")
    assert E.shape == nu.shape == (len(g),)
    assert pos.shape == (n_frames, len(g), 3) and np.all(np.isfinite(pos))
    # frame 0 is the object file's pose, at rest
    np.testing.assert_allclose(pos[0], g.means, atol=1e-5)
    p = np.load(out / "gt" / "particles.npz")
    assert p["positions"].shape == (n_frames,) + p["rest"].shape
    assert np.all(np.isfinite(p["positions"]))
    assert len(p["E"]) == len(p["nu"]) == len(p["volume"]) == len(p["rest"])
    # every mask has object pixels, and the visible object never overlaps the hand
    for k in range(n_frames):
        m = read_mask(out / "masks" / f"{k:06d}.png")
        h = read_mask(out / "gt" / "hand_masks" / f"{k:06d}.png")
        assert m.sum() > 20, f"{name}: frame {k} mask nearly empty"
        assert not np.any(m & h), f"{name}: frame {k} visible mask overlaps the hand"
    return info


def check_material(info: dict, out: Path, name: str) -> float:
    E = np.load(out / "gt" / "youngs_modulus.npy")
    nu = np.load(out / "gt" / "poisson_ratio.npy")
    assert np.all(E > 0) and np.all(np.isfinite(E))
    assert np.all((nu > 0) & (nu < 0.5)), f"{name}: Poisson ratio outside (0, 0.5)"
    ratio = float(E.max() / E.min())
    assert info["youngs_modulus"]["range"] == pytest.approx(ratio, rel=1e-5)
    p = np.load(out / "gt" / "particles.npz")
    assert np.all((p["nu"] > 0) & (p["nu"] < 0.5))
    return ratio


# ------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """Every scene at small size, SMALL_FRAMES frames: name -> (folder, gt.json, seconds)."""
    root = tmp_path_factory.mktemp("synth_small")
    done = {}
    for name in ALL:
        t0 = time.perf_counter()
        info = generate(name, root / name, size="small", frames=SMALL_FRAMES, log=lambda *a: None)
        done[name] = (root / name, info, time.perf_counter() - t0)
    print("\nsmall generation: " + ", ".join(f"{n} {s:.1f}s" for n, (_, _, s) in done.items()))
    return done


# ------------------------------------------------------------------------------ tests
def test_list_has_every_scene():
    names = [n for n, *_ in list_scenes()]
    assert sorted(names) == ALL and len(names) == 12
    assert all(kind in ("pointAdherent", "pointNonAdherent", "surfaceNonAdherent") for _, _, kind, _ in list_scenes())


@pytest.mark.parametrize("name", ALL)
def test_scene_writes_capture_folder(small, name):
    out, info, _ = small[name]
    got = check_capture_folder(out, name, SMALL_FRAMES)
    assert got == json.loads(json.dumps(info))
    assert got["hidden_effect"] is None
    assert got["interaction"]["type"] == SCENES[name].interaction


@pytest.mark.parametrize("name", ALL)
def test_ground_truth_projects_into_masks(small, name):
    """Independent of our camera code: cv2.projectPoints from transforms.json only."""
    out, _, _ = small[name]
    shares = projection_shares(out)
    amodal = projection_shares(out, amodal=True)
    worst = int(np.argmin(shares))
    print(f"{name}: worst frame {worst}: {shares[worst]:.4f} of the Gaussians inside the visible mask; "
          f"amodal worst {min(amodal):.4f}")
    assert min(shares) >= PROJECTION_MIN_SHARE, (name, shares)
    assert min(amodal) >= PROJECTION_MIN_SHARE, (name, amodal)


def test_projection_check_catches_camera_convention_errors(small):
    """The projection check is not vacuous: the same capture read with a wrong convention fails it
    (camera-to-world taken as OpenCV axes, its rotation transposed, the image upside down)."""
    out, _, _ = small["flower"]
    tr = json.loads((out / "transforms.json").read_text())
    pos = np.load(out / "gt" / "gaussian_positions.npy")[0]
    obj = cv2.dilate(read_mask(out / "gt" / "amodal_masks" / "000000.png").astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert share_in_mask(pos, tr, obj) >= PROJECTION_MIN_SHARE
    c2w = np.asarray(tr["transform_matrix"])
    transposed = c2w.copy()
    transposed[:3, :3] = c2w[:3, :3].T
    for bad in (c2w @ np.diag([1.0, -1.0, -1.0, 1.0]), transposed):
        assert share_in_mask(pos, {**tr, "transform_matrix": bad.tolist()}, obj) < 0.7
    assert share_in_mask(pos, tr, obj[::-1]) < 0.7


@pytest.mark.parametrize("name", ALL)
def test_material_is_spatially_varying(small, name):
    out, info, _ = small[name]
    ratio = check_material(info, out, name)
    # every scene's field spans 5x (docs/synth.md): a stiff part and soft ones
    assert ratio >= 4.9, f"{name}: E max/min = {ratio:.2f}"   # graded fields: the surface stops short of the ends


def test_hidden_effect_recorded_and_visible(small, tmp_path):
    """damping at strength 1 is recorded in gt.json and moves the frames away from the control's
    (the small fixture's tow_rope: same seed, same frames; tow_rope is the cheapest to simulate)."""
    ctl_dir, ctl, _ = small["tow_rope"]
    hid = generate("tow_rope", tmp_path / "damped", size="small", frames=SMALL_FRAMES, hidden="damping",
                   strength=1.0, log=lambda *a: None)
    assert ctl["hidden_effect"] is None
    eff = hid["hidden_effect"]
    assert eff["name"] == "damping" and eff["strength"] == 1.0
    assert eff["parameters"]["coefficient"] > 0
    assert eff["effect_px"] > 0.1
    on_disk = json.loads((tmp_path / "damped" / "gt" / "gt.json").read_text())["hidden_effect"]
    assert on_disk == json.loads(json.dumps(eff))
    # same object, same start; later ground truth and frames differ measurably
    a = np.load(ctl_dir / "gt" / "gaussian_positions.npy")
    b = np.load(tmp_path / "damped" / "gt" / "gaussian_positions.npy")
    np.testing.assert_array_equal(a[0], b[0])
    assert np.abs(a[-1] - b[-1]).max() > 1e-3       # metres
    last = f"{SMALL_FRAMES - 1:06d}.png"
    fa = cv2.imread(str(ctl_dir / "frames" / last)).astype(float)
    fb = cv2.imread(str(tmp_path / "damped" / "frames" / last)).astype(float)
    assert np.abs(fa - fb).max() > 20 and np.abs(fa - fb).mean() > 0.05


def test_same_seed_same_frames(small, tmp_path):
    out, _, _ = small["tow_rope"]
    # a generator stopped while writing left a marked, half-written folder: --force replaces it
    (tmp_path / "again" / "frames").mkdir(parents=True)
    (tmp_path / "again" / "frames" / "000000.png").write_bytes(b"half")
    (tmp_path / "again" / WRITING).write_text("")
    generate("tow_rope", tmp_path / "again", size="small", frames=SMALL_FRAMES, force=True, log=lambda *a: None)
    assert not (tmp_path / "again" / WRITING).exists()
    for sub in ("frames", "masks"):
        for k in range(SMALL_FRAMES):
            a = cv2.imread(str(out / sub / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
            b = cv2.imread(str(tmp_path / "again" / sub / f"{k:06d}.png"), cv2.IMREAD_UNCHANGED)
            np.testing.assert_array_equal(a, b, err_msg=f"{sub} {k}")
    np.testing.assert_array_equal(np.load(out / "gt" / "gaussian_positions.npy"),
                                  np.load(tmp_path / "again" / "gt" / "gaussian_positions.npy"))
    assert (out / "object.ply").read_bytes() == (tmp_path / "again" / "object.ply").read_bytes()


def test_bad_input(tmp_path):
    from physinteract_usd.errors import InputError

    with pytest.raises(InputError):
        generate("no_such_scene", tmp_path / "x", log=lambda *a: None)
    with pytest.raises(InputError):
        generate("bow_tie", tmp_path / "x", frames=2, log=lambda *a: None)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "keep.txt").write_text("mine")
    with pytest.raises(InputError):
        generate("bow_tie", tmp_path / "busy", force=True, log=lambda *a: None)
    assert (tmp_path / "busy" / "keep.txt").read_text() == "mine"


@pytest.mark.slow
def test_telephone_cable_full_clip_is_stable(tmp_path):
    """The coil carries its own weight: the full small clip stays finite and the poke is visible."""
    info = generate("telephone_cable", tmp_path / "tc", size="small", log=lambda *a: None)
    n = info["n_frames"]
    check_capture_folder(tmp_path / "tc", "telephone_cable", n)
    p = np.load(tmp_path / "tc" / "gt" / "particles.npz")
    disp = np.linalg.norm(p["positions"] - p["rest"][None], axis=2)
    assert disp.max() < 0.06            # no collapse under gravity
    assert disp.max() > 0.01            # the poke moves the coil
    assert min(projection_shares(tmp_path / "tc")) >= PROJECTION_MIN_SHARE


@pytest.mark.slow
@pytest.mark.parametrize("name", ALL)
def test_paper_size_smoke(tmp_path, name):
    """Every scene generates at paper size (3 frames) on the CPU."""
    t0 = time.perf_counter()
    info = generate(name, tmp_path / name, size="paper", frames=3, log=lambda *a: None)
    secs = time.perf_counter() - t0
    check_capture_folder(tmp_path / name, name, 3)
    check_material(info, tmp_path / name, name)
    shares = projection_shares(tmp_path / name)
    print(f"\npaper {name}: {secs:.1f} s, {info['gt_sim']['particles']} GT particles, "
          f"{info['gt_sim']['substeps_per_frame']} substeps/frame, worst projection share {min(shares):.4f}")
    assert min(shares) >= PROJECTION_MIN_SHARE
