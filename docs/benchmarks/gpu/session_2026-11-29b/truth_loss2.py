"""Session 32 (#24): as truth_loss.py, with the fit's own problem (hand pixels left out, as the fit's) and at both
paths: the true one (the contacts' own) and the one the fit moved jointly."""
import json, sys, time
import numpy as np
import torch
from scipy.spatial import cKDTree

stage, cap = sys.argv[1], sys.argv[2]
over = json.loads(sys.argv[3]) if len(sys.argv) > 3 else {"parts_start": 20, "trend_start": 20}
from physinteract_usd import api
from physinteract_usd.app.fit import make_problem, prepare_fit

t = time.perf_counter()
out = api.fit(stage, iterations=20, contact_from=cap + "/gt", device="cpu", progress=False, warm=False, keep_best=False,
              log=lambda m: print(m, file=sys.stderr, flush=True), settings_overrides=over)
r = out.result
job = prepare_fit(stage, contact_from=cap + "/gt", device="cpu", warm=False, yes=True, log=lambda m: None, progress=False)
prob = make_problem(job)
gt = np.load(cap + "/gt/particles.npz")
idx = cKDTree(gt["rest"]).query(np.asarray(prob.x0))[1]
E_t, nu_t = gt["E"][idx].astype(np.float64), gt["nu"][idx].astype(np.float64)
T = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=prob.tdtype, device=prob.tdev)   # noqa: E731
fitted = [T(r.trajectories[n]) for n in prob.sim.slot_names()]


def rec(E, nu, tr=None):
    with torch.no_grad():
        return float(prob.loss(T(E), T(nu), tr)["rec"])


rows = {}
for pname, tr in (("true path", None), ("fitted path", fitted)):
    rows[pname] = {"fit field": rec(r.youngs, r.poisson, tr), "truth E+nu": rec(E_t, nu_t, tr),
                   "truth E, fit nu": rec(E_t, r.poisson, tr),
                   f"uniform {np.median(r.youngs):.3g}, fit nu": rec(np.full(len(E_t), np.median(r.youngs)), r.poisson, tr)}
from physinteract_usd import metrics as M
from physinteract_usd.synth.gt import read_gt_array
ma = M.material_accuracy(np.asarray(r.youngs_gaussian, np.float64), np.asarray(read_gt_array(cap + "/gt", "youngs_modulus.npy"), np.float64))
print(json.dumps({"over": over, "ma": ma, "final_loss": r.final_loss, "rec": rows, "wall_s": round(time.perf_counter() - t, 1)}, indent=1))
