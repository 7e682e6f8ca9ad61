"""What `diagnose`'s ground candidate sees on a fitted stage with a hidden ground (issue #22): the synth's plane
(gt/gt.json), the video's lowest particle per frame (gt/particles.npz), the base fit's lowest point, the probe
heights (`probes_for`, and the pre-fix range: the lowest point to rest), each probe's share of the loss after
the base's linear step. **Development data** (the synthetic suite). CPU: one base rollout and one per probe.

    python benchmarks/ground_probe_heights.py STAGE.usda CAPTURE_DIR
"""
import json
import sys
from pathlib import Path

import numpy as np
import torch


def main(stage, cap):
    from physinteract_usd.app.adapters import load_observations, read_scene, stage_contacts
    from physinteract_usd.app.diagnose import superset_effects
    from physinteract_usd.diagnose.core import ground_reach
    from physinteract_usd.diagnose.residual import ImageResidual
    from physinteract_usd.fit.problem import FitProblem

    gt = json.load(open(Path(cap) / "gt" / "gt.json"))["hidden_effect"]
    xs = np.load(Path(cap) / "gt" / "particles.npz")["positions"]
    sd = read_scene(stage)
    fitted = {t.contact_set: t.positions for t in sd.trajectories if t.stage == "fitted"}
    cs = [c.replace(trajectory=np.asarray(fitted[c.name])) if c.name in fitted and c.is_interaction else c
          for c in stage_contacts(sd)]
    prob = FitProblem(sd, load_observations(sd), cs, effects=superset_effects(sd, {}))
    st = sd.settings
    E = torch.as_tensor(np.clip(sd.youngs_modulus, st.youngs_min, st.youngs_max), dtype=prob.tdtype)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=prob.tdtype)
    res = ImageResidual(prob, max_pixels=6000)

    def run(eff):
        with torch.no_grad():
            x, F = prob.sim.simulate(E, nu, None, effects=eff)
        return x, res(x, F)

    x0, r0 = run({})
    y = x0[..., 1].min(1).values.numpy()
    rest, low = float(y[0]), float(y.min())
    reach = ground_reach(prob)
    print(f"truth plane h {gt['parameters']['height']:.4f} (friction {gt['parameters'].get('friction')})")
    print(f"video lowest particle per frame {np.round(xs[..., 1].min(1), 4).tolist()}")
    print(f"base fit lowest per frame {np.round(y, 4).tolist()}")
    print(f"base fit rest {rest:.4f} low {low:.4f}; grid dx {prob.grid.dx:.4f}, reach {reach:.4f}")
    L0 = float(np.sum(r0 ** 2))
    hs = sorted(set([low + q * (rest - low) for q in (0.25, 0.5, 0.75)] + [low - f * reach for f in (1.0, 0.75, 0.5, 0.25)]
                    + [low, gt["parameters"]["height"]]))
    for h in hs:
        for mu in (0.5,):
            _, r = run({"ground": {"height": h, "friction": mu}})
            col = r - r0
            a = -float(col @ r0) / max(float(col @ col), 1e-30)
            best = float(np.sum((r0 + min(max(a, 0), 1.0) * col) ** 2))
            full = float(np.sum(r ** 2))
            print(f"h {h:.4f} ({(h - low) / reach:+.2f} reach from low) mu {mu}: loss with plane / base {full / L0:.4f}; "
                  f"best step on its column {best / L0:.4f} (a {a:.3g})")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
