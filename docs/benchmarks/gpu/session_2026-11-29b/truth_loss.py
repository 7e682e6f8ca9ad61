"""Session 32 (#24): is a suite scene's wrong field the model's preference? The CPU fit with both starts on (as on
CUDA), then the reconstruction loss (true contacts' paths) at: the fit's field, the truth's E and nu (each particle the
nearest truth particle's), the truth's E with the fit's nu, and uniform E's."""
import json, sys, time
import numpy as np
import torch
from scipy.spatial import cKDTree

stage, cap = sys.argv[1], sys.argv[2]
from physinteract_usd import api
from physinteract_usd import metrics as M
from physinteract_usd.fit import FitProblem
from physinteract_usd.synth.gt import read_gt_array
from physinteract_usd.usd.stage import read_stage

t = time.perf_counter()
out = api.fit(stage, iterations=20, contact_from=cap + "/gt", device="cpu", progress=False, warm=False, keep_best=False,
              log=lambda m: print(m, file=sys.stderr, flush=True), settings_overrides={"parts_start": 20, "trend_start": 20})
r = out.result
e_gt_g = np.asarray(read_gt_array(cap + "/gt", "youngs_modulus.npy"), np.float64)
ma = M.material_accuracy(np.asarray(r.youngs_gaussian, np.float64), e_gt_g)
sd = read_stage(stage)
prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, cap + "/gt"))
gt = np.load(cap + "/gt/particles.npz")
idx = cKDTree(gt["rest"]).query(np.asarray(prob.x0))[1]
E_t, nu_t = gt["E"][idx].astype(np.float64), gt["nu"][idx].astype(np.float64)
T = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=prob.tdtype, device=prob.tdev)   # noqa: E731


def rec(E, nu):
    with torch.no_grad():
        return float(prob.loss(T(E), T(nu))["rec"])


rows = {"fit": rec(r.youngs, r.poisson), "truth E, truth nu": rec(E_t, nu_t), "truth E, fit nu": rec(E_t, r.poisson)}
for e in (7.5e3, float(np.median(r.youngs)), 1.5e4, 2.5e4):
    rows[f"uniform {e:.3g}, nu 0.3"] = rec(np.full(len(E_t), e), np.full(len(E_t), 0.3))
print(json.dumps({"ma": ma, "final_loss": r.final_loss, "rec": rows, "wall_s": round(time.perf_counter() - t, 1)}, indent=1))
