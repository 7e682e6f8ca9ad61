"""A CPU probe of the fit's pre-load design (#23): a soft cantilever's truth settled on its clamp, then
pulled up at its free end and let go (10 frames, undamped, from its settled state: the prestress exact). Its model
starts from the settled shape (the scan) and is swept over E: (a) stress-free (init today), (b) pre-loaded with the
left stretch of the scan's own settle at a wrong reference E, scaled as I + (V - I) E_ref / E, (c) as (b) with the
settle redone at each E, (d) the stress that balances the scan on its clamp (`sim.preload`, what `fit --preload`
uses). Where is each one's loss minimum?

    python benchmarks/preload_probe.py [E_TRUE]     # default 2e4 (a 10.8 cm sag); 2e5: a 2 cm sag
"""
import numpy as np
import torch
import sys
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sim_helpers import block
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from physinteract_usd.sim.preload import equilibrium_stress, preload_F

dx, sp, RHO = 0.02, 0.01, 1000.0
pts = block((14, 3, 3), sp, (0.1, 0.3, 0.1))
grid = GridSpec((0, 0, 0), dx, (20, 24, 12))
clamp = np.nonzero(pts[:, 0] < pts[:, 0].min() + 1.5 * sp)[0]
tip = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1.5 * sp)[0]
E_TRUE, T = float(sys.argv[1]) if len(sys.argv) > 1 else 2e4, 10


def settle(x0, E, F0=None, frames=40):
    m = SimModel.create(x0, sp ** 3, RHO, E, 0.3, grid=grid, fps=20, E_max=10 * E_TRUE, dtype="float64",
                        effects={"damping": {"coefficient": 25.0}})
    ro = Rollout(m, Control([Contact("fixed", indices=clamp)], n_frames=frames), graphs=False)
    with torch.no_grad():
        x, F = ro(F0=F0)
    return x[-1].numpy(), F[-1]


def clip(x0, E, F0, traj):
    m = SimModel.create(x0, sp ** 3, RHO, E, 0.3, grid=grid, fps=20, E_max=10 * E_TRUE, dtype="float64")
    ro = Rollout(m, Control([Contact("pointAdherent", indices=tip, trajectory=traj, release_frame=5),
                             Contact("fixed", indices=clamp)], n_frames=T), graphs=False)
    with torch.no_grad():
        x, _ = ro(F0=F0)
    return x.numpy()


def left_stretch(F):
    U, S, Vh = torch.linalg.svd(F)
    return U @ torch.diag_embed(S) @ U.transpose(-1, -2)        # V = U S U^T (F = V R, R = U Vh)


xs, Fs = settle(pts, E_TRUE)
c0 = xs[tip].mean(0)
traj = np.repeat(c0[None], T + 1, 0)
traj[:, 1] += 0.03 * np.clip(np.arange(T + 1) / 4.0, 0, 1)
truth = clip(xs, E_TRUE, Fs, traj)
print(f"E_true {E_TRUE:g}: sag {1000 * np.abs(xs[:, 1] - pts[:, 1]).max():.1f} mm")
E_REF = 0.5 * E_TRUE
_, Fm = settle(xs, E_REF)                                       # the scan's own settle at a wrong E
V = left_stretch(Fm)
I = torch.eye(3, dtype=torch.float64)
scan = SimModel.create(xs, sp ** 3, RHO, E_TRUE, 0.3, grid=grid, fps=20, E_max=10 * E_TRUE, dtype="float64")
pre = equilibrium_stress(scan, Control([Contact("fixed", indices=clamp)], n_frames=T))   # sim.preload: once, any E
rows = []
for f in (0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8, 4.0, 8.0):
    E = f * E_TRUE
    la = np.mean((clip(xs, E, None, traj) - truth) ** 2)
    lb = np.mean((clip(xs, E, I + (V - I) * (E_REF / E), traj) - truth) ** 2)
    _, Fe = settle(xs, E)
    lc = np.mean((clip(xs, E, left_stretch(Fe), traj) - truth) ** 2)
    ld = np.mean((clip(xs, E, preload_F(pre, torch.tensor(E, dtype=torch.float64), 0.3), traj) - truth) ** 2)
    rows.append((f, la, lb, lc, ld))
    print(f"E x{f:<5} stress-free {la:.3e}  preload(E_ref x0.5, scaled) {lb:.3e}  preload(settled at E) {lc:.3e}  "
          f"equilibrium stress {ld:.3e}", flush=True)
for i, name in ((1, "stress-free"), (2, "preload scaled"), (3, "preload at E"), (4, "equilibrium stress")):
    print(name, "minimum at E x", rows[int(np.argmin([r[i] for r in rows]))][0])
