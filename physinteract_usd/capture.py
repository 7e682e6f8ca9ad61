"""The capture folder of the design, read into typed objects.

```
DIR/object.ply | object.obj | .glb | .stl | .ply mesh     the static object
DIR/frames/000000.png ...  or  DIR/video.mp4               the video (frames/ wins)
DIR/masks/000000.png ...                                   optional silhouettes
DIR/transforms.json                                        camera (nerfstudio convention)
DIR/gt/                                                    synthetic ground truth: never read here
```
Every problem is an `InputError` naming the file: the CLI prints it as one line and exits 2.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera, rotation_problem
from .errors import InputError
from .frames import VIDEO_EXTS, FrameSource, ImageSequence, VideoFile, list_images, read_mask
from .gaussians import Gaussians, is_gaussian_ply, read_ply

MESH_EXTS = (".obj", ".glb", ".gltf", ".stl", ".ply", ".off", ".dae")
DEFAULT_MESH_GAUSSIANS = 20000


@dataclass
class ObjectData:
    """The static object: Gaussians always (a mesh is sampled into surfels); the mesh if given."""

    path: Path
    gaussians: Gaussians
    mesh: object | None = None  # trimesh.Trimesh

    @property
    def kind(self) -> str:
        return "mesh" if self.mesh is not None else "gaussians"


@dataclass
class Capture:
    object: ObjectData
    frames: FrameSource
    camera: Camera
    fps: float
    fps_source: str
    camera_path: Path
    masks: list[Path] | None = None
    masks_amodal: bool = False
    root: Path | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def read_masks(self) -> np.ndarray | None:
        if self.masks is None:
            return None
        return np.stack([read_mask(p) for p in self.masks])


# --------------------------------------------------------------------------------------- object
def read_object(path: str | os.PathLike, mesh_gaussians: int = DEFAULT_MESH_GAUSSIANS) -> ObjectData:
    """A 3DGS PLY, or any mesh trimesh reads (sampled into surface Gaussians for rendering)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    ext = path.suffix.lower()
    if ext == ".ply" and is_gaussian_ply(path):
        return ObjectData(path, read_ply(path))
    if ext not in MESH_EXTS:
        raise InputError(path, f"unsupported object format '{ext}' (expected a 3DGS .ply or a mesh: "
                         + ", ".join(MESH_EXTS) + ")")
    mesh = _load_mesh(path)
    from .fill import gaussians_from_mesh

    return ObjectData(path, gaussians_from_mesh(mesh, mesh_gaussians), mesh)


def _load_mesh(path: Path):
    import trimesh

    try:
        scene_or_mesh = trimesh.load(str(path), process=False)
    except Exception as exc:
        from .gaussians import ply_truncation

        cut = ply_truncation(path) if path.suffix.lower() == ".ply" else None
        raise InputError(path, cut or f"cannot be read as a mesh ({exc.__class__.__name__}: {exc})") from None
    if isinstance(scene_or_mesh, trimesh.Scene):
        geoms = [g for g in scene_or_mesh.dump() if isinstance(g, trimesh.Trimesh)]
        if not geoms:
            raise InputError(path, "contains no triangle mesh")
        mesh = trimesh.util.concatenate(geoms)
    else:
        mesh = scene_or_mesh
    if not isinstance(mesh, trimesh.Trimesh) or len(getattr(mesh, "faces", [])) == 0:
        if path.suffix.lower() == ".ply":
            raise InputError(path, "PLY has neither the 3D Gaussian properties (x y z f_dc_0.. opacity "
                             "scale_0.. rot_0..) nor faces: not a 3DGS capture and not a mesh")
        raise InputError(path, "contains no triangle faces")
    if not np.isfinite(mesh.vertices).all():
        raise InputError(path, "mesh has non-finite vertices")
    ext = np.ptp(np.asarray(mesh.vertices, np.float64), axis=0)
    if not ext.max() > 0 or ext.min() <= 1e-6 * ext.max():
        raise InputError(path, f"mesh is flat ({len(mesh.faces)} face{'s' if len(mesh.faces) != 1 else ''}, all in one "
                         "plane): a soft object needs a volume (a closed surface, or at least a solid one)")
    return mesh


def find_object(root: Path) -> Path:
    candidates = sorted(p for p in root.glob("object.*") if p.suffix.lower() in MESH_EXTS)
    if not candidates:
        raise InputError(root, "no object file (object.ply, object.obj, object.glb, object.stl)")
    ply = [p for p in candidates if p.suffix.lower() == ".ply"]
    return ply[0] if ply else candidates[0]


# --------------------------------------------------------------------------------------- camera
_INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def read_transforms(path: str | os.PathLike, n_frames: int | None = None):
    """nerfstudio transforms.json -> (Camera, fps or None)."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise InputError(path, "expected a JSON object")
    frames = data.get("frames") or []

    def intr(key):
        vals = {f.get(key) for f in frames if isinstance(f, dict) and key in f}
        if len(vals) > 1:
            raise InputError(path, f"'{key}' varies between frames: varying intrinsics are not supported")
        if key in data:
            return data[key]
        return vals.pop() if vals else None

    values = {k: intr(k) for k in _INTRINSICS}
    if values["fl_x"] is not None and values["fl_y"] is None:
        values["fl_y"] = values["fl_x"]
    missing = [k for k, v in values.items() if v is None]
    if missing:
        raise InputError(path, "camera intrinsics missing: " + ", ".join(missing)
                         + " (nerfstudio fields fl_x fl_y cx cy w h)")
    try:
        fx, fy, cx, cy = (float(values[k]) for k in ("fl_x", "fl_y", "cx", "cy"))
        w, h = int(values["w"]), int(values["h"])
    except (TypeError, ValueError):
        raise InputError(path, "camera intrinsics must be numbers") from None
    if not (fx > 0 and fy > 0 and w > 0 and h > 0):
        raise InputError(path, "focal lengths and image size must be positive")
    dist = [k for k in _DISTORTION if abs(float(intr(k) or 0.0)) > 1e-12]
    if dist:
        raise InputError(path, "lens distortion (" + ", ".join(dist) + ") is not supported: "
                         "undistort the frames and set the coefficients to 0")

    def matrix(m, where):
        try:
            a = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != (4, 4) or not np.isfinite(a).all():
            raise InputError(path, f"{where}: transform_matrix must be a finite 4x4 matrix")
        if abs(np.linalg.det(a[:3, :3])) < 1e-9:
            raise InputError(path, f"{where}: transform_matrix has a singular rotation")
        problem = rotation_problem(a)
        if problem:
            raise InputError(path, f"{where}: transform_matrix: {problem}")
        return a

    per_frame = [f for f in frames if isinstance(f, dict) and "transform_matrix" in f]
    if per_frame:
        poses = np.stack([matrix(f["transform_matrix"], f"frames[{i}]") for i, f in enumerate(per_frame)])
        if n_frames is not None and len(poses) != n_frames:
            raise InputError(path, f"{len(poses)} per-frame camera poses for {n_frames} video frames")
        if np.allclose(poses, poses[0], atol=1e-12):
            poses = poses[0]
    elif "transform_matrix" in data:
        poses = matrix(data["transform_matrix"], "top level")
    else:
        raise InputError(path, "no camera pose: add a top-level transform_matrix (static camera) "
                         "or one per frame in 'frames'")
    fps = data.get("fps")
    if fps is not None:
        try:
            fps = float(fps)
        except (TypeError, ValueError):
            raise InputError(path, "'fps' must be a number") from None
        if not fps > 0:
            raise InputError(path, "'fps' must be positive")
    return Camera(fx, fy, cx, cy, w, h, poses), fps


# -------------------------------------------------------------------------------------- capture
def read_capture(capture_dir=None, *, object=None, video=None, camera=None, masks=None,
                 fps: float | None = None, masks_amodal: bool = False,
                 mesh_gaussians: int = DEFAULT_MESH_GAUSSIANS) -> Capture:
    """Read a capture folder, or the individual files (per-file arguments win over the folder)."""
    root = Path(capture_dir) if capture_dir is not None else None
    if root is not None and not root.is_dir():
        raise InputError(root, "capture folder not found")

    # frames
    if video is not None:
        video = Path(video)
        frames = ImageSequence.from_folder(video) if video.is_dir() else _video_or_images(video)
    elif root is not None and (root / "frames").is_dir():
        frames = ImageSequence.from_folder(root / "frames")
    elif root is not None and _find_video(root) is not None:
        frames = VideoFile(_find_video(root))
    else:
        raise InputError(root if root is not None else "video", "no frames: give DIR/frames/*.png or "
                         "DIR/video.mp4 (or --video)")
    if isinstance(frames, ImageSequence):
        frames.check_sizes()

    # camera
    cam_path = Path(camera) if camera is not None else (root / "transforms.json" if root else None)
    if cam_path is None:
        raise InputError("camera", "no camera: give DIR/transforms.json or --camera")
    cam, cam_fps = read_transforms(cam_path, len(frames))
    if (cam.width, cam.height) != frames.size:
        raise InputError(cam_path, f"camera image size {cam.width}x{cam.height} differs from the "
                         f"frames' {frames.size[0]}x{frames.size[1]} ({frames.path})")

    # fps: transforms.json, else the video's, else the argument
    if cam_fps is not None:
        fps_value, fps_source = cam_fps, str(cam_path)
    elif frames.fps is not None:
        fps_value, fps_source = frames.fps, str(frames.path)
    elif fps is not None:
        if not fps > 0:
            raise InputError("--fps", "must be positive")
        fps_value, fps_source = float(fps), "--fps"
    else:
        raise InputError(cam_path, "no fps anywhere: add \"fps\" to transforms.json, use a video with "
                         "a frame rate, or pass --fps")

    # masks
    mask_paths = None
    mdir = Path(masks) if masks is not None else (root / "masks" if root is not None else None)
    if mdir is not None and (masks is not None or mdir.is_dir()):
        mask_paths = list_images(mdir)
        if len(mask_paths) != len(frames):
            raise InputError(mdir, f"{len(mask_paths)} masks for {len(frames)} frames")
        import cv2

        covered = []
        for p in mask_paths:
            m = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if m is None:
                raise InputError(p, "mask cannot be decoded")
            if (m.shape[1], m.shape[0]) != frames.size:
                raise InputError(p, f"mask is {m.shape[1]}x{m.shape[0]} but frames are "
                                 f"{frames.size[0]}x{frames.size[1]}")
            on = (m[:, :, :3].max(axis=2) if m.ndim == 3 else m) > (32767 if m.dtype == np.uint16 else 127)
            covered.append(float(on.mean()))
            if covered[-1] >= 1.0:
                raise InputError(p, "mask covers the whole frame (all white): a silhouette marks the object's "
                                 "pixels (>127) and leaves the rest black (inverted masks?)")
        if max(covered) == 0.0:
            raise InputError(mdir, f"all {len(mask_paths)} masks are empty (all black): no pixel marks the object "
                             "(>127 = object)")
        if covered[0] == 0.0:
            raise InputError(mask_paths[0], "the first mask is empty (all black), but frame 0 is the object at rest, "
                             "in view")

    # object
    if object is not None:
        obj_path = Path(object)
    elif root is not None:
        obj_path = find_object(root)
    else:
        raise InputError("object", "no object: give DIR/object.ply (or a mesh) or --object")
    obj = read_object(obj_path, mesh_gaussians)
    return Capture(object=obj, frames=frames, camera=cam, fps=fps_value, fps_source=fps_source,
                   camera_path=cam_path, masks=mask_paths, masks_amodal=masks_amodal, root=root)


def _find_video(root: Path) -> Path | None:
    vids = sorted(p for p in root.iterdir() if p.suffix.lower() in VIDEO_EXTS and p.is_file())
    video = [p for p in vids if p.stem == "video"]
    return (video or vids or [None])[0]


def _video_or_images(path: Path) -> FrameSource:
    if not path.exists():
        raise InputError(path, "file not found")
    if path.suffix.lower() in VIDEO_EXTS:
        return VideoFile(path)
    raise InputError(path, f"unsupported video format '{path.suffix}' (give an mp4 or a folder of frames)")
