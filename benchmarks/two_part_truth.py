"""Usage: python benchmarks/two_part_truth.py [WORKDIR] (docs/benchmarks/fit.md, 2026-11-26 later; #24).
Two-part bar: the training / held-back loss at the true part E vs the found ones."""
import sys, time, math
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "tests"))
import numpy as np, torch
torch.set_num_threads(1)
import fit_scene as fs
import test_fit_select as tfs
from physinteract_usd.app.fit import prepare_fit
from physinteract_usd.fit import FitProblem
from physinteract_usd.fit.select import holdout_frames, PartProbe, part_candidates
from physinteract_usd.fit.optimize import FitSettings

class MP:
    def setattr(self, obj, name, val): setattr(obj, name, val)

root = __import__("pathlib").Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/two_part_truth")
import shutil; shutil.rmtree(root, ignore_errors=True)
b, stiff = tfs._two_part_bar(root, 1e4, MP())
job = prepare_fit(b["stage"], iterations=1, contact_from=b["gt"], joint=False, log=lambda *a: None)
prob = FitProblem(job.scene, job.observations, job.contacts)
train, val = holdout_frames(prob.T, 3, keep=[5])
print("train", train, "val", val)
held = np.asarray(prob.held_particles(), bool)
lab = stiff.astype(np.int64)   # 1 = stiff
print("P", len(lab), "stiff", lab.sum(), "held", held.sum(), "held&stiff", (held & stiff).sum(), "held&~stiff", (held & ~stiff).sum())
cands = part_candidates(prob, FitSettings(), None)
from physinteract_usd.fit.regions import same_partition
for c in cands: print("cand", c["kind"], c["parts"], "same as truth:", same_partition(c["labels"], lab), np.bincount(c["labels"]))
P = len(lab)
nu = torch.full((P,), fs.NU_TRUE, dtype=prob.tdtype)
trajs = [t.clone() for t in prob.initial_trajectories()] or None
allf = list(range(1, prob.T))
def per_frame(le):
    E = torch.as_tensor(np.exp(np.asarray(le))[lab], dtype=prob.tdtype)
    with torch.no_grad():
        x, F = prob.simulate(E, nu, trajs)
        return np.array([float(prob.frame_loss(k, prob.render_frame(k, x[k], F[k]))["total"]) for k in allf])
pts = {"truth": (1e4, 1e5), "sweep": (10.9e3, 76.2e3), "polish": (11.5e3, 74.4e3), "uniform204": (2.04e5, 2.04e5)}
t0 = time.process_time()
for name, (es, eh) in pts.items():
    fl = per_frame(np.log([es, eh]))
    tr = np.mean([fl[k - 1] for k in train]); va = [round(fl[k - 1], 5) for k in val]
    print(f"{name:10s} soft {es:.4g} stiff {eh:.4g}: train {tr:.5f} held {np.mean(va):.5f} {va}", flush=True)
print("cpu per probe", (time.process_time() - t0) / len(pts))
# a 2-D scan around the truth on the training frames
f = PartProbe(prob, train, lab, nu, trajs, None, "never")
for es in [0.9e4, 1e4, 1.1e4, 1.2e4]:
    row = []
    for eh in [0.6e5, 0.75e5, 0.9e5, 1e5, 1.15e5, 1.3e5]:
        row.append(f([math.log(es), math.log(eh)]))
    print(f"soft {es:.3g}: " + " ".join(f"{v:.5f}" for v in row), flush=True)
