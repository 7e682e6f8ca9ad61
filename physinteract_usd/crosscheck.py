"""Cross-check of the sim-ready asset with a simulator we did not write: Newton (NVIDIA's open
Warp-based physics engine, `pip install 'physinteract-usd[newton]'`), on Warp's CPU backend.

Newton loads the exported file alone (`ModelBuilder.add_usd`: the TetMesh with the AOUSD
volume-deformable schemas becomes a soft body with mu, lambda from the bound material); the
per-tetrahedron E and nu primvars are read by the same importer (declared as Newton custom
attributes of tetrahedron frequency) and set as its per-tetrahedron Lamé parameters. The
supports' and the grasp's PhysicsAttachments are parsed by Newton too (it cannot lower a
volume-to-world attachment yet and says so): their points are held, or moved along the hand's
time-sampled translate read from the same file.

The same two loads are applied to our MPM (`simulation.build_simulation`, the stage's particles,
fitted field and contacts), both with the same mass-proportional damping so that each settles to
its static equilibrium, which does not depend on damping or mass distribution in time:
- `sag`: gravity, the supports held, from rest;
- `pull`: the same, with the grasped points moved smoothly by the fitted interaction's largest
  displacement (from its grasp frame to the frame where the hand is farthest from where it
  grasped), then held there.
Compared: the tip's displacement (the free point farthest from the supports; mean over a ball of
1.5 particle spacings, our particles vs Newton's mesh points) and the deformed surface (every
mesh surface point's displacement, ours interpolated from the particles as the Gaussians are
bound: inverse-distance over the 4 nearest).

Newton's solver here is `SolverVBD` (vertex block descent): its tetrahedral energy is the stable
Neo-Hookean of Smith et al. 2018 with the Lamé parameters remapped so that its small-strain limit is
linear elasticity with (E, nu); `SolverSemiImplicit`'s tetrahedral force uses k_mu, k_lambda without
that remapping (0.73 x E at nu 0.3 in the small-strain limit), so it is not used for the comparison.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

TIP_RADIUS = 1.5     # particle spacings
DAMPING = 25.0       # 1/s, mass-proportional, both simulators
SETTLE = 1.5         # s simulated per load
# VBD starts each step's 10 Gauss-Seidel sweeps from the inertial prediction (x + v dt + g dt^2), so a
# state it settles to is off equilibrium by what 10 sweeps leave of g dt^2: 34% on a hanging bar at
# dt = 2.5 ms, 0.03% at 0.5 ms (tests/test_simready.py). Small steps, then.
NEWTON_RATE = 2000   # steps per second


def _require_newton():
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except ImportError as exc:
        raise ImportError("the Newton cross-check needs Newton: pip install 'physinteract-usd[newton]' "
                          f"(newton 1.8 and newton-usd-schemas; {exc})") from None


@dataclass
class Load:
    """What is held and moved: support points, grasped points and their displacement (3,) reached
    over `ramp` seconds (smoothstep), for `duration` seconds with damping `damping` [1/s]."""

    name: str
    displacement: np.ndarray
    ramp: float
    duration: float = SETTLE
    damping: float = DAMPING


def smoothstep(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s)


def pull_of(grasp: dict, fps: float) -> tuple[np.ndarray, float]:
    """The fitted interaction's largest displacement (from where it grasped) and the time it took:
    (displacement (3,), seconds)."""
    traj, en = grasp["trajectory"], grasp["enabled"]
    on = np.flatnonzero(en)
    g = int(on[0]) if len(on) else 0
    last = int(on[-1]) if len(on) else len(traj) - 1
    d = traj[g:last + 1] - traj[g]
    k = int(np.argmax(np.linalg.norm(d, axis=1)))
    return d[k], max(k, 1) / fps


def loads_for(asset: dict) -> list[Load]:
    """`sag`, and `pull` when the asset has a grasp (its first)."""
    out = [Load("sag", np.zeros(3), 0.0)]
    if asset["grasps"]:
        g = next(iter(asset["grasps"].values()))
        d, ramp = pull_of(g, asset["fps"])
        out.append(Load("pull", d, ramp))
    return out


# ---------------------------------------------------------------------------------- Newton
def newton_model(asset_path, *, per_tet: bool = True, grasped: bool = True, device: str = "cpu"):
    """(builder-finalised Newton model, info) for the asset file: loaded by `add_usd` alone; with
    `per_tet`, each tetrahedron's Lamé parameters from the exported E, nu primvars (read by the
    importer as custom attributes); the supports' points held, and the grasps' when `grasped`. info: {"soft": {"particle": (p0, p1), "tet": (t0, t1)},
    "supports": [vertex arrays], "grasps": [vertex arrays], "warnings": [str],
    "body_mu_lambda": (mu, lambda) as the importer set them}."""
    _require_newton()
    import newton
    import warp as wp

    wp.config.quiet = True
    b = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -9.81, 0.0))
    for key in ("youngsModulus", "poissonRatio"):
        b.add_custom_attribute(newton.ModelBuilder.CustomAttribute(
            name=key, namespace="physinteract", frequency=newton.Model.AttributeFrequency.TETRAHEDRON,
            dtype=wp.float32, default=0.0, usd_attribute_name=f"primvars:physinteract:{key}"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = b.add_usd(str(asset_path), return_deformable_results=True)
    soft = res.get("path_soft_map", {})
    if len(soft) != 1:
        raise ValueError(f"{asset_path}: Newton imported {len(soft)} soft bodies (expected 1)")
    sim_path, ranges = next(iter(soft.items()))
    p0, p1 = ranges["particle"]
    t0, t1 = ranges["tet"]
    supports, grasps = [], []
    for path, attrs in res.get("path_attachment_attrs", {}).items():
        if attrs.get("src0") != sim_path or attrs.get("type0") != "point":
            continue
        idx = np.asarray(attrs.get("indices0", []), np.int64)
        (grasps if attrs.get("src1") else supports).append(idx)
    held = supports + (grasps if grasped else [])
    held = np.concatenate(held) if held else np.zeros(0, np.int64)
    inactive = ~int(newton.ParticleFlags.ACTIVE)
    for i in held:
        b.particle_mass[p0 + int(i)] = 0.0
        b.particle_flags[p0 + int(i)] = int(b.particle_flags[p0 + int(i)]) & inactive
    body_mu_lambda = tuple(float(v) for v in b.tet_materials[t0][:2])
    b.color()
    model = b.finalize(device=device)
    if per_tet:
        E = model.physinteract.youngsModulus.numpy()[t0:t1].astype(np.float64)
        nu = model.physinteract.poissonRatio.numpy()[t0:t1].astype(np.float64)
        if not (np.all(E > 0) and np.all((nu > -1) & (nu < 0.5))):
            raise ValueError(f"{asset_path}: the per-tetrahedron E / nu primvars are missing or out of range")
        mats = model.tet_materials.numpy()
        mats[t0:t1, 0] = E / (2 * (1 + nu))
        mats[t0:t1, 1] = E * nu / ((1 + nu) * (1 - 2 * nu))
        model.tet_materials.assign(mats)
    info = {"soft": {"particle": (p0, p1), "tet": (t0, t1)}, "supports": supports, "grasps": grasps,
            "warnings": sorted({str(w.message) for w in caught}), "body_mu_lambda": body_mu_lambda,
            "path": sim_path}
    return model, info


def run_newton(asset_path, load: Load, *, per_tet: bool = True, substeps_per_second: int = NEWTON_RATE,
               iterations: int = 10, device: str = "cpu") -> dict:
    """Newton's settled state under `load`: {"rest" (V, 3), "final" (V, 3), "residual_speed" [m/s],
    "seconds", "steps", "warnings"}."""
    import newton

    t_start = time.perf_counter()
    pulled = bool(np.any(load.displacement))
    model, info = newton_model(asset_path, per_tet=per_tet, grasped=pulled, device=device)
    p0, p1 = info["soft"]["particle"]
    solver = newton.solvers.SolverVBD(model, iterations=iterations)
    s0, s1, ctl = model.state(), model.state(), model.control()
    rest = s0.particle_q.numpy().astype(np.float64).copy()
    hand = (np.concatenate(info["grasps"]) + p0) if info["grasps"] and pulled else np.zeros(0, np.int64)
    dt = 1.0 / substeps_per_second
    steps = int(math.ceil(load.duration / dt))
    decay = math.exp(-load.damping * dt)
    for k in range(steps):
        if len(hand):
            s = smoothstep((k + 1) * dt / load.ramp) if load.ramp > 0 else 1.0
            q = s0.particle_q.numpy()
            q[hand] = rest[hand] + s * load.displacement
            s0.particle_q.assign(q)
        s0.clear_forces()
        solver.step(s0, s1, ctl, None, dt)
        s0, s1 = s1, s0
        s0.particle_qd.assign(s0.particle_qd.numpy() * decay)
    final = s0.particle_q.numpy().astype(np.float64)
    speed = np.linalg.norm(s0.particle_qd.numpy(), axis=1)
    if not np.all(np.isfinite(final)):
        raise FloatingPointError(f"{asset_path}: Newton's simulation went non-finite")
    return {"rest": rest[p0:p1], "final": final[p0:p1], "residual_speed": float(speed[p0:p1].max()),
            "seconds": time.perf_counter() - t_start, "steps": steps, "warnings": info["warnings"],
            "body_mu_lambda": info["body_mu_lambda"]}


def static_residual(rest, tets, final, youngs, poisson, density, held, gravity=(0.0, -9.81, 0.0)) -> float:
    """How far a settled state is from static equilibrium under the energy Newton's VBD uses (the
    stable Neo-Hookean, P = mu F + (lambda + mu)(J - 1 - mu / (lambda + mu)) cof F, per
    tetrahedron, masses lumped density * volume / 4 per point): the largest net force on a free
    point over the largest weight of one (0 at equilibrium)."""
    X, Y = np.asarray(rest, np.float64), np.asarray(final, np.float64)
    T = np.asarray(tets, np.int64)
    edges = lambda P: np.stack([P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]], P[T[:, 3]] - P[T[:, 0]]], 2)  # noqa: E731
    Dm = edges(X)
    inv = np.linalg.inv(Dm)
    vol = np.linalg.det(Dm) / 6.0
    F = edges(Y) @ inv
    E, nu = np.asarray(youngs, np.float64), np.asarray(poisson, np.float64)
    mu = E / (2 * (1 + nu))
    lam = E * nu / ((1 + nu) * (1 - 2 * nu)) + mu
    J = np.linalg.det(F)
    cof = J[:, None, None] * np.linalg.inv(F).transpose(0, 2, 1)
    P = mu[:, None, None] * F + (lam * (J - 1 - mu / lam))[:, None, None] * cof
    H = -vol[:, None, None] * (P @ inv.transpose(0, 2, 1))
    f = np.zeros_like(X)
    for c in range(3):
        np.add.at(f, T[:, c + 1], H[:, :, c])
    np.add.at(f, T[:, 0], -H.sum(2))
    m = np.zeros(len(X))
    np.add.at(m, T.reshape(-1), np.repeat(np.asarray(density, np.float64) * vol / 4.0, 4))
    free = np.setdiff1d(np.arange(len(X)), np.asarray(held, np.int64))
    net = f[free] + m[free, None] * np.asarray(gravity)
    return float(np.linalg.norm(net, axis=1).max() / max((m[free] * np.linalg.norm(gravity)).max(), 1e-30))


# ------------------------------------------------------------------------------------- ours
def run_mpm(sd, asset: dict, load: Load, *, device: str = "cpu") -> dict:
    """Our MPM's settled particles under `load` (the stage's particles, fitted E and nu, supports
    and grasped particles): {"rest" (P, 3), "final" (P, 3), "residual_speed", "seconds", "frames"}."""
    import torch

    from .contacts import ContactSet
    from .simulation import build_simulation, grid_covering

    t_start = time.perf_counter()
    fps = sd.fps
    n = int(math.ceil(load.duration * fps)) + 1
    contacts = [ContactSet(c.name, "fixed", c.indices, source=c.source) for c in sd.contacts if c.type == "fixed"]
    if np.any(load.displacement):
        hand = next(c for c in sd.contacts if c.type == "pointAdherent")
        x0 = sd.particles_positions[hand.indices].mean(0)
        s = smoothstep(np.arange(n) / fps / load.ramp) if load.ramp > 0 else np.ones(n)
        contacts.append(ContactSet(hand.name, "pointAdherent", hand.indices, 0, None,
                                   x0 + s[:, None] * load.displacement, source=hand.source))
    # the stage's grid, grown (same lattice) to hold the object with room to sag around it whether
    # or not a hand moves it (the fit's grid is grown by its hand's trajectory; a sag has none)
    grid = grid_covering(sd.settings, sd.particles_positions, [sd.particles_positions])
    st = dataclasses.replace(sd.settings, domain_min=np.asarray(grid.lower),
                             domain_max=np.asarray(grid.lower) + np.asarray(grid.resolution) * grid.dx,
                             grid_resolution=grid.resolution)
    sd_n = dataclasses.replace(sd, end_frame=sd.start_frame + n - 1, settings=st)
    sim = build_simulation(sd_n, contacts, n, effects={"damping": {"coefficient": load.damping}}, device=device)
    E = torch.as_tensor(np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), dtype=sim.tdtype)
    nu = torch.as_tensor(np.clip(sd.poisson_ratio, 1e-3, st.poisson_max), dtype=sim.tdtype)
    with torch.no_grad():
        x, _ = sim.simulate(E, nu)
    x = x.cpu().numpy().astype(np.float64)
    return {"rest": sd.particles_positions.copy(), "final": x[-1],
            "residual_speed": float(np.linalg.norm(x[-1] - x[-2], axis=1).max() * fps),
            "seconds": time.perf_counter() - t_start, "frames": n}


# ---------------------------------------------------------------------------------- compare
def tip_point(sd) -> np.ndarray:
    """The free particle farthest from every support (rest position)."""
    x0 = sd.particles_positions
    sup = np.concatenate([c.indices for c in sd.contacts if c.type == "fixed"] or [np.zeros(0, np.int64)])
    if len(sup) == 0:
        return x0[np.argmin(x0[:, 1])]
    d, _ = cKDTree(x0[sup]).query(x0)
    return x0[int(np.argmax(d))]


def compare(ours: dict, theirs: dict, surface_vertices: np.ndarray, tip: np.ndarray, spacing: float,
            held: np.ndarray | None = None) -> dict:
    """Tip displacement and surface displacement of Newton (`theirs`, mesh points) against ours
    (particles). Relative errors are |u_theirs - u_ours| / |u_ours| (tip) and RMS over the
    surface points of |u_theirs - u_ours| over the RMS of |u_ours|; `free_surface_error` the same
    over the surface points farther than 2 spacings from every `held` point (what neither simulator
    is told where to put)."""
    u_ours = ours["final"] - ours["rest"]
    u_theirs = theirs["final"] - theirs["rest"]
    r = TIP_RADIUS * spacing
    near_p = np.linalg.norm(ours["rest"] - tip, axis=1) <= r
    near_v = np.linalg.norm(theirs["rest"] - tip, axis=1) <= r
    tip_ours = u_ours[near_p].mean(0)
    tip_theirs = u_theirs[near_v].mean(0) if np.any(near_v) else u_theirs[np.argmin(np.linalg.norm(theirs["rest"] - tip, axis=1))]
    # ours at the mesh's surface points: inverse-distance weights over the 4 nearest particles
    vs = theirs["rest"][surface_vertices]
    d, i = cKDTree(ours["rest"]).query(vs, k=4)
    w = 1.0 / np.maximum(d, 1e-9)
    w /= w.sum(1, keepdims=True)
    u_ours_s = np.einsum("nk,nkj->nj", w, u_ours[i])
    u_theirs_s = u_theirs[surface_vertices]
    diff = np.linalg.norm(u_theirs_s - u_ours_s, axis=1)
    rms_ours = float(np.sqrt(np.mean(np.sum(u_ours_s ** 2, axis=1))))
    free = np.ones(len(vs), bool)
    if held is not None and len(held):
        free = cKDTree(theirs["rest"][held]).query(vs)[0] > 2 * spacing
    rms_free = float(np.sqrt(np.mean(np.sum(u_ours_s[free] ** 2, axis=1)))) if np.any(free) else 0.0
    return {"tip_ours_m": tip_ours.tolist(), "tip_newton_m": tip_theirs.tolist(),
            "tip_ours_norm_m": float(np.linalg.norm(tip_ours)), "tip_newton_norm_m": float(np.linalg.norm(tip_theirs)),
            "tip_error": float(np.linalg.norm(tip_theirs - tip_ours) / max(np.linalg.norm(tip_ours), 1e-12)),
            "surface_error": float(np.sqrt(np.mean(diff ** 2)) / max(rms_ours, 1e-12)),
            "surface_rms_ours_m": rms_ours, "surface_mean_diff_m": float(diff.mean()),
            "free_surface_error": float(np.sqrt(np.mean(diff[free] ** 2)) / max(rms_free, 1e-12)) if np.any(free) else 0.0,
            "free_surface_points": int(free.sum())}


def crosscheck(sd, asset_path, *, per_tet: bool = True, duration: float = SETTLE, damping: float = DAMPING,
               newton_substeps: int = NEWTON_RATE, iterations: int = 10, loads=None, log=print) -> dict:
    """Both simulators under each load (`sag`, `pull`): {"loads": {name: compare(...) + timings},
    "newton_warnings": [...], "asset": {...}}. `sd` is the stage the asset came from."""
    from .usd.simready import read_sim_ready

    asset = read_sim_ready(asset_path)
    spacing = float(sd.settings.particle_spacing)
    tip = tip_point(sd)
    surf = np.unique(asset["surface"])
    out = {"loads": {}, "tip_point_m": tip.tolist(), "asset": {"tetrahedra": len(asset["tets"]),
                                                             "points": len(asset["points"])}}
    for load in loads or loads_for(asset):
        load = dataclasses.replace(load, duration=duration, damping=damping)
        ours = run_mpm(sd, asset, load)
        log(f"  {load.name}: MPM {ours['frames']} frames in {ours['seconds']:.0f} s")
        theirs = run_newton(asset_path, load, per_tet=per_tet, substeps_per_second=newton_substeps,
                            iterations=iterations)
        log(f"  {load.name}: Newton {theirs['steps']} steps in {theirs['seconds']:.0f} s")
        held = list(asset["supports"].values()) + ([g["vertices"] for g in asset["grasps"].values()]
                                                     if np.any(load.displacement) else [])
        c = compare(ours, theirs, surf, tip, spacing, np.concatenate(held) if held else None)
        c.update({"mpm_seconds": ours["seconds"], "newton_seconds": theirs["seconds"],
                  "mpm_residual_speed": ours["residual_speed"], "newton_residual_speed": theirs["residual_speed"],
                  "displacement_m": np.asarray(load.displacement).tolist()})
        out["loads"][load.name] = c
        out["newton_warnings"] = theirs["warnings"]
    return out
