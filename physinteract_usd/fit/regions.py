"""Material regions: a piecewise-constant E field whose parts are found from the data.

The fit's model selection (`fit.fit`, schedule "ladder") starts from one E for the whole
object and splits a region in two only when the data ask for it:

- the *score* of a split is the loss's first derivative along the split's direction: with
  g_p = dL / dlog E_p at the current fit and a candidate part A of region R, the direction
  v = 1_A - (|A| / |R|) 1_R (zero mean over R, so the region's own parameter cannot absorb it)
  has derivative d = g . v (a Lagrange-multiplier / score test for the omitted parameter);
- its curvature h = v^T H v comes from two extra loss evaluations along v, and the predicted
  loss drop of the split is d^2 / (2 h);
- candidate parts come from the motion (where the score says "stiffer" vs "softer", smoothed
  over the particle graph) and from the appearance (colour clusters: material parts tend to
  differ in colour), each cut into connected pieces.

This module is the geometry and the bookkeeping (numpy, scipy); the loss evaluations are the
optimiser's.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def particle_graph(points: np.ndarray, radius: float) -> sp.csr_matrix:
    """Symmetric adjacency (P, P) of the particles within `radius` of each other."""
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    P = len(points)
    if len(pairs) == 0:
        return sp.csr_matrix((P, P))
    i, j = pairs[:, 0], pairs[:, 1]
    A = sp.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(P, P))
    return A.tocsr()


def smooth(values: np.ndarray, graph: sp.csr_matrix, steps: int = 3, within: np.ndarray | None = None) -> np.ndarray:
    """`steps` rounds of averaging each value with its graph neighbours (a heat-diffusion denoiser).
    With `within` (P,) labels, only neighbours of the same label are averaged."""
    A = graph
    if within is not None:
        A = A.tocoo()
        keep = within[A.row] == within[A.col]
        A = sp.csr_matrix((A.data[keep], (A.row[keep], A.col[keep])), shape=graph.shape)
    deg = np.asarray(A.sum(1)).ravel()
    v = np.asarray(values, np.float64).copy()
    for _ in range(steps):
        v = (v + A @ v) / (1.0 + deg)
    return v


def components(mask: np.ndarray, graph: sp.csr_matrix) -> list[np.ndarray]:
    """The connected pieces (index arrays) of the particles where `mask` is true, largest first."""
    idx = np.where(mask)[0]
    if len(idx) == 0:
        return []
    sub = graph[idx][:, idx]
    n, lab = connected_components(sub, directed=False)
    parts = [idx[lab == k] for k in range(n)]
    return sorted(parts, key=len, reverse=True)


def split_direction(labels: np.ndarray, region: int, part: np.ndarray) -> np.ndarray:
    """v (P,): +1 - |A|/|R| on the part A, -|A|/|R| on the rest of region R, 0 elsewhere."""
    v = np.zeros(len(labels))
    inside = labels == region
    a = np.zeros(len(labels), bool)
    a[part] = True
    share = a.sum() / max(inside.sum(), 1)
    v[inside] = -share
    v[a] += 1.0
    return v


def score_parts(score: np.ndarray, labels: np.ndarray, region: int, graph: sp.csr_matrix,
                min_size: int) -> list[np.ndarray]:
    """Candidate parts of `region` from the motion: where the (smoothed) score says the material
    wants to be stiffer (negative dL/dlogE) against softer, split at the score's weighted median,
    each side's largest connected piece (at least `min_size` particles, at most all but
    `min_size`)."""
    inside = labels == region
    n = int(inside.sum())
    if n < 2 * min_size:
        return []
    s = smooth(score, graph, steps=4, within=labels)
    cut = float(np.median(s[inside]))
    out = []
    for side in (s < cut, s >= cut):
        for piece in components(side & inside, graph)[:1]:
            if min_size <= len(piece) <= n - min_size:
                out.append(piece)
    return out


def appearance_parts(features: np.ndarray | None, labels: np.ndarray, region: int, graph: sp.csr_matrix,
                     min_size: int, min_contrast: float = 0.08, seed: int = 0) -> list[np.ndarray]:
    """Candidate parts of `region` from the appearance: two colour clusters (k-means on the
    particles' local mean colours) when their centres differ by more than `min_contrast` (RGB
    distance), each cluster's connected pieces of at least `min_size` particles."""
    if features is None:
        return []
    from scipy.cluster.vq import kmeans2

    inside = np.where(labels == region)[0]
    if len(inside) < 2 * min_size:
        return []
    f = np.asarray(features, np.float64)[inside]
    rng = np.random.default_rng(seed)
    init = f[rng.choice(len(f), 2, replace=False)]
    centres, lab = kmeans2(f, init, minit="matrix", seed=seed)
    if len(np.unique(lab)) < 2 or np.linalg.norm(centres[0] - centres[1]) < min_contrast:
        return []
    out = []
    for k in (0, 1):
        mask = np.zeros(len(labels), bool)
        mask[inside[lab == k]] = True
        for piece in components(mask, graph):
            if min_size <= len(piece) <= len(inside) - min_size:
                out.append(piece)
    return out


def relabel_split(labels: np.ndarray, part: np.ndarray) -> np.ndarray:
    """The labels with `part` as a new region (the next free label)."""
    out = labels.copy()
    out[part] = labels.max() + 1
    return out


def attach_held(labels: np.ndarray, held: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Held particles (a support holds them: the video cannot see their material) take the label
    of the nearest free particle."""
    held = np.asarray(held, bool)
    if not held.any() or held.all():
        return labels
    free = np.where(~held)[0]
    _, nn = cKDTree(points[free]).query(points[held])
    out = labels.copy()
    out[held] = labels[free[nn]]
    return out


def one_hot(labels: np.ndarray) -> np.ndarray:
    """(P, m) indicator basis of the regions 0..m-1 (a partition of unity)."""
    m = int(labels.max()) + 1
    B = np.zeros((len(labels), m))
    B[np.arange(len(labels)), labels] = 1.0
    return B


# ---------------------------------------------------------------------- parts (schedule "select")

def colour_clusters(features: np.ndarray | None, free: np.ndarray, min_contrast: float = 0.08, k_max: int = 3,
                    seed: int = 0) -> np.ndarray | None:
    """Colour clusters of the free particles (k-means on their local mean colours; -1 on held
    ones), or None when the colours do not differ. The rule for k: k = 2 when its two centres
    differ by more than `min_contrast` (RGB distance); k = 3 (up to `k_max`) only when every pair
    of its centres differs by more than `min_contrast`, no centre lies within `min_contrast` of the
    segment between two others (not the blended colours along the edge between two parts), and the
    third cluster removes at least half of the within-cluster scatter k = 2 leaves (a third colour,
    not the texture of two)."""
    if features is None:
        return None
    from scipy.cluster.vq import kmeans2

    free = np.asarray(free, bool)
    idx = np.where(free)[0]
    if len(idx) < 4:
        return None
    f = np.asarray(features, np.float64)[idx]
    best, sse_prev = None, None
    for k in range(2, int(k_max) + 1):
        if len(f) < 2 * k:
            break
        # k-means++ starts, the best of a few seeds (k-means falls into local minima)
        runs = []
        for r in range(4):
            c, lab = kmeans2(f, k, minit="++", seed=seed + r)
            sse = float(((f - c[lab]) ** 2).sum())
            runs.append((sse, c, lab))
        sse, c, lab = min(runs, key=lambda t: t[0])
        used = np.unique(lab)
        if len(used) < k:
            break
        d = np.linalg.norm(c[:, None] - c[None], axis=-1)[np.triu_indices(k, 1)]
        if d.min() < min_contrast or (k >= 3 and _blend(c) < min_contrast):
            break
        if sse_prev is not None and sse > 0.5 * sse_prev:
            break
        best, sse_prev = lab, sse
    if best is None:
        return None
    out = np.full(len(free), -1, np.int64)
    out[idx] = best
    return out


THICK_RATIO = 1.25   # `thickness_clusters`: the thick class's median local thickness over the thin class's, at least
                     # (the 12 suite scenes at init --grid auto, 2026-11-29, development data: a glove's palm 44 mm
                     # against its fingers' 26 (1.67), a toy rope's knots against the rope (1.31), a tow rope's hooks
                     # (1.32), a flower's stem (2.06); an object of one thickness 1.00-1.06: a bar, a rope, a ball)


def thickness_clusters(points: np.ndarray, spacing: float, free: np.ndarray, graph: sp.csr_matrix,
                       min_ratio: float = THICK_RATIO, steps: int = 3) -> tuple[np.ndarray | None, tuple]:
    """Two clusters of the free particles by shape: thin against thick (-1 on held ones), or None where the object is of
    one thickness. The particles' local thickness (`thickness.point_thickness`), its log smoothed over the particle graph
    (`steps` rounds), split where the two classes' variance of log thickness is least (Otsu's threshold); kept only
    where the thick class's median is at least `min_ratio` times the thin one's. Why (#24): the parts of a composite
    object are often of different thickness and material both (a glove's palm and its fingers, a rope's knots), and
    where the colours are a pattern (a checker, stripes: `separation`) or one colour, shape is the prior left.
    Returns (labels or None, (thin median, thick median) in metres, or ())."""
    from ..thickness import point_thickness

    free = np.asarray(free, bool)
    if free.sum() < 8:
        return None, ()
    t = point_thickness(points, spacing)
    if not np.isfinite(t).all():
        return None, ()
    lt = smooth(np.log(t), graph, steps=steps)
    v = np.sort(lt[free])
    n = len(v)
    c = np.cumsum(v)
    k = np.arange(1, n)                       # the thin class: the first k values
    m0, m1 = c[:-1] / k, (c[-1] - c[:-1]) / (n - k)
    between = k * (n - k) * (m0 - m1) ** 2    # Otsu: the largest between-class variance, the least within
    between[v[1:] <= v[:-1]] = -1.0           # a threshold between two different values only
    j = int(np.argmax(between))
    if between[j] <= 0:
        return None, ()
    cut = 0.5 * (v[j] + v[j + 1])
    thick = lt >= cut
    if not (free & thick).any() or not (free & ~thick).any():
        return None, ()
    med = (float(np.median(t[free & ~thick])), float(np.median(t[free & thick])))
    if med[1] < min_ratio * med[0]:
        return None, med
    return np.where(free, thick.astype(np.int64), -1), med


def _blend(c: np.ndarray) -> float:
    """How far the centre nearest a blend of two others lies from the segment between them (RGB
    distance): the local mean colours at the edge between two colours lie on that segment."""
    out = float("inf")
    for i in range(len(c)):
        for j in range(len(c)):
            for k in range(j + 1, len(c)):
                if i in (j, k):
                    continue
                a, b = c[j], c[k]
                t = float(np.clip(np.dot(c[i] - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0.0, 1.0))
                out = min(out, float(np.linalg.norm(c[i] - (a + t * (b - a)))))
    return out


def connected_parts(cluster: np.ndarray, graph: sp.csr_matrix, min_size: int, max_parts: int) -> np.ndarray | None:
    """Parts (labels 0..m-1, -1 where `cluster` is -1) from cluster labels: each cluster's connected
    pieces are parts; a piece smaller than `min_size` joins the neighbouring part it shares most
    graph edges with (largest pieces first keep their own). With more than `max_parts` connected
    parts left, each cluster is one part (its pieces share one E: same colour, same material).
    None when fewer than two parts are left."""
    cluster = np.asarray(cluster, np.int64)
    lab = np.full(len(cluster), -1, np.int64)
    pieces = []
    for c in np.unique(cluster[cluster >= 0]):
        pieces += [(c, p) for p in components(cluster == c, graph)]
    pieces.sort(key=lambda t: -len(t[1]))
    big = [p for p in pieces if len(p[1]) >= min_size]
    for j, (_, p) in enumerate(big):
        lab[p] = j
    small = [p for _, p in pieces if len(p) < min_size]
    G = graph.tocsr()
    for _ in range(len(small) + 1):      # a small piece may touch only another small one: repeat
        left = []
        for p in small:
            nb = G[p].indices
            nb = nb[lab[nb] >= 0]
            if len(nb):
                lab[p] = np.bincount(lab[nb]).argmax()
            else:
                left.append(p)
        if len(left) == len(small):
            break
        small = left
    for p in small:                      # isolated: the nearest part by graph-free distance
        lab[p] = 0 if len(big) else -1
    m = int(lab.max()) + 1
    if m > max_parts:
        cl = np.unique(cluster[cluster >= 0])
        lab = np.where(cluster >= 0, np.searchsorted(cl, cluster), -1)
        m = len(cl)
    return lab if m >= 2 else None


def section_average(values: np.ndarray, points: np.ndarray, radius: float, weights: np.ndarray) -> np.ndarray:
    """Each particle's value averaged (by `weights`, e.g. 1 on free particles and 0 on held ones)
    over the particles within `radius` of it, itself included; where no weighted particle is near,
    the value itself."""
    P = len(points)
    w = np.asarray(weights, np.float64)
    pairs = cKDTree(points).query_pairs(float(radius), output_type="ndarray")
    i, j = (pairs[:, 0], pairs[:, 1]) if len(pairs) else (np.zeros(0, int), np.zeros(0, int))
    A = sp.coo_matrix((np.ones(2 * len(i)), (np.r_[i, j], np.r_[j, i])), shape=(P, P)).tocsr() + sp.eye(P, format="csr")
    num, den = A @ (w * np.asarray(values, np.float64)), A @ w
    return np.where(den > 0, num / np.maximum(den, 1e-300), values)


def motion_clusters(score: np.ndarray, free: np.ndarray, graph: sp.csr_matrix, steps: int = 4,
                    points: np.ndarray | None = None, section: float | None = None) -> np.ndarray | None:
    """Two clusters of the free particles from the motion: the (smoothed) score dL/dlog E split at
    its median, the side that wants a stiffer material (negative score) against the softer one;
    -1 on held particles. None without a free particle on either side. With `section` (metres, the
    object's thickness) and `points`, the score is averaged over a ball that wide around each
    particle (`section_average`) rather than `steps` rounds over the particle graph: a section of a
    rod or a sheet bends and stretches as one (the video sees its stiffness, E integrated over the
    section), so the score's variation across a section (one side of a bend against the other) is
    not the material's, and a cut on it splits the object lengthwise (hemp_rope on an H200: two
    parts side by side over the rope's lower half, fitted 15.9 and 13.3 kPa)."""
    free = np.asarray(free, bool)
    if free.sum() < 4:
        return None
    if section is not None and points is not None and section > 0:
        s = section_average(np.where(free, score, 0.0), points, section, free)
    else:
        s = smooth(np.where(free, score, 0.0), graph, steps=steps, within=free.astype(np.int64))
    cut = float(np.median(s[free]))
    out = np.where(free, (s >= cut).astype(np.int64), -1)
    if len(np.unique(out[free])) < 2:
        return None
    return out


def separation(points: np.ndarray, labels: np.ndarray) -> float:
    """How far apart a partition's parts lie, at the scale of the parts themselves: for each part, the mean distance
    from its particles to the nearest particle of another part over the part's thinnest extent (the square root of
    its positions' smallest covariance eigenvalue), averaged over the parts by their particle shares. Regions (a bar's
    two halves, a flower's stem, centre and petals) score ~2-5; the two colour classes of a pattern (a checker, stripes,
    dots: each class spread over the whole object, every particle near the other class) ~0.25-0.9 (the 12 suite
    scenes, docs/benchmarks/fit.md). A flat layer against one neighbour scores sqrt(3) = 1.73 whatever its thickness (a
    little more where it is few particles thick); a layer between two, ~0.87 (#24). inf for fewer than two parts."""
    x = np.asarray(points, np.float64)
    lab = np.asarray(labels)
    parts = [k for k in np.unique(lab) if k >= 0]
    if len(parts) < 2:
        return float("inf")
    total, weight = 0.0, 0
    for k in parts:
        m = lab == k
        if m.sum() < 4 or (~m).sum() == 0:
            continue
        d = cKDTree(x[~m]).query(x[m])[0]
        thin = float(np.sqrt(max(np.linalg.eigvalsh(np.cov(x[m].T))[0], 0.0)))
        r = float(d.mean()) / thin if thin > 0 else float("inf")
        total += m.sum() * r
        weight += int(m.sum())
    return total / weight if weight else float("inf")


def same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two labelings split the particles alike (the same parts under any names)."""
    a, b = np.asarray(a), np.asarray(b)
    pairs = np.unique(np.stack([a, b], 1), axis=0)
    return len(pairs) == len(np.unique(a)) == len(np.unique(b))


def harmonic_fill(values: np.ndarray, known: np.ndarray, graph: sp.csr_matrix) -> np.ndarray:
    """`values` where `known`, and elsewhere the harmonic extension of the known values over the
    particle graph: each unknown value is the mean of its graph neighbours' (the discrete Laplace
    equation with the known particles as its boundary). An unknown region attached to one known
    material takes that material's value exactly (a constant is harmonic); one between two takes a
    blend weighted by how near each is along the graph. A piece of unknown particles that touches no
    known one keeps its own values (nothing to attach it to)."""
    from scipy.sparse.linalg import spsolve

    v = np.asarray(values, np.float64).copy()
    known = np.asarray(known, bool)
    if known.all() or not known.any():
        return v
    A = sp.csr_matrix(graph, dtype=np.float64)
    # the unknown pieces that reach a known particle; the others keep their values
    reach = np.zeros(len(v), bool)
    for piece in components(~known, A):
        if A[piece][:, known].nnz:
            reach[piece] = True
    iu, ik = np.where(reach)[0], np.where(known)[0]
    if not len(iu):
        return v
    deg = np.asarray(A[iu].sum(1)).ravel()
    L_uu = sp.diags(deg) - A[iu][:, iu]
    rhs = A[iu][:, ik] @ v[ik]
    v[iu] = spsolve(sp.csc_matrix(L_uu), rhs)
    return v
