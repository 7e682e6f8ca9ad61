"""Extraction on a small synthetic scene (hemp rope, 10 frames, gt/ moved away before extraction):
the hand masks, type, timing, contact and supports against the ground truth; the written stage
round-trips into the fit's contacts; hints, --type and the user's own contact sets win; bad hints
are InputErrors naming the problem."""

import json
import shutil

import numpy as np
import pytest
from pxr import Sdf, Usd, UsdValidation, Vt

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd.errors import InputError
from physinteract_usd.api import Hint, extract, parse_hint
from physinteract_usd.frames import read_mask
from physinteract_usd.usd.extract_io import extract_dir
from physinteract_usd.usd.layout import LayerPaths
from physinteract_usd.usd.stage import read_stage

SCENE = "hemp_rope"


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    from physinteract_usd.synth import generate

    root = tmp_path_factory.mktemp("extract_synth")
    cap = root / SCENE
    generate(SCENE, cap, frames=10, log=lambda *a: None)
    gt = root / "gt"
    shutil.copytree(cap / "gt", gt)
    shutil.rmtree(cap / "gt")  # extraction never sees the ground truth
    return root, cap, gt


def _stage(capture, name):
    root, cap, gt = capture
    g = json.loads((gt / "gt.json").read_text())["suggested_init"]
    stage = root / name / "scene.usda"
    stage.parent.mkdir()
    api.init(stage, cap, grid=g["grid"], padding=g["padding"], youngs_range=tuple(g["youngs_range"]),
             max_poisson=g["max_poisson"], density=g["density"])
    return stage


@pytest.fixture(scope="module")
def extracted(capture):
    stage = _stage(capture, "auto")
    result = extract(stage, log=lambda *a: None)
    return stage, result


def test_hand_masks_match_the_truth(capture, extracted):
    _, _, gt = capture
    _, result = extracted
    T = len(result.hand_masks)
    truth = np.stack([read_mask(gt / "hand_masks" / f"{k:06d}.png") for k in range(T)])
    iou = (truth & result.hand_masks).sum() / (truth | result.hand_masks).sum()
    assert iou > 0.9


def test_type_timing_contact_and_supports(capture, extracted):
    _, _, gt_dir = capture
    stage, result = extracted
    sd = read_stage(stage)
    truth = api.true_contacts(sd, gt_dir)
    g = json.loads((gt_dir / "gt.json").read_text())["interaction"]
    assert result.interaction_type == g["type"] == "pointAdherent"
    assert abs(result.grasp_frame - g["grasp_frame"]) <= 1
    assert abs(result.release_frame - g["release_frame"]) <= 2
    h = sd.settings.particle_spacing
    hand = result.interaction[0]
    dist = np.linalg.norm(sd.particles_positions[hand.indices].mean(0) - sd.particles_positions[truth[0].indices].mean(0))
    assert dist < 4 * h  # "within a few particle spacings" (issue 7); ~3 h on this short clip
    fixed_true = set(truth[-1].indices.tolist())
    fixed = set(np.concatenate([c.indices for c in result.supports]).tolist())
    assert len(fixed_true & fixed) >= 0.8 * len(fixed_true)
    assert not (fixed & set(hand.indices.tolist()))  # one pin per particle
    # T0 follows the pull in the image (depth is not seen): within a few pixels
    cam = sd.camera.at(0)
    gf, rf = g["grasp_frame"], g["release_frame"]
    tt = truth[0].trajectory
    mine = hand.trajectory - hand.trajectory[gf] + tt[gf]
    err = np.linalg.norm(cam.project(mine[gf:rf + 1])[0] - cam.project(tt[gf:rf + 1])[0], axis=1)
    assert err.max() < 4.0


def test_written_stage_round_trips(extracted):
    stage, result = extracted
    sd = read_stage(stage)
    names = {c.name: c for c in sd.contacts}
    assert names["hand"].type == "pointAdherent" and names["hand"].source == "extracted"
    assert any(c.type == "fixed" for c in sd.contacts)
    tr = [t for t in sd.trajectories if t.contact_set == "hand"]
    assert len(tr) == 1 and tr[0].stage == "initial" and tr[0].positions.shape == (sd.n_frames, 3)
    assert np.allclose(tr[0].positions, result.interaction[0].trajectory, atol=1e-6)
    assert len(sd.hand_mask_assets) == sd.n_frames
    hm = api.load_observations(sd).hand_masks
    assert np.array_equal(hm, result.loss_masks)
    assert (hm >= result.hand_masks).all() and hm.sum() > result.hand_masks.sum()
    assert (extract_dir(stage) / "preview.png").exists()
    # the fit takes them as they are
    specs = api.stage_contacts(sd)
    assert {s.type for s in specs} == {"pointAdherent", "fixed"}
    # the hook was seen holding the rope still: a measured support, not a guess the fit may resize
    assert all(not s.guessed and s.source == "extracted" for s in specs if s.type == "fixed")
    assert not any(c.guessed for c in sd.contacts)
    from physinteract_usd.sim import Contact, Control

    Control([Contact(s.type, indices=s.indices, trajectory=s.trajectory, grasp_frame=s.grasp_frame,
                     release_frame=s.release_frame) for s in specs], n_frames=sd.n_frames - 1)
    # the composed stage still validates
    ustage = Usd.Stage.Open(str(stage))
    ctx = UsdValidation.ValidationContext(UsdValidation.ValidationRegistry().GetOrLoadAllValidators())
    errors = [e for e in ctx.Validate(ustage) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert not errors, [e.GetMessage() for e in errors]


def test_rerun_replaces_its_contacts_and_keeps_the_rest(capture):
    stage = _stage(capture, "rerun")
    extract(stage, log=lambda *a: None)
    # something else in the fit layer (a report of an earlier fit) must survive
    lp = LayerPaths.of(stage)
    layer = Sdf.Layer.FindOrOpen(str(lp.fit))
    s = Usd.Stage.Open(layer)
    rp = s.DefinePrim("/World/PhysInteract/FitReport_v1", "PhysInteractFitReport")
    rp.GetAttribute("physinteract:version").Set(1)
    layer.Save()
    extract(stage, hint=Hint(particles=np.array([0, 1, 2])), interaction_type="pointAdherent", log=lambda *a: None)
    sd = read_stage(stage)
    assert sorted(c.name for c in sd.contacts if c.type != "fixed") == ["hand"]
    assert [t.name for t in sd.trajectories] == ["hand_initial"]
    assert [r["version"] for r in sd.reports] == [1]
    assert sorted(next(c for c in sd.contacts if c.name == "hand").indices.tolist()) == [0, 1, 2]


def test_hints_and_type_win(capture):
    stage = _stage(capture, "hints")
    sd = read_stage(stage)
    # a pixel: the contact is where it says, even far from the hand
    top = int(np.argmax(sd.particles_positions[:, 1]))
    uv, _ = sd.camera.at(0).project(sd.particles_positions[top][None])
    res = extract(stage, hint=parse_hint(f"0,{uv[0, 0] - 0.5:.2f},{uv[0, 1] - 0.5:.2f}"), log=lambda *a: None)
    c = res.interaction[0]
    assert np.linalg.norm(sd.particles_positions[c.indices].mean(0) - sd.particles_positions[top]) < 2.5 * sd.settings.particle_spacing
    assert c.source == "user"  # a hinted contact is the user's choice (the stage's token)
    # particles win as they are; --type wins over detection
    res = extract(stage, hint=Hint(particles=np.array([5, 6])), interaction_type="pointNonAdherent", log=lambda *a: None)
    assert res.interaction_type == "pointNonAdherent" and res.type_source == "user"
    sd = read_stage(stage)
    finger = next(c for c in sd.contacts if c.type == "pointNonAdherent")
    assert finger.radius > 0
    assert res.evidence["finger_radius_source"] == "measured" and "grasp_radius_m" not in res.evidence
    # --grasp-radius is the fingertip's radius for a poke
    res = extract(stage, hint=parse_hint(grasp_radius=0.012), interaction_type="pointNonAdherent", log=lambda *a: None)
    assert res.interaction[0].radius == 0.012 and res.evidence["finger_radius_source"] == "user"
    finger = next(c for c in read_stage(stage).contacts if c.type == "pointNonAdherent")
    assert finger.radius == pytest.approx(0.012)
    specs = api.stage_contacts(sd)
    assert next(s for s in specs if s.type == "pointNonAdherent").radius > 0


def test_grasp_radius_sets_how_much_the_hand_holds(capture, extracted):
    """The video shows where the hand grasps, not how much it holds: by default the grasp is a
    pinch (3 cm) and the extraction says so; --grasp-radius sets it, the centre staying put."""
    _, auto = extracted
    x0 = read_stage(extracted[0]).particles_positions
    assert auto.evidence["grasp_radius_source"] == "pinch" and auto.evidence["grasp_radius_m"] == pytest.approx(0.03)
    assert any(n.startswith("grasp:") and "--grasp-radius" in n for n in auto.notes)
    default = auto.interaction[0].indices
    stage = _stage(capture, "grasp_radius")
    sizes = {}
    for r in (0.02, 0.045):
        res = extract(stage, hint=parse_hint(grasp_radius=r), log=lambda *a: None)
        c = res.interaction[0]
        assert res.evidence["grasp_radius_source"] == "user" and res.evidence["grasp_radius_m"] == r
        assert not any(n.startswith("grasp:") for n in res.notes)
        # a ball of that radius: no two grasped particles further apart than its diameter
        d = np.linalg.norm(x0[c.indices][:, None] - x0[c.indices][None], axis=2)
        assert d.max() <= 2 * r + 1e-9
        assert c.source == "extracted"  # where it grasps is still the extraction's
        sizes[r] = set(c.indices.tolist())
        stored = next(s for s in read_stage(stage).contacts if s.type == "pointAdherent")
        assert set(stored.indices.tolist()) == sizes[r]
    assert len(sizes[0.02]) < len(default) < len(sizes[0.045])
    assert sizes[0.02] < set(default.tolist()) < sizes[0.045]
    with pytest.raises(InputError, match="--grasp-radius.*object's extent"):
        extract(stage, hint=parse_hint(grasp_radius=3.0), log=lambda *a: None)


def test_bad_hints_are_input_errors(capture):
    stage = _stage(capture, "bad")
    with pytest.raises(InputError, match="frame 99 is outside"):
        extract(stage, hint=parse_hint("99,10,10"), log=lambda *a: None)
    with pytest.raises(InputError, match="outside the 128x96 frame"):
        extract(stage, hint=parse_hint("1,500,10"), log=lambda *a: None)
    with pytest.raises(InputError, match="not on or next to the object"):
        extract(stage, hint=parse_hint("0,1,1"), log=lambda *a: None)
    with pytest.raises(InputError, match="--hint-particles"):
        extract(stage, hint=Hint(particles=np.array([10 ** 6])), log=lambda *a: None)
    with pytest.raises(InputError, match="--type"):
        extract(stage, interaction_type="grab", log=lambda *a: None)
    assert not read_stage(stage).contacts  # nothing written


def test_the_users_contact_set_wins(capture):
    stage = _stage(capture, "user")
    root = Sdf.Layer.FindOrOpen(str(stage))
    s = Usd.Stage.Open(root)
    cp = s.DefinePrim("/World/PhysInteract/grip", "PhysInteractContactSet")
    cp.GetAttribute("physinteract:particleIndices").Set(Vt.IntArray([3, 4, 5]))
    cp.GetAttribute("physinteract:contactType").Set("pointAdherent")
    cp.GetAttribute("physinteract:graspTime").Set(1.0)
    cp.GetAttribute("physinteract:releaseTime").Set(5.0)
    root.Save()
    res = extract(stage, interaction_type="surfaceNonAdherent", log=lambda *a: None)
    assert res.type_source == "stage" and res.interaction_type == "pointAdherent"
    sd = read_stage(stage)
    inter = [c for c in sd.contacts if c.type != "fixed"]
    assert [c.name for c in inter] == ["grip"]
    assert [t.contact_set for t in sd.trajectories] == ["grip"]  # its T0 was added
    fixed = set(np.concatenate([c.indices for c in sd.contacts if c.type == "fixed"]).tolist())
    assert not fixed & {3, 4, 5}
    assert len(api.stage_contacts(sd)) == len(sd.contacts)


@pytest.fixture(scope="module")
def fitted(capture):
    stage = _stage(capture, "fit")
    api.fit(stage, iterations=1, progress=False, log=lambda *a: None)
    return stage


@pytest.mark.slow
def test_fit_runs_extraction_when_the_stage_has_no_contacts(fitted):
    sd = read_stage(fitted)
    assert any(c.source == "extracted" for c in sd.contacts)
    assert {c.type for c in sd.contacts} == {"pointAdherent", "fixed"}


@pytest.mark.slow
def test_hand_masks_survive_a_fit(fitted):
    assert read_stage(fitted).hand_mask_assets


def test_support_hints_win(capture):
    _, _, gt = capture
    stage = _stage(capture, "support_hints")
    sd = read_stage(stage)
    x0, h = sd.particles_positions, sd.settings.particle_spacing
    truth = next(c for c in api.true_contacts(sd, gt) if c.type == "fixed").indices
    hand = next(c for c in api.true_contacts(sd, gt) if c.type != "fixed").indices
    cam = sd.camera.at(0)

    def pixel(p):
        uv, _ = cam.project(np.asarray(p, float)[None])
        return f"0,{uv[0, 0] - 0.5:.2f},{uv[0, 1] - 0.5:.2f}"

    def supports(res):
        return [c for c in res.contacts if c.type == "fixed"]

    # pointing at the true support keeps the still region detected there
    res = extract(stage, hint=parse_hint(support_pixels=[pixel(x0[truth].mean(0))]), log=lambda *a: None)
    (s,) = supports(res)
    assert s.source == "user"  # a hinted support is the user's choice
    assert np.linalg.norm(x0[s.indices].mean(0) - x0[truth].mean(0)) < 2.0 * h
    assert len(np.intersect1d(s.indices, truth)) >= 0.8 * len(truth)
    # pointing where nothing is still (half way down the rope) holds the particles there instead
    mid = x0[np.argmin(np.linalg.norm(x0 - 0.5 * (x0[truth].mean(0) + x0[hand].mean(0)), axis=1))]
    res = extract(stage, hint=parse_hint(support_pixels=[pixel(mid)]), log=lambda *a: None)
    (s,) = supports(res)
    assert np.linalg.norm(x0[s.indices].mean(0) - mid) < 0.03 + h
    assert not len(np.intersect1d(s.indices, truth))
    assert np.all(np.linalg.norm(x0[s.indices] - x0[s.indices].mean(0), axis=1) < 0.03 + 2 * h)
    # particles win as they are, and are what the stage holds
    res = extract(stage, hint=parse_hint(support_particles=",".join(map(str, truth[:5]))), log=lambda *a: None)
    (s,) = supports(res)
    assert sorted(s.indices.tolist()) == sorted(truth[:5].tolist())
    fixed = [c for c in read_stage(stage).contacts if c.type == "fixed"]
    assert len(fixed) == 1 and sorted(fixed[0].indices.tolist()) == sorted(truth[:5].tolist())
    # the hinted set is the user's choice on the stage: no fit resizes it
    assert fixed[0].source == "user" and not fixed[0].guessed
    # bad support hints are one-line input errors naming the flag
    with pytest.raises(InputError, match="--support-pixel.*outside the 128x96 frame"):
        extract(stage, hint=parse_hint(support_pixels=["0,500,10"]), log=lambda *a: None)
    with pytest.raises(InputError, match="--support-pixel.*not on the object"):
        extract(stage, hint=parse_hint(support_pixels=["0,1,1"]), log=lambda *a: None)
    with pytest.raises(InputError, match="--support-particles"):
        extract(stage, hint=parse_hint(support_particles="1000000"), log=lambda *a: None)
    with pytest.raises(InputError, match="--support-particles"):
        parse_hint(support_particles="a,b")


def test_grasp_and_release_frames_win_through_the_cli(capture, capsys):
    """`extract --grasp-frame K --release-frame K|never`: the user's timing wins, is recorded on the
    stage (the contact's frames, its source 'user') and in the notes; bad values exit 2 naming the
    flag."""
    from physinteract_usd.cli import main

    stage = _stage(capture, "timing_cli")
    capsys.readouterr()                        # init's own lines (its grid line) are not extract's output
    assert main(["extract", str(stage), "--grasp-frame", "3", "--release-frame", "7", "--json", "--no-preview"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert (out["grasp_frame"], out["release_frame"]) == (3, 7)
    assert out["evidence"]["timing_source"] == {"grasp": "user", "release": "user"}
    assert any("--grasp-frame" in n for n in out["notes"]) or out["evidence"].get("grasp_frame") == 3
    hand = next(c for c in read_stage(stage).contacts if c.type == "pointAdherent")
    assert (hand.grasp_frame, hand.release_frame, hand.source) == (3, 7, "user")
    assert not np.allclose(hand.trajectory[3], hand.trajectory[6])      # T0 moves inside the window ...
    assert np.allclose(hand.trajectory[0], hand.trajectory[3])          # ... and not before the grasp
    # never released; a grasp alone keeps a detected release that comes after it
    assert main(["extract", str(stage), "--release-frame", "never", "--no-preview"]) == 0
    hand = next(c for c in read_stage(stage).contacts if c.type == "pointAdherent")
    assert hand.release_frame is None and hand.source == "user"
    # detection alone: the source is the extraction's again
    assert main(["extract", str(stage), "--no-preview"]) == 0
    assert next(c for c in read_stage(stage).contacts if c.type == "pointAdherent").source == "extracted"
    capsys.readouterr()
    for args, flag in ((["--grasp-frame", "x"], "--grasp-frame"), (["--grasp-frame", "9"], "--grasp-frame"),
                       (["--release-frame", "0"], "--release-frame"), (["--release-frame", "sometime"], "--release-frame"),
                       (["--grasp-frame", "5", "--release-frame", "4"], "--release-frame")):
        assert main(["extract", str(stage), "--no-preview", *args]) == 2, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and flag in err[0], (args, err)
