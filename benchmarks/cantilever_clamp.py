"""Usage: python benchmarks/cantilever_clamp.py GRIDS RULES [ES], e.g. `10,16,auto,32 4:0,5:0.4 1e5`
(docs/benchmarks/fit.md, 2026-11-26 later; #24). The default clamp's cantilever against beam theory: tip sag and first frequency vs grid and pin
rule, with three sag readings (half the first low; the mean of the first low and the next high;
the time-mean over whole periods)."""
import sys, time, math, dataclasses, pathlib, shutil, json
sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[1] / "tests"))
import numpy as np, torch
torch.set_num_threads(1)
import fit_scene as fs
from physinteract_usd import simulation
from physinteract_usd.simulation import build_simulation
from physinteract_usd.usd.stage import read_stage

def run(grid, rule, E=1e5, T=120, fps=240.0, root=pathlib.Path("/tmp/cantilever_clamp")):
    simulation.PIN_RULE = rule
    rho = E / 200.0
    r = root / f"g{grid}_{rule[0]}_{rule[1]}_{E:g}"
    shutil.rmtree(r, ignore_errors=True)
    b = fs.build(r, E=E, density=rho, n_frames=4, release=1, e_range=(1e3, 1e7), lift=0 * fs.LIFT, grid=grid)
    sd = dataclasses.replace(read_stage(b["stage"]), end_frame=T - 1, fps=fps)
    hand, support = fs.contacts(sd, lift=0 * fs.LIFT, release=1)
    sim = build_simulation(sd, [hand.replace(trajectory=np.repeat(hand.trajectory[:1], T, 0)), support], T)
    P = len(sd.particles_positions)
    c0 = time.process_time()
    with torch.no_grad():
        x, _ = sim.simulate(torch.full((P,), E), torch.full((P,), fs.NU_TRUE))
    cpu = time.process_time() - c0
    x = x.numpy()
    x0 = sd.particles_positions
    free = np.setdiff1d(np.arange(P), support.indices)
    tip = free[np.argsort(x0[free, 0])[-10:]]
    y = x[:, tip, 1].mean(1) - x[0, tip, 1].mean()
    L = float(x0[:, 0].max() - x0[support.indices, 0].max())
    h = fs.THICK
    sag_th = 1.5 * rho * 9.81 * L ** 4 / (E * h ** 2)
    f_th = 1.875 ** 2 / (2 * math.pi) * math.sqrt(E * h ** 2 / 12 / (rho * L ** 4))
    lows = [k for k in range(1, T - 1) if y[k] < y[k - 1] and y[k] <= y[k + 1]]
    highs = [k for k in range(1, T - 1) if y[k] > y[k - 1] and y[k] >= y[k + 1]]
    def sub(k):   # the low's time by a parabola through its neighbours
        a, b, c = y[k - 1], y[k], y[k + 1]
        den = a - 2 * b + c
        return k + (0.5 * (a - c) / den if den > 0 else 0.0)
    tl = [sub(k) for k in lows]
    period = (tl[-1] - tl[0]) / (len(tl) - 1) / fps
    period1 = (lows[1] - lows[0]) / fps
    s1 = -0.5 * y[lows[0]]
    h1 = [k for k in highs if k > lows[0]][0]
    s2 = -0.5 * (y[lows[0]] + y[h1])
    s3 = -y[lows[0]:lows[-1]].mean() if len(lows) > 2 else float("nan")   # whole periods
    # cells across the thickness, the held band
    dx = sim.grid.dx if hasattr(sim.grid, "dx") else None
    from test_known_answers import timoshenko_cantilever
    s_t, f_t = timoshenko_cantilever(L, h, fs.NU_TRUE)
    out = dict(f_timoshenko=1 / period / f_th / f_t, sag_timoshenko=s3 / sag_th / s_t, grid=grid, rule=list(rule), E=E, P=P, dx=dx, L=L, cells_thick=h / dx if dx else None,
               f=1 / period / f_th, f_test=1 / period1 / f_th, sag_half_low=s1 / sag_th, sag_low_high=s2 / sag_th, sag_mean=s3 / sag_th,
               decay=float(-y[lows[1]] / -y[lows[0]]) if len(lows) > 1 else None,
               prod=s3 / sag_th * (1 / period / f_th) ** 2, cpu=cpu, lows=lows[:4])
    print(json.dumps({k: (round(float(v), 4) if isinstance(v, (float, np.floating)) else v) for k, v in out.items()}), flush=True)
    return out

if __name__ == "__main__":
    grids = [int(g) if g != "auto" else g for g in sys.argv[1].split(",")]
    rules = [tuple(float(v) for v in r.split(":")) for r in sys.argv[2].split(",")]
    Es = [float(e) for e in sys.argv[3].split(",")] if len(sys.argv) > 3 else [1e5]
    for g in grids:
        for rule in rules:
            for E in Es:
                run(g, rule, E)
