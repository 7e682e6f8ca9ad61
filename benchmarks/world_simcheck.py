"""Our simulator against the world generator's, in 3-D, with everything else true (#24).

The truth sweep (world_bias.py) finds that on several development captures our model's best uniform E
is far below the truth's, with a sharp minimum. Is that the simulators' difference (our MPM, its grasp
as particle kinematics, its clamp rule, its grid) or the loss (renderer, masks)? This script leaves
the renderer out: our particles are simulated with the TRUE interaction (contacts, supports and
hand path from the ground truth, the floor from it as the `ground` effect) and the truth's material
(each particle takes the E and nu of the nearest truth particle at rest), scaled by a factor, and
their motion is compared with the truth's particles' (each of ours against its nearest truth particle
at rest, displacement against displacement). Per factor and per pin rule (the default and the clamp
band, `simulation.PIN_RULE`): the mean displacement error over the frames of the interaction and
over the frames after the release, against the truth's mean displacement.

    python benchmarks/world_simcheck.py --work data/world_dev --seeds 6 --factors 0.125,0.25,0.5,1,2 --device cuda
    python benchmarks/world_simcheck.py --work data/world_stiff --seeds 141 --cap 3000 --grid-scales 1,1.5 \
        --steps fit,truth --blends rate,substep --rules default,band,gain1       # the #24 stiff-bias variants

Variants of OUR side (the truth is what it is), each crossed with the pin rules: `--grid-scales`: the fit's
grid, 1 = `init --grid auto` within `--cap`, 1.5 = round(1.5 x that) cells (the cap lifted: 1.5^3 the
particles); `--steps`: `fit` (the adaptive substep at CFL 0.6, its E rung) or `truth` (the truth's own
substeps a frame, gt.json gt_sim, at every factor); `--blends`: `rate` (the fit's: a partial pin, collider
or floor blend acts at a rate per unit time) or `substep` (the generator's: once per substep, blend_dt 0).
Per (capture, variant) the best factor is refined by a parabola through the three least errors in log E.

A tuning tool: it refuses the validation split. Results in docs/benchmarks/world_fits.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

import physinteract_usd  # noqa: F401
from physinteract_usd import simulation
from physinteract_usd.errors import SimulationError

sys.path.insert(0, str(Path(__file__).resolve().parent))

from world_bias import gt_dir, per_capture, prepare_stage  # noqa: E402
from world_fit import add_ground  # noqa: E402

# "gain1": the world generator's own blend (a node moves with the held share of its mass, pin_gain 1)
RULES = {"default": simulation.PIN_RULE, "band": simulation.CLAMP_BAND, "gain1": (1.0, 0.0)}
# a rule per contact kind (simulation.SUPPORT_RULE, #24): (the grasps' rule, the supports' rule)
KIND_RULES = {"supband": (simulation.DEFAULT_PIN_RULE, simulation.CLAMP_BAND),
              "graspband": (simulation.CLAMP_BAND, simulation.DEFAULT_PIN_RULE),
              "supgain1": (simulation.DEFAULT_PIN_RULE, (1.0, 0.0)),
              "graspgain1": ((1.0, 0.0), simulation.DEFAULT_PIN_RULE)}


def set_rule(rule: str) -> None:
    """`simulation`'s pin rules for a rule's name: KIND_RULES (grasps and supports apart), RULES or any name
    `simulation.pin_rule` reads (every pin)."""
    if rule in KIND_RULES:
        simulation.PIN_RULE, simulation.SUPPORT_RULE = KIND_RULES[rule]
    else:
        simulation.PIN_RULE, simulation.SUPPORT_RULE = RULES.get(rule) or simulation.pin_rule(rule), None

# what our SimModel.create is given, per variant: a forced substep count, the blend once per substep
FORCE = {"substeps": None, "blend": "rate"}


@contextlib.contextmanager
def forced(substeps=None, blend="rate", cfl=None):
    """Within it, `simulation`'s models take `substeps` a frame (None: the adaptive step, at CFL number `cfl`
    when given) and, with blend "substep", the partial blends once per substep (blend_dt 0, the generator's);
    the class and the CFL are restored after."""
    create = simulation.SimModel.__dict__["create"]
    orig = create.__func__

    def _create(cls, *a, **kw):
        if FORCE["substeps"]:
            kw["substeps"] = int(FORCE["substeps"])
        if FORCE["blend"] == "substep":
            kw["blend_dt"] = 0.0
        return orig(cls, *a, **kw)

    FORCE.update({"substeps": substeps, "blend": blend})
    simulation.SimModel.create = classmethod(_create)
    cfl0 = simulation.CFL
    if cfl is not None:
        simulation.CFL = cfl
    try:
        yield
    finally:
        simulation.SimModel.create = create
        simulation.CFL = cfl0
        FORCE.update({"substeps": None, "blend": "rate"})


def best_factor(pairs: list[tuple[float, float]]) -> float | None:
    """The factor of least error, refined by a parabola through the least and its neighbours in log factor
    (the grid's end when the least is at an end)."""
    pairs = sorted(pairs)
    if not pairs:
        return None
    i = min(range(len(pairs)), key=lambda k: pairs[k][1])
    if i == 0 or i == len(pairs) - 1:
        return pairs[i][0]
    (a, fa), (b, fb), (c, fc) = [(np.log(pairs[k][0]), pairs[k][1]) for k in (i - 1, i, i + 1)]
    den = (b - a) * (fb - fc) - (b - c) * (fb - fa)
    if den == 0:
        return pairs[i][0]
    x = b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)) / den
    return float(np.exp(np.clip(x, a, c)))


def compare(x: np.ndarray, x0: np.ndarray, truth: np.ndarray, nn: np.ndarray) -> np.ndarray:
    """(T,) mean distance between our particles' displacement and their nearest truth particle's."""
    du = x - x0[None]
    dt = truth[:, nn] - truth[0, nn][None]
    return np.linalg.norm(du - dt, axis=-1).mean(axis=1)


def one(work: Path, n: str, cap_n: int, factors: list[float], rules: list[str], device: str, scratch: Path,
        log=print, grid_scales=(1.0,), steps=("fit",), blends=("rate",)) -> list[dict]:
    rows = []
    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    n_auto = None
    for gs in grid_scales:
        grid = "auto"
        if gs != 1.0:
            if n_auto is None:
                n_auto = int(prepare_stage(work / n, gt, scratch / f"{n}_{cap_n}_probe", cap_n).get("grid"))
            grid = int(round(gs * n_auto))
        for stp in steps:
            for bl in blends:
                # fit: the adaptive step; cflC: the adaptive step at CFL number C; truth: the truth's; N: N a frame
                cfl = float(stp[3:]) if stp.startswith("cfl") else None
                n_sub = None if stp == "fit" or cfl else g["gt_sim"]["substeps_per_frame"] if stp == "truth" else stp
                with forced(int(n_sub) if n_sub else None, bl, cfl):
                    rs = one_variant(work, n, cap_n, factors, rules, device, scratch, log, grid=grid)
                for r in rs:
                    r.update({"grid_scale": gs, "step": stp, "blend": bl})
                rows += rs
    return rows


def one_variant(work: Path, n: str, cap_n: int, factors: list[float], rules: list[str], device: str, scratch: Path,
                log=print, grid="auto") -> list[dict]:
    from scipy.spatial import cKDTree

    from physinteract_usd.app.fit import make_problem, prepare_fit

    gt = gt_dir(work, n)
    g = json.loads((gt / "gt.json").read_text())
    out = scratch / f"{n}_{cap_n}_{grid}"
    gc = prepare_stage(work / n, gt, out, cap_n if grid == "auto" else 10 ** 7, grid=grid)
    stage = out / "scene.usda"
    if g.get("floor"):
        add_ground(stage, g["floor"]["height"], g["floor"].get("friction", 0.5))
    tr = np.load(gt / "particles.npz")
    rest, pos = tr["rest"], tr["positions"]
    it = g["interaction"]
    grasp, release = it.get("grasp_frame"), it.get("release_frame")
    rows = []
    for rule in rules:
        set_rule(rule)
        job = prepare_fit(stage, iterations=1, contact_from=gt, device=device, log=lambda *a: None, warm=False)
        prob = make_problem(job)
        x0 = np.asarray(prob.x0)
        nn = cKDTree(rest).query(x0)[1]
        T = min(prob.T, len(pos))
        E_t = torch.as_tensor(tr["E"][nn], dtype=prob.tdtype, device=prob.tdev)
        nu_t = torch.as_tensor(tr["nu"][nn], dtype=prob.tdtype, device=prob.tdev)
        scale = float(np.linalg.norm(pos[:T] - pos[0][None], axis=-1).mean())
        inter = list(range(max(1, grasp or 1), (release if release is not None else T)))
        after = list(range(release + 1, T)) if release is not None else []
        for f in factors:
            t0 = time.perf_counter()
            row = {"scene": n, "cap": cap_n, "grid": gc.get("grid"), "cells_across": gc.get("cellsAcross"),
                   "particles": len(x0), "truth_particles": len(rest), "rule": rule, "factor": f,
                   "e_true": float(np.median(tr["E"])), "truth_mean_disp_m": scale,
                   "shape": g.get("world", {}).get("shape"), "scenario": g.get("world", {}).get("scenario"),
                   "type": it.get("type"), "grasp": grasp, "release": release,
                   "substeps": None, "truth_substeps": g.get("gt_sim", {}).get("substeps_per_frame"),
                   "truth_dx": g.get("gt_sim", {}).get("dx"), "dx": float(prob.sim.grid.dx)}
            try:
                with torch.no_grad():
                    x, _ = prob.simulate(E_t * f, nu_t)
                row["substeps"] = int(prob.sim.model.substeps)
                err = compare(x[:T].detach().cpu().numpy(), x0, pos[:T], nn)
                row.update({"err_all_m": float(err[1:].mean()),
                            "err_interaction_m": float(err[inter].mean()) if inter else None,
                            "err_after_m": float(err[after].mean()) if after else None,
                            "err_per_frame_m": err.tolist()})
            except SimulationError as exc:
                # the message's first line, whole up to its advice (the table shows it shortened: `short_error`)
                row["error"] = str(exc).splitlines()[0][:700]
                row["error_kind"] = getattr(exc, "kind", "")
                row["error_frame"] = getattr(exc, "frame", None)
            row["sim_s"] = time.perf_counter() - t0
            rows.append(row)
            log(json.dumps({k: v for k, v in row.items() if k != "err_per_frame_m"}), flush=True)
    set_rule("default")
    return rows


def short_error(msg: str | None) -> str:
    """A SimulationError's first line in a few words for the table: "left grid f21 -y 0.75c (1) alone" (frame, the
    face, how far past in cells, how many; "alone": the particle had come off the object), "non-finite f19 (1,
    p 13254) J 0.47 lone" (how many, one of them, its J at the frame's start, "lone": no other particle within its
    stencil); else its first 40 characters (the JSON keeps the line whole: row["error"])."""
    import re

    if not msg:
        return "failed"
    m = msg.removeprefix("simulation ")
    fr = re.search(r"at frame (\d+)", m)
    f = f" f{fr.group(1)}" if fr else ""
    if m.startswith("left the grid"):
        n = re.search(r"\((\d+) particles", m)
        face = re.search(r"nearest the ([-+][xyz]) face", m)
        past = re.search(r"by up to ([\d.]+) cells", m)
        return (f"left grid{f}" + (f" {face.group(1)}" if face else "") + (f" {past.group(1)}c" if past else "")
                + (f" ({n.group(1)})" if n else "") + (" alone" if "alone: it had come off" in m else ""))
    if m.startswith("state became non-finite"):
        n = re.search(r"\((\d+) particles, e\.g\. particle (\d+)", m)
        head = "non-finite" + f + (f" ({n.group(1)}, p {n.group(2)})" if n else "")
        j = re.search(r"J (-?[\d.e+-]+), stretch", m)
        return head + (f" J {j.group(1)}" if j else "") + (" lone" if "(a lone particle" in m else "")
    return m[:40]


def table(rows: list[dict]) -> str:
    """One line per (capture, variant, rule): the error at each factor (mm), the factor with the least
    (over all frames, refined by a parabola in log E; and after the release, on the grid)."""
    out = ["| capture | what | particles (truth) | grid x, dx / truth's | step: substeps (truth's) | blend | rule | mean truth displacement "
           "| error (mm) at E x factor: all / interaction / after release | best factor all (refined) / after |",
           "|---|---|---|---|---|---|---|---:|---|---|"]
    key = lambda r: (r["scene"], r.get("grid_scale", 1.0), r.get("step", "fit"), r.get("blend", "rate"), r["rule"])  # noqa: E731
    for k in sorted({key(r) for r in rows}, key=lambda k: tuple(map(str, k))):
        rs = sorted([r for r in rows if key(r) == k], key=lambda r: r["factor"])
        ok = [r for r in rs if "err_all_m" in r]
        cells = []
        for r in rs:
            if "err_all_m" not in r:
                cells.append(f"x{r['factor']:g}: {short_error(r.get('error'))}")
                continue
            ea = r["err_after_m"]
            cells.append(f"x{r['factor']:g}: {1e3 * r['err_all_m']:.1f} / {1e3 * (r['err_interaction_m'] or 0):.1f} / "
                         + (f"{1e3 * ea:.1f}" if ea is not None else "-"))
        bf = best_factor([(r["factor"], r["err_all_m"]) for r in ok])
        aft = [r for r in ok if r["err_after_m"] is not None]
        best_after = min(aft, key=lambda r: r["err_after_m"])["factor"] if aft else None
        r0 = rs[0]
        sub = sorted({r.get("substeps") for r in ok if r.get("substeps")})
        subs = f"{sub[0]}-{sub[-1]}" if len(sub) > 1 else (str(sub[0]) if sub else "-")
        dxr = r0["dx"] / r0["truth_dx"] if r0.get("dx") and r0.get("truth_dx") else float("nan")
        out.append(f"| {k[0]} | {r0.get('shape')} {r0.get('scenario')}, {r0.get('type')} | {r0['particles']} ({r0['truth_particles']}) "
                   f"| {k[1]:g}, {dxr:.2f} | {k[2]}: {subs} ({r0.get('truth_substeps')}) | {k[3]} | {k[4]} "
                   f"| {1e3 * r0['truth_mean_disp_m']:.1f} mm | {'; '.join(cells)} "
                   f"| {'-' if bf is None else f'{bf:.2f}'} / {best_after} |")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--seeds", required=True)
    ap.add_argument("--cap", type=int, default=15000, help="init's --max-particles (grid auto)")
    ap.add_argument("--factors", default="0.125,0.25,0.5,1,2")
    ap.add_argument("--rules", default="default,band")
    ap.add_argument("--grid-scales", default="1", help="our grid: 1 = init --grid auto within --cap; 1.5 = 1.5x its cells")
    ap.add_argument("--steps", default="fit", help="fit (adaptive substep, CFL 0.6), cflC (adaptive at CFL C, e.g. "
                                                   "cfl0.3), truth (the truth's substeps) and/or N (N a frame)")
    ap.add_argument("--blends", default="rate", help="rate (the fit's partial blends per unit time) and/or substep (the generator's)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", default=None)
    ap.add_argument("--scratch", default="/tmp/world_simcheck")
    a = ap.parse_args(argv)
    factors = [float(f) for f in a.factors.split(",")]
    rules = [r for r in a.rules.split(",") if r]
    bad = [r for r in rules if r not in RULES and r not in KIND_RULES]
    if bad:
        print(f"world_simcheck.py: error: --rules: unknown {bad[0]!r} ({', '.join([*RULES, *KIND_RULES])})",
              file=sys.stderr)
        return 2
    steps = [t for t in a.steps.split(",") if t]
    blends = [t for t in a.blends.split(",") if t]
    def _step_ok(v):
        if v.isdigit():
            return int(v) > 0
        try:
            return v.startswith("cfl") and 0 < float(v[3:]) <= 1
        except ValueError:
            return False

    for flag, vals, ok in (("--steps", [v for v in steps if not _step_ok(v)], ("fit", "truth", "N", "cflC")),
                           ("--blends", blends, ("rate", "substep"))):
        if any(v not in ok or v in ("N", "cflC") for v in vals):
            print(f"world_simcheck.py: error: {flag}: unknown {[v for v in vals if v not in ok][0]!r} ({', '.join(ok)})",
                  file=sys.stderr)
            return 2
    try:
        scales = [float(t) for t in a.grid_scales.split(",") if t]
    except ValueError:
        print(f"world_simcheck.py: error: --grid-scales: not numbers: {a.grid_scales!r}", file=sys.stderr)
        return 2
    return per_capture("world_simcheck.py", Path(a.work), a.seeds,
                       lambda n: one(Path(a.work), n, a.cap, factors, rules, a.device, Path(a.scratch), log=lambda *x, **k: print(*x, file=sys.stderr, **k),
                                     grid_scales=scales, steps=steps, blends=blends),
                       a.json, table, show=lambda r: json.dumps({k: v for k, v in r.items() if k != "err_per_frame_m"}))

if __name__ == "__main__":
    sys.exit(main())
