"""A volumetric (tetrahedral) mesh of the twin: what `export --sim-ready` writes for simulators that
use finite elements rather than particles. No USD here (usd/simready.py writes it).

The object is what the simulator fills: the particles of `fill` sit one per lattice cell of spacing
h, so the object's volume is the union of those cells. Its surface is the 0.5 isosurface of that
occupancy (marching cubes, scikit-image), which lies on the union's boundary up to the cubes'
corner cuts; TetGen (the `tetgen` package, PLC mode `p`) fills it without moving it: every
boundary face of the tetrahedral mesh lies on the isosurface. So the tetrahedral mesh's surface is
within half a particle spacing of the cells' boundary, and `surface_distances` measures how far
the object's Gaussians are from it (on the bundled sample: max 0.48 h, see docs/simready.md).

Why TetGen (and not fTetWild / pytetwild): it keeps the input surface exactly (fTetWild moves it
within an envelope), runs in milliseconds on these meshes and is deterministic (fTetWild is not
across runs), and imports without PyVista/VTK (pytetwild 0.3-0.4 imports PyVista at import time,
and upstream now requires it). Its licence is the AGPL-3.0 (or a commercial licence from WIAS);
the wrapper is MIT: see docs/simready.md.

    mesh = tetmesh_from_particles(positions, spacing)
    E_tet = element_values(mesh, positions, E, log=True)
    region, reps = cluster_regions(E_tet, nu_tet, mesh.volumes())
    tet, bary = embed_points(mesh, gaussian_means)      # splats follow the tetrahedra
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

# spread of E inside one clustered material region: within the Material Accuracy bar (20%)
REGION_TOLERANCE = 0.2
MAX_REGIONS = 4


@dataclass
class TetMesh:
    """points (V, 3) [m]; tets (T, 4) vertex indices, positively oriented (det[x1-x0, x2-x0, x3-x0]
    > 0: USD's rightHanded TetMesh, and what Newton accepts); surface (F, 3) boundary triangles,
    counter-clockwise seen from outside."""

    points: np.ndarray
    tets: np.ndarray
    surface: np.ndarray

    def edges(self) -> np.ndarray:
        """(T, 3, 3) rest edge matrices [x1-x0, x2-x0, x3-x0] (columns)."""
        p = self.points[self.tets]
        return np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)

    def volumes(self) -> np.ndarray:
        return np.linalg.det(self.edges()) / 6.0

    def centroids(self) -> np.ndarray:
        return self.points[self.tets].mean(axis=1)

    def surface_vertices(self) -> np.ndarray:
        return np.unique(self.surface)


def surface_from_particles(positions: np.ndarray, spacing: float, *, step: int = 1):
    """The closed surface (vertices (V, 3), outward triangles (F, 3)) bounding the particles'
    lattice cells: the 0.5 isosurface of their occupancy. `step` > 1 samples it coarser."""
    from skimage import measure

    x = np.asarray(positions, np.float64)
    h = float(spacing)
    lo = x.min(0) - 2.0 * h
    idx = np.round((x - lo) / h).astype(np.int64)
    occ = np.zeros(tuple(idx.max(0) + 3), np.float32)
    occ[tuple(idx.T)] = 1.0
    # the field increases inwards: marching cubes' triangles then face inwards, so flip them
    v, f, _, _ = measure.marching_cubes(occ, 0.5, spacing=(h, h, h), step_size=int(step),
                                        allow_degenerate=False)
    return _clean(v + lo, f[:, ::-1])


def _clean(v: np.ndarray, f: np.ndarray):
    """Merge coincident vertices and drop faces that collapse."""
    key = np.round(v / (1e-9 + np.abs(v).max()) * 2**30).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    v, f = v[first], inv[f]
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    used, f = np.unique(f, return_inverse=True)
    return v[used], f.reshape(-1, 3)


def tetrahedralize(vertices: np.ndarray, faces: np.ndarray, *, quality: float = 1.5,
                   max_volume: float | None = None) -> TetMesh:
    """Fill a closed, outward-oriented surface with tetrahedra (TetGen `p` + radius-edge quality
    bound `q`; boundary faces stay on the input surface). ValueError if TetGen cannot."""
    import tetgen

    v = np.ascontiguousarray(vertices, np.float64)
    f = np.ascontiguousarray(faces, np.int32)
    try:
        nodes, elems = tetgen.TetGen(v, f).tetrahedralize(plc=True, quality=True, minratio=float(quality),
                                                          maxvolume=float(max_volume or -1.0), quiet=True)[:2]
    except RuntimeError as exc:  # TetGen's self-intersection / bad-PLC errors
        raise ValueError(f"TetGen could not fill the surface ({exc})") from None
    nodes = np.asarray(nodes, np.float64)
    tets = np.asarray(elems, np.int64).reshape(-1, 4)
    if len(tets) == 0:
        raise ValueError("TetGen produced no tetrahedra")
    mesh = TetMesh(nodes, tets, np.zeros((0, 3), np.int64))
    neg = mesh.volumes() < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    mesh.surface = boundary_faces(tets)
    return mesh


def tetmesh_from_particles(positions: np.ndarray, spacing: float, *, step: int = 1, quality: float = 1.5) -> TetMesh:
    """The tetrahedral mesh of the volume the particles fill (see the module's docstring)."""
    v, f = surface_from_particles(positions, spacing, step=step)
    return tetrahedralize(v, f, quality=quality)


_FACES = np.array([[0, 1, 3], [0, 2, 1], [0, 3, 2], [1, 2, 3]])  # outward for a positive tet


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """(F, 3) faces that belong to one tetrahedron only, outward (as UsdGeom.TetMesh.ComputeSurfaceFaces)."""
    faces = tets[:, _FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.reshape(-1)] == 1]


def surface_distances(mesh: TetMesh, points: np.ndarray) -> np.ndarray:
    """(N,) unsigned distance [m] from each point to the mesh's boundary surface."""
    import trimesh

    surf = trimesh.Trimesh(mesh.points, mesh.surface, process=False)
    _, d, _ = trimesh.proximity.closest_point(surf, np.asarray(points, np.float64))
    return np.asarray(d)


def element_values(mesh: TetMesh, positions: np.ndarray, values: np.ndarray, *, k: int = 4, log: bool = False) -> np.ndarray:
    """(T,) a per-particle field at each tetrahedron's centroid: inverse-distance weights over the
    k nearest particles (as the Gaussians are bound to the particles); `log` averages log values
    (for E, which varies over decades)."""
    vals = np.asarray(values, np.float64)
    k = min(k, len(vals))
    d, i = cKDTree(np.asarray(positions, np.float64)).query(mesh.centroids(), k=k)
    d, i = d.reshape(len(d), -1), i.reshape(len(i), -1)
    w = 1.0 / np.maximum(d, 1e-9)
    w /= w.sum(1, keepdims=True)
    src = np.log(vals[i]) if log else vals[i]
    out = (w * src).sum(1)
    return np.exp(out) if log else out


def cluster_regions(youngs: np.ndarray, poisson: np.ndarray, volumes: np.ndarray, *,
                    tolerance: float = REGION_TOLERANCE, max_regions: int = MAX_REGIONS):
    """A few material regions for a per-element field: the fewest clusters of log E (1-D k-means,
    at most `max_regions`) such that every element's E is within `tolerance` of its region's
    (volume-weighted geometric mean) E, when that many suffice. Returns (labels (T,) int, regions:
    list of {"youngs", "poisson", "volume", "count", "spread"}), regions sorted by E; `spread` is
    the largest |E / E_region - 1| inside the region."""
    logE = np.log(np.asarray(youngs, np.float64))
    nu = np.asarray(poisson, np.float64)
    vol = np.abs(np.asarray(volumes, np.float64))
    best = None
    for K in range(1, max_regions + 1):
        labels = _kmeans_1d(logE, vol, K)
        regions = _regions(labels, logE, nu, vol)
        best = (labels, regions)
        if max(r["spread"] for r in regions) <= tolerance:
            break
    return best


def _kmeans_1d(x: np.ndarray, w: np.ndarray, K: int, iters: int = 50) -> np.ndarray:
    """Weighted Lloyd iterations from quantile seeds; labels ordered by centre."""
    if K == 1 or np.ptp(x) == 0:
        return np.zeros(len(x), np.int64)
    c = np.quantile(x, (np.arange(K) + 0.5) / K)
    for _ in range(iters):
        lab = np.abs(x[:, None] - c[None]).argmin(1)
        new = np.array([np.average(x[lab == j], weights=w[lab == j]) if np.any(lab == j) else c[j] for j in range(K)])
        if np.allclose(new, c):
            break
        c = new
    used = np.unique(lab)
    order = np.argsort(c[used])
    remap = np.empty(K, np.int64)
    remap[used[order]] = np.arange(len(used))
    return remap[lab]


def _regions(labels, logE, nu, vol) -> list[dict]:
    out = []
    for j in range(int(labels.max()) + 1):
        m = labels == j
        e = float(np.exp(np.average(logE[m], weights=vol[m])))
        out.append({"youngs": e, "poisson": float(np.average(nu[m], weights=vol[m])), "volume": float(vol[m].sum()),
                    "count": int(m.sum()), "spread": float(np.max(np.abs(np.exp(logE[m]) / e - 1.0)))})
    return out


def body_material(youngs: np.ndarray, poisson: np.ndarray, volumes: np.ndarray) -> tuple[float, float]:
    """The one material a simulator that reads one per body gets: the volume-weighted geometric
    mean of E and the volume-weighted mean of nu."""
    vol = np.abs(np.asarray(volumes, np.float64))
    return (float(np.exp(np.average(np.log(youngs), weights=vol))), float(np.average(poisson, weights=vol)))


def embed_points(mesh: TetMesh, points: np.ndarray, *, candidates: int = 16):
    """Bind points to the tetrahedra: (tet index (N,), barycentric weights (N, 4)) such that
    point = sum_i w_i * mesh.points[mesh.tets[tet, i]] at rest. A point inside the mesh gets the
    tetrahedron containing it (weights in [0, 1]); one outside (a splat's centre just beyond the
    surface) gets the nearest tetrahedron among `candidates` with weights that extrapolate
    (some slightly negative), so it still follows that tetrahedron's affine motion exactly."""
    pts = np.asarray(points, np.float64)
    if len(pts) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4))
    k = min(candidates, len(mesh.tets))
    _, cand = cKDTree(mesh.centroids()).query(pts, k=k)
    cand = cand.reshape(len(pts), -1)
    inv = np.linalg.inv(mesh.edges())                                  # (T, 3, 3)
    x0 = mesh.points[mesh.tets[:, 0]]                                  # (T, 3)
    b = np.einsum("nkij,nkj->nki", inv[cand], pts[:, None, :] - x0[cand])   # (N, k, 3)
    w = np.concatenate([1.0 - b.sum(-1, keepdims=True), b], axis=-1)    # (N, k, 4)
    best = w.min(-1).argmax(1)
    rows = np.arange(len(pts))
    return cand[rows, best].astype(np.int64), w[rows, best]


def embedded_positions(mesh_points: np.ndarray, tets: np.ndarray, tet: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """(N, 3) positions of embedded points for (deformed) vertex positions `mesh_points`."""
    return np.einsum("ni,nij->nj", bary, np.asarray(mesh_points)[tets[tet]])


def vertices_held_by(mesh: TetMesh, particle_positions: np.ndarray, particle_indices: np.ndarray,
                     spacing: float) -> np.ndarray:
    """The mesh vertices a set of particles holds: those whose nearest particle is in the set
    (the particle whose lattice cell they lie in or on), within one spacing."""
    idx = np.asarray(particle_indices, np.int64)
    if len(idx) == 0:
        return np.zeros(0, np.int64)
    d, nearest = cKDTree(np.asarray(particle_positions, np.float64)).query(mesh.points)
    held = np.isin(nearest, idx) & (d <= spacing)
    return np.flatnonzero(held)


def unloaded_points(mesh: TetMesh, inv_stretch: np.ndarray, held: np.ndarray, *, iterations: int = 200,
                    tol: float = 1e-7) -> np.ndarray:
    """(V, 3) the mesh's points at its stress-free rest, from the scan's preload (#23): `inv_stretch` (T, 3, 3) per
    tetrahedron undoes the preload's stretch there (V^-1 of the scan's F0 = R V: the stress fixes V, not the rotation),
    and the `held` vertices (a support, the ground) stay where the scan has them. Each tetrahedron's unloaded edges are
    V^-1 D (D its scan edges) turned by a rotation of its own: the rest and the rotations are found together by
    alternating a sparse least squares for the points (volume-weighted, its matrix factorised once) and each
    tetrahedron's best rotation (Procrustes), as-rigid-as-possible solvers do, until the points move less than `tol`
    of the mesh's size. A bent cantilever unbends: the rotations carry its curvature. A simulator that starts the
    mesh there and lets gravity act on its supports settles it back into the scan."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    pts = np.asarray(mesh.points, np.float64)
    tets = np.asarray(mesh.tets, np.int64)
    held = np.asarray(held, bool)
    if not held.any():
        raise ValueError("nothing holds the mesh: its unloaded rest is defined up to a rigid motion")
    V, T = len(pts), len(tets)
    target = np.einsum("tij,tjk->tik", np.asarray(inv_stretch, np.float64), mesh.edges())     # (T, 3, 3) columns
    w = np.sqrt(np.abs(mesh.volumes()))
    rows, cols, vals = [], [], []
    for e in range(3):                       # edge e of tet t: x[tets[t, e + 1]] - x[tets[t, 0]] = (R_t target_t)[:, e]
        r = np.arange(T) * 3 + e
        rows += [r, r]
        cols += [tets[:, e + 1], tets[:, 0]]
        vals += [w, -w]
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * T, V))
    free = ~held
    Af, Ah = A[:, free].tocsc(), A[:, held]
    lu = splu((Af.T @ Af).tocsc())
    fixed = Ah @ pts[held]
    size = float(np.max(np.ptp(pts, axis=0)))
    out = pts.copy()
    R = _linear_rotations(A, free, held, pts, target, w)     # the start: small rotations, solved with the points
    for _ in range(int(iterations)):
        b = (np.einsum("tij,tjk->tik", R, target).transpose(0, 2, 1) * w[:, None, None]).reshape(3 * T, 3) - fixed
        new = out.copy()
        new[free] = lu.solve(np.asarray(Af.T @ b))
        moved = float(np.abs(new - out).max())
        out = new
        p = out[tets]
        D = np.stack([p[:, 1] - p[:, 0], p[:, 2] - p[:, 0], p[:, 3] - p[:, 0]], axis=2)
        U, _, Wt = np.linalg.svd(D @ np.transpose(target, (0, 2, 1)))
        U[np.linalg.det(U @ Wt) < 0, :, 2] *= -1.0
        R = U @ Wt
        if moved < tol * size:
            break
    return out


def _linear_rotations(A, free, held, pts, target, w):
    """(T, 3, 3) each tetrahedron's rotation from the linearised problem: the points and a small rotation w_t per
    tetrahedron (D_t = (I + [w_t]x) target_t) in one sparse least squares, the rotations then exp([w_t]x). It integrates
    the curvature the stretches carry in one solve, where the alternating solve alone needs thousands of rounds to
    carry a rotation along a long bar."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    T = len(target)
    nf = int(free.sum())
    Af = A[:, free]
    # rows (t, edge e, axis a); the points' block acts on each axis alike: kron(Af, I3) with rows (t e) a
    Ax = sp.kron(Af, sp.identity(3, format="csr"), format="csr")                 # (9T, 3 nf)
    t = target.transpose(0, 2, 1)                                                 # (T, 3 edges, 3 xyz): edge vectors
    # [t]x w = t x w: the residual (x_j - x_i) - t - w x t = (x_j - x_i) - t + t x w
    cross = np.zeros((T, 3, 3, 3))                                                # (T, edge, axis, w component)
    cross[..., 0, 1], cross[..., 0, 2] = -t[..., 2], t[..., 1]
    cross[..., 1, 0], cross[..., 1, 2] = t[..., 2], -t[..., 0]
    cross[..., 2, 0], cross[..., 2, 1] = -t[..., 1], t[..., 0]
    cross *= w[:, None, None, None]
    r = np.arange(9 * T).reshape(T, 3, 3)
    c = 3 * np.arange(T)[:, None, None, None] + np.arange(3)[None, None, None, :]
    Aw = sp.csr_matrix((cross.ravel(), (np.broadcast_to(r[..., None], cross.shape).ravel(),
                                        np.broadcast_to(c, cross.shape).ravel())), shape=(9 * T, 3 * T))
    M = sp.hstack([Ax, Aw], format="csc")
    b = (t * w[:, None, None]).reshape(9 * T) - sp.kron(A[:, held], sp.identity(3, format="csr")) @ pts[held].ravel()
    # a light Tikhonov term on the rotations (their gauge along a tetrahedron's own symmetry is otherwise free)
    N = (M.T @ M + sp.diags(np.r_[np.zeros(3 * nf), np.full(3 * T, 1e-9 * float(np.mean(w ** 2)) + 1e-30)])).tocsc()
    sol = spsolve(N, M.T @ b)
    om = sol[3 * nf:].reshape(T, 3)
    ang = np.linalg.norm(om, axis=1)
    k = om / np.maximum(ang, 1e-30)[:, None]
    K = np.zeros((T, 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - np.transpose(K, (0, 2, 1))                                             # [k]x, skew
    s, c1 = np.sin(ang)[:, None, None], (1 - np.cos(ang))[:, None, None]
    return np.eye(3) + s * K + c1 * (K @ K)
