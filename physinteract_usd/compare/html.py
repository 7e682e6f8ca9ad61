"""The report as one self-contained HTML page: the headline, the summary against the noise floor,
the plots and side-by-side frames inlined as base64 PNG, the per-frame table and the versions."""

from __future__ import annotations

import base64
import html

from .phases import PHASE_COLORS

CSS = """
body{font-family:system-ui,sans-serif;margin:24px;max-width:1200px;color:#222;background:#fff}
h1{font-size:20px;margin:0 0 4px} h2{font-size:16px;margin:24px 0 6px}
.headline{padding:12px 16px;border-radius:6px;font-size:16px;margin:12px 0}
.adequate{background:#e5f5e0;border:1px solid #74c476} .inadequate{background:#fee0d2;border:1px solid #fb6a4a}
table{border-collapse:collapse;font-size:12px} td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f0f0f0} .fail{color:#cb181d;font-weight:bold} .note{color:#555;font-size:13px;max-width:900px}
img.plot{max-width:100%;display:block;margin:6px 0} img.frame{max-width:100%;display:block;margin:4px 0}
"""


def img(png: bytes, cls: str, alt: str) -> str:
    return f'<img class="{cls}" alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _num(v, fmt="{:.2f}"):
    return "" if v is None else fmt.format(v)


def page(title: str, data: dict, plots: dict, frames: list[tuple[int, bytes]], notes: dict) -> str:
    """`data`: the report's JSON; `plots`: {name: PNG bytes} (metrics, split, whiteness, residual_map,
    versions); `frames`: [(frame, PNG)]; `notes`: {name: what the plot means}."""
    e = html.escape
    v = data["verdict"]
    fl = data.get("noise_floor", {})
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(title)}</title><style>{CSS}</style></head><body>",
           f"<h1>{e(title)}</h1>", f"<div class='headline {v}' id='headline'><b>{e(v)}</b>: {e(data['headline'])}</div>",
           "<table id='summary'><tr><th>PSNR</th><th>PSNR masked</th><th>SSIM</th><th>IoU</th><th>track error</th>"
           "<th>pixel noise</th><th>PSNR floor (masked)</th><th>tracker floor</th></tr>",
           f"<tr><td>{_num(data.get('psnr'))} dB</td><td>{_num(data.get('psnr_masked'))} dB</td>"
           f"<td>{_num(data.get('ssim'), '{:.3f}')}</td><td>{_num(data.get('iou'), '{:.3f}')}</td>"
           f"<td>{_num(data.get('track_error_px'))} px</td><td>{_num(fl.get('pixel_sigma'), '{:.4f}')}</td>"
           f"<td>{_num(fl.get('psnr_floor_db'))} dB</td><td>{_num(fl.get('track_px_mean'))} px</td></tr></table>",
           "<p class='note'>Phases: " + " ".join(
               f"<span style='background:{c};padding:0 6px'>{p}</span>" for p, c in PHASE_COLORS.items()) + "</p>"]
    for name, heading in (("metrics", "Per frame, against the noise floor"), ("split", "Residual motion, split"),
                          ("residual_map", "Where on the object"), ("whiteness", "Whiteness and correlation with the input"),
                          ("versions", "Fit versions")):
        if name in plots:
            out.append(f"<h2 id='{name}'>{e(heading)}</h2>")
            if notes.get(name):
                out.append(f"<p class='note'>{e(notes[name])}</p>")
            out.append(img(plots[name], "plot", name))
    if frames:
        out.append("<h2 id='frames'>Frames: video | model | error</h2>")
        if notes.get("frames"):
            out.append(f"<p class='note'>{e(notes['frames'])}</p>")
        out.extend(img(png, "frame", f"frame {k}") for k, png in frames)
    out.append("<h2 id='table'>Per frame</h2><table><tr><th>frame</th><th>phase</th><th>PSNR</th><th>PSNR masked</th>"
               "<th>SSIM</th><th>IoU</th><th>track error px</th><th>floor px</th><th>tracks</th><th>fails</th></tr>")
    for d in data["frames"]:
        cls = " class='fail'" if d.get("fails") else ""
        out.append(f"<tr{cls}><td>{d['frame']}</td><td style='background:{PHASE_COLORS.get(d['phase'], '#fff')}'>"
                   f"{e(d['phase'])}</td><td>{_num(d.get('psnr'))}</td><td>{_num(d.get('psnr_masked'))}</td>"
                   f"<td>{_num(d.get('ssim'), '{:.3f}')}</td><td>{_num(d.get('iou'), '{:.3f}')}</td>"
                   f"<td>{_num(d.get('track_error_px'))}</td><td>{_num(d.get('track_floor_px'))}</td>"
                   f"<td>{d.get('tracks', '')}</td><td>{'yes' if d.get('fails') else ''}</td></tr>")
    out.append("</table>")
    if data.get("versions"):
        out.append("<h2>Versions</h2><table><tr><th>version</th><th>effects</th><th>mean PSNR</th><th>final loss</th></tr>")
        for d in data["versions"]:
            out.append(f"<tr><td>{d['version']}</td><td>{e(', '.join(d.get('effects') or []) or 'base')}</td>"
                       f"<td>{_num(d.get('psnr'))}</td><td>{_num(d.get('loss'), '{:.5g}')}</td></tr>")
        out.append("</table>")
    out.append(f"<p class='note'>{e(data.get('generator', ''))}</p></body></html>")
    return "\n".join(out)
