"""`physinteract-usd effects`: switch a physical effect on (`add`) or off (`remove`) in the stage's
root layer, or list them (the verb: `physinteract_usd.app.effects`)."""

from __future__ import annotations

import json

NAMES = ("damping", "plasticity", "ground", "viscoelasticity")
# flag -> (effect's parameter, help); aliases as in sim/effects.py
PARAM_FLAGS = {
    "coefficient": (("--coefficient", "--c"), "damping rate c [1/s] (damping)"),
    "yieldStress": (("--yield-stress", "--tau-y"), "yield stress tau_Y [Pa] (plasticity)"),
    "height": (("--height", "--h"), "plane height h [m] (ground)"),
    "friction": (("--friction", "--mu"), "Coulomb friction mu (ground)"),
    "modulus": (("--modulus", "--e-v"), "Maxwell branch modulus E_v [Pa] (viscoelasticity)"),
    "relaxationTime": (("--relaxation-time", "--tau"), "relaxation time tau [s] (viscoelasticity)"),
}


def add_parser(sub):
    s = sub.add_parser("effects", help="switch a physical effect of the model on or off, or list them")
    vs = s.add_subparsers(dest="action", required=True, metavar="ACTION")
    add = vs.add_parser("add", help="switch an effect on (in your root layer); the next fit warm-starts from "
                        "the current version and fits its parameters")
    add.add_argument("stage")
    add.add_argument("name", metavar="NAME", help=f"one of {', '.join(NAMES)}")
    for p, (flags, h) in PARAM_FLAGS.items():
        add.add_argument(*flags, dest=p, metavar="VALUE", default=None, help=f"start value of the {h}")
    add.add_argument("--fixed", action="store_true", help="keep the values as given (not fitted)")
    add.add_argument("--json", action="store_true", help="print the outcome as JSON")
    rm = vs.add_parser("remove", help="switch an effect off (its API and values removed from your root layer)")
    rm.add_argument("stage")
    rm.add_argument("name", metavar="NAME", help=f"one of {', '.join(NAMES)}")
    rm.add_argument("--json", action="store_true", help="print the outcome as JSON")
    ls = vs.add_parser("list", help="which effects are on, their values (set and fitted) and whether fitted")
    ls.add_argument("stage")
    ls.add_argument("--json", action="store_true", help="print the list as JSON")
    return s


def _num(v) -> str:
    return "-" if v is None else f"{v:.4g}"


def run(a) -> int:
    from .. import api

    if a.action == "add":
        params = {p: getattr(a, p) for p in PARAM_FLAGS if getattr(a, p) is not None}
        out = api.effects_add(a.stage, a.name, params, fixed=a.fixed)
        if a.json:
            print(json.dumps(out, indent=2))
        else:
            vals = ", ".join(f"{k} {_num(v)} ({out['source'][k]})" for k, v in out["values"].items())
            how = "fixed" if not out["fit"] else "fitted by the next `fit`"
            print(f"{out['effect']} on in {out['layer']}: {vals}; {how}")
        return 0
    if a.action == "remove":
        out = api.effects_remove(a.stage, a.name)
        if a.json:
            print(json.dumps(out, indent=2))
        else:
            print(f"{out['effect']} off in {out['layer']}: the next `fit` warm-starts from the current version "
                  "without it")
        return 0
    d = api.effects_list(a.stage)
    if a.json:
        print(json.dumps(d, indent=2))
        return 0
    cur = d["current_version"]
    on = [e for e in d["effects"] if e["on"]]
    if not on:
        print(f"{d['stage']}: no effects on (the base model)")
    for e in on:
        parts = []
        for p, v in e["parameters"].items():
            unit = f" {v['unit']}" if v["unit"] else ""
            fitted = f", fitted {_num(v['fitted'])}{unit} (v{cur})" if v["fitted"] is not None else ""
            parts.append(f"{p} {_num(v['value'])}{unit}{fitted}")
        mode = "fitted" if e["fit"] else "fixed"
        print(f"{e['effect']:<16} {mode:<7} {'; '.join(parts)}")
    off = [e["effect"] for e in d["effects"] if not e["on"]]
    if off:
        print(f"off: {', '.join(off)} (`effects add {d['stage']} NAME`)")
    return 0
