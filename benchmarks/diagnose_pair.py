"""What separates two confusable candidates on one fitted stage (issue #22): runs `diagnose` (the
default rule, the pair step on) and prints, for every candidate accepted on held-back frames, its
refit's held-back loss per frame beside the base's (and the pair's joint refit, when the pair step
ran), where in the image its held-back residual reduction lives (the bottom band of the video's
silhouette, the rows within 15% of its height above its lowest row, against the rest), before and
after the release, and which particles its refitted model moves (the lowest 10% at rest against all).
With the capture's gt/particles.npz it also prints each model's particle error against the truth at
the bottom and over the body (the truth's particles matched to the model's nearest at rest).

    python benchmarks/diagnose_pair.py STAGE.usda [--capture DIR] [--out result.json] [--no-pair-step]
        [--pair-signature]

With damping and ground both accepted it also prints the ground's signature (`refit.bottom_signature`: the paired
held-back test from damping's refitted model to the ground's at the lowest points and over the rest).

CPU: one foam_bar case at fit grid 16 is ~15 min of CPU (docs/benchmarks/diagnose_named.md)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def image_split(diag, r_base: np.ndarray, r_c: np.ndarray, m: np.ndarray, R: int | None, band: float = 0.15):
    """Shares of the held-back reduction of the squared residual (base -> candidate) in the bottom band of
    the video's silhouette and elsewhere, before and after the release R."""
    res, prob = diag._ctx["res"], diag._ctx["prob"]
    nf, h, w, _ = res.shape
    d = (np.square(r_base) - np.square(r_c)) * m
    d = d.reshape(nf, h, w, 4).sum(-1)
    sil = (res.masks.cpu().numpy() > 0.5) if res.masks is not None else None
    out = {"bottom": 0.0, "rest": 0.0, "bottom_before": 0.0, "bottom_after": 0.0, "rest_before": 0.0,
           "rest_after": 0.0, "bottom_pixels": 0, "pixels": 0}
    for i, k in enumerate(res.frames):
        if not m.reshape(nf, h, w, 4)[i].any():
            continue
        if sil is None:
            continue
        rows = np.nonzero(sil[k].any(1))[0]
        if not len(rows):
            continue
        lo, hi = rows.max(), rows.min()
        cut = lo - band * max(lo - hi, 1)
        bottom = np.arange(h)[:, None] >= cut
        bottom = np.broadcast_to(bottom, (h, w))
        ph = "after" if R is not None and k >= R else "before"
        out["bottom"] += float(d[i][bottom].sum())
        out["rest"] += float(d[i][~bottom].sum())
        out[f"bottom_{ph}"] += float(d[i][bottom].sum())
        out[f"rest_{ph}"] += float(d[i][~bottom].sum())
        near = sil[k] | np.roll(sil[k], 2, 0) | np.roll(sil[k], -2, 0)
        out["bottom_pixels"] += int((bottom & near).sum())
        out["pixels"] += int(near.sum())
    return out


def simulate(diag, state):
    import torch

    from physinteract_usd.diagnose.refit import rung_for
    from physinteract_usd.fit.select import pinned_substep

    prob, base = diag._ctx["prob"], diag._ctx["base"]
    with torch.no_grad():
        if state is None:
            x, _ = prob.simulate(base.E, base.nu, None, effects=base.effects)
        else:
            with pinned_substep(prob, rung_for(diag, state["E"])):
                x, _ = prob.simulate(state["E"], state["nu"], state["trajectories"], effects=state["full_effects"])
    return x.detach().cpu().numpy().astype(np.float64)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("stage")
    ap.add_argument("--capture", default=None, help="the synthetic capture (its gt/particles.npz)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--no-pair-step", action="store_true")
    ap.add_argument("--pair-signature", action="store_true", help="damping vs ground decided by the signature")
    ap.add_argument("--candidates", default=None, help="as diagnose --candidates (e.g. damping,ground: a cheaper look)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--starts", type=int, default=1, help="as benchmarks/diagnose_floor_rule.py (1: the stage's fit)")
    a = ap.parse_args(argv)

    import physinteract_usd.app.diagnose as AD
    from physinteract_usd import api
    from physinteract_usd.diagnose.evidence import release_frame
    from physinteract_usd.diagnose.refit import per_frame_loss, residual_at

    AD.PAIR_STEP = not a.no_pair_step
    got = {}
    orig = AD.refit_confusable

    def keep(diag, *args, **kw):
        got["diag"] = diag
        return orig(diag, *args, **kw)

    AD.refit_confusable = keep
    t0, c0 = time.perf_counter(), time.process_time()
    out = api.diagnose(a.stage, device=a.device, starts=a.starts, pair_signature=a.pair_signature, candidates=a.candidates, progress=False, write_stage=False, log=lambda *x, **k: print(*x))
    cpu = time.process_time() - c0
    diag = got["diag"]
    prob = diag._ctx["prob"]
    R = release_frame(prob)
    print(f"\nverdict {out['verdict']}: {out['reason']}\n(diagnose: {time.perf_counter() - t0:.0f} s wall, {cpu:.0f} CPU s)")
    acc = [c for c in diag.results if c.accepted and getattr(c, "_held", None) is not None]
    r0 = residual_at(diag, None, None)[0]
    rows = {"verdict": out["verdict"], "named": [c["effect"] for c in out["candidates"]], "release": R,
            "cpu_s": round(cpu, 1), "candidates": {}, "confusable": out.get("confusable")}
    pair = next((c.pair_test for c in diag.results if getattr(c, "pair_test", None)), None)
    if pair:
        rows["pair_test"] = pair
        print(f"\npair step: {pair['why']}")
    print("\nheld-back loss per frame (x1e-3), folds pooled:")
    pf = pair["per_frame"] if pair else {"base": per_frame_loss(diag, [(m, r0) for m, _ in acc[0]._held])} if acc else {}
    for c in acc:
        pf.setdefault(c.effect, per_frame_loss(diag, c._held))
    frames = sorted({k for v in pf.values() for k in v})
    print("| model | " + " | ".join(str(k) for k in frames) + " |")
    print("|---" * (len(frames) + 1) + "|")
    for name, v in pf.items():
        print(f"| {name} | " + " | ".join(f"{1e3 * v[k]:.3f}" if k in v else "-" for k in frames) + " |")
    print(f"(release at frame {R})")

    x_base = simulate(diag, None)
    y0 = prob.x0[:, 1] if not hasattr(prob.x0, "cpu") else prob.x0.cpu().numpy()[:, 1]
    y0 = np.asarray(y0, dtype=np.float64)
    low = y0 <= np.quantile(y0, 0.10)
    truth = None
    if a.capture and (Path(a.capture) / "gt" / "particles.npz").exists():
        z = np.load(Path(a.capture) / "gt" / "particles.npz")
        key = next((k for k in z.files if z[k].ndim == 3), None)
        if key is not None:
            xt = z[key]
            x0 = np.asarray(prob.x0.cpu().numpy() if hasattr(prob.x0, "cpu") else prob.x0, np.float64)
            from scipy.spatial import cKDTree

            idx = cKDTree(xt[0]).query(x0)[1]
            truth = xt[:, idx]
            print(f"\ntruth: gt/particles.npz[{key}] {xt.shape}, matched to the model's {len(x0)} particles")
    print("\nwhere each candidate's refit acts and helps:")
    print("| model | held-back reduction in the bottom band (share of pixels) | its shares before / after release (bottom; rest) "
          "| particle change vs base: lowest 10% / all [mm] | error vs truth: lowest 10% / all [mm] |")
    print("|---|---|---|---|---|")
    models = [("base", None, None)] + [(c.effect, c._states[0], c._held) for c in acc if getattr(c, "_states", None)]
    pj = next((c._pair_joint for c in diag.results if getattr(c, "_pair_joint", None)), None)
    if pj is not None:
        models.append(("+".join(pj["effects"]), pj["states"][0], pj["held"]))
    for name, st, held in models:
        x = x_base if st is None else simulate(diag, st)
        dx = np.linalg.norm(x - x_base, axis=-1)[1:]
        ch = f"{1e3 * dx[:, low].mean():.2f} / {1e3 * dx.mean():.2f}"
        err = "-"
        if truth is not None and len(truth) == len(x):
            e = np.linalg.norm(x - truth, axis=-1)[1:]
            err = f"{1e3 * e[:, low].mean():.2f} / {1e3 * e.mean():.2f}"
        img = "-"
        ph = "-"
        if held is not None:
            sp = [image_split(diag, r0, r1, mk, R) for mk, r1 in held]
            tot = {k: sum(s[k] for s in sp) for k in sp[0]}
            allr = tot["bottom"] + tot["rest"]
            img = (f"{100 * tot['bottom'] / allr:.0f}% ({100 * tot['bottom_pixels'] / max(tot['pixels'], 1):.0f}% of "
                   f"the silhouette's pixels)" if allr else "0")
            ph = (f"{100 * tot['bottom_before'] / allr:.0f}% / {100 * tot['bottom_after'] / allr:.0f}%; "
                  f"{100 * tot['rest_before'] / allr:.0f}% / {100 * tot['rest_after'] / allr:.0f}%") if allr else "-"
        rows["candidates"][name] = {"particle_change_mm": ch, "truth_error_mm": err, "image_bottom": img, "phases": ph,
                                    "estimate": None if st is None else st["effects"]}
        print(f"| {name} | {img} | {ph} | {ch} | {err} |")
    by = {c.effect: c for c in acc}
    if "damping" in by and "ground" in by:
        from physinteract_usd.diagnose.refit import bottom_signature

        sig = bottom_signature(diag, by["damping"], by["ground"])
        if sig is not None:
            rows["bottom_signature"] = sig
            print(f"\nthe ground's signature (damping's refit -> the ground's): {sig['why']}")
    if a.out:
        Path(a.out).write_text(json.dumps(rows, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
