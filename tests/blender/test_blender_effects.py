"""The panel's "Add <effect> and refit" against the project's own CLI (not a stand-in): `effects add`
switches the effect on in the user's root layer, the refit warm-starts from the current version and
writes a new one with the effect's fitted value, and the result is re-imported."""

from __future__ import annotations

import json
import shutil

import bpy
import pytest
from pxr import Sdf


def test_add_damping_and_refit_through_the_panel(addon, cli, twin, tmp_path):
    from test_blender_resimulate import import_twin

    addon.clicaps.probe_in_background([cli]).join(60)
    if "effects" not in addon.clicaps.verbs([cli]):
        pytest.skip("this physinteract-usd has no `effects` verb")
    src = twin["stage"].parent.parent           # the twin's folder: capture and stage (kept for other tests)
    shutil.copytree(src, tmp_path / "t")
    stage = tmp_path / "t" / twin["stage"].relative_to(src)
    fit_layer = stage.with_name("scene.fit.usdc")
    init_before = stage.with_name("scene.init.usdc").read_bytes()

    def reports() -> dict:
        """{report prim name: (effects, effect parameters, resumed from)} in the fit layer."""
        lay = Sdf.Layer.OpenAsAnonymous(str(fit_layer))
        spec = lay.GetPrimAtPath("/World/PhysInteract")
        out = {}
        for c in spec.nameChildren:
            if c.name.startswith("FitReport_v"):
                a = c.attributes
                get = lambda n: a[n].default if n in a else None  # noqa: E731
                out[c.name] = (list(get("physinteract:effects") or []), get("physinteract:effectParameters") or "{}",
                               str(get("physinteract:resumedFrom") or ""))
        return out

    before = set(reports())
    s = import_twin(addon, stage, fit_iterations=1)
    job = addon.build_job(bpy.context, "effect:damping")
    assert job.steps[0].argv[-4:] == ["effects", "add", str(stage), "damping"]
    assert bpy.ops.physinteract.run(steps="effect:damping") == {"FINISHED"}, s.error
    root = stage.read_text()
    assert "PhysInteractDampingAPI" in root and "physinteract:damping:fit = 1" in root
    assert stage.with_name("scene.init.usdc").read_bytes() == init_before     # only the root was edited
    new = set(reports()) - before
    assert len(new) == 1, new
    effects, params, resumed = reports()[new.pop()]
    assert effects == ["damping"]
    assert json.loads(params)["damping"]["coefficient"] > 0
    assert resumed.startswith("warm:v")
    assert s.last_collection in bpy.data.collections                          # re-imported
