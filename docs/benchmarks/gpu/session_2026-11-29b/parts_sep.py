import json, sys
import numpy as np
sys.path.insert(0, ".dev")
from parts_shape import stage_for


def main(scene):
    from physinteract_usd import api
    from physinteract_usd.fit import FitProblem, FitSettings
    from physinteract_usd.fit.regions import separation
    from physinteract_usd.fit.select import part_candidates
    from physinteract_usd.usd.stage import read_stage
    st, cap = stage_for(scene)
    sd = read_stage(st)
    prob = FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, cap / "gt"))
    c = [c for c in part_candidates(prob, FitSettings(), None) if c["kind"] == "appearance" and c["parts"] > 1]
    print(scene, round(separation(np.asarray(prob.x0), c[0]["labels"]), 3) if c else "no parts")


main(sys.argv[1])
