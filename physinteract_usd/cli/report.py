"""`physinteract-usd report`: compare the fitted model with the measurements and say where it fails
(the verb: `physinteract_usd.app.report`)."""

from __future__ import annotations

import json

def add_parser(sub):
    s = sub.add_parser("report", help="compare the fitted model with the video: where and when it fails",
                       description="Compare the fitted model with the measurements (video frames, silhouettes, "
                                   "point tracks): per-frame PSNR, SSIM, IoU and track error against the noise "
                                   "floor measured from the video, shaded by phase; where on the object it fails "
                                   "(residual primvars on SimParticles); a headline verdict.")
    s.add_argument("stage")
    s.add_argument("--html", metavar="OUT.html", help="write a self-contained HTML page (plots, frames, table)")
    s.add_argument("--video", metavar="OUT.mp4", help="write the side-by-side frames (video | model | error) as MP4")
    s.add_argument("--frames", metavar="DIR", help="write the side-by-side frames as PNGs into DIR")
    s.add_argument("--resimulate", action="store_true",
                   help="simulate the stage's material as composed now (e.g. an E you authored over the fit) "
                        "under the fitted interaction, instead of the animation the stage holds")
    s.add_argument("--no-stage", action="store_true", help="do not write the residual primvars into the fit layer")
    s.add_argument("--force", action="store_true", help="replace output files this verb did not write")
    s.add_argument("--device", default="cpu", help="cpu or cuda (rendering, re-simulation)")
    s.add_argument("--json", action="store_true", help="print the report as JSON")
    return s


def run(a) -> int:
    import sys

    from .. import api

    d = api.report(a.stage, html=a.html, video=a.video, frames_dir=a.frames, write_stage=not a.no_stage,
                   resimulate=a.resimulate, force=a.force, device=a.device, progress=not a.json and sys.stderr.isatty(),
                   log=(lambda *m: print(*m, file=sys.stderr)) if a.json else print)
    if a.json:
        print(json.dumps(d, indent=1, allow_nan=False, default=_jsonable))
        return 0
    print(f"{d['verdict'].upper()}: {d['headline']}")
    print(f"{'frame':>5} {'phase':8} {'PSNR':>6} {'masked':>6} {'SSIM':>6} {'IoU':>5} {'track px':>8} {'floor':>6}")
    for f in d["frames"]:
        n = lambda v, fmt: "" if v is None else fmt.format(v)  # noqa: E731
        print(f"{f['frame']:5d} {f['phase']:8} {n(f['psnr'], '{:6.2f}')} {n(f['psnr_masked'], '{:6.2f}')} "
              f"{n(f['ssim'], '{:6.3f}')} {n(f['iou'], '{:5.2f}')} {n(f['track_error_px'], '{:8.2f}')} "
              f"{n(f['track_floor_px'], '{:6.2f}')}{'  FAILS' if f.get('fails') else ''}")
    n = lambda v, fmt: "-" if v is None else fmt.format(v)  # noqa: E731
    print(f"mean: PSNR {n(d['psnr'], '{:.2f}')} dB, masked {n(d['psnr_masked'], '{:.2f}')} dB, SSIM "
          f"{n(d['ssim'], '{:.3f}')}, IoU {n(d['iou'], '{:.3f}')}, track error {n(d['track_error_px'], '{:.2f}')} px "
          f"({d['tracked_points']} points)")
    for key, label in (("html", "HTML"), ("video", "video"), ("frames", "frames"), ("stage_layer", "residual primvars in")):
        if key in d["outputs"]:
            print(f"{label}: {d['outputs'][key]}")
    return 0


def _jsonable(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return str(o)
