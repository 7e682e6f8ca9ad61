"""Tile-based 3D Gaussian splatting rasterizer in Warp: forward and backward, CPU and CUDA,
float32 and float64.

Pipeline (one static pinhole camera, see `camera.Camera` for the conventions):

1. ``project``: per Gaussian, world mean -> OpenCV camera frame (``w2c_cv``), EWA splat
   ``cov2d = J W Sigma W^T J^T + low_pass * I`` (J the perspective Jacobian, evaluated with the
   camera-frame x/z and y/z clamped to 1.3x the field of view as in 3DGS / gsplat), its inverse
   (the conic), the 2D mean ``u = fx x / z + cx`` (pixel (i, j)'s centre at (i + 0.5, j + 0.5)),
   and the rectangle of tiles (``tile_size``: 16x16 on CUDA, one 256-thread block per tile; 8x8
   on CPU) covered by the bounding box of its cut-off ellipse.
2. Sort: Gaussians by float32 camera z (stable radix sort, ties by index), then the
   (tile, Gaussian) pairs, emitted in depth order, stably by tile id: each tile's list is front
   to back.
3. ``rasterize_forward``: one thread per pixel, front-to-back alpha compositing over its tile's
   list. Outputs colour (premultiplied, over black), alpha = 1 - T and the alpha-weighted
   camera-frame z; stores the final transmittance and the end of the contributing range for the
   backward pass. The background is composited outside (``rgb + (1 - alpha) * bg``, in torch).
4. ``rasterize_backward``: one thread per pixel, back to front, reconstructing T_i by division by
   (1 - alpha_i), accumulating per-Gaussian gradients (2D mean, conic, opacity, z, colour) with
   atomics; then ``project_backward`` chains them to the 3D mean and the covariance.

Cut-offs (the dense torch reference in tests/render_reference.py states and applies the same):

- a Gaussian is culled when its camera z is not in (near, far), or when opacity < alpha_min;
- default (``floor="subtract"``): alpha = min(alpha_max, opacity exp(-sigma^2 / 2) - alpha_min)
  with sigma^2 = d^T conic d, and a Gaussian touches pixel p only where that is > 0 (out to
  sigma^2 = 2 ln(opacity / alpha_min) <= 11.1, i.e. ~3.3 sigma). Alpha is continuous where a
  footprint ends, so moving Gaussians change images smoothly and the analytic gradient matches
  finite differences (3DGS's hard cut made it ~20% low on a fit scene: docs/render.md);
- ``floor="cut"`` (3DGS): touches only when sigma^2 <= 9 (``extent_sigma`` = 3) and
  alpha = min(alpha_max, opacity exp(-sigma^2 / 2)) >= alpha_min (1/255);
- ``alpha_max`` = 0.99 in both;
- front to back, the first Gaussian that would take T below ``t_min`` (1e-4) stops the pixel
  and is itself left out (as in 3DGS);
- 2D low-pass: ``low_pass`` = 0.3 px^2 added to the diagonal of the 2D covariance, so flat
  (surfel) and needle Gaussians stay at least ~0.55 px wide and invertible.
"""


import math
from dataclasses import dataclass

import warp as wp

FLOAT32_MAX = 3.0e38


@dataclass(frozen=True)
class RasterSettings:
    """Renderer cut-offs and tiling. The defaults are 3DGS's."""

    tile_size: int | None = None   # None: 16 on CUDA (one 256-thread block per tile), 8 on CPU
    low_pass: float = 0.3          # px^2 added to the 2D covariance diagonal
    extent_sigma: float = 3.0      # Gaussians are cut at this Mahalanobis distance
    alpha_min: float = 1.0 / 255.0  # contributions below this alpha are skipped
    alpha_max: float = 0.99        # alpha is clamped to this
    t_min: float = 1e-4            # transmittance cut-off (the Gaussian that crosses it is left out)
    fov_clamp: float = 0.3         # J uses x/z clamped to (W - cx)/fx + fov_clamp * 0.5 W / fx (gsplat)
    lockstep: bool | None = None   # backward: all pixels of a tile walk its list together (None: on CUDA)
    floor: str = "subtract"        # "subtract": alpha = opacity G - alpha_min, cut where it reaches 0
                                   # (continuous: no jump where a pixel leaves a footprint, so the
                                   # gradient matches finite differences); "cut": 3DGS's hard cut
                                   # at extent_sigma and alpha_min
    backward: str = "pixel"        # "pixel": per-pixel atomics; "tiled": block reduction per Gaussian
                                   # (launch_tiled; CUDA, or CPU with wp.config.enable_cpu_blocks)

    def resolved_tile_size(self, device) -> int:
        if self.tile_size is not None:
            return int(self.tile_size)
        return 16 if str(device).startswith("cuda") else 8

    def resolved_lockstep(self, device) -> bool:
        if self.lockstep is not None:
            return bool(self.lockstep)
        return str(device).startswith("cuda")


# --------------------------------------------------------------------------------- kernels
def _build(scalar):
    """Kernels for one float type (closures over the type; one Warp module per type)."""
    vec2 = wp.types.vector(2, scalar)
    vec3 = wp.types.vector(3, scalar)
    vec6 = wp.types.vector(6, scalar)
    vec8 = wp.types.vector(8, scalar)
    mat22 = wp.types.matrix((2, 2), scalar)
    mat23 = wp.types.matrix((2, 3), scalar)
    mat33 = wp.types.matrix((3, 3), scalar)
    mod = "physinteract_render_f%d" % (8 * wp.types.type_size_in_bytes(scalar))

    @wp.struct
    class Cam:
        R: mat33
        t: vec3
        fx: scalar
        fy: scalar
        cx: scalar
        cy: scalar
        width: int
        height: int
        near: scalar
        far: scalar
        lim_xp: scalar
        lim_xn: scalar
        lim_yp: scalar
        lim_yn: scalar
        low_pass: scalar
        ext2: scalar
        cut2: scalar
        sub: scalar
        thr: scalar
        alpha_min: scalar
        alpha_max: scalar
        t_min: scalar
        tile_size: int
        tiles_x: int
        tiles_y: int

    @wp.func
    def sym33(c: vec6):
        return mat33(c[0], c[1], c[2], c[1], c[3], c[4], c[2], c[4], c[5])

    @wp.kernel(module=mod)
    def project(means: wp.array(dtype=vec3), cov6: wp.array(dtype=vec6), opac: wp.array(dtype=scalar),
                cams: wp.array(dtype=Cam), n_per: int, pack: wp.array(dtype=vec8), rect: wp.array(dtype=wp.vec4i),
                count: wp.array(dtype=wp.int32), dkey: wp.array(dtype=wp.float32), order: wp.array(dtype=wp.int32)):
        i = wp.tid()
        cam = cams[i / n_per]       # Gaussian i belongs to image i / n_per (n_per Gaussians each)
        order[i] = i
        count[i] = 0
        dkey[i] = wp.float32(FLOAT32_MAX)
        pc = cam.R * means[i] + cam.t
        x = pc[0]
        y = pc[1]
        z = pc[2]
        op = opac[i]
        if not (z > cam.near and z < cam.far and op >= cam.alpha_min):
            return
        rz = scalar(1.0) / z
        tx = z * wp.min(cam.lim_xp, wp.max(-cam.lim_xn, x * rz))
        ty = z * wp.min(cam.lim_yp, wp.max(-cam.lim_yn, y * rz))
        J = mat23(cam.fx * rz, scalar(0.0), -cam.fx * tx * rz * rz,
                  scalar(0.0), cam.fy * rz, -cam.fy * ty * rz * rz)
        Wc = cam.R * sym33(cov6[i]) * wp.transpose(cam.R)
        c2 = J * Wc * wp.transpose(J)
        a = c2[0, 0] + cam.low_pass
        b = scalar(0.5) * (c2[0, 1] + c2[1, 0])
        c = c2[1, 1] + cam.low_pass
        det = a * c - b * b
        if not (det > scalar(0.0)):
            return
        u = cam.fx * x * rz + cam.cx
        v = cam.fy * y * rz + cam.cy
        # pixels that can pass both per-pixel cut-offs lie inside the ellipse sigma^2 <= ext2
        ext2 = wp.min(cam.ext2, scalar(2.0) * wp.log(op / cam.alpha_min))
        rx = wp.sqrt(ext2 * a)
        ry = wp.sqrt(ext2 * c)
        if not (wp.abs(u) < scalar(1.0e7) and wp.abs(v) < scalar(1.0e7) and rx < scalar(1.0e7) and ry < scalar(1.0e7)):
            return
        # pixel i covers centre i + 0.5; one pixel of slack on each side
        i0 = int(wp.floor(u - rx - scalar(0.5)))
        i1 = int(wp.ceil(u + rx - scalar(0.5)))
        j0 = int(wp.floor(v - ry - scalar(0.5)))
        j1 = int(wp.ceil(v + ry - scalar(0.5)))
        i0 = wp.max(i0, 0)
        j0 = wp.max(j0, 0)
        i1 = wp.min(i1, cam.width - 1)
        j1 = wp.min(j1, cam.height - 1)
        if i0 > i1 or j0 > j1:
            return
        tx0 = i0 / cam.tile_size
        tx1 = i1 / cam.tile_size + 1
        ty0 = j0 / cam.tile_size
        ty1 = j1 / cam.tile_size + 1
        inv_det = scalar(1.0) / det
        pack[i] = vec8(u, v, c * inv_det, -b * inv_det, a * inv_det, op, z, scalar(0.0))
        rect[i] = wp.vec4i(tx0, ty0, tx1, ty1)
        count[i] = (tx1 - tx0) * (ty1 - ty0)
        dkey[i] = wp.float32(z)

    @wp.kernel(module=mod)
    def gather_counts(order: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                      out: wp.array(dtype=wp.int32)):
        k = wp.tid()
        out[k] = count[order[k]]

    @wp.kernel(module=mod)
    def emit_pairs(order: wp.array(dtype=wp.int32), counts_sorted: wp.array(dtype=wp.int32),
                   incl: wp.array(dtype=wp.int32), rect: wp.array(dtype=wp.vec4i), tiles_x: int,
                   n_per: int, n_tiles: int,
                   keys: wp.array(dtype=wp.int32), vals: wp.array(dtype=wp.int32)):
        k = wp.tid()
        n = counts_sorted[k]
        if n == 0:
            return
        g = order[k]
        o = incl[k] - n
        r = rect[g]
        base = (g / n_per) * n_tiles        # the tiles of Gaussian g's image
        for ty in range(r[1], r[3]):
            for tx in range(r[0], r[2]):
                keys[o] = base + ty * tiles_x + tx
                vals[o] = g
                o += 1

    @wp.kernel(module=mod)
    def tile_ranges(keys: wp.array(dtype=wp.int32), n: int, ranges: wp.array2d(dtype=wp.int32)):
        i = wp.tid()
        t = keys[i]
        if i == 0:
            ranges[t, 0] = i
        elif keys[i - 1] != t:
            ranges[t, 0] = i
        if i == n - 1:
            ranges[t, 1] = i + 1
        elif keys[i + 1] != t:
            ranges[t, 1] = i + 1

    @wp.kernel(module=mod)
    def gather_pairs(ids: wp.array(dtype=wp.int32), pack: wp.array(dtype=vec8), colors: wp.array(dtype=vec3),
                     pk: wp.array(dtype=vec8), pcol: wp.array(dtype=vec3)):
        """Per-pair copies in tile/depth order: the per-pixel loops then read contiguous memory
        with no dependent (indirect) load."""
        i = wp.tid()
        g = ids[i]
        pk[i] = pack[g]
        pcol[i] = colors[g]

    @wp.func
    def pixel_of(tid: int, cam: Cam):
        """Thread -> (tile over all images, image, pixel x, y); images one after another, each
        tiles_x * tiles_y tiles of tile_size^2 threads."""
        ts2 = cam.tile_size * cam.tile_size
        tile = tid / ts2
        loc = tid - tile * ts2
        n_tiles = cam.tiles_x * cam.tiles_y
        img = tile / n_tiles
        lt = tile - img * n_tiles
        tyi = lt / cam.tiles_x
        txi = lt - tyi * cam.tiles_x
        px = txi * cam.tile_size + loc % cam.tile_size
        py = tyi * cam.tile_size + loc / cam.tile_size
        return tile, img, px, py

    @wp.kernel(module=mod)
    def rasterize_forward(pk: wp.array(dtype=vec8), pcol: wp.array(dtype=vec3),
                          ranges: wp.array2d(dtype=wp.int32), cam: Cam,
                          out_rgb: wp.array(dtype=vec3), out_alpha: wp.array(dtype=scalar),
                          out_depth: wp.array(dtype=scalar), out_T: wp.array(dtype=scalar),
                          out_last: wp.array(dtype=wp.int32), tile_last: wp.array(dtype=wp.int32)):
        tile, img, px, py = pixel_of(wp.tid(), cam)
        if px >= cam.width or py >= cam.height:
            return
        pix = (img * cam.height + py) * cam.width + px
        pxc = scalar(px) + scalar(0.5)
        pyc = scalar(py) + scalar(0.5)
        r0 = ranges[tile, 0]
        r1 = ranges[tile, 1]
        T = scalar(1.0)
        C = vec3(scalar(0.0))
        D = scalar(0.0)
        last = r0
        for k in range(r0, r1):
            p = pk[k]
            dx = p[0] - pxc
            dy = p[1] - pyc
            s2 = p[2] * dx * dx + scalar(2.0) * p[3] * dx * dy + p[4] * dy * dy
            if s2 > cam.cut2:
                continue
            al = wp.min(cam.alpha_max, p[5] * wp.exp(scalar(-0.5) * s2) - cam.sub)
            if al < cam.thr:
                continue
            Tn = T * (scalar(1.0) - al)
            if Tn < cam.t_min:
                break
            w = al * T
            C += pcol[k] * w
            D += p[6] * w
            T = Tn
            last = k + 1
        out_rgb[pix] = C
        out_alpha[pix] = scalar(1.0) - T
        out_depth[pix] = D
        out_T[pix] = T
        out_last[pix] = last
        if last > r0:
            wp.atomic_max(tile_last, tile, last)

    @wp.kernel(module=mod)
    def rasterize_backward(pk: wp.array(dtype=vec8), pcol: wp.array(dtype=vec3),
                           ids: wp.array(dtype=wp.int32), ranges: wp.array2d(dtype=wp.int32), cam: Cam,
                           T_final: wp.array(dtype=scalar), last_idx: wp.array(dtype=wp.int32),
                           tile_last: wp.array(dtype=wp.int32), lockstep: int,
                           g_rgb: wp.array(dtype=vec3), g_alpha: wp.array(dtype=scalar),
                           g_depth: wp.array(dtype=scalar),
                           g_pack: wp.array(dtype=vec8), g_colors: wp.array(dtype=vec3)):
        tile, img, px, py = pixel_of(wp.tid(), cam)
        if px >= cam.width or py >= cam.height:
            return
        pix = (img * cam.height + py) * cam.width + px
        start = ranges[tile, 0]
        last = last_idx[pix]
        # lockstep: every pixel of the tile walks the same k (uniform loads and atomics on a GPU)
        kmax = last
        if lockstep != 0:
            kmax = tile_last[tile]
        if kmax <= start:
            return
        pxc = scalar(px) + scalar(0.5)
        pyc = scalar(py) + scalar(0.5)
        Tf = T_final[pix]
        T = Tf
        gC = g_rgb[pix]
        gA = g_alpha[pix]
        gD = g_depth[pix]
        Sc = vec3(scalar(0.0))
        Sd = scalar(0.0)
        for kk in range(kmax - start):
            k = kmax - 1 - kk
            if k >= last:
                continue
            p = pk[k]
            dx = p[0] - pxc
            dy = p[1] - pyc
            s2 = p[2] * dx * dx + scalar(2.0) * p[3] * dx * dy + p[4] * dy * dy
            if s2 > cam.cut2:
                continue
            G = wp.exp(scalar(-0.5) * s2)
            ar = p[5] * G - cam.sub
            al = wp.min(cam.alpha_max, ar)
            if al < cam.thr:
                continue
            om = scalar(1.0) - al
            T = T / om
            w = al * T
            c = pcol[k]
            z = p[6]
            g = ids[k]
            wp.atomic_add(g_colors, g, gC * w)
            dLda = wp.dot(gC, c * T - Sc / om) + gD * (z * T - Sd / om) + gA * Tf / om
            Sc += c * w
            Sd += z * w
            gop = scalar(0.0)
            gs2 = scalar(0.0)
            if ar <= cam.alpha_max:
                gop = dLda * G
                gs2 = scalar(-0.5) * dLda * p[5] * G
            gu = gs2 * scalar(2.0) * (p[2] * dx + p[3] * dy)
            gv = gs2 * scalar(2.0) * (p[3] * dx + p[4] * dy)
            wp.atomic_add(g_pack, g, vec8(gu, gv, gs2 * dx * dx, gs2 * scalar(2.0) * dx * dy,
                                          gs2 * dy * dy, gop, gD * w, scalar(0.0)))

    vec11 = wp.types.vector(11, scalar)

    @wp.kernel(module=mod)
    def rasterize_backward_tiled(pk: wp.array(dtype=vec8), pcol: wp.array(dtype=vec3),
                                 ids: wp.array(dtype=wp.int32), ranges: wp.array2d(dtype=wp.int32), cam: Cam,
                                 T_final: wp.array(dtype=scalar), last_idx: wp.array(dtype=wp.int32),
                                 tile_last: wp.array(dtype=wp.int32),
                                 g_rgb: wp.array(dtype=vec3), g_alpha: wp.array(dtype=scalar),
                                 g_depth: wp.array(dtype=scalar),
                                 g_pack: wp.array(dtype=vec8), g_colors: wp.array(dtype=vec3)):
        """One block per tile (block_dim = tile_size^2, launch_tiled): the block walks the tile's
        list in lockstep and sums each Gaussian's gradient over its pixels with a block
        reduction, then one thread adds it (one atomic per Gaussian and tile instead of one per
        pixel). Same arithmetic as rasterize_backward."""
        tile, lane = wp.tid()
        ts = cam.tile_size
        n_tiles = cam.tiles_x * cam.tiles_y
        img = tile / n_tiles
        lt = tile - img * n_tiles
        tyi = lt / cam.tiles_x
        txi = lt - tyi * cam.tiles_x
        px = txi * ts + lane % ts
        py = tyi * ts + lane / ts
        inside = px < cam.width and py < cam.height
        pix = (img * cam.height + wp.min(py, cam.height - 1)) * cam.width + wp.min(px, cam.width - 1)
        start = ranges[tile, 0]
        kmax = tile_last[tile]
        last = start
        Tf = scalar(0.0)
        gC = vec3(scalar(0.0))
        gA = scalar(0.0)
        gD = scalar(0.0)
        if inside:
            last = last_idx[pix]
            Tf = T_final[pix]
            gC = g_rgb[pix]
            gA = g_alpha[pix]
            gD = g_depth[pix]
        T = Tf
        pxc = scalar(px) + scalar(0.5)
        pyc = scalar(py) + scalar(0.5)
        Sc = vec3(scalar(0.0))
        Sd = scalar(0.0)
        for kk in range(kmax - start):
            k = kmax - 1 - kk
            g = ids[k]
            contrib = vec11(scalar(0.0))
            if k < last:
                p = pk[k]
                dx = p[0] - pxc
                dy = p[1] - pyc
                s2 = p[2] * dx * dx + scalar(2.0) * p[3] * dx * dy + p[4] * dy * dy
                if s2 <= cam.cut2:
                    G = wp.exp(scalar(-0.5) * s2)
                    ar = p[5] * G - cam.sub
                    al = wp.min(cam.alpha_max, ar)
                    if al >= cam.thr:
                        om = scalar(1.0) - al
                        T = T / om
                        w = al * T
                        c = pcol[k]
                        z = p[6]
                        dLda = wp.dot(gC, c * T - Sc / om) + gD * (z * T - Sd / om) + gA * Tf / om
                        Sc += c * w
                        Sd += z * w
                        gop = scalar(0.0)
                        gs2 = scalar(0.0)
                        if ar <= cam.alpha_max:
                            gop = dLda * G
                            gs2 = scalar(-0.5) * dLda * p[5] * G
                        contrib = vec11(gs2 * scalar(2.0) * (p[2] * dx + p[3] * dy),
                                        gs2 * scalar(2.0) * (p[3] * dx + p[4] * dy),
                                        gs2 * dx * dx, gs2 * scalar(2.0) * dx * dy, gs2 * dy * dy,
                                        gop, gD * w, gC[0] * w, gC[1] * w, gC[2] * w, scalar(0.0))
            tot = wp.tile_sum(wp.tile(contrib, preserve_type=True))
            if lane == 0:
                v = tot[0]
                wp.atomic_add(g_pack, g, vec8(v[0], v[1], v[2], v[3], v[4], v[5], v[6], scalar(0.0)))
                wp.atomic_add(g_colors, g, vec3(v[7], v[8], v[9]))

    @wp.kernel(module=mod)
    def project_backward(means: wp.array(dtype=vec3), cov6: wp.array(dtype=vec6), count: wp.array(dtype=wp.int32),
                         pack: wp.array(dtype=vec8), g_pack: wp.array(dtype=vec8), cams: wp.array(dtype=Cam),
                         n_per: int, g_means: wp.array(dtype=vec3), g_cov6: wp.array(dtype=vec6)):
        i = wp.tid()
        if count[i] == 0:
            return
        cam = cams[i / n_per]
        gp = g_pack[i]
        p = pack[i]
        pc = cam.R * means[i] + cam.t
        x = pc[0]
        y = pc[1]
        z = pc[2]
        rz = scalar(1.0) / z
        rz2 = rz * rz
        rz3 = rz2 * rz
        xr = x * rz
        yr = y * rz
        tx = z * wp.min(cam.lim_xp, wp.max(-cam.lim_xn, xr))
        ty = z * wp.min(cam.lim_yp, wp.max(-cam.lim_yn, yr))
        J = mat23(cam.fx * rz, scalar(0.0), -cam.fx * tx * rz2,
                  scalar(0.0), cam.fy * rz, -cam.fy * ty * rz2)
        Wc = cam.R * sym33(cov6[i]) * wp.transpose(cam.R)
        # conic = inverse(cov2d): g_cov2d = -M G_M M (symmetric parametrisation, b counted twice)
        M = mat22(p[2], p[3], p[3], p[4])
        GM = mat22(gp[2], scalar(0.5) * gp[3], scalar(0.5) * gp[3], gp[4])
        G2 = -(M * GM * M)
        gW = wp.transpose(J) * G2 * J
        gJ = scalar(2.0) * (G2 * J * Wc)
        gS = wp.transpose(cam.R) * gW * cam.R
        g_cov6[i] = vec6(gS[0, 0], gS[0, 1] + gS[1, 0], gS[0, 2] + gS[2, 0],
                         gS[1, 1], gS[1, 2] + gS[2, 1], gS[2, 2])
        gu = gp[0]
        gv = gp[1]
        gx = gu * cam.fx * rz
        gy = gv * cam.fy * rz
        gz = gp[6] - (gu * cam.fx * x + gv * cam.fy * y) * rz2
        gz += -cam.fx * rz2 * gJ[0, 0] - cam.fy * rz2 * gJ[1, 1]
        if xr <= cam.lim_xp and xr >= -cam.lim_xn:
            gx += -cam.fx * rz2 * gJ[0, 2]
            gz += scalar(2.0) * cam.fx * x * rz3 * gJ[0, 2]
        else:
            gz += cam.fx * tx * rz3 * gJ[0, 2]
        if yr <= cam.lim_yp and yr >= -cam.lim_yn:
            gy += -cam.fy * rz2 * gJ[1, 2]
            gz += scalar(2.0) * cam.fy * y * rz3 * gJ[1, 2]
        else:
            gz += cam.fy * ty * rz3 * gJ[1, 2]
        g_means[i] = wp.transpose(cam.R) * vec3(gx, gy, gz)

    class K:
        pass

    k = K()
    k.scalar, k.vec3, k.vec6, k.vec8, k.mat33, k.Cam = scalar, vec3, vec6, vec8, mat33, Cam
    k.project, k.gather_counts, k.emit_pairs, k.tile_ranges = project, gather_counts, emit_pairs, tile_ranges
    k.gather_pairs = gather_pairs
    k.rasterize_forward, k.rasterize_backward, k.project_backward = rasterize_forward, rasterize_backward, project_backward
    k.rasterize_backward_tiled = rasterize_backward_tiled
    k.module = mod
    # our backward is hand-written: no Warp adjoints (halves the compile time)
    wp.get_module(mod).options["enable_backward"] = False
    return k


_KERNELS: dict = {}


def kernels(scalar):
    """The kernel set for wp.float32 or wp.float64 (built once)."""
    if scalar not in _KERNELS:
        _KERNELS[scalar] = _build(scalar)
    return _KERNELS[scalar]


# ---------------------------------------------------------------------------- host side
def make_cam(k, camera, settings: RasterSettings, device="cpu"):
    """Fill the kernel camera struct from a static `camera.Camera`."""
    w2c = camera.w2c_cv()
    c = k.Cam()
    c.R = k.mat33(*[float(v) for v in w2c[:3, :3].ravel()])
    c.t = k.vec3(*[float(v) for v in w2c[:3, 3]])
    c.fx, c.fy, c.cx, c.cy = float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)
    W, H = int(camera.width), int(camera.height)
    c.width, c.height = W, H
    c.near, c.far = float(camera.near), float(camera.far)
    m = settings.fov_clamp
    c.lim_xp = (W - camera.cx) / camera.fx + m * 0.5 * W / camera.fx
    c.lim_xn = camera.cx / camera.fx + m * 0.5 * W / camera.fx
    c.lim_yp = (H - camera.cy) / camera.fy + m * 0.5 * H / camera.fy
    c.lim_yn = camera.cy / camera.fy + m * 0.5 * H / camera.fy
    c.low_pass = settings.low_pass
    if settings.floor not in ("subtract", "cut"):
        raise ValueError("RasterSettings.floor must be 'subtract' or 'cut'")
    if settings.floor == "cut":
        c.ext2 = c.cut2 = settings.extent_sigma ** 2
        c.sub, c.thr = 0.0, settings.alpha_min
    else:  # the footprint ends where opacity G = alpha_min: sigma^2 = 2 ln(opacity / alpha_min)
        c.ext2 = c.cut2 = FLOAT32_MAX
        c.sub, c.thr = settings.alpha_min, 1e-12
    c.alpha_min, c.alpha_max, c.t_min = settings.alpha_min, settings.alpha_max, settings.t_min
    ts = settings.resolved_tile_size(device)
    c.tile_size = ts
    c.tiles_x = (W + ts - 1) // ts
    c.tiles_y = (H + ts - 1) // ts
    return c


def make_cams(k, cameras, settings: RasterSettings, device="cpu"):
    """(the first camera's struct, a Warp array of every image's struct) for a list of static
    cameras of one image size (one image each)."""
    cams = [make_cam(k, c, settings, device) for c in cameras]
    if not cams:
        raise ValueError("the renderer needs at least one camera")
    for c in cams[1:]:
        if (c.width, c.height) != (cams[0].width, cams[0].height):
            raise ValueError("a batched render needs cameras of one image size "
                             f"({cams[0].width}x{cams[0].height} vs {c.width}x{c.height})")
    return cams[0], wp.array(cams, dtype=k.Cam, device=device)


@dataclass
class ForwardState:
    """What the backward pass needs from the forward pass (Warp arrays)."""

    k: object
    cam: object           # the first image's camera struct (the image size and cut-offs all share)
    device: object
    n: int                # Gaussians over all images
    n_pairs: int
    pack: object
    rect: object
    count: object
    ids: object
    ranges: object
    T: object
    last: object
    tile_last: object
    lockstep: bool
    backward: str = "pixel"
    pk: object = None     # per-pair copies of pack / colours, in tile and depth order
    pcol: object = None
    cams: object = None   # every image's camera struct (Warp array)
    n_per: int = 0        # Gaussians per image
    n_img: int = 1


def forward(means, cov6, colors, opacities, camera, settings: RasterSettings,
            out_rgb, out_alpha, out_depth):
    """Run the forward pipeline on Warp arrays.

    means (N,) vec3, cov6 (N,) vec6 (xx, xy, xz, yy, yz, zz), colors (N,) vec3, opacities (N,)
    scalar, all of one float type and device; out_rgb (H*W,) vec3, out_alpha, out_depth (H*W,)
    scalar are written. Returns a ForwardState for `backward`.

    Several images in one pass: `camera` a list of M static cameras of one image size, the
    Gaussians M sets of N / M one after another (image m: Gaussians m N/M .. (m+1) N/M - 1), the
    outputs M images one after another (M*H*W,). Each image is what it would be alone, bit for
    bit: one depth sort over all Gaussians is stable (ties by index), so each image's tile lists
    hold its Gaussians in the order its own sort gives, and every per-pixel loop is unchanged.
    """
    scalar = opacities.dtype
    k = kernels(scalar)
    dev = opacities.device
    cameras = list(camera) if isinstance(camera, (list, tuple)) else [camera]
    cam, cams = make_cams(k, cameras, settings, dev)
    M = len(cameras)
    lockstep = settings.resolved_lockstep(dev)
    n = int(opacities.shape[0])
    if n % M:
        raise ValueError(f"{n} Gaussians do not split into {M} images")
    n_per = max(n // M, 1)
    W, H = cam.width, cam.height
    n_tiles = cam.tiles_x * cam.tiles_y * M     # over all images
    ts2 = cam.tile_size * cam.tile_size
    pack = wp.empty(max(n, 1), dtype=k.vec8, device=dev)
    rect = wp.empty(max(n, 1), dtype=wp.vec4i, device=dev)
    count = wp.empty(max(n, 1), dtype=wp.int32, device=dev)
    dkey = wp.empty(2 * max(n, 1), dtype=wp.float32, device=dev)
    order = wp.empty(2 * max(n, 1), dtype=wp.int32, device=dev)
    ranges = wp.zeros((n_tiles, 2), dtype=wp.int32, device=dev)
    n_pairs = 0
    if n > 0:
        wp.launch(k.project, n, inputs=[means, cov6, opacities, cams, n_per],
                  outputs=[pack, rect, count, dkey, order], device=dev)
        wp.utils.radix_sort_pairs(dkey, order, n)
        counts_sorted = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(k.gather_counts, n, inputs=[order, count], outputs=[counts_sorted], device=dev)
        incl = wp.empty(n, dtype=wp.int32, device=dev)
        wp.utils.array_scan(counts_sorted, incl, inclusive=True)
        n_pairs = int(incl[n - 1:n].numpy()[0])
    keys = wp.empty(2 * max(n_pairs, 1), dtype=wp.int32, device=dev)
    ids = wp.empty(2 * max(n_pairs, 1), dtype=wp.int32, device=dev)
    if n_pairs > 0:
        wp.launch(k.emit_pairs, n, inputs=[order, counts_sorted, incl, rect, cam.tiles_x, n_per,
                                           cam.tiles_x * cam.tiles_y],
                  outputs=[keys, ids], device=dev)
        wp.utils.radix_sort_pairs(keys, ids, n_pairs, 0, max(1, int(n_tiles - 1).bit_length()))
        wp.launch(k.tile_ranges, n_pairs, inputs=[keys, n_pairs], outputs=[ranges], device=dev)
    pk = wp.empty(max(n_pairs, 1), dtype=k.vec8, device=dev)
    pcol = wp.empty(max(n_pairs, 1), dtype=k.vec3, device=dev)
    if n_pairs > 0:
        wp.launch(k.gather_pairs, n_pairs, inputs=[ids, pack, colors], outputs=[pk, pcol], device=dev)
    T = wp.empty(M * W * H, dtype=scalar, device=dev)
    last = wp.empty(M * W * H, dtype=wp.int32, device=dev)
    tile_last = wp.zeros(n_tiles, dtype=wp.int32, device=dev)
    wp.launch(k.rasterize_forward, n_tiles * ts2, inputs=[pk, pcol, ranges, cam],
              outputs=[out_rgb, out_alpha, out_depth, T, last, tile_last], device=dev)
    if settings.backward not in ("pixel", "tiled"):
        raise ValueError(f"backward must be 'pixel' or 'tiled', not {settings.backward!r}")
    return ForwardState(k, cam, dev, n, n_pairs, pack, rect, count, ids, ranges, T, last, tile_last, lockstep,
                        settings.backward, pk, pcol, cams, n_per, M)


def backward(st: ForwardState, means, cov6, colors, g_rgb, g_alpha, g_depth,
             g_means, g_cov6, g_colors, g_pack):
    """Gradients of the forward pass. g_means, g_cov6, g_colors, g_pack (N,) vec8 must be zeroed
    (g_pack[:, 5] is the opacity gradient, [:, 0:2] the 2D-mean gradient)."""
    k, cam, dev = st.k, st.cam, st.device
    if st.n == 0 or st.n_pairs == 0:
        return
    ts2 = cam.tile_size * cam.tile_size
    n_tiles = cam.tiles_x * cam.tiles_y * st.n_img
    if st.backward == "tiled":
        wp.launch_tiled(k.rasterize_backward_tiled, dim=[n_tiles],
                        inputs=[st.pk, st.pcol, st.ids, st.ranges, cam, st.T, st.last, st.tile_last,
                                g_rgb, g_alpha, g_depth],
                        outputs=[g_pack, g_colors], block_dim=ts2, device=dev)
    else:
        wp.launch(k.rasterize_backward, n_tiles * ts2,
                  inputs=[st.pk, st.pcol, st.ids, st.ranges, cam, st.T, st.last, st.tile_last, int(st.lockstep),
                          g_rgb, g_alpha, g_depth],
                  outputs=[g_pack, g_colors], device=dev)
    wp.launch(k.project_backward, st.n, inputs=[means, cov6, st.count, st.pack, g_pack, st.cams, st.n_per],
              outputs=[g_means, g_cov6], device=dev)


def tiles_for(width: int, height: int, tile_size: int) -> tuple[int, int]:
    return math.ceil(width / tile_size), math.ceil(height / tile_size)


def warp_scalar(dtype) -> type:
    """wp.float32 / wp.float64 for a torch or numpy float dtype."""
    name = str(dtype)
    if "float64" in name or "double" in name:
        return wp.float64
    if "float32" in name or "float" == name:
        return wp.float32
    raise TypeError(f"the renderer works in float32 or float64, not {dtype}")


__all__ = ["RasterSettings", "ForwardState", "forward", "backward", "kernels", "make_cam", "make_cams"]
