"""Session 32 (#24): how each suite scene's appearance parts lie: the share of a part's particles that touch another
part (a pattern's parts are interleaved, a material's are regions). Small captures of 3 frames (the parts do not
depend on the frames), init --grid auto as the suite does."""
import json, subprocess, sys
from pathlib import Path
import numpy as np

W = Path("/tmp/pa")
PY = sys.executable


def stage_for(scene):
    cap, st = W / scene, W / f"{scene}.usda"
    if not st.exists():
        subprocess.run([PY, "-m", "physinteract_usd", "synth", scene, str(cap), "--size", "small", "--frames", "3",
                        "--force"], check=True, capture_output=True)
        sug = json.loads((cap / "gt" / "gt.json").read_text())["suggested_init"]
        subprocess.run([PY, "-m", "physinteract_usd", "init", str(st), "--capture", str(cap), "--grid", "auto",
                        "--padding", str(sug["padding"]), "--youngs-range", ",".join(map(str, sug["youngs_range"])),
                        "--max-poisson", str(sug["max_poisson"]), "--density", str(sug["density"])],
                       check=True, capture_output=True)
    return st, cap


def main(scene):
    from physinteract_usd import api
    from physinteract_usd.fit import FitProblem, FitSettings
    from physinteract_usd.fit import regions as R
    from physinteract_usd.fit.select import part_candidates
    from physinteract_usd.usd.stage import read_stage
    from physinteract_usd.synth.gt import read_gt_array

    st, cap = stage_for(scene)
    sd = read_stage(st)
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, cap / "gt"))
    s = FitSettings()
    cands = [c for c in part_candidates(prob, s, None) if c["kind"] == "appearance" and c["parts"] > 1]
    graph = R.particle_graph(prob.x0, 1.6 * sd.settings.particle_spacing).tocoo()
    P = len(prob.x0)
    if not cands:
        print(json.dumps({"scene": scene, "P": P, "parts": 0}))
        return
    lab = np.asarray(cands[0]["labels"])
    i, j = graph.row, graph.col
    cross = np.zeros(P, bool)
    np.logical_or.at(cross, i, lab[i] != lab[j])
    rows = []
    for k in range(int(lab.max()) + 1):
        m = lab == k
        rows.append({"part": k, "share": round(float(m.mean()), 3), "touching": round(float(cross[m].mean()), 3)})
    print(json.dumps({"scene": scene, "P": P, "parts": len(rows), "touching_all": round(float(cross.mean()), 3),
                      "rows": rows}))


if __name__ == "__main__":
    main(sys.argv[1])
