"""Procedural solids for the synthetic suite: analytic signed distances (negative inside) for
exact inside tests and interior lattices, and trimesh meshes for area-uniform surface samples.

A `Shape` is a union of labelled parts; a point belongs to the part with the smallest SDF.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class _LazyTrimesh:
    """trimesh, imported on first use: `evaluate` reads the ground truth through this package and
    needs no meshes; importing trimesh costs ~1 s of CPU per process (#26)."""

    def __getattr__(self, name):
        import trimesh
        import trimesh.creation  # noqa: F401  (the submodules used here)
        import trimesh.sample  # noqa: F401
        import trimesh.util  # noqa: F401

        return getattr(trimesh, name)


trimesh = _LazyTrimesh()


def _rot_to(axis) -> np.ndarray:
    """Rotation matrix taking +z to `axis`."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, a)
    c = float(np.dot(z, a))
    if c < -0.999999:
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


@dataclass
class Part:
    label: str

    def sdf(self, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def mesh(self) -> trimesh.Trimesh:
        raise NotImplementedError


@dataclass
class Capsule(Part):
    a: tuple = (0, 0, 0)
    b: tuple = (0, 1, 0)
    r: float = 0.05

    def sdf(self, p):
        a, b = np.asarray(self.a, float), np.asarray(self.b, float)
        ab = b - a
        t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
        return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - self.r

    def mesh(self):
        a, b = np.asarray(self.a, float), np.asarray(self.b, float)
        h = float(np.linalg.norm(b - a))
        m = trimesh.creation.capsule(height=h, radius=self.r, count=[24, 24])
        T = np.eye(4)
        T[:3, :3] = _rot_to(b - a)
        T[:3, 3] = 0.5 * (a + b)
        m.apply_transform(T)
        return m


@dataclass
class Ellipsoid(Part):
    c: tuple = (0, 0, 0)
    radii: tuple = (0.1, 0.1, 0.1)
    R: np.ndarray | None = None  # rotation (local -> world)

    def _local(self, p):
        R = np.eye(3) if self.R is None else np.asarray(self.R)
        return (p - np.asarray(self.c, float)) @ R

    def sdf(self, p):
        q = self._local(p) / np.asarray(self.radii, float)
        return (np.linalg.norm(q, axis=1) - 1.0) * float(np.min(self.radii))

    def mesh(self):
        m = trimesh.creation.icosphere(4)
        m.vertices *= np.asarray(self.radii, float)
        T = np.eye(4)
        T[:3, :3] = np.eye(3) if self.R is None else np.asarray(self.R)
        T[:3, 3] = self.c
        m.apply_transform(T)
        return m


@dataclass
class Box(Part):
    c: tuple = (0, 0, 0)
    half: tuple = (0.1, 0.1, 0.1)
    R: np.ndarray | None = None
    rounding: float = 0.0

    def sdf(self, p):
        R = np.eye(3) if self.R is None else np.asarray(self.R)
        q = np.abs((p - np.asarray(self.c, float)) @ R) - (np.asarray(self.half, float) - self.rounding)
        out = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(1), 0.0)
        return out - self.rounding

    def mesh(self):
        m = trimesh.creation.box(extents=2 * np.asarray(self.half, float))
        m = m.subdivide().subdivide().subdivide()
        T = np.eye(4)
        T[:3, :3] = np.eye(3) if self.R is None else np.asarray(self.R)
        T[:3, 3] = self.c
        m.apply_transform(T)
        return m


@dataclass
class Torus(Part):
    c: tuple = (0, 0, 0)
    major: float = 0.1
    minor: float = 0.03
    axis: tuple = (0, 1, 0)

    def sdf(self, p):
        R = _rot_to(self.axis)
        q = (p - np.asarray(self.c, float)) @ R  # local: axis = z
        ring = np.linalg.norm(q[:, :2], axis=1) - self.major
        return np.sqrt(ring ** 2 + q[:, 2] ** 2) - self.minor

    def mesh(self):
        m = trimesh.creation.torus(self.major, self.minor, major_sections=64, minor_sections=24)
        T = np.eye(4)
        T[:3, :3] = _rot_to(self.axis)
        T[:3, 3] = self.c
        m.apply_transform(T)
        return m


@dataclass
class Tube(Part):
    """A tube of radius r along a polyline (a chain of capsules): ropes, cables, coils."""

    points: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    r: float = 0.02

    def sdf(self, p):
        pts = np.asarray(self.points, float)
        best = np.full(len(p), np.inf)
        for a, b in zip(pts[:-1], pts[1:]):
            best = np.minimum(best, Capsule(self.label, tuple(a), tuple(b), self.r).sdf(p))
        return best

    def mesh(self):
        pts = np.asarray(self.points, float)
        return trimesh.util.concatenate([Capsule(self.label, tuple(a), tuple(b), self.r).mesh()
                                         for a, b in zip(pts[:-1], pts[1:])])

    def arclength(self, p: np.ndarray) -> np.ndarray:
        """Arc-length coordinate (0 at the first point) of the tube axis point nearest to p."""
        pts = np.asarray(self.points, float)
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        best = np.full(len(p), np.inf)
        s = np.zeros(len(p))
        for i, (a, b) in enumerate(zip(pts[:-1], pts[1:])):
            ab = b - a
            t = np.clip(((p - a) @ ab) / (ab @ ab), 0.0, 1.0)
            d = np.linalg.norm(p - (a + t[:, None] * ab), axis=1)
            better = d < best
            best[better] = d[better]
            s[better] = cum[i] + t[better] * seg[i]
        return s


class Shape:
    """A union of parts."""

    def __init__(self, parts: list[Part]):
        self.parts = list(parts)
        self.labels = [p.label for p in self.parts]

    def sdf(self, p: np.ndarray) -> np.ndarray:
        return np.min(np.stack([q.sdf(p) for q in self.parts]), axis=0)

    def part_of(self, p: np.ndarray) -> np.ndarray:
        """Index of the part each point belongs to (the one with the smallest SDF)."""
        return np.argmin(np.stack([q.sdf(p) for q in self.parts]), axis=0)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        vs = np.concatenate([q.mesh().vertices for q in self.parts])
        return vs.min(0), vs.max(0)

    def normals(self, p: np.ndarray, eps: float = 1e-4) -> np.ndarray:
        g = np.stack([(self.sdf(p + eps * e) - self.sdf(p - eps * e)) / (2 * eps) for e in np.eye(3)], 1)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)

    def sample_surface(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """~n area-uniform points on the union's surface (samples inside other parts dropped),
        with their part index."""
        rng = np.random.default_rng(seed)
        meshes = [q.mesh() for q in self.parts]
        areas = np.array([m.area for m in meshes])
        over = 1.5  # oversample: internal faces and overlaps are dropped below
        for _ in range(6):
            pts, lab = [], []
            for i, m in enumerate(meshes):
                k = max(8, int(round(over * n * areas[i] / areas.sum())))
                s, _ = trimesh.sample.sample_surface(m, k, seed=int(rng.integers(1 << 30)))
                pts.append(s)
                lab.append(np.full(len(s), i))
            pts = np.concatenate(pts)
            lab = np.concatenate(lab)
            # keep points on the union's boundary: a part's mesh may hold internal faces (a tube's
            # overlapping capsule ends) and parts overlap, so drop samples inside the union; then
            # put the rest exactly on the surface (one Newton step on the SDF: meshes are polygonal)
            tol = 1e-3 * float(np.max(np.ptp(pts, axis=0)))
            keep = self.sdf(pts) > -tol
            pts, lab = pts[keep], lab[keep]
            if len(pts) >= n:
                break
            over *= 1.2 * n / max(len(pts), 1)
        pts = pts - self.sdf(pts)[:, None] * self.normals(pts)
        if len(pts) > n:
            sel = np.sort(rng.choice(len(pts), n, replace=False))
            pts, lab = pts[sel], lab[sel]
        return pts, lab

    def lattice(self, spacing: float, origin=None) -> np.ndarray:
        """Cell centres of a lattice of the given spacing that lie inside the shape."""
        lo, hi = self.bounds()
        o = lo if origin is None else np.asarray(origin, float)
        i0 = np.floor((lo - o) / spacing) - 1
        i1 = np.ceil((hi - o) / spacing) + 1
        axes = [o[d] + (np.arange(i0[d], i1[d]) + 0.5) * spacing for d in range(3)]
        g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return g[self.sdf(g) < 0]

    def mesh(self) -> trimesh.Trimesh:
        return trimesh.util.concatenate([q.mesh() for q in self.parts])


def helix(centre, radius, pitch, turns, n_per_turn=24, axis_dir=-1.0) -> np.ndarray:
    """Points of a vertical helix (y axis) starting at the top."""
    t = np.linspace(0.0, 2 * np.pi * turns, int(n_per_turn * turns) + 1)
    c = np.asarray(centre, float)
    return np.stack([c[0] + radius * np.cos(t), c[1] + axis_dir * pitch * t / (2 * np.pi),
                     c[2] + radius * np.sin(t)], 1)
