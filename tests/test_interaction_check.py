"""The check `fit` prints at the end (fit/interaction_check.py): a residual that peaks around the
grasp or the release frame, or that sits at the contact, is said, with the override that fixes it;
a residual spread evenly over frames and pixels is not."""

from __future__ import annotations

import numpy as np
import pytest

from physinteract_usd.fit.interaction_check import check_interaction

T, H, W = 24, 40, 60


def _base(seed=0):
    rng = np.random.default_rng(seed)
    res = 0.002 * (1 + 0.2 * rng.random((T, H, W)))
    reg = np.zeros((T, H, W), bool)
    reg[:, 10:30, 10:50] = True
    return res, reg


def test_an_even_residual_is_not_a_wrong_interaction():
    res, reg = _base()
    res *= np.linspace(1, 1.4, T)[:, None, None]      # a slow drift, the usual
    uv = np.tile([30.0, 20.0], (T, 1))
    out = check_interaction(res, reg, 5, 15, contact_uv=uv, radius_px=4)
    assert out["suspect"] == [] and out["notes"] == []
    assert 0 < out["contact_share"] < 0.2


def test_a_peak_at_the_grasp_names_the_grasp_flag():
    res, reg = _base()
    res[6] *= 4          # the model starts to pull a frame after the video's hand did
    out = check_interaction(res, reg, 5, 15)
    assert out["suspect"] == ["grasp"] and out["peak_frame"] == 6
    assert "extract --grasp-frame K" in out["notes"][0] and "frame 6" in out["notes"][0]


def test_a_peak_at_the_release_names_the_release_flag_and_a_far_peak_nothing():
    res, reg = _base()
    res[16] *= 4
    out = check_interaction(res, reg, 5, 15)
    assert out["suspect"] == ["release"] and "--release-frame" in out["notes"][0]
    res, reg = _base()
    res[10] *= 4          # mid-pull, far from both: not the timing's signature
    assert check_interaction(res, reg, 3, 20)["suspect"] == []
    # held to the end: no release to blame
    res, reg = _base()
    res[16] *= 4
    assert check_interaction(res, reg, 5, None)["suspect"] == []


def test_a_residual_at_the_contact_names_the_hint_pixel():
    res, reg = _base()
    uv = np.tile([40.0, 20.0], (T, 1))
    yy, xx = np.mgrid[0:H, 0:W]
    disk = (xx + 0.5 - 40) ** 2 + (yy + 0.5 - 20) ** 2 <= 16
    res[5:16, disk] *= 12   # the model pulls from elsewhere: the video's contact area stays wrong
    out = check_interaction(res, reg, 5, 15, contact_uv=uv, radius_px=4)
    assert "contact" in out["suspect"]
    assert any("--hint-pixel 5,U,V" in n for n in out["notes"])
    # the same blob elsewhere on the object is not at the contact
    out = check_interaction(res, reg, 5, 15, contact_uv=np.tile([15.0, 12.0], (T, 1)), radius_px=4)
    assert "contact" not in out["suspect"]


def test_fit_prints_the_check(tmp_path):
    """A real (tiny) fit ends with the check's line: the cantilever of tests/fit_scene.py, fitted
    from its true contacts, is not flagged."""
    import fit_scene as fs

    from physinteract_usd import api

    sc = fs.build(tmp_path / "base")
    stage = fs.copy_scene(sc["root"], tmp_path / "run")
    lines = []
    out = api.fit(stage, iterations=2, contact_from=stage.parent / "gt", settings_overrides=fs.SMOKE_SETTINGS,
                  progress=False, log=lambda *m: lines.append(" ".join(map(str, m))))
    assert out.result is not None
    said = [s for s in lines if s.startswith("interaction check") or "may be" in s]
    assert said == ["interaction check: the residual is not largest around the grasp or release frames, "
                    "nor at the contact"], lines[-5:]


# ------------------------------------------------------------------ the fitted hand path (#22)

def _path_and_cameras(T=20):
    from physinteract_usd.camera import Camera

    cam = Camera.look_at((0.0, 0.0, 1.0), (0.0, 0.0, 0.0), width=200, height=200, fov_y_deg=40.0)
    measured = np.stack([np.linspace(-0.05, 0.05, T), np.zeros(T), np.zeros(T)], 1)
    return measured, [cam] * T, cam.fx     # 1 m away: 1 mm of sideways motion is fx / 1000 px


def test_a_fitted_path_that_strays_beyond_its_measurement_is_said_to_soak_up_model_error():
    from physinteract_usd.fit.interaction_check import check_trajectory

    measured, cams, fx = _path_and_cameras()
    fitted = measured.copy()
    mm = 10.0 / fx * 1e3                     # 10 px sideways, i.e. 5 sigma of 2 px
    fitted[6:12, 1] += mm * 1e-3
    out = check_trajectory(measured, fitted, cams, grasp=4, release=15)
    assert out["suspect"] and out["frames_over"] == 6
    assert abs(out["max_px"] - 10.0) < 0.2 and 6 <= out["max_frame"] < 12
    assert "soaking up" in out["note"] and "diagnose" in out["note"]
    # before the grasp and after the release the hand does not hold the object: not counted
    assert np.isnan(out["deviation_px"][2]) and np.isnan(out["deviation_px"][17])


def test_a_path_within_its_uncertainty_or_moved_only_in_depth_is_not_suspect():
    from physinteract_usd.fit.interaction_check import check_trajectory

    measured, cams, fx = _path_and_cameras()
    near = measured.copy()
    near[:, 1] += 4.0 / fx                    # 4 px: 2 sigma
    assert not check_trajectory(measured, near, cams, grasp=0, release=None)["suspect"]
    brief = measured.copy()
    brief[8:10, 1] += 20.0 / fx               # far, but for 2 frames only
    assert not check_trajectory(measured, brief, cams, grasp=0, release=None)["suspect"]
    deep = measured.copy()
    deep[:, 2] += 0.03                        # 3 cm towards the camera on the optical axis ...
    deep[:, 0] *= 0.97                        # ... keeping every pixel where it was
    out = check_trajectory(measured, deep, cams, grasp=0, release=None)
    assert not out["suspect"] and out["max_px"] < 0.5 and abs(out["depth_mm"] + 30.0) < 1.0


def test_a_release_frame_two_late_is_confirmed_by_the_model_one_earlier_and_the_true_one_is_not(tmp_path):
    """The timing check's counterfactual (`shifted_losses`): the tests' bar released at frame 2, fitted
    once with its true release and once told frame 4: with the wrong frame, the fitted model released a
    frame earlier explains the video better by far more than CONFIRM_DROP; with the true frame, neither
    neighbour does."""
    import json

    import fit_scene as fs

    from physinteract_usd.app.fit import prepare_fit, run_fit
    from physinteract_usd.fit.interaction_check import CONFIRM_DROP, shifted_losses

    sc = fs.build(tmp_path / "base", n_frames=6, release=2)
    drops = {}
    for name, rel in (("true", 2), ("late", 4)):
        stage = fs.copy_scene(sc["root"], tmp_path / name)
        gt = stage.parent / "gt"
        g = json.loads((gt / "gt.json").read_text())
        g["interaction"]["release_frame"] = rel
        (gt / "gt.json").write_text(json.dumps(g))
        job = prepare_fit(stage, iterations=2, contact_from=gt, joint=False, log=lambda *a: None,
                          settings_overrides={**fs.SMOKE_SETTINGS, "confidence_probes": 0})
        res = run_fit(job, progress=False, log=lambda *a: None)
        c = [c for c in job.contacts if c.type != "fixed"][0]
        assert c.release_frame == rel
        ls = shifted_losses(job.problem, res, c, "release_frame")
        assert set(ls) == {-1, 0, 1}
        drops[name] = max((ls[0] - ls[d]) / ls[0] for d in (-1, 1))
        if name == "late":
            assert ls[-1] < ls[0] * (1 - CONFIRM_DROP), ls
            # the same losses with the shifts' frames simulated from the fitted model's checkpoint only (frames
            # 3.. and 4.. of 5) and the variants on two threads (#26)
            from physinteract_usd import simulation as simulation_mod
            from physinteract_usd.fit.interaction_check import Counterfactuals
            cf = Counterfactuals(job.problem, res)
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(simulation_mod, "SIM_THREADS", 2)
                assert shifted_losses(job.problem, res, c, "release_frame", cf=cf) == ls
            assert cf.frames_simulated == 5 + 2 + 1, cf.frames_simulated
    assert drops["true"] < CONFIRM_DROP, drops


def test_a_contact_three_centimetres_off_is_confirmed_by_the_model_moved_back(tmp_path):
    """The contact's counterfactual (`moved_losses`): the tests' bar fitted once from its true grasp and
    once from one 3 cm along the bar towards the support (held particles and hand path moved with it):
    the model moved back (two particle spacings, across the image) explains the video better by more than
    CONFIRM_DROP; from the true grasp no move does."""
    import json

    import fit_scene as fs

    from physinteract_usd.app.fit import prepare_fit, run_fit
    from physinteract_usd.fit.interaction_check import CONFIRM_DROP, moved_losses

    sc = fs.build(tmp_path / "base", n_frames=5)
    off = np.asarray(fs.SUPPORT_CENTRE, float) - np.asarray(fs.HAND_CENTRE, float)
    off = 0.03 * off / np.linalg.norm(off)
    drops = {}
    for name, o in (("true", np.zeros(3)), ("off", off)):
        stage = fs.copy_scene(sc["root"], tmp_path / name)
        gt = stage.parent / "gt"
        g = json.loads((gt / "gt.json").read_text())
        g["interaction"]["contact_point"] = (np.asarray(g["interaction"]["contact_point"]) + o).tolist()
        g["interaction"]["trajectory"] = (np.asarray(g["interaction"]["trajectory"]) + o).tolist()
        (gt / "gt.json").write_text(json.dumps(g))
        job = prepare_fit(stage, iterations=2, contact_from=gt, joint=False, log=lambda *a: None,
                          settings_overrides={**fs.SMOKE_SETTINGS, "confidence_probes": 0})
        res = run_fit(job, progress=False, log=lambda *a: None)
        c = [c for c in job.contacts if c.type != "fixed"][0]
        ls = moved_losses(job.problem, res, c)
        assert set(ls) == {"0", "right+", "right-", "up+", "up-"}
        drops[name] = max((ls["0"] - v) / ls["0"] for k, v in ls.items() if k != "0")
    print(drops)
    assert drops["off"] >= CONFIRM_DROP, drops
    assert drops["true"] < CONFIRM_DROP, drops
