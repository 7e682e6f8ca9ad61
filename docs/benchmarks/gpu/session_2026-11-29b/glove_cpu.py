"""Session 32 (#24): glove on the CPU (grid 24, 14 frames, true contacts, 20 iterations, both starts on as on CUDA),
the parts' separation rule on (1.4) or off (0): a CPU proxy for the H200 suite's glove row."""
import json, sys, time
import numpy as np

stage, gt, sep = sys.argv[1], sys.argv[2], float(sys.argv[3])
import physinteract_usd.fit.parts_start as PS
PS.PARTS_MIN_SEPARATION = sep
from physinteract_usd import api
from physinteract_usd import metrics as M
from physinteract_usd.synth.gt import read_gt_array

t = time.perf_counter()
out = api.fit(stage, iterations=20, contact_from=gt, device="cpu", progress=False, warm=False, keep_best=False,
              log=lambda m: print(m, file=sys.stderr, flush=True),
              settings_overrides={"parts_start": 20, "trend_start": 20})
r = out.result
e_gt = np.asarray(read_gt_array(gt, "youngs_modulus.npy"), np.float64)
e_fit = np.asarray(r.youngs_gaussian, np.float64)
print(json.dumps({"sep_rule": sep, "ma": M.material_accuracy(e_fit, e_gt), "final_loss": r.final_loss,
                  "median_e": float(np.median(r.youngs)), "wall_s": round(time.perf_counter() - t, 1)}))
