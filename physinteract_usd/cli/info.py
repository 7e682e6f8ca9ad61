"""`physinteract-usd info`: summarise a stage (the verb: `physinteract_usd.app.info`)."""

from __future__ import annotations

import json


def add_parser(sub):
    s = sub.add_parser("info", help="summarise a stage")
    s.add_argument("stage")
    s.add_argument("--json", action="store_true", help="print JSON")
    return s


def run(a) -> int:
    from .. import api

    d = api.info(a.stage)
    print(json.dumps(d, indent=2) if a.json else format_info(d))
    return 0


def format_info(d: dict) -> str:
    o, p, f, c, s, m = d["object"], d["particles"], d["frames"], d["camera"], d["simulation"], d["material"]
    lines = [
        f"stage       {d['stage']}  ({d['generator']})",
        f"object      {o['kind']}: {o['gaussians']} Gaussians, SH degree {o['sh_degree']}, "
        f"bounds {o['bounds'][0]} .. {o['bounds'][1]} m",
        f"particles   {p['count']} ({p['surface']} at the surface), spacing {p['spacing_m'] * 1000:.2f} mm, "
        f"volume {p['total_volume_m3'] * 1e6:.1f} cm^3, mass {p['mass_kg'] * 1000:.1f} g, {p['constitutive_model']}",
        f"frames      {f['count']} at {f['fps']:g} fps, {f['size'][0]}x{f['size'][1]}, from {f['source']}"
        + (f", {f['masks']} masks ({'amodal' if f['masks_amodal'] else 'visible-only'})" if f["masks"] else ", no masks"),
        f"camera      fx {c['fx']:.2f} fy {c['fy']:.2f} cx {c['cx']:.2f} cy {c['cy']:.2f}, "
        f"{'static' if c['static'] else 'moving'}, at {c['position']}",
        f"simulation  grid {'x'.join(map(str, s['grid']))}, dx {s['cell_size_m'] * 1000:.2f} mm, "
        f"{s['substeps_per_frame']} substeps/frame, E in [{s['youngs_range_pa'][0]:.3g}, {s['youngs_range_pa'][1]:.3g}] Pa"
        + (f"; {gc['cellsAcross']:.1f} cells across the thinnest part ({gc['thinnestPart'] * 1000:.3g} mm, "
           f"grid {'auto' if gc['mode'] == 'auto' else 'as given'})" if (gc := s.get("grid_choice")) else "")
        + (f"; rate transfer tau {s['transfer_tau_s'] * 1000:.3g} ms" if s.get("transfer_tau_s") else "")
        + ({True: "; preloaded scan (prestressed on its supports)", None: "; the scan's preload: the first fit decides"}
           .get(s.get("preload"), ""))
        + (f" [the fit: {s['preload_reason']}]" if s.get("preload_reason") else ""),
        f"material    E {m['youngs_modulus_pa']['min']:.3g} .. {m['youngs_modulus_pa']['max']:.3g} Pa "
        f"(median {m['youngs_modulus_pa']['median']:.3g}), nu {m['poisson_ratio']['min']:.3f} .. "
        f"{m['poisson_ratio']['max']:.3f}" + ("" if m["fitted"] else "  (not fitted yet)"),
    ]
    if "confidence" in m:
        cf = m["confidence"]
        lines.append(f"confidence  mean {cf['mean']:.2f} (min {cf['min']:.2f}, max {cf['max']:.2f}); "
                     f"{cf['low_share'] * 100:.0f}% of particles below 0.5: the video says little about E there")
    idf = m.get("identifiability") or {}
    if idf.get("sentence"):
        lines.append(f"identified  {idf['level']}: {idf['sentence']}")
    lines.append("effects     " + (", ".join(f"{k} {v}" for k, v in d["effects"].items()) or "none (base model)"))
    if d["contacts"]:
        for ct in d["contacts"]:
            lines.append(f"contact     {ct['name']}: {ct['type']}, {ct['particles']} particles, "
                         + (f"frames {ct['grasp']}..{ct['release']}" if ct['release'] is not None else f"from frame {ct['grasp']} on")
                         + f" ({ct['source']})")
    else:
        lines.append("contact     none yet (`physinteract-usd extract` finds them; `fit` runs it)")
    for t in d["trajectories"]:
        lines.append(f"trajectory  {t['name']}: {t['stage']}, {t['samples']} samples, moves {t['contact']}")
    if d["fits"]:
        for r in d["fits"]:
            psnr = f"PSNR {r['psnr']:.2f} dB, " if r["psnr"] is not None else ""
            tags = ([r["status"]] if r.get("status", "complete") != "complete" else []) + \
                (["current"] if r.get("current") else []) + ([] if r.get("restorable", True) else ["report only"])
            lines.append(f"fit v{r['version']:<6} effects [{', '.join(r['effects']) or 'none'}], {psnr}"
                         f"loss {r['final_loss']:.4g}, {r['runtime_s']:.0f} s on {r['device']}"
                         + (f"  ({', '.join(tags)})" if tags else ""))
    else:
        lines.append("fits        none yet")
    return "\n".join(lines)
