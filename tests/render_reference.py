"""Dense pure-torch 3D Gaussian splatting renderer: the oracle for the Warp rasterizer's tests.

It imports nothing from physinteract_usd.render. Every pixel looks at every Gaussian (no tiles),
so it is only for small scenes. It applies the same cut-offs as the renderer, stated here:

- camera: OpenCV frame from the world-to-camera 4x4 ``w2c``; ``u = fx x / z + cx``, pixel
  (i, j)'s centre at (i + 0.5, j + 0.5);
- a Gaussian is culled when its camera z is not in (near, far) or when opacity < ALPHA_MIN;
- EWA: cov2d = J (R Sigma R^T) J^T + LOW_PASS * I, J the perspective Jacobian at the camera-frame
  point whose x/z (y/z) is clamped to [-(cx/fx + m tan_x), (W - cx)/fx + m tan_x] with
  tan_x = 0.5 W / fx and m = FOV_CLAMP (gsplat's rule; same for y);
- floor "subtract" (the renderer's default): alpha = min(ALPHA_MAX, opacity exp(-sigma^2 / 2) -
  ALPHA_MIN), sigma^2 = d^T cov2d^-1 d, and a Gaussian touches a pixel only where that is > 0;
  floor "cut" (3DGS): only when sigma^2 <= EXTENT_SIGMA^2 (3 sigma) and
  alpha = min(ALPHA_MAX, opacity exp(-sigma^2 / 2)) >= ALPHA_MIN;
- order: by float32 camera z, ties by index;
- front to back, the first Gaussian that would take the transmittance below T_MIN stops the
  pixel and is itself left out;
- outputs: rgb = sum c_i a_i T_i + T_final * background, alpha = 1 - T_final,
  depth_acc = sum z_i a_i T_i.
"""

from __future__ import annotations

import torch

LOW_PASS = 0.3
EXTENT_SIGMA = 3.0
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
FOV_CLAMP = 0.3

SH_C0 = 0.28209479177387814


def _sym(cov):
    if cov.dim() == 2:  # (N, 6) upper triangle xx xy xz yy yz zz
        c = cov
        return torch.stack([torch.stack([c[:, 0], c[:, 1], c[:, 2]], -1),
                            torch.stack([c[:, 1], c[:, 3], c[:, 4]], -1),
                            torch.stack([c[:, 2], c[:, 4], c[:, 5]], -1)], 1)
    return 0.5 * (cov + cov.transpose(1, 2))


def reference_project(means, cov, w2c, fx, fy, cx, cy, width, height):
    """Per Gaussian: u, v, conic (a, b, c), camera z, cov2d (N, 2, 2) (low-pass included)."""
    dt = means.dtype
    w2c = torch.as_tensor(w2c, dtype=dt)
    R, t = w2c[:3, :3], w2c[:3, 3]
    pc = means @ R.T + t
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    tanx, tany = 0.5 * width / fx, 0.5 * height / fy
    lxp, lxn = (width - cx) / fx + FOV_CLAMP * tanx, cx / fx + FOV_CLAMP * tanx
    lyp, lyn = (height - cy) / fy + FOV_CLAMP * tany, cy / fy + FOV_CLAMP * tany
    tx = z * torch.clamp(x / z, -lxn, lxp)
    ty = z * torch.clamp(y / z, -lyn, lyp)
    zero = torch.zeros_like(z)
    J = torch.stack([torch.stack([fx / z, zero, -fx * tx / z ** 2], -1),
                     torch.stack([zero, fy / z, -fy * ty / z ** 2], -1)], 1)
    Wc = R @ _sym(cov) @ R.T
    c2 = J @ Wc @ J.transpose(1, 2)
    a = c2[:, 0, 0] + LOW_PASS
    b = 0.5 * (c2[:, 0, 1] + c2[:, 1, 0])
    c = c2[:, 1, 1] + LOW_PASS
    det = a * c - b * b
    conic = torch.stack([c / det, -b / det, a / det], -1)
    u = fx * x / z + cx
    v = fy * y / z + cy
    cov2 = torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], 1)
    return u, v, conic, z, cov2, det


def reference_render(means, cov, colors, opacities, w2c, fx, fy, cx, cy, width, height,
                     near=0.01, far=100.0, background=None, floor="subtract"):
    """Dense render. means (N,3), cov (N,3,3) or (N,6), colors (N,3), opacities (N,).
    Returns rgb (H,W,3), alpha (H,W), depth_acc (H,W); differentiable by torch autograd."""
    dt = means.dtype
    u, v, conic, z, _, det = reference_project(means, cov, w2c, fx, fy, cx, cy, width, height)
    valid = (z > near) & (z < far) & (opacities >= ALPHA_MIN) & (det > 0)
    jj, ii = torch.meshgrid(torch.arange(height, dtype=dt), torch.arange(width, dtype=dt), indexing="ij")
    px = (ii.reshape(-1) + 0.5)[:, None]
    py = (jj.reshape(-1) + 0.5)[:, None]
    dx = u[None, :] - px
    dy = v[None, :] - py
    s2 = conic[:, 0] * dx * dx + 2.0 * conic[:, 1] * dx * dy + conic[:, 2] * dy * dy
    if floor == "subtract":  # continuous: alpha = opacity G - ALPHA_MIN where that is > 0
        ar = opacities[None, :] * torch.exp(-0.5 * s2) - ALPHA_MIN
        al = torch.clamp(ar, max=ALPHA_MAX)
        contrib = valid[None, :] & (al > 0)
    else:  # 3DGS's hard cut
        ar = opacities[None, :] * torch.exp(-0.5 * s2)
        al = torch.clamp(ar, max=ALPHA_MAX)
        contrib = valid[None, :] & (s2 <= EXTENT_SIGMA ** 2) & (al >= ALPHA_MIN)
    al = torch.where(contrib, al, torch.zeros_like(al))
    order = torch.sort(z.detach().float(), stable=True).indices
    al = al[:, order]
    keep = torch.cumprod(1.0 - al.detach(), 1) >= T_MIN
    al = torch.where(keep, al, torch.zeros_like(al))
    one_m = 1.0 - al
    Tinc = torch.cumprod(one_m, 1)
    T = torch.cat([torch.ones_like(Tinc[:, :1]), Tinc[:, :-1]], 1)
    w = al * T
    rgb = w @ colors[order]
    T_final = Tinc[:, -1] if al.shape[1] else torch.ones(px.shape[0], dtype=dt)
    alpha = 1.0 - T_final
    depth = w @ z[order]
    if background is not None:
        rgb = rgb + T_final[:, None] * torch.as_tensor(background, dtype=dt).reshape(-1, 3)
    return rgb.reshape(height, width, 3), alpha.reshape(height, width), depth.reshape(height, width)


def reference_render_camera(means, cov, colors, opacities, camera, background=None, floor="subtract"):
    """reference_render with the intrinsics and pose of a static physinteract_usd.camera.Camera."""
    return reference_render(means, cov, colors, opacities, camera.w2c_cv(), camera.fx, camera.fy,
                            camera.cx, camera.cy, camera.width, camera.height, camera.near, camera.far,
                            background, floor)


# ------------------------------------------------------------------------- test scenes
def random_rotations(n, generator, dtype=torch.float64):
    q = torch.randn(n, 4, generator=generator, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(1)
    R = torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    return R.to(dtype)


def make_scene(seed, n, dtype=torch.float64, *, radius=0.4, scale=(0.02, 0.08), thin=0.0,
               opacity=(0.05, 1.0)):
    """Random Gaussians around the origin: anisotropic covariances (a share `thin` of them
    surfel-like, one axis 1e-4 of the others), colours in [0, 1], opacities in `opacity`.
    Returns (means (n,3), covs (n,3,3), colors (n,3), opacities (n,)) in `dtype`."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    means = radius * d / d.norm(dim=1, keepdim=True) * torch.rand(n, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    lo, hi = scale
    s = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(torch.log(torch.tensor(lo)).item(),
                                                                   torch.log(torch.tensor(hi)).item(), generator=g))
    flat = torch.rand(n, generator=g, dtype=torch.float64) < thin
    s[flat, 2] = s[flat, 0] * 1e-4
    Rm = random_rotations(n, g)
    M = Rm * s[:, None, :]
    covs = M @ M.transpose(1, 2)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    op = opacity[0] + (opacity[1] - opacity[0]) * torch.rand(n, generator=g, dtype=torch.float64)
    return tuple(t.to(dtype) for t in (means, covs, colors, op))
