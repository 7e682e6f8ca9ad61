"""The world suite (synth/world.py) and extraction on it: a tiny randomised capture is complete and
repeatable; extraction on three tiny world captures of different toucher looks (a plain sphere
pulling a bar on a floor, a stick poking an upright clamped bar, a gloved hand pulling a hanging
rope)
finds the type, the timing within a frame, the contact within 3 cm, the support where something
holds the object and none (a floor: friction) where nothing does; the validation split's guard
makes every tuning entry point refuse validation data."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import physinteract_usd  # noqa: F401
from physinteract_usd import api
from physinteract_usd.errors import InputError
from physinteract_usd.synth.splits import MARKER, mark_validation, refuse_validation, validation_marker
from physinteract_usd.synth.world import draw_world

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"

# tiny: 96x72, 16 frames at 20 fps, few ground-truth particles (~20-40 s each on a busy 2-core box)
TINY = {"width": 96, "aspect": "4:3", "fps": 20.0, "frames": 16, "masks": "clean", "encoding": "png",
        "noise": 0.004, "blur": 1, "flicker": 0.0, "gaussians": 900, "gt_ratio": 0.7, "e_ratio": 1.0,
        "e_field": "uniform", "grasp_at": 0.2, "motion_share": 0.45, "dwell": 1, "never_released": False,
        "fill": 0.7, "roll": 0.0, "tremor_mm": 0.5,
        "settle": False}     # the unsettled truth these cases were made with (tests/test_world_settle.py: settled)
CASES = {
    "floor_sphere": dict(TINY, scenario="floor", shape="bar", interaction="pointAdherent", look="sphere",
                         e_max=2e4, length=0.2, thickness=0.35, azimuth=20.0, elevation=30.0,
                         toucher_colour_kind="skin"),
    "clamped_stick": dict(TINY, scenario="clamped", shape="bar", interaction="pointNonAdherent", look="stick",
                          e_max=2e4, length=0.2, thickness=0.45, azimuth=-20.0, elevation=20.0,
                          toucher_colour_kind="tool"),
    "hanging_glove": dict(TINY, scenario="hanging", shape="rope", interaction="pointAdherent", look="glove",
                          e_max=1.5e4, length=0.24, thickness=0.4, azimuth=15.0, elevation=15.0, support_drawn=True),
}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """The three tiny captures, each initialised with its README's settings and extracted (gt/
    moved out of the capture first: extraction never sees it)."""
    root = tmp_path_factory.mktemp("world")
    out = {}
    for name, ov in CASES.items():
        cap, gt = root / name, root / f"{name}.gt"
        info = api.synth(None, cap, random=7, split="dev", overrides=ov, log=lambda *a: None)
        shutil.move(str(cap / "gt"), str(gt))
        s = info["suggested_init"]
        stage = root / f"{name}.stage" / "scene.usda"
        stage.parent.mkdir()
        api.init(stage, cap, grid=s["grid"], padding=s["padding"], youngs_range=tuple(s["youngs_range"]),
                 max_poisson=s["max_poisson"], density=s["density"])
        res = api.extract(stage, log=lambda *a: None, preview=False)
        out[name] = (cap, gt, stage, info, res)
    return out


# ------------------------------------------------------------------------------ the generator
def test_draws_are_repeatable_and_the_splits_differ():
    assert draw_world(3, "dev") == draw_world(3, "dev")
    assert draw_world(3, "dev") != draw_world(3, "validation")
    assert draw_world(3, "dev", {"look": "sphere"})["look"] == "sphere"
    with pytest.raises(InputError, match="unknown world parameters"):
        draw_world(3, "dev", {"colour_of_the_sky": 1})
    with pytest.raises(InputError):
        draw_world(-1, "dev")
    # the drawn ranges the suite promises, over a few dozen draws
    ws = [draw_world(s, "dev") for s in range(40)]
    assert all(1e3 <= w["e_max"] / w["e_ratio"] and w["e_max"] <= 1e6 for w in ws)
    assert all(15 <= w["fps"] <= 60 and 96 <= w["width"] <= 512 for w in ws)
    assert {w["scenario"] for w in ws} == {"hanging", "clamped", "anchored", "floor"}
    assert len({w["look"] for w in ws}) >= 8 and {"png", "jpeg", "mp4"} <= {w["encoding"] for w in ws}


def test_a_tiny_world_capture_is_complete(world):
    cap, gt, stage, info, res = world["floor_sphere"]
    assert (cap / "object.ply").exists() and (cap / "transforms.json").exists() and (cap / "preview.png").exists()
    assert len(list((cap / "frames").glob("*.png"))) == 16 and len(list((cap / "masks").glob("*.png"))) == 16
    g = json.loads((gt / "gt.json").read_text())
    assert g["split"] == "dev" and g["world"]["look"] == "sphere" and g["n_frames"] == 16
    for f in ("youngs_modulus.npy", "poisson_ratio.npy", "gaussian_positions.npy", "particles.npz"):
        assert (gt / f).exists()
    # resting on a floor: no support in the truth, the floor's friction instead
    assert g["supports"] == [] and g["floor"] is not None and "ground" in g["effects"]
    assert g["gt_sim"]["pin_gain"] == 1.0
    # the truth's particles are not the fit's lattice (jittered) and finer than the fit's
    p = np.load(gt / "particles.npz")["rest"]
    sd = api.read_scene(stage)
    assert g["gt_sim"]["spacing"] < sd.settings.particle_spacing
    frac = (p / g["gt_sim"]["spacing"]) % 1.0
    assert np.std(frac) > 0.2
    assert not (cap / "VALIDATION_SPLIT").exists()
    assert not (cap / ".synth-writing").exists()   # the generator's writing marker is gone once it finished


def test_validation_captures_carry_the_marker(tmp_path):
    out = tmp_path / "v"
    ov = dict(CASES["hanging_glove"], frames=3, gaussians=300)
    info = api.synth(None, out, random=0, split="validation", overrides=ov, log=lambda *a: None)
    assert info["split"] == "validation" and (out / MARKER).exists()
    assert validation_marker(out / "gt") is not None
    with pytest.raises(InputError, match="validation split"):
        refuse_validation(out / "frames", "a tuner")


# ------------------------------------------------------------------------------ extraction
def _truth(gt: Path):
    it = json.loads((gt / "gt.json").read_text())["interaction"]
    return it, it["grasp_frame"], it["release_frame"]


@pytest.mark.parametrize("name", sorted(CASES))
def test_extraction_on_world_captures_of_different_toucher_looks(world, name):
    cap, gt, stage, info, res = world[name]
    it, g, r = _truth(gt)
    assert res.interaction_type == it["type"]
    assert abs(res.grasp_frame - g) <= 1, (res.grasp_frame, g)
    assert res.release_frame is not None and abs(res.release_frame - r) <= 1, (res.release_frame, r)
    sd = api.read_scene(stage)
    true = api.true_contacts(sd, gt)
    x0 = sd.particles_positions
    mine = res.interaction[0]
    if it["type"] == "pointAdherent":
        d = np.linalg.norm(x0[true[0].indices].mean(0) - x0[mine.indices].mean(0))
    else:
        d = np.linalg.norm(np.asarray(it["contact_point"]) - mine.point(x0))
    assert d < 0.03, d
    held = [c for c in true if c.type == "fixed"]
    if held:   # held: a support where the truth's is
        found = set(np.concatenate([c.indices for c in res.supports]).tolist()) if res.supports else set()
        assert len(found & set(held[0].indices.tolist())) >= 0.5 * len(held[0].indices)
    else:      # free on a floor: no support invented, the floor reported
        assert not res.supports and res.evidence.get("floor")
        assert any("ground" in n for n in res.notes)


def test_a_floor_is_friction_not_a_support_on_the_stage(world):
    cap, gt, stage, info, res = world["floor_sphere"]
    sd = api.read_scene(stage)
    assert not [c for c in sd.contacts if c.type == "fixed"]
    fl = res.evidence["floor"]
    assert abs(fl["height"] - info["floor"]["height"]) < 0.01


# ------------------------------------------------------------------------------ the guard
def _fake_validation(tmp_path) -> Path:
    """A folder of the validation split as the tools meet it (no need to simulate one)."""
    work = tmp_path / "val"
    for n in ("validation_0000", "dev_0000"):
        (work / n / "gt").mkdir(parents=True)
    (work / "validation_0000" / "gt" / "gt.json").write_text(json.dumps({"split": "validation"}))
    (work / "dev_0000" / "gt" / "gt.json").write_text(json.dumps({"split": "dev"}))
    mark_validation(work)
    return work


def _bench(name):
    sys.path.insert(0, str(BENCH))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(BENCH))


def test_tuning_entry_points_refuse_the_validation_split(tmp_path, capsys, monkeypatch):
    from physinteract_usd.synth import scenes as S

    # eval_extract registers its extra scene (balloon_poke) in the scene registry: on a copy here
    monkeypatch.setattr(S, "SCENES", dict(S.SCENES))
    work = _fake_validation(tmp_path)
    eval_extract, world_suite, world_fit = _bench("eval_extract"), _bench("world_suite"), _bench("world_fit")
    with pytest.raises(InputError, match="validation split"):
        eval_extract.main(["--work", str(work), "--scenes", "hemp_rope"])
    assert world_suite.main(["extract", "--split", "dev", "--work", str(work)]) == 2
    assert world_fit.main(["--work", str(work), "--json", str(tmp_path / "f.json")]) == 2
    assert _bench("world_probe").main([str(work), "dev_0000", "sugg", "1"]) == 2     # the folder is validation's
    assert _bench("world_bias").main(["--work", str(work), "--seeds", "0", "--init-only"]) == 2
    assert _bench("world_simcheck").main(["--work", str(work), "--seeds", "0"]) == 2
    assert _bench("world_diagnose").main(["--work", str(work), "--seeds", "0"]) == 2
    assert _bench("world_timing").main(["--work", str(work), "dev_0000"]) == 2
    # reading it at all needs --final (and is logged in the marker)
    assert world_suite.main(["extract", "--split", "validation", "--work", str(work)]) == 2
    assert world_fit.main(["--work", str(work), "--split", "validation", "--json", str(tmp_path / "f.json")]) == 2
    assert "validation" in capsys.readouterr().err
    # a dev folder that holds one validation capture is refused too (by its gt.json)
    dev = tmp_path / "dev"
    (dev / "dev_0001" / "gt").mkdir(parents=True)
    (dev / "dev_0001" / "gt" / "gt.json").write_text(json.dumps({"split": "validation"}))
    assert world_suite.main(["extract", "--split", "dev", "--work", str(dev)]) == 2
    assert _bench("world_timing").main(["--work", str(dev), "dev_0001"]) == 2
    assert not (tmp_path / "f.json").exists()
    # seeds whose captures are not there: one line and exit 2, not an empty table
    empty = tmp_path / "empty_dev"
    empty.mkdir()
    assert _bench("world_diagnose").main(["--work", str(empty), "--seeds", "3"]) == 2
    assert "none of the seeds' captures" in capsys.readouterr().err


def test_synth_cli_world_flags(tmp_path, capsys):
    from physinteract_usd.cli import main

    for args in (["--random", "1", "--validation", "2", str(tmp_path / "a")], ["--random", "1"],
                 ["--random", "1", str(tmp_path / "a"), "--hidden", "damping"],
                 ["--validation", "-3", str(tmp_path / "a")]):
        assert main(["synth", *args]) == 2, args
        assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_a_truth_that_keeps_leaving_its_grid_gets_a_box_it_can_hang_in(monkeypatch):
    """The generator's ground truth: after three runs that leave the grid (dev_0007: a soft sheet
    clamped at one edge flops down past the box), a fourth runs in a box reaching the object's whole
    length below it; the three runs before are as they were (no capture that generated changes)."""
    import torch

    import physinteract_usd.sim as sim
    from physinteract_usd.errors import SimulationError
    from physinteract_usd.synth.world import World

    boxes = []

    class Leaves:
        def __init__(self, model, control):
            self.model = model

        def __call__(self, E, nu):
            g = self.model.grid
            boxes.append((np.asarray(g.lower, float).copy(), g.dx, np.asarray(g.resolution)))
            if len(boxes) < 4:
                raise SimulationError("simulation left the grid domain (1 particles)")
            P = len(self.model.x0)
            return torch.zeros((2, P, 3)), torch.zeros((2, P, 3, 3))

    monkeypatch.setattr(sim, "Rollout", Leaves)
    w = draw_world(7, "dev", dict(CASES["clamped_stick"]))
    world = World(w)
    world.run()
    assert len(boxes) == 4
    lows = [b[0][1] for b in boxes]
    assert lows[1] < lows[0] and lows[2] < lows[1]            # the pad doubled, as before
    pts_low = min(world.x0[:, 1].min(), world.trajectory[:, 1].min())
    assert lows[3] <= pts_low - world.extent                    # room to hang by its whole length


def test_path_error_tells_a_lift_read_as_a_move_toward_the_camera():
    """world_suite's path metric: a grasp lifted 5 cm that the extraction moved 5 cm along z strays
    sqrt(2) x 5 cm from the truth's path, lifts nothing, and it only counts the acting frames."""
    from types import SimpleNamespace as NS

    ws = _bench("world_suite")
    T = 10
    true = np.zeros((T, 3))
    mine = np.zeros((T, 3)) + 0.3                 # where it is does not count, how it moves does
    true[2:7, 1] = np.linspace(0, 0.05, 5)
    mine[2:7, 2] += np.linspace(0, 0.05, 5)
    true[7:, 1], mine[7:] = 0.05, [0.3, 0.3, 0.35]
    mine[8:, 0] += 1.0                            # after the release: not the toucher's acting path
    r = ws.path_error(NS(trajectory=true), NS(trajectory=mine), 2, 7, T)
    assert r["path_cm"] == pytest.approx(5 * np.sqrt(2), rel=1e-9)
    assert r["path_rel"] == pytest.approx(np.sqrt(2), rel=1e-9)
    assert (r["lift_true_cm"], r["lift_cm"]) == (pytest.approx(5.0), pytest.approx(0.0))
    assert ws.path_error(NS(trajectory=None), NS(trajectory=mine), 2, 7, T) == {}


def test_moved_before_contact_reads_a_sag_before_the_hand_arrives(tmp_path):
    """world_suite's capture property: an object 0.2 m long whose every particle sags 2 cm by the hand's arrival
    (frame 3) moved 10% of its size before contact; the hand's path, planned from the rest centroid, is 2 cm from
    the held particles at its arrival; an object at rest until the arrival reads 0 / 0."""
    ws = _bench("world_suite")
    rest = np.stack([np.linspace(0, 0.2, 21), np.zeros(21), np.zeros(21)], 1)
    T, arrive = 6, 3
    sag = np.minimum(np.arange(T), arrive) / arrive * 0.02
    X = rest[None] - sag[:, None, None] * np.array([0.0, 1.0, 0.0])
    held_at = rest[20]
    traj = np.repeat(held_at[None], T, 0)
    it = {"type": "pointAdherent", "contact_point": held_at.tolist(), "contact_radius": 0.005,
          "trajectory": traj.tolist(), "arrive_frame": arrive, "grasp_frame": arrive + 1}
    np.savez(tmp_path / "particles.npz", rest=rest, positions=X)
    r = ws.moved_before_contact(tmp_path, {"interaction": it})
    assert r["pre_contact_pct"] == pytest.approx(10.0, rel=1e-9)
    assert r["drawn_gap_mm"] == pytest.approx(20.0, rel=1e-9)
    np.savez(tmp_path / "particles.npz", rest=rest, positions=np.repeat(rest[None], T, 0))
    r = ws.moved_before_contact(tmp_path, {"interaction": it})
    assert r["pre_contact_pct"] == 0.0 and r["drawn_gap_mm"] == pytest.approx(0.0, abs=1e-12)
    assert ws.moved_before_contact(tmp_path / "nothing", {"interaction": it}) == {}
