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
        print(json.dumps({**{k: d[k] for k in keys}, "ma_best_uniform": d["ma_best_uniform"]}, indent=2))
    else:
        print(f"{'metric':22s} value")
        print(f"{'MA':22s} {d['ma']:.3f}   (best uniform E: {d['ma_best_uniform']:.3f} at {d['best_uniform_e']:.3g} Pa)")
        print(f"{'PSNR':22s} {d['psnr']:.2f} dB")
        print(f"{'PSNR (masked)':22s} {d['psnr_masked']:.2f} dB")
        print(f"{'SSIM':22s} {d['ssim']:.3f}")
        print(f"{'IoU':22s} {d['iou']:.3f}")
        print(f"{'position error':22s} {d['position_error_m'] * 1000:.2f} mm")
    return 0
