"""The panel's pieces for verbs the CLI gains over time (report, diagnose, effects, versions,
export --sim-ready): shown and used when the installed CLI has them, one clear line when not.

A CLI that has them is stood in for by a small wrapper: it answers `-h`, `report --json`,
`diagnose --json`, `effects add` and `versions use` with what the design's contract says (the
JSON keys of `report --json` and `diagnose --json`) and hands every other verb to the real CLI.
"""

from __future__ import annotations

import json
import sys

import bpy
import pytest
from test_blender_addon import FakeLayout

REPORT = {"psnr": 24.5, "psnr_masked": 18.25, "ssim": 0.91, "iou": 0.8, "track_error_px": 1.5,
          "frames": [{"frame": k, "psnr": 20.0 + k, "ssim": 0.9, "iou": 0.8, "phase": "grasped"} for k in range(6)],
          "versions": [{"version": 1, "effects": [], "psnr": 24.5, "loss": 0.1}],
          "verdict": "inadequate", "headline": "inadequate from frame 4 on (load): the model sags too much (the "
          "video hangs higher): 6.2 mm on average"}
VERSIONS = {"stage": "scene.usda", "current": 2,
            "versions": [{"version": 1, "status": "complete", "effects": [], "psnr": 22.5},
                         {"version": 2, "status": "interrupted", "effects": ["damping"], "psnr": 23.0}]}
DIAGNOSE = {"verdict": "missing_effect", "reason": "the motion decays faster than elasticity allows",
            "candidates": [{"effect": "damping", "score": 0.8, "predicted_loss_drop": 0.02, "realized_loss_drop": None,
                            "estimate": {"c": 3.0}, "evidence": "amplitude ratio 0.4 per swing"},
                           {"effect": "interaction:timing", "score": 0.3, "predicted_loss_drop": 0.005,
                            "realized_loss_drop": None, "estimate": {}, "evidence": "--grasp-frame 2 fits better"}]}

WRAPPER = r'''#!{python}
import json, os, sys
REAL, LOG = {real!r}, {log!r}
NEW = {{"report": ["--json"], "diagnose": ["--json"], "effects": [], "versions": ["--json"]}}
a = sys.argv[1:]
def log(*words):
    with open(LOG, "a") as f:
        f.write(" ".join(words) + "\n")
if a == ["-h"]:
    print("usage: physinteract-usd [-h] [--version] VERB ...\n\npositional arguments:\n  VERB\n"
          + "".join(f"    {{v}}      x\n" for v in ("init", "info", "extract", "fit", "simulate", "export", *NEW))
          + "\noptions:\n  -h, --help  show this help message and exit")
elif len(a) == 2 and a[1] == "-h" and a[0] in NEW:
    print(f"usage: physinteract-usd {{a[0]}} [-h] " + " ".join(NEW[a[0]]) + " stage")
elif a[:2] == ["export", "-h"]:
    print("usage: physinteract-usd export [-h] [--ply-sequence DIR] [--sim-ready] stage out")
elif a and a[0] == "report":
    log(*a); print("Warp 1.10 initialized:"); print(json.dumps({report}))
elif a and a[0] == "diagnose":
    log(*a); print(json.dumps({diagnose}))
elif a[:2] == ["versions", "list"]:
    log(*a); print(json.dumps({versions}))
elif a and a[0] in ("effects", "versions"):
    log(*a); print("ok")
elif a and a[0] == "export" and "--sim-ready" in a:
    log(*a); a.remove("--sim-ready"); os.execv(REAL, [REAL, *a])
else:
    os.execv(REAL, [REAL, *a])
'''


@pytest.fixture
def newer_cli(addon, cli, tmp_path):
    """The add-on pointed at a CLI with report / diagnose / effects / versions / --sim-ready."""
    path, log = tmp_path / "physinteract-usd-newer", tmp_path / "calls.log"
    path.write_text(WRAPPER.format(python=sys.executable, real=cli, log=str(log),
                                   report=repr(REPORT), diagnose=repr(DIAGNOSE),
                                   versions=repr(VERSIONS)))
    path.chmod(0o755)
    prefs = bpy.context.preferences.addons["physinteract_usd_blender"].preferences
    prefs.cli_path = str(path)           # the update clears what the add-on knew of the old CLI
    addon.clicaps.probe_in_background([str(path)]).join(60)
    yield log
    prefs.cli_path = cli


def draw(panel) -> list:
    log = []
    panel.draw(type("P", (), {"layout": FakeLayout(log)})(), bpy.context)
    return log


def known_caps(addon, cli):
    addon.clicaps.probe_in_background([cli]).join(60)


def test_without_the_verbs_the_panel_says_so(addon, cli, twin):
    from test_blender_resimulate import import_twin

    known_caps(addon, cli)
    s = import_twin(addon, twin["stage"])
    have = addon.clicaps.verbs([cli])
    log = draw(bpy.types.PHYSINTERACT_PT_report)
    labels = [e[1] for e in log if e[0] == "label"]
    for verb in ("diagnose",):
        if verb not in have:
            assert f"{verb}: not in this physinteract-usd (update it)" in labels
            with pytest.raises(RuntimeError, match=f"no `{verb}` verb"):
                bpy.ops.physinteract.run(steps=verb)
    if "effects" not in have:
        with pytest.raises(RuntimeError, match="no `effects` verb"):
            bpy.ops.physinteract.run(steps="effect:damping")
    if "versions" not in have:
        with pytest.raises(RuntimeError, match="no `versions` verb"):
            bpy.ops.physinteract.run(steps="version:1")
    if not addon.clicaps.has([cli], "export", "--sim-ready"):
        labels = [e[1] for e in draw(bpy.types.PHYSINTERACT_PT_fit) if e[0] == "label"]
        assert "export --sim-ready: not in this physinteract-usd (update it)" in labels
    assert s.error.startswith("this physinteract-usd has no") or not (
        {"diagnose", "effects", "versions"} - have)


def test_report_and_diagnosis_from_a_cli_that_has_them(addon, newer_cli, twin):
    from test_blender_resimulate import import_twin

    s = import_twin(addon, twin["stage"])
    assert bpy.ops.physinteract.run(steps="report,diagnose") == {"FINISHED"}, s.error
    assert json.loads(s.report_json)["psnr"] == 24.5 and s.note == ""
    assert json.loads(s.diagnose_json)["verdict"] == "missing_effect"
    calls = newer_cli.read_text().splitlines()
    assert calls == [f"report {twin['stage']} --json", f"diagnose {twin['stage']} --json"]
    bpy.context.scene.frame_set(3)
    assert s.frame_psnr == pytest.approx(23.0)          # the curve, keyed per frame
    log = draw(bpy.types.PHYSINTERACT_PT_report)
    labels = [e[1] for e in log if e[0] == "label"]
    assert "PSNR 24.50 dB (masked 18.25), SSIM 0.910, IoU 0.800" in labels
    assert "verdict: inadequate" in labels
    assert "inadequate from frame 4 on (load): the model sags too much (the video" in labels
    assert "track error 1.50 px" in labels
    assert "frame 3: PSNR 23.00, SSIM 0.900, IoU 0.800 (grasped)" in labels
    assert [e[1] for e in log if e[0] == "progress"] == [f"{k}: {20 + k:.1f} dB" for k in range(6)]
    assert "verdict: missing_effect" in labels
    assert any(t.startswith("damping: score 0.8") for t in labels)
    assert "  amplitude ratio 0.4 per swing" in labels and "  --grasp-frame 2 fits better" in labels
    ops = [(e[1], e[2]) for e in log if e[0] == "operator"]
    assert ("physinteract.run", "Add damping and refit") in ops
    assert not any("interaction:timing" in (t or "") for _, t in ops)     # not an effect: no button
    assert not any("not in this physinteract-usd" in t for t in labels)


def test_add_effect_refits_and_versions_use_reimports(addon, newer_cli, twin):
    from test_blender_resimulate import import_twin

    s = import_twin(addon, twin["stage"])
    job = addon.build_job(bpy.context, "effect:damping")
    assert [st.label for st in job.steps] == ["effects add damping", "fit", "info", "versions list", "import",
                                              "report", "residual"]
    assert job.steps[0].argv[-4:] == ["effects", "add", str(twin["stage"]), "damping"]
    with pytest.raises(RuntimeError, match="unknown effect 'wind'"):
        bpy.ops.physinteract.run(steps="effect:wind")
    assert bpy.ops.physinteract.run(steps="version:1") == {"FINISHED"}, s.error
    assert newer_cli.read_text().splitlines()[-2:] == [f"versions use {twin['stage']} 1",
                                                        f"versions list {twin['stage']} --json"]
    assert s.last_collection in bpy.data.collections                      # re-imported
    log = draw(bpy.types.PHYSINTERACT_PT_report)
    labels = [e[1] for e in log if e[0] == "label"]
    assert "v1: base, PSNR 22.50" in labels and "v2: damping, PSNR 23.00 (interrupted)" in labels
    assert [e[2] for e in log if e[0] == "operator"].count("Use") == 1      # not for the current one


def test_sim_ready_export_button(addon, cli, twin, tmp_path):
    """The panel's "Simulation-ready export" runs `export <stage> <out> --sim-ready --force` with the
    project's CLI into its own file (the plain export, which the panel imports, is left alone), shows
    the command's summary line, and runs again over its own output."""
    from pxr import Usd
    from test_blender_resimulate import import_twin

    known_caps(addon, cli)
    assert addon.clicaps.has([cli], "export", "--sim-ready"), "the project's CLI lacks export --sim-ready"
    s = import_twin(addon, twin["stage"])
    s.export_path = str(tmp_path / "twin.usdc")
    log = draw(bpy.types.PHYSINTERACT_PT_fit)
    assert ("operator", "physinteract.run", "Simulation-ready export") in log
    assert ("prop", "sim_ready_path") in log
    job = addon.build_job(bpy.context, "export_sim_ready")
    out = tmp_path / "twin_simready.usdc"                        # the default: beside the export
    assert job.steps[0].argv[-5:] == ["export", str(twin["stage"]), str(out), "--sim-ready", "--force"]
    for _ in range(2):                                          # the second run replaces the first (--force)
        assert bpy.ops.physinteract.run(steps="export_sim_ready") == {"FINISHED"}, s.error
    assert not (tmp_path / "twin.usdc").exists()
    st = Usd.Stage.Open(str(out))
    assert [p.GetPath().pathString for p in st.Traverse() if p.GetTypeName() == "TetMesh"] == ["/World/Twin/SimMesh"]
    assert s.sim_ready_summary.startswith("sim-ready: ") and " tetrahedra, " in s.sim_ready_summary
    assert ("label", s.sim_ready_summary) in draw(bpy.types.PHYSINTERACT_PT_fit)
    s.sim_ready_path = str(twin["stage"])                        # never over the stage
    with pytest.raises(RuntimeError, match="is the stage itself"):
        bpy.ops.physinteract.run(steps="export_sim_ready")
