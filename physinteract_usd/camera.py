"""Pinhole camera with the design's conventions.

- Intrinsics in pixels: fx, fy, cx, cy, width, height. Continuous pixel coordinates put pixel
  (i, j)'s centre at (i + 0.5, j + 0.5), so ``u = fx X / Z + cx`` in the OpenCV camera frame equals
  what ``cv2.projectPoints`` returns for K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
- Extrinsics: ``c2w`` is the nerfstudio ``transform_matrix``: 4x4 camera-to-world, column vectors,
  OpenGL axes (the camera looks along -Z, +Y up). A camera may carry one pose per frame
  (``c2w`` of shape (T, 4, 4)); `at(frame)` gives the static camera of one frame.
- The OpenCV camera frame (x right, y down, z forward) is ``c2w @ diag(1, -1, -1, 1)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
ORTHONORMAL_TOL = 1e-3   # max |R^T R - I| of a camera pose's rotation


def rotation_problem(c2w) -> str | None:
    """None for a rigid camera-to-world matrix (orthonormal rotation, det +1, last row 0 0 0 1);
    else what is wrong with it, in words."""
    m = np.asarray(c2w, np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        return "the transform must be a finite 4x4 matrix"
    r = m[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > ORTHONORMAL_TOL:
        norms = np.linalg.norm(r, axis=0)
        return (f"the rotation is not orthonormal (max |R^T R - I| = {err:.3g}, column lengths "
                f"{', '.join(f'{x:.4g}' for x in norms)}): a camera pose is a rotation and a translation")
    if np.linalg.det(r) < 0:
        return "the rotation is a reflection (det < 0)"
    if abs(float(m[3, 3]) - 1.0) > 1e-6 or np.abs(m[3, :3]).max() > 1e-6:
        return "the last row must be 0 0 0 1"
    return None


@dataclass
class Camera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    c2w: np.ndarray  # (4, 4) or (T, 4, 4), nerfstudio / OpenGL camera-to-world
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self):
        self.c2w = np.asarray(self.c2w, dtype=np.float64)
        if self.c2w.shape[-2:] != (4, 4):
            raise ValueError("c2w must be 4x4 (or T x 4 x 4)")
        self.width = int(self.width)
        self.height = int(self.height)

    # ------------------------------------------------------------------ poses
    @property
    def is_static(self) -> bool:
        return self.c2w.ndim == 2

    def at(self, frame: int) -> "Camera":
        """The static camera of one frame (the last pose holds beyond the pose list)."""
        if self.is_static:
            return self
        pose = self.c2w[min(max(int(frame), 0), len(self.c2w) - 1)]
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, pose,
                      self.near, self.far)

    def _static_pose(self) -> np.ndarray:
        if not self.is_static:
            raise ValueError("camera has one pose per frame: call .at(frame) first")
        return self.c2w

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def w2c_cv(self) -> np.ndarray:
        """4x4 world-to-camera in the OpenCV camera frame (x right, y down, z forward)."""
        return np.linalg.inv(self._static_pose() @ GL_TO_CV)

    def rvec_tvec(self):
        """Rodrigues vector and translation for cv2.projectPoints."""
        import cv2

        w2c = self.w2c_cv()
        rvec, _ = cv2.Rodrigues(w2c[:3, :3])
        return rvec.reshape(3), w2c[:3, 3].copy()

    @property
    def position(self) -> np.ndarray:
        return self._static_pose()[:3, 3].copy()

    # ------------------------------------------------------------- projection
    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points to the OpenCV camera frame."""
        w2c = self.w2c_cv()
        return np.asarray(points, dtype=np.float64) @ w2c[:3, :3].T + w2c[:3, 3]

    def project(self, points: np.ndarray):
        """Project (N, 3) world points: returns (uv (N, 2) continuous pixel coords, depth (N,))."""
        pc = self.world_to_camera(points)
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * pc[:, 0] / z + self.cx
            v = self.fy * pc[:, 1] / z + self.cy
        return np.stack([u, v], 1), z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Back-project pixels (continuous coords) at camera-frame depth z to world points.

        This is the design's X_p = T_c^-1 pi^-1(x_p, d_p).
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        z = np.asarray(depth, dtype=np.float64).reshape(-1)
        pc = np.stack([(uv[:, 0] - self.cx) / self.fx * z, (uv[:, 1] - self.cy) / self.fy * z, z], 1)
        c2w_cv = self._static_pose() @ GL_TO_CV
        return pc @ c2w_cv[:3, :3].T + c2w_cv[:3, 3]

    def scaled(self, factor: float) -> "Camera":
        """The same camera at another image resolution (width and height times factor)."""
        return Camera(self.fx * factor, self.fy * factor, self.cx * factor, self.cy * factor,
                      int(round(self.width * factor)), int(round(self.height * factor)),
                      self.c2w, self.near, self.far)

    # ----------------------------------------------------------- construction
    @staticmethod
    def look_at(eye, target, up=(0.0, 1.0, 0.0), *, width: int, height: int,
                fov_y_deg: float = 40.0) -> "Camera":
        """A camera at `eye` looking at `target` (OpenGL axes), square pixels, centred principal point."""
        eye = np.asarray(eye, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - eye
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, np.asarray(up, dtype=np.float64))
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -fwd, eye
        f = 0.5 * height / np.tan(np.radians(fov_y_deg) / 2)
        return Camera(f, f, width / 2.0, height / 2.0, width, height, c2w)

    def to_transforms_dict(self, fps: float | None = None) -> dict:
        """The nerfstudio transforms.json fields for this camera."""
        d = {"fl_x": self.fx, "fl_y": self.fy, "cx": self.cx, "cy": self.cy,
             "w": self.width, "h": self.height, "camera_model": "OPENCV"}
        if fps is not None:
            d["fps"] = fps
        if self.is_static:
            d["transform_matrix"] = self.c2w.tolist()
        else:
            d["frames"] = [{"transform_matrix": m.tolist()} for m in self.c2w]
        return d
