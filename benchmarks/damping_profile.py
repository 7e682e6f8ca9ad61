"""The image loss over damping c on a fitted stage of a synthetic capture (issue #22; development data).

`benchmarks/damping_bias.py` found that the simulator at the fit's resolution matches the damped truth's
motion best near c_true (1.1x with the true E field, 0.94x with a uniform one): the resolution does not
bias c low. This script asks the same of the fit's own reconstruction loss (L1 + SSIM + silhouette on the
video, `FitProblem.loss`), with the true interaction (`fit --contact-from gt`): the loss over c at (a) the
truth's E field and Poisson ratio (nearest ground-truth particle), (b) the stage's fitted field (its
current version: the base fit, which had no damping), (c) the fitted field scaled, to see what c trades
against. Prints one JSON line.

    python benchmarks/damping_profile.py out/walkthrough/scene.usda out/walkthrough/capture/gt --c 0,0.6,1.3,2,2.6,3.5
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from damping_bias import parabola_min  # benchmarks/, beside this script


def main(argv=None):
    import torch
    from scipy.spatial import cKDTree

    from physinteract_usd import api
    from physinteract_usd.app.adapters import load_observations, true_contacts, true_hand_masks
    from physinteract_usd.fit import FitProblem

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("stage")
    ap.add_argument("gt")
    ap.add_argument("--c", default="0,0.6,1.3,2,2.6,3.5")
    ap.add_argument("--scales", default="", help="the fitted field x these too (comma-separated)")
    ap.add_argument("--fitted-path", action="store_true",
                    help="the interaction's path as the stage's current version fitted it (the base fit's), not the truth's")
    a = ap.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    sd = api.read_scene(a.stage)
    obs = load_observations(sd)
    obs.hand_masks = true_hand_masks(a.gt, sd.n_frames)
    contacts = true_contacts(sd, a.gt)
    fitted_paths = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    if a.fitted_path:                  # the stage's fitted hand path instead of the true one (as a warm refit)
        inter = [i for i, c in enumerate(contacts) if c.is_interaction]
        for i in inter:
            path = fitted_paths.get(contacts[i].name)
            if path is None and len(inter) == 1 and len(fitted_paths) == 1:
                path = next(iter(fitted_paths.values()))
            if path is None:
                raise SystemExit(f"no fitted path for {contacts[i].name} (fitted: {list(fitted_paths)})")
            contacts[i] = contacts[i].replace(trajectory=np.asarray(path))
    prob = FitProblem(sd, obs, contacts, effects={"damping": {"coefficient": 0.0}})
    gt = np.load(f"{a.gt}/particles.npz")
    _, idx = cKDTree(gt["rest"]).query(sd.particles_positions)
    st = sd.settings
    fields = {"truth": (gt["E"][idx], gt["nu"][idx]), "fitted": (sd.youngs_modulus, sd.poisson_ratio)}
    for s in [float(v) for v in a.scales.split(",") if v.strip()]:
        fields[f"fitted x{s:g}"] = (sd.youngs_modulus * s, sd.poisson_ratio)
    cs = [float(v) for v in a.c.split(",")]
    gpos = np.load(f"{a.gt}/gaussian_positions.npy")
    with torch.no_grad():
        m0 = prob.gaussians_at(torch.as_tensor(sd.particles_positions, dtype=prob.tdtype),
                               torch.eye(3, dtype=prob.tdtype).expand(len(sd.particles_positions), 3, 3))[0]
    if gpos.shape[1] != len(m0) or float(np.abs(m0.cpu().numpy() - gpos[0]).max()) > 1e-4:
        print(f"the stage's Gaussians are not the truth's ({len(m0)} vs {gpos.shape[1]}): no geometric check")
        gpos = None
    rel = int(json.load(open(f"{a.gt}/gt.json"))["interaction"]["release_frame"])
    if gpos is not None:          # the free end: the 15% of Gaussians farthest from the supports' particles
        sup = [c for c in contacts if c.type == "fixed"]
        at = (sd.particles_positions[np.asarray(sup[0].indices)].mean(0) if sup and len(sup[0].indices)
              else gpos[0].mean(0))
        d = np.linalg.norm(gpos[0] - at, axis=1)
        tip = np.argsort(d)[-max(3, int(0.15 * len(d))):]
    truth_c = json.load(open(f"{a.gt}/gt.json"))["hidden_effect"]["parameters"]["coefficient"]
    out = {"stage": a.stage, "fitted_path": a.fitted_path, "c_true": truth_c, "c": cs, "profiles": {}}
    for name, (E, nu) in fields.items():
        Et = torch.as_tensor(np.clip(E, st.youngs_min, st.youngs_max), dtype=prob.tdtype)
        nut = torch.as_tensor(np.minimum(nu, st.poisson_max), dtype=prob.tdtype)
        prof, geo, geo_after, tip_after = [], [], [], []
        for c in cs:
            with torch.no_grad():
                x, F = prob.simulate(Et, nut, None, {"damping": {"coefficient": c}})
                prof.append(float(prob.loss(Et, nut, None, effects={"damping": {"coefficient": c}},
                                            simulated=(x, F))["rec"]))
                if gpos is not None:     # the Gaussians' centres against the truth's (the renderer's input)
                    m = np.stack([prob.gaussians_at(x[k], F[k])[0].cpu().numpy() for k in range(prob.T)])
                    geo.append(float(np.mean(np.sum((m[1:] - gpos[1:]) ** 2, -1))))
                    geo_after.append(float(np.mean(np.sum((m[rel:] - gpos[rel:]) ** 2, -1))))
                    tip_after.append(float(np.mean(np.sum((m[rel:, tip].mean(1) - gpos[rel:, tip].mean(1)) ** 2, -1))))
        out["profiles"][name] = {"loss": prof, "c_star": parabola_min(cs, prof), "median_E": float(np.median(E))}
        if geo:
            gstar = parabola_min(cs, geo)
            after = {}
            for key, g in (("after_release", geo_after), ("tip_after_release", tip_after)):
                jj = int(np.argmin(g))
                after[key] = {"msd": g, "c_min": cs[jj]}
            out["profiles"][name].update(gaussian_msd=geo, gaussian_c_star=gstar, **after)
            print(name, "after release: all Gaussians' c_min", after["after_release"]["c_min"], "; the free end's mean",
                  after["tip_after_release"]["c_min"], flush=True)
            print(name, "Gaussians' mean square distance to the truth's [m^2]", [f"{v:.3g}" for v in geo],
                  f"c* {gstar:.3g}", flush=True)
        print(name, [f"{v:.5f}" for v in prof], f"c* {cstar:.3g}", flush=True)
    out["seconds"] = {"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
