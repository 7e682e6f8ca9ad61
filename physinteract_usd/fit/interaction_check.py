"""Does the fitted interaction look wrong? A check `fit` prints at the end (#23).

A material field cannot make up for an interaction that is wrong: a grasp that starts too early or
too late, a release at the wrong frame, a contact in the wrong place. What is left of such an error
after the fit is a residual where the interaction is wrong: at the frames around the grasp or the
release (the model moves while the video does not, or the other way round) or at the contact (the
model pulls the object from another place). `check_interaction` reads the fitted model's per-pixel
residual for those two signatures and says what to try: `extract --grasp-frame K`,
`--release-frame K` or `--hint-pixel K,U,V`. It only points: the residual of a good fit is largest
somewhere too, so a peak counts only when it stands well above the rest (`peak_ratio`,
`contact_ratio`).

`check_trajectory` asks the same of the hand's path: a joint fit that moves it far beyond its
measurement uncertainty is soaking up model error (#22), and says so.

`residual_maps` renders the fit (no USD here) and `check_fit` joins them for `app/fit.py`.
"""

from __future__ import annotations

import numpy as np

PEAK_RATIO = 1.6       # a frame's residual at least this many times the median frame's
NEAR = 2               # frames either side of the grasp / release that count as "around" it
CONTACT_RATIO = 3.0    # the contact disk's share of the residual over its share of the pixels
CONTACT_SHARE = 0.2    # ... and at least this share of the residual over the contact frames
MIN_RESIDUAL = 1e-4    # mean squared error per pixel (of [0, 1] RGB) below which nothing is "wrong"
CONFIRM_DROP = 0.03    # a grasp / release frame one off must lower the fitted model's loss by this share to be named


def check_interaction(residual: np.ndarray, region: np.ndarray, grasp: int, release: int | None, *,
                      contact_uv: np.ndarray | None = None, radius_px: float = 0.0, kind: str = "hand") -> dict:
    """`residual` (T, H, W): the fitted model's squared colour error per pixel; `region` (T, H, W)
    bool: where it counts (the model's and the video's silhouettes, the hand left out). `grasp`,
    `release`: the interaction's frames (release None: held to the end); `contact_uv` (T, 2): the
    contact's pixel per frame, `radius_px` the disk around it that is "at the contact".

    Returns {"frame_residual": per frame (nan where no region), "peak_frame", "suspect": a subset of
    ("grasp", "release", "contact"), "notes": one plain sentence per suspect, naming the override}."""
    residual = np.asarray(residual, np.float64)
    region = np.asarray(region, bool)
    T = len(residual)
    per = np.full(T, np.nan)
    for k in range(1, T):   # frame 0 is the rest pose: no interaction yet
        if region[k].any():
            per[k] = float(residual[k][region[k]].mean())
    out = {"frame_residual": per.tolist(), "peak_frame": None, "suspect": [], "notes": []}
    fin = np.isfinite(per)
    if fin.sum() < 4:
        return out
    p = int(np.nanargmax(per))
    med = float(np.nanmedian(per))
    out["peak_frame"] = p
    peaked = per[p] >= PEAK_RATIO * med and per[p] >= MIN_RESIDUAL
    if peaked:
        which = []
        if abs(p - grasp) <= NEAR:
            which.append("grasp")
        if release is not None and abs(p - release) <= NEAR:
            which.append("release")
        for w in which:
            k = grasp if w == "grasp" else release
            flag = "--grasp-frame" if w == "grasp" else "--release-frame"
            what = "takes hold of" if w == "grasp" else "lets go of"
            out["suspect"].append(w)
            out["notes"].append(
                f"the interaction may be wrong: the fit's residual is largest at frame {p} "
                f"({per[p] / med:.1f}x the median frame's), next to the {w} at frame {k}; check in the "
                f"preview when the {kind} {what} the object and give it: extract {flag} K")
    if contact_uv is not None and radius_px > 0:
        last = T - 1 if release is None else min(int(release), T - 1)
        ks = [k for k in range(max(grasp, 1), last + 1) if fin[k]]
        share, area = [], []
        H, W = residual.shape[1:]
        yy, xx = np.mgrid[0:H, 0:W]
        for k in ks:
            u, v = contact_uv[k]
            if not (np.isfinite(u) and np.isfinite(v)):
                continue
            disk = ((xx + 0.5 - u) ** 2 + (yy + 0.5 - v) ** 2 <= radius_px ** 2) & region[k]
            tot = residual[k][region[k]].sum()
            if tot <= 0 or not disk.any():
                continue
            share.append(residual[k][disk].sum() / tot)
            area.append(disk.sum() / region[k].sum())
        if share:
            s, a = float(np.mean(share)), float(np.mean(area))
            out["contact_share"], out["contact_area_share"] = s, a
            if s >= CONTACT_SHARE and s >= CONTACT_RATIO * a and med >= MIN_RESIDUAL:
                k0 = max(grasp, 0)
                out["suspect"].append("contact")
                out["notes"].append(
                    f"the contact may be in the wrong place: {100 * s:.0f}% of the fit's residual while the "
                    f"{kind} holds the object lies within {radius_px:.0f} px of the contact ({100 * a:.0f}% of "
                    f"the object's pixels); check the preview and give the pixel where it touches: extract "
                    f"--hint-pixel {k0},U,V")
    return out


TRAJ_SIGMA_PX = 2.0    # the measured hand path's uncertainty in the image plane (mask centroid, contact pixel)
TRAJ_SIGMAS = 3.0      # a fitted path further than this many sigmas from the measured one is suspect ...
TRAJ_FRAMES = 3        # ... over at least this many frames


def check_trajectory(measured: np.ndarray, fitted: np.ndarray, cameras, grasp: int, release: int | None, *,
                     sigma_px: float = TRAJ_SIGMA_PX, kind: str = "hand") -> dict:
    """Is the fitted hand path soaking up model error? The joint fit may move the trajectory away
    from the path the video shows (T0) to make up for what the model lacks (a missing effect, a
    wrong material): a free trajectory can hide a missing effect completely. The image-plane
    distance between the two, per frame the hand holds the object, is compared with the measured
    path's uncertainty `sigma_px`; depth (along the camera ray) is reported, not judged (the video
    hardly measures it). Returns {"deviation_px" per frame (nan outside the hold), "max_px",
    "max_frame", "depth_mm" at that frame, "frames_over" (frames beyond TRAJ_SIGMAS sigma),
    "suspect", "note"}."""
    measured, fitted = np.asarray(measured, float), np.asarray(fitted, float)
    T = min(len(measured), len(fitted), len(cameras))
    last = T - 1 if release is None else min(int(release), T - 1)
    dev = np.full(T, np.nan)
    depth = np.full(T, np.nan)
    for k in range(max(int(grasp), 0), last + 1):
        (uv_m, uv_f), z = cameras[k].project(np.stack([measured[k], fitted[k]]))
        dev[k] = float(np.linalg.norm(uv_f - uv_m))
        depth[k] = float(z[1] - z[0])
    out = {"deviation_px": dev.tolist(), "max_px": None, "max_frame": None, "depth_mm": None, "frames_over": 0,
           "suspect": False, "note": "", "sigma_px": float(sigma_px)}
    if not np.isfinite(dev).any():
        return out
    k = int(np.nanargmax(dev))
    over = np.flatnonzero(np.nan_to_num(dev, nan=0.0) > TRAJ_SIGMAS * sigma_px)
    out.update(max_px=float(dev[k]), max_frame=k, depth_mm=float(1e3 * depth[k]), frames_over=int(len(over)))
    if len(over) >= TRAJ_FRAMES:
        out["suspect"] = True
        out["note"] = (f"the fitted {kind} path strays from the one the video shows: up to {dev[k]:.1f} px at frame "
                       f"{k} ({dev[k] / sigma_px:.0f} sigma of its measurement, {len(over)} frames beyond "
                       f"{TRAJ_SIGMAS:.0f} sigma): the trajectory is soaking up something the model lacks (an "
                       f"effect, the material) or a wrong extraction; `diagnose` ranks the candidates, `fit "
                       f"--no-joint` keeps the measured path")
    return out


def residual_maps(prob, result) -> tuple[np.ndarray, np.ndarray]:
    """The fitted model rendered at every frame against the video: (residual (T, H, W) squared
    colour error per pixel, region (T, H, W) the two silhouettes' union without the hand's pixels).
    `prob` a FitProblem, `result` its FitResult."""
    import torch

    from ..render import render

    obs = prob.obs
    T = len(obs.frames)
    res, reg = [], []
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.tdtype, device=prob.tdev)  # noqa: E731
    for k in range(T):
        with torch.no_grad():
            out = render(t(result.gaussian_means[k]), t(result.gaussian_covs[k]), prob.colors, prob.opacities,
                         prob.cameras[k], background=prob.background)
        rgb = out["rgb"].detach().cpu().numpy().astype(np.float64)
        sil = out["alpha"].detach().cpu().numpy() > 0.5
        true = np.asarray(obs.frames[k], np.float64)
        r = ((rgb - true) ** 2).mean(-1)
        m = sil | (obs.masks[k] if obs.masks is not None else sil)
        if obs.hand_masks is not None:
            m = m & ~obs.hand_masks[k]
        res.append(r)
        reg.append(m)
    return np.stack(res), np.stack(reg)


def _fitted_inputs(prob, result):
    import torch

    t = lambda a: torch.as_tensor(np.asarray(a), dtype=prob.sim.tdtype, device=prob.sim.tdev)  # noqa: E731
    names = prob.sim.slot_names()
    tr = [t(result.trajectories[n]) for n in names] if result.trajectories else None
    eff = {e: dict(p) for e, p in (result.effects or {}).items()}
    for e, ps in (result.effect_parameters or {}).items():
        eff.setdefault(e, {}).update(ps)
    return t(result.youngs), t(result.poisson), tr, names, eff or None


class Counterfactuals:
    """The fitted model (its E, nu, hand paths and effects) re-simulated under other contacts, forward
    passes only, for `confirm`'s suspects. The model as fitted is simulated once and shared: its loss is
    every suspect's reference, and its per-frame states let a variant that agrees with it before frame
    `start` (a grasp or release frame moved, never earlier than `start`) simulate frames start.. only
    (`Simulation.simulate_from`: bitwise the whole forward). With `simulation.sim_threads()` > 1 the
    variants' forwards run on that many threads (each its own eager twin; Warp's CPU launches release the
    GIL), the losses after them in the calling thread: the same values in any case."""

    def __init__(self, prob, result):
        self.prob = prob
        self.E, self.nu, self.tr, self.names, self.eff = _fitted_inputs(prob, result)
        self._base = None                     # (loss, twin, per-frame states or None)
        self.frames_simulated = 0             # frames simulated over the calls (what the windows save)

    def _trajs(self, offsets: dict):
        import torch

        if self.tr is None:
            return None
        return [t + torch.as_tensor(np.asarray(offsets.get(n, np.zeros(3))), dtype=t.dtype, device=t.device)
                for n, t in zip(self.names, self.tr)]

    def _loss(self, x, F, trk) -> float:
        import torch

        with torch.no_grad():
            return float(self.prob.loss(self.E, self.nu, trk, effects=self.eff, simulated=(x, F))["rec"])

    def base(self) -> float:
        """The loss of the model as fitted (simulated once)."""
        if self._base is None:
            import torch

            from ..errors import SimulationError

            sim = self.prob.sim.forward_twin(list(self.prob.contacts))
            trk = self._trajs({})
            try:
                with torch.no_grad():
                    x, F = sim.simulate(self.E, self.nu, trk, effects=self.eff)
                self.frames_simulated += self.prob.T - 1
                self._base = (self._loss(x, F, trk), self._model(sim), sim.rollout.checkpoints())
            except SimulationError:
                self._base = (float("inf"), None, None)
        return self._base[0]

    @staticmethod
    def _model(sim) -> tuple:
        """What must match for a variant to start from the model as fitted's states: rung, substep, grid."""
        return sim.e_bound, sim.substeps, sim.grid

    def losses(self, variants: dict) -> dict:
        """`variants` {key: (contacts, {slot name: path offset (3,)}, start)}: start the first frame whose
        step may differ from the model as fitted (0: any). Returns {key: loss} (the reconstruction loss over
        frames 1.., the fit's own measure; inf where the simulation failed)."""
        import threading

        import torch

        from .. import simulation as simulation_mod
        from ..errors import SimulationError

        self.base()
        _, model, states = self._base

        def prepare(key, cs, offsets, start):
            sim = self.prob.sim.forward_twin(cs)
            if sim.adaptive:
                sim.ensure_stable(float(self.E.max()))      # here, not in a worker: it may build a rollout
            same = states is not None and self._model(sim) == model
            k0 = int(start) if same and int(start) > 0 else 0
            self.frames_simulated += self.prob.T - 1 - k0
            return [key, sim, self._trajs(offsets), k0, None]

        def run(job):
            key, sim, trk, k0, _ = job
            try:
                with torch.no_grad():
                    job[4] = sim.simulate_from(k0, states, self.E, self.nu, trk, effects=self.eff) if k0 else \
                        sim.simulate(self.E, self.nu, trk, effects=self.eff)
            except SimulationError as e:
                job[4] = e
            job[1] = None                                   # the twin's buffers go with it

        def loss(job) -> float:
            r = job[4]
            job[4] = None
            return float("inf") if isinstance(r, SimulationError) else self._loss(*r, job[2])

        n = min(simulation_mod.sim_threads(self.prob.sim.device), len(variants)) if len(variants) > 1 else 1
        out = {}
        if n == 1:          # one twin at a time (a paper-size twin's buffers are GBs)
            for key, v in variants.items():
                job = prepare(key, *v)
                run(job)
                out[key] = loss(job)
            return out
        jobs = [prepare(key, *v) for key, v in variants.items()]
        todo, lock, failed = iter(jobs), threading.Lock(), []

        def work():
            try:
                while True:
                    with lock:
                        job = next(todo, None)
                    if job is None:
                        return
                    run(job)
            except BaseException as e:  # noqa: BLE001  (re-raised in the calling thread)
                failed.append(e)

        workers = [threading.Thread(target=work, daemon=True) for _ in range(n - 1)]
        for t in workers:
            t.start()
        work()
        for t in workers:
            t.join()
        if failed:
            raise failed[0]
        return {job[0]: loss(job) for job in jobs}


def variant_losses(prob, result, variants: dict, cf: Counterfactuals | None = None) -> dict:
    """The fitted model (its E, nu, hand paths and effects) re-simulated with other contacts, forward
    passes only: `variants` {key: (contacts, {slot name: path offset (3,)}[, start])} (`Counterfactuals.
    losses`); returns {key: loss} (the reconstruction loss over frames 1.., the fit's own measure; inf where
    the simulation failed)."""
    cf = Counterfactuals(prob, result) if cf is None else cf
    return cf.losses({k: (v[0], v[1], v[2] if len(v) > 2 else 0) for k, v in variants.items()})


def shifted_losses(prob, result, c, what: str, shifts=(-1, 1), cf: Counterfactuals | None = None) -> dict:
    """`variant_losses` with contact `c`'s `what` ("grasp_frame" or "release_frame") moved by each of
    `shifts` frames: {0: the loss as fitted, shift: its loss}; shifts that leave the clip or cross the other
    frame are left out. A shift changes nothing before the earlier of the two frames: only the frames from
    there on are simulated (`Counterfactuals`)."""
    import dataclasses

    T = prob.T
    cf = Counterfactuals(prob, result) if cf is None else cf
    if getattr(c, what) is None:
        return {}
    variants = {}
    k0 = int(getattr(c, what))
    for d in shifts:
        v = k0 + d
        if what == "grasp_frame" and not (0 <= v < (T - 1 if c.release_frame is None else int(c.release_frame))):
            continue
        if what == "release_frame" and not (int(c.grasp_frame) < v <= T - 1):
            continue
        variants[d] = ([dataclasses.replace(x, **{what: v}) if x.name == c.name else x for x in prob.contacts], {},
                       max(min(k0, v), 0))
    return {0: cf.base(), **cf.losses(variants)}


def moved_losses(prob, result, c, steps: float = 2.0, cf: Counterfactuals | None = None) -> dict:
    """`variant_losses` with contact `c` moved on the object by `steps` particle spacings along the first
    frame's camera right and up (`contacts.moved_contact`: the held particles, the hand's path with them):
    {"0": the loss as fitted, "right+" / "right-" / "up+" / "up-": theirs}. The contact acts from its grasp
    frame: the frames before it are the model as fitted's (`Counterfactuals`)."""
    from ..contacts import moved_contact

    cf = Counterfactuals(prob, result) if cf is None else cf
    x0 = np.asarray(prob.x0.detach().cpu().numpy() if hasattr(prob.x0, "detach") else prob.x0, float)
    w2c = prob.cameras[0].w2c_cv()[:3, :3]              # rows: the camera's axes in world coordinates
    d = steps * float(prob.scene.settings.particle_spacing)
    variants = {}
    for lab, axis in (("right", w2c[0]), ("up", -w2c[1])):   # OpenCV's y points down the image
        v = axis / max(np.linalg.norm(axis), 1e-12)
        for sgn in (1, -1):
            off = sgn * d * v
            nc = moved_contact(c, off, x0, prob.contacts)
            variants[f"{lab}{'+' if sgn > 0 else '-'}"] = (
                [nc if x.name == c.name else x for x in prob.contacts], {c.name: off}, max(int(c.grasp_frame), 0))
    return {"0": cf.base(), **cf.losses(variants)}


def confirm(prob, result, c, out: dict) -> None:
    """A suspect the residual points at is named only if the video agrees: the fitted model with the grasp
    or release frame one off, or the contact moved two particle spacings across the image, must explain it
    better by CONFIRM_DROP (the material's error peaks at the release too, where the free motion starts,
    and the strain is largest at the contact: the residual alone warned on 6 of 12 suite fits from true
    contacts and on the README demo). Rewrites `out`'s suspects and notes in place; the losses go to
    out["confirm"]."""
    checks = {}
    keep_s, keep_n = [], []
    cf = Counterfactuals(prob, result)       # the model as fitted simulated once for every suspect
    for sus, note in zip(out["suspect"], out["notes"]):
        if sus not in ("grasp", "release", "contact"):
            keep_s.append(sus)
            keep_n.append(note)
            continue
        try:
            ls = moved_losses(prob, result, c, cf=cf) if sus == "contact" else \
                shifted_losses(prob, result, c, f"{sus}_frame", cf=cf)
        except Exception as exc:  # noqa: BLE001 - a check never costs the fit; unconfirmed, it is kept as it was
            checks[sus] = {"error": f"{type(exc).__name__}: {exc}"}
            keep_s.append(sus)
            keep_n.append(note)
            continue
        zero = "0" if sus == "contact" else 0
        base = ls.get(zero)
        alt = {d: v for d, v in ls.items() if d != zero and np.isfinite(v)}
        checks[sus] = {"losses": {str(d): v for d, v in ls.items()}}
        if base is None or not alt:
            continue
        d = min(alt, key=alt.get)
        drop = (base - alt[d]) / max(base, 1e-12)
        checks[sus].update(best=str(d), drop=drop)
        if drop < CONFIRM_DROP:
            continue
        keep_s.append(sus)
        if sus == "contact":
            where = {"right+": "right", "right-": "left", "up+": "up", "up-": "down"}[d]
            keep_n.append(f"{note} (the fitted model with the contact moved {where} in the image explains the "
                          f"video {100 * drop:.0f}% better)")
        else:
            k = int(getattr(c, f"{sus}_frame")) + d
            flag = "--grasp-frame" if sus == "grasp" else "--release-frame"
            keep_n.append(f"{note} (the fitted model with the {sus} at frame {k} explains the video "
                          f"{100 * drop:.0f}% better: try {flag} {k})")
    out["suspect"], out["notes"] = keep_s, keep_n
    if checks:
        out["confirm"] = checks


def check_fit(prob, result, contacts) -> dict | None:
    """`check_interaction` on a finished fit: the first interaction contact's frames, its fitted
    trajectory projected as the contact's pixel, a disk of its grasp size (at least 3 px). None
    when the fit has no interaction contact."""
    inter = [c for c in contacts if c.type != "fixed"]
    if not inter:
        return None
    c = inter[0]
    res, reg = residual_maps(prob, result)
    T = len(res)
    traj = result.trajectories.get(c.name)
    if traj is None:
        traj = c.trajectory
    uv, rad = None, 0.0
    if traj is not None and len(traj) == T:
        cams = prob.cameras
        uv = np.stack([cams[k].project(np.asarray(traj[k], float)[None])[0][0] for k in range(T)])
        # the contact's size: its held particles' spread (a collider: its radius), at least 3 px
        x0 = np.asarray(prob.x0.detach().cpu().numpy() if hasattr(prob.x0, "detach") else prob.x0, float)
        size = c.radius if c.type != "pointAdherent" or not len(c.indices) else \
            float(np.linalg.norm(x0[c.indices] - x0[c.indices].mean(0), axis=1).max())
        g = max(min(int(c.grasp_frame), T - 1), 0)
        z = cams[g].world_to_camera(np.asarray(traj[g], float)[None])[0, 2]
        rad = max(3.0, 1.5 * cams[g].fx * max(size, 0.01) / max(z, 1e-6))
    kind = {"pointAdherent": "hand", "pointNonAdherent": "fingertip", "surfaceNonAdherent": "palm"}.get(c.type, "hand")
    out = check_interaction(res, reg, int(c.grasp_frame), c.release_frame, contact_uv=uv, radius_px=rad, kind=kind)
    out["contact"] = c.name
    confirm(prob, result, c, out)
    if traj is not None and c.trajectory is not None and traj is not c.trajectory and len(traj) == T \
            and len(c.trajectory) == T:
        tc = check_trajectory(c.trajectory, traj, prob.cameras, int(c.grasp_frame), c.release_frame, kind=kind)
        out["trajectory"] = tc
        if tc["suspect"]:
            out["suspect"].append("trajectory")
            out["notes"].append(tc["note"])
    return out
