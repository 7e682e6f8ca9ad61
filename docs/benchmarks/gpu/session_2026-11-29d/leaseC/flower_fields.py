"""Session 34 (#24): flower's loss at the truth's field and at the parts start's two simplex ends (capped, extended),
on the suite's stage (training loss over every frame, the fit's problem, CUDA)."""
import json, sys, time
import numpy as np, torch
from scipy.spatial import cKDTree
from physinteract_usd.app.fit import make_problem, prepare_fit
from physinteract_usd.fit.select import field_frame_losses
stage, cap = sys.argv[1], sys.argv[2]
job = prepare_fit(stage, contact_from=cap + "/gt", device=__import__("os").environ.get("DEVICE", "cuda"), warm=False, yes=True, log=lambda m: None, progress=False)
prob = make_problem(job)
gt = np.load(cap + "/gt/particles.npz")
idx = cKDTree(gt["rest"]).query(np.asarray(prob.x0))[1]
E_t, nu_t = gt["E"][idx].astype(np.float64), gt["nu"][idx].astype(np.float64)
part = np.where(E_t > 3e4, 1, np.where(E_t > 1e4, 2, 0))      # 0 petals, 1 stem, 2 centre
print("particles per part (petals, stem, centre):", np.bincount(part))
T = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=prob.tdtype, device=prob.tdev)
frames = list(range(1, prob.T))
rows = {"truth E, truth nu": (E_t, nu_t)}
for name, v in {"truth": (7500, 37500, 15000), "capped simplex (33rd)": (6906, 37680, 7697),
                "extended simplex (34th)": (5651, 36170, 23810), "truth, centre 2.38e4": (7500, 37500, 23810),
                "extended, centre 1.5e4": (5651, 36170, 15000), "petals 6.5e3, stem, centre 2.38e4": (6500, 37500, 23810)}.items():
    rows[name] = (np.asarray(v, float)[part], np.full(len(part), 0.3))
bound = 4e4
for name, (E, nu) in rows.items():
    t = time.perf_counter()
    h = field_frame_losses(prob, T(E), T(nu), None, None, frames, bound)
    print(f"{name:38s} mean loss {np.mean(h):.5f}  ({time.perf_counter() - t:.1f} s)", flush=True)
