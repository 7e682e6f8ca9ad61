"""3D Gaussians: the object's appearance, decoded (activated) values, and the INRIA 3DGS PLY layout.

A `Gaussians` holds decoded values, the form USD and the renderer use:

- ``means``      (N, 3) float, metres
- ``scales``     (N, 3) float, linear standard deviations along the local axes (PLY stores log)
- ``quats``      (N, 4) float, unit quaternions **w x y z** (PLY stores unnormalised w x y z)
- ``opacities``  (N,)   float in (0, 1) (PLY stores the logit)
- ``sh``         (N, K, 3) float, real spherical-harmonic coefficients, K = (degree + 1)^2,
                 coefficient-major per Gaussian (what UsdVol stores); colour = 0.5 + sh . Y(dir),
                 so the DC colour is 0.5 + 0.28209479 * sh[:, 0]. (PLY stores f_rest channel-major.)

Reading uses trimesh's PLY reader; writing packs a binary little-endian PLY with numpy.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError

SH_C0 = 0.28209479177387814
# logits are clamped so that sigmoid(logit) stays representable and logit(sigmoid(x)) round-trips
OPACITY_EPS = 1e-6
MAX_SCALE_FRACTION = 0.25  # a Gaussian wider than this share of the object's extent is clamped


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def logit(p):
    p = np.clip(p, OPACITY_EPS, 1.0 - OPACITY_EPS)
    return np.log(p) - np.log1p(-p)


def sh_degree_from_count(k: int) -> int:
    d = int(round(np.sqrt(k))) - 1
    if (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients is not (degree+1)^2")
    return d


@dataclass
class Gaussians:
    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    normals: np.ndarray | None = None
    extra: dict = field(default_factory=dict)  # unknown PLY vertex properties, kept for round trips

    def __post_init__(self):
        n = len(self.means)
        self.means = np.asarray(self.means, dtype=np.float64).reshape(n, 3)
        self.scales = np.asarray(self.scales, dtype=np.float64).reshape(n, 3)
        self.quats = np.asarray(self.quats, dtype=np.float64).reshape(n, 4)
        self.opacities = np.asarray(self.opacities, dtype=np.float64).reshape(n)
        self.sh = np.asarray(self.sh, dtype=np.float64)
        if self.sh.ndim == 2:
            self.sh = self.sh.reshape(n, -1, 3)
        sh_degree_from_count(self.sh.shape[1])

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_count(self.sh.shape[1])

    @property
    def colors(self) -> np.ndarray:
        """View-independent (DC) colour, (N, 3), clipped to [0, 1]."""
        return np.clip(0.5 + SH_C0 * self.sh[:, 0, :], 0.0, 1.0)

    def rotations(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices of the (normalised) quaternions."""
        return quat_to_rotmat(self.quats)

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) world covariances R S S^T R^T."""
        R = self.rotations()
        M = R * self.scales[:, None, :]
        return M @ np.transpose(M, (0, 2, 1))

    def subset(self, idx) -> "Gaussians":
        return Gaussians(self.means[idx], self.scales[idx], self.quats[idx], self.opacities[idx],
                         self.sh[idx], None if self.normals is None else self.normals[idx],
                         {k: v[idx] for k, v in self.extra.items()})

    @staticmethod
    def from_colors(means, colors, scales, opacities=None, quats=None) -> "Gaussians":
        """Degree-0 Gaussians from RGB colours in [0, 1]."""
        means = np.asarray(means, dtype=np.float64)
        n = len(means)
        colors = np.broadcast_to(np.asarray(colors, dtype=np.float64), (n, 3))
        sh = ((colors - 0.5) / SH_C0)[:, None, :]
        s = np.asarray(scales, dtype=np.float64)
        if s.ndim == 0 or s.shape == (n,):
            s = np.repeat(np.broadcast_to(s, (n,))[:, None], 3, axis=1)
        scales = np.broadcast_to(s, (n, 3)).copy()
        if quats is None:
            quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        if opacities is None:
            opacities = np.full(n, 0.9)
        return Gaussians(means, scales, quats, np.broadcast_to(opacities, (n,)).copy(), sh)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """(…, 3, 3) rotation matrices to unit quaternions w x y z with w >= 0."""
    from scipy.spatial.transform import Rotation

    shape = R.shape[:-2]
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    q = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    q[q[:, 0] < 0] *= -1
    return q.reshape(shape + (4,))


# ----------------------------------------------------------------------------------------- PLY
_REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def scales_quats_from_covariance(cov) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3, 3) covariances -> (scales (N, 3) linear, quats (N, 4) w x y z, w >= 0), numpy, for
    writing deformed Splats (eigen-decomposition; eigenvalues clamped at 0)."""
    c = cov.detach().cpu().numpy() if hasattr(cov, "detach") else np.asarray(cov)
    c = 0.5 * (c + np.swapaxes(c, -1, -2)).astype(np.float64)
    evals, evecs = np.linalg.eigh(c)
    det = np.linalg.det(evecs)
    evecs[det < 0, :, 0] *= -1.0
    return np.sqrt(np.maximum(evals, 0.0)), rotmat_to_quat(evecs)


def is_gaussian_ply(path: str | os.PathLike) -> bool:
    """True when the PLY's vertex element carries the 3DGS properties (reads the header only)."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
    except OSError:
        return False
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return False
    props = {ln.split()[-1] for ln in head[:end].decode("ascii", "replace").splitlines()
             if ln.startswith("property")}
    return all(p in props for p in _REQUIRED)


# PLY scalar types -> numpy type codes (the names first, then their sized aliases); write_ply uses the names
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
              "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2",
              "int32": "i4", "uint32": "u4", "float32": "f4", "float64": "f8"}


def ply_truncation(path: str | os.PathLike) -> str | None:
    """What is wrong with a PLY cut short, or None when it is not (or that cannot be told: an
    ASCII body, list properties). Reads the header and the file's size only."""
    try:
        with open(path, "rb") as f:
            head = f.read(65536)
        size = os.path.getsize(path)
    except OSError:
        return None
    if not head.startswith(b"ply"):
        return None
    end = head.find(b"end_header")
    if end < 0:
        return "the PLY header ends before end_header (the file is truncated)"
    body_start = head.find(b"\n", end) + 1
    lines = head[:end].decode("ascii", "replace").splitlines()
    if not any(ln.startswith("format binary") for ln in lines):
        return None
    need, count, row = 0, None, 0
    for ln in lines + ["element _end 0"]:
        w = ln.split()
        if not w:
            continue
        if w[0] == "element":
            if count is not None:
                need += count * row
            count, row = int(w[2]) if len(w) > 2 and w[2].isdigit() else 0, 0
        elif w[0] == "property" and count is not None:
            if w[1] == "list" or w[1] not in _PLY_TYPES:
                return None
            row += np.dtype(_PLY_TYPES[w[1]]).itemsize
    have = size - body_start
    if have < need:
        return f"the PLY is truncated: its header declares {need} bytes of data, the file holds {have}"
    return None


def read_ply(path: str | os.PathLike) -> Gaussians:
    """Read a 3DGS PLY (INRIA layout) into decoded `Gaussians`. Raises InputError on bad files."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise InputError(path, "file not found")
    try:
        with open(path, "rb") as f:
            loaded = trimesh.exchange.ply.load_ply(f)
    except Exception as exc:  # trimesh raises many kinds
        cut = ply_truncation(path)
        raise InputError(path, cut or f"not a readable PLY file ({exc.__class__.__name__}: {exc})") from None
    raw = (loaded.get("metadata") or {}).get("_ply_raw") or {}
    vert = raw.get("vertex", {}).get("data")
    if vert is None or vert.dtype.names is None:
        raise InputError(path, "PLY has no vertex element")
    names = vert.dtype.names
    missing = [p for p in _REQUIRED if p not in names]
    if missing:
        raise InputError(path, "PLY lacks the 3D Gaussian properties " + ", ".join(missing)
                         + " (expected the INRIA 3DGS layout; a mesh PLY needs faces)")
    n = len(vert)
    if n == 0:
        raise InputError(path, "PLY has no Gaussians")
    col = lambda k: np.asarray(vert[k], dtype=np.float64)  # noqa: E731
    means = np.stack([col("x"), col("y"), col("z")], 1)
    rest = sorted((k for k in names if k.startswith("f_rest_")), key=lambda k: int(k[7:]))
    if len(rest) % 3:
        raise InputError(path, f"PLY has {len(rest)} f_rest properties, not a multiple of 3")
    k_rest = len(rest) // 3
    try:
        sh_degree_from_count(k_rest + 1)
    except ValueError:
        raise InputError(path, f"PLY has {len(rest)} f_rest properties: not a whole SH degree") from None
    sh = np.zeros((n, k_rest + 1, 3))
    sh[:, 0] = np.stack([col("f_dc_0"), col("f_dc_1"), col("f_dc_2")], 1)
    if k_rest:
        fr = np.stack([col(k) for k in rest], 1).reshape(n, 3, k_rest)  # channel-major
        sh[:, 1:] = np.transpose(fr, (0, 2, 1))
    log_scales = np.stack([col("scale_0"), col("scale_1"), col("scale_2")], 1)
    quats = np.stack([col("rot_0"), col("rot_1"), col("rot_2"), col("rot_3")], 1)
    qn = np.linalg.norm(quats, axis=1)
    bad = ~np.isfinite(means).all(1) | ~np.isfinite(log_scales).all(1) | ~(qn > 0)
    if bad.any():
        raise InputError(path, f"{int(bad.sum())} Gaussians have non-finite positions/scales or a zero quaternion")
    normals = None
    if all(k in names for k in ("nx", "ny", "nz")):
        normals = np.stack([col("nx"), col("ny"), col("nz")], 1)
    known = set(_REQUIRED) | set(rest) | {"nx", "ny", "nz"}
    extra = {k: np.asarray(vert[k]) for k in names if k not in known}
    return Gaussians(means, np.exp(log_scales), quats / qn[:, None], sigmoid(col("opacity")), sh,
                     normals, extra)


def write_ply(g: Gaussians, path: str | os.PathLike) -> None:
    """Write `Gaussians` as a binary little-endian INRIA 3DGS PLY (encoded: logit, log, raw SH)."""
    n = len(g)
    k_rest = g.sh.shape[1] - 1
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    extra = list(g.extra.keys())
    dtype = [(k, "<f4") for k in names] + [(k, g.extra[k].dtype.newbyteorder("<").str) for k in extra]
    arr = np.zeros(n, dtype=dtype)
    for i, k in enumerate("xyz"):
        arr[k] = g.means[:, i]
        if g.normals is not None:
            arr["n" + k] = g.normals[:, i]
    for c in range(3):
        arr[f"f_dc_{c}"] = g.sh[:, 0, c]
        for j in range(k_rest):
            arr[f"f_rest_{c * k_rest + j}"] = g.sh[:, 1 + j, c]
    arr["opacity"] = logit(g.opacities)
    for i in range(3):
        arr[f"scale_{i}"] = np.log(g.scales[:, i])
    for i in range(4):
        arr[f"rot_{i}"] = g.quats[:, i]
    for k in extra:
        arr[k] = g.extra[k]
    plytype = {code: name for name, code in reversed(_PLY_TYPES.items())}  # the first name of each code
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    for k, t in dtype:
        header.append(f"property {plytype[np.dtype(t).str[1:]]} {k}")
    header.append("end_header")
    data = ("\n".join(header) + "\n").encode("ascii") + arr.tobytes()
    _atomic_write_bytes(path, data)


def _atomic_write_bytes(path, data: bytes) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)
