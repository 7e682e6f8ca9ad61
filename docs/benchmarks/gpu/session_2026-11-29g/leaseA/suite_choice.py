"""The fit's preload choice on suite scenes (stress-free truths): synth small 14 frames, init --grid auto without a
preload flag, the choice from the true contacts (fit/preload_choice.choose_preload), one row a scene."""
import json, os, subprocess, sys, time
DEV = os.environ.get("DEVICE", "cuda")
from pathlib import Path

from physinteract_usd.app.fit import make_problem, prepare_fit
from physinteract_usd.fit.preload_choice import choose_preload

work = Path(sys.argv[1]); out = Path(sys.argv[2]); scenes = sys.argv[3].split(",")
work.mkdir(parents=True, exist_ok=True)
for sc in scenes:
    t = time.time()
    cap, st = work / sc, work / f"{sc}.usda"
    row = {"scene": sc}
    try:
        r = subprocess.run([sys.executable, "-m", "physinteract_usd", "synth", sc, str(cap), "--size", "small",
                            "--frames", "14", "--device", DEV, "--force"], capture_output=True, text=True)
        if r.returncode:
            raise RuntimeError("synth: " + r.stderr[-300:])
        sug = json.loads((cap / "gt" / "gt.json").read_text())["suggested_init"]
        args = ["init", str(st), "--capture", str(cap), "--grid", "auto", "--padding", str(sug["padding"]),
                "--youngs-range", ",".join(str(v) for v in sug["youngs_range"]), "--max-poisson",
                str(sug["max_poisson"]), "--density", str(sug["density"]), "--force"]
        r = subprocess.run([sys.executable, "-m", "physinteract_usd", *args], capture_output=True, text=True)
        if r.returncode:
            raise RuntimeError("init: " + r.stderr[-300:])
        row["synth_init_s"] = round(time.time() - t, 1)
        t1 = time.time()
        job = prepare_fit(st, contact_from=cap / "gt", device=DEV, log=lambda *a: None, progress=False)
        prob = make_problem(job)
        c = choose_preload(prob, job.settings.search_evals)
        row.update(preload=c["preload"], loss=c["loss"], E=c["E"], reason=c["reason"],
                   true_e_median=json.loads((cap / "gt" / "gt.json").read_text())["youngs_modulus"],
                   choice_s=round(time.time() - t1, 1))
    except Exception as exc:  # noqa: BLE001
        row["error"] = f"{type(exc).__name__}: {exc}"
    with open(out, "a") as fh:
        fh.write(json.dumps(row) + "\n")
    print(json.dumps(row), flush=True)
