"""The batch's summary table: one row per manifest item, as CSV and as an HTML page (per-item
numbers, a per-frame PSNR sparkline, the extraction preview, links to each item's report page,
JSON and exported asset, the diagnosis; failed items with their one-line error).

Layer 2: the standard library only. Written atomically (a temp file renamed into place).
"""

from __future__ import annotations

import csv
import html
import io
import math
import os
from pathlib import Path

COLUMNS = ("name", "status", "error", "source", "seconds", "version", "final_loss", "psnr", "psnr_masked", "ssim",
           "iou", "track_error_px", "verdict", "diagnosis", "top_candidate", "youngs_median_pa", "asset",
           "report_html", "notes")


def atomic_write_text(path, text: str) -> None:
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def summary_row(record: dict, out_dir) -> dict:
    """A record's flat row (paths relative to `out_dir`)."""
    m = record.get("metrics") or {}
    o = record.get("outputs") or {}

    def rel(p):
        if not p:
            return ""
        try:
            return os.path.relpath(p, out_dir)
        except ValueError:
            return str(p)

    return {"name": record.get("name", ""), "status": record.get("status", ""), "error": record.get("error") or "",
            "source": str(record.get("source", "")), "seconds": _num(record.get("seconds"), 1),
            "version": m.get("version", ""), "final_loss": _num(m.get("final_loss"), 6), "psnr": _num(m.get("psnr"), 2),
            "psnr_masked": _num(m.get("psnr_masked"), 2), "ssim": _num(m.get("ssim"), 4), "iou": _num(m.get("iou"), 4),
            "track_error_px": _num(m.get("track_error_px"), 3), "verdict": m.get("verdict", ""),
            "diagnosis": m.get("diagnosis", ""), "top_candidate": m.get("top_candidate", ""),
            "youngs_median_pa": _num(m.get("youngs_median_pa"), 1), "asset": rel(o.get("asset")),
            "report_html": rel(o.get("report_html")), "notes": "; ".join(record.get("notes") or [])}


def _num(v, digits):
    if v is None or v == "":
        return ""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "" if not math.isfinite(f) else round(f, digits)


def write_csv(path, records: list[dict], out_dir) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in records:
        w.writerow(summary_row(r, out_dir))
    atomic_write_text(path, buf.getvalue())


def sparkline(values, width=120, height=28) -> str:
    """An inline SVG polyline of `values` (non-finite values skipped)."""
    pts = [(i, float(v)) for i, v in enumerate(values or []) if v is not None and math.isfinite(float(v))]
    if len(pts) < 2:
        return ""
    lo = min(v for _, v in pts)
    hi = max(v for _, v in pts)
    span = hi - lo or 1.0
    n = max(i for i, _ in pts) or 1
    xy = " ".join(f"{2 + (width - 4) * i / n:.1f},{height - 3 - (height - 6) * (v - lo) / span:.1f}" for i, v in pts)
    return (f"<svg width='{width}' height='{height}' role='img'><title>PSNR per frame {lo:.1f}..{hi:.1f} dB</title>"
            f"<polyline fill='none' stroke='#3182bd' stroke-width='1.5' points='{xy}'/></svg>")


_STYLE = """body{font-family:system-ui,sans-serif;margin:24px;color:#222}
table{border-collapse:collapse;font-size:12px} td,th{border:1px solid #ccc;padding:3px 6px;vertical-align:top}
th{background:#f0f0f0;text-align:left} td.n{text-align:right} tr.failed{background:#fee0d2}
tr.interrupted{background:#fff3cd} .err{color:#a50f15;max-width:420px} .small{color:#666;font-size:11px}
img.thumb{max-width:160px;max-height:110px}"""


def write_html(path, records: list[dict], out_dir, *, title: str, totals: dict) -> None:
    esc = html.escape
    out_dir = Path(out_dir)
    head = ", ".join(f"{k} {v}" for k, v in totals.items())
    rows = []
    for r in records:
        row = summary_row(r, out_dir)
        m = r.get("metrics") or {}
        o = r.get("outputs") or {}
        links = []
        for key, label in (("report_html", "report"), ("report_json", "report JSON"), ("diagnose_json", "diagnosis JSON"),
                           ("asset", "asset"), ("sim_ready", "sim-ready"), ("log", "log")):
            if o.get(key) and Path(o[key]).exists():
                links.append(f"<a href='{esc(os.path.relpath(o[key], out_dir))}'>{label}</a>")
        thumb = ""
        if o.get("preview") and Path(o["preview"]).exists():
            thumb = f"<img class='thumb' src='{esc(os.path.relpath(o['preview'], out_dir))}' alt='extraction preview'>"
        diag = esc(str(m.get("diagnosis", "")))
        if m.get("top_candidate"):
            diag += f"<br><span class='small'>best: {esc(str(m['top_candidate']))}</span>"
        if m.get("diagnosis_reason"):
            diag += f"<br><span class='small'>{esc(str(m['diagnosis_reason']))}</span>"
        verdict = esc(str(m.get("verdict", "")))
        if m.get("headline"):
            verdict += f"<br><span class='small'>{esc(str(m['headline']))}</span>"
        status = esc(row["status"]) + (f"<div class='err'>{esc(row['error'])}</div>" if row["error"] else "")
        if row["notes"]:
            status += f"<div class='small'>{esc(row['notes'])}</div>"
        nums = "".join(f"<td class='n'>{esc(str(row[k]))}</td>" for k in
                       ("seconds", "version", "final_loss", "psnr", "psnr_masked", "ssim", "iou", "track_error_px",
                        "youngs_median_pa"))
        rows.append(f"<tr class='{esc(row['status'])}'><td><b>{esc(row['name'])}</b><br>"
                    f"<span class='small'>{esc(row['source'])}</span></td><td>{status}</td>{nums}"
                    f"<td>{sparkline(m.get('frames_psnr'))}</td><td>{verdict}</td><td>{diag}</td>"
                    f"<td>{thumb}</td><td>{' | '.join(links)}</td></tr>")
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(title)}</title><style>{_STYLE}</style>"
            f"</head><body><h1>{esc(title)}</h1><p>{esc(head)}</p><table><tr><th>item</th><th>status</th>"
            "<th>s</th><th>version</th><th>loss</th><th>PSNR</th><th>PSNR masked</th><th>SSIM</th><th>IoU</th>"
            "<th>track px</th><th>median E [Pa]</th><th>PSNR per frame</th><th>report</th><th>diagnosis</th>"
            "<th>extraction</th><th>files</th></tr>" + "".join(rows) + "</table></body></html>")
    atomic_write_text(path, page)
