"""`physinteract-usd versions`: list a stage's fit versions, make one current (the verb:
`physinteract_usd.app.versions`)."""

from __future__ import annotations

import json


def add_parser(sub):
    s = sub.add_parser("versions", help="list the stage's fit versions, or make one current")
    vs = s.add_subparsers(dest="action", required=True, metavar="ACTION")
    ls = vs.add_parser("list", help="every fit version: status, loss, metrics, which one is current")
    ls.add_argument("stage")
    ls.add_argument("--json", action="store_true", help="print the list as JSON")
    use = vs.add_parser("use", help="make version N current (its material, animation and contacts)")
    use.add_argument("stage")
    use.add_argument("version", metavar="N")
    use.add_argument("--json", action="store_true", help="print the outcome as JSON")
    return s


def _fmt(x, spec):
    return "-" if x is None else format(x, spec)


def run(a) -> int:
    from .. import api

    if a.action == "use":
        out = api.use_version(a.stage, a.version)
        if a.json:
            print(json.dumps(out, indent=2))
        else:
            prev = f" (was v{out['previous']})" if out["previous"] else ""
            print(f"v{out['version']} is now current{prev}: {out['layer']}")
        return 0
    d = api.list_versions(a.stage)
    if a.json:
        print(json.dumps(d, indent=2))
        return 0
    if not d["versions"]:
        print(f"{d['stage']}: no fit versions yet (`physinteract-usd fit` makes v1)")
        return 0
    print(f"{'':2}{'version':>7}  {'status':<11} {'created':<25} {'loss':>10} {'PSNR':>6} {'masked':>6} "
          f"{'SSIM':>5} {'IoU':>5} {'its':>5}  effects")
    for v in d["versions"]:
        mark = "* " if v["current"] else "  "
        note = "" if v["snapshot"] else "  (report only: cannot be restored)"
        print(f"{mark}{'v' + str(v['version']):>7}  {v['status']:<11} {v['created'] or '-':<25} "
              f"{_fmt(v['final_loss'], '10.5f')} {_fmt(v['psnr'], '6.2f')} {_fmt(v['psnr_masked'], '6.2f')} "
              f"{_fmt(v['ssim'], '5.3f')} {_fmt(v['iou'], '5.3f')} {v['iterations']:>5}  "
              f"{', '.join(v['effects']) or 'base'}{note}")
    cur = d["current"]
    print(f"current: v{cur} (*)" if cur else "current: none (the initial field)")
    return 0
