"""`physinteract-usd evaluate`: score a fitted stage against synthetic ground truth (the verb: `physinteract_usd.app.evaluate`)."""

from __future__ import annotations

import json


def add_parser(sub):
    s = sub.add_parser("evaluate", help="score a fitted stage against synthetic ground truth")
    s.add_argument("stage")
    s.add_argument("--gt", required=True, metavar="DIR/gt", help="the synth capture's gt/ folder")
    s.add_argument("--device", default="cpu", help="cpu or cuda (rendering)")
    s.add_argument("--json", action="store_true", help="print JSON")
    return s


def run(a) -> int:
    from .. import api

    d = api.evaluate(a.stage, a.gt, device=a.device)
    keys = ("ma", "psnr", "psnr_masked", "ssim", "iou", "position_error_m")
    if a.json:
        print(json.dumps({**{k: d[k] for k in keys}, "ma_best_uniform": d["ma_best_uniform"],
                          "by_truth_level": d["by_truth_level"], "calibration": d["calibration"],
                          "truth_resolution": d["truth_resolution"],
                          "truth_resolution_unchecked": d["truth_resolution_unchecked"]}, indent=2))
    else:
        print(f"{'metric':22s} value")
        print(f"{'MA':22s} {d['ma']:.3f}   (best uniform E: {d['ma_best_uniform']:.3f} at {d['best_uniform_e']:.3g} Pa)")
        print(f"{'PSNR':22s} {d['psnr']:.2f} dB")
        print(f"{'PSNR (masked)':22s} {d['psnr_masked']:.2f} dB")
        print(f"{'SSIM':22s} {d['ssim']:.3f}")
        print(f"{'IoU':22s} {d['iou']:.3f}")
        print(f"{'position error':22s} {d['position_error_m'] * 1000:.2f} mm")
        print("\nwhere MA is lost, per material of the truth (strain: the truth's own peak Green strain there):")
        print(f"{'E truth':>10s} {'share':>6s} {'MA':>6s} {'E fit/truth (q25-q75)':>24s} {'confidence':>10s} {'strain':>7s}")
        for r in d["by_truth_level"]:
            conf = f"{r['confidence']:.2f}" if "confidence" in r else "-"
            print(f"{r['e_truth']:10.3g} {r['share']:6.2f} {r['ma']:6.2f} "
                  f"{r['ratio_median']:10.2f} ({r['ratio_q25']:.2f}-{r['ratio_q75']:.2f}){'':>3s} {conf:>10s} "
                  f"{r['exposure']:7.3f}")
        c = d["calibration"]
        if c is not None:
            print(f"confidence: the fit expects MA {c['claimed']:.2f}, finds {c['ma']:.2f}; "
                  f"confident (>= 0.8) and wrong: {c['confident_wrong']:.2f} of the Gaussians")
        tr = d["truth_resolution"]
        if tr is not None and tr["note"]:
            print(f"note: {tr['note']}")
        if d.get("truth_resolution_unchecked"):
            print(f"note: {d['truth_resolution_unchecked']}")
    return 0
