"""The rate transfer's settings (#24, docs/sim.md): `init --transfer-tau` on the stage (PhysInteractScene
physinteract:transferTau, read back by read_stage, used by build_simulation's SimModel), the default 0 (APIC),
one-line errors for a negative value; `synth --transfer-tau` for the truth's model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_factory import make_capture
from physinteract_usd.cli import main
from physinteract_usd.errors import InputError


def run(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_init_writes_it_and_the_simulation_uses_it(tmp_path, capsys):
    from physinteract_usd.simulation import build_simulation
    from physinteract_usd.usd.stage import read_stage

    cap = make_capture(tmp_path / "cap")
    code, out, err = run(["init", tmp_path / "a.usda", "--capture", cap, "--grid", "12"], capsys)
    assert code == 0, err
    code, out, err = run(["init", tmp_path / "b.usda", "--capture", cap, "--grid", "12", "--transfer-tau", "0.02"],
                         capsys)
    assert code == 0, err
    a, b = read_stage(tmp_path / "a.usda"), read_stage(tmp_path / "b.usda")
    assert a.settings.transfer_tau == 0.0
    assert b.settings.transfer_tau == pytest.approx(0.02)
    assert b.settings.to_dict()["transfer_tau"] == pytest.approx(0.02)
    sim = build_simulation(b, [])
    assert sim.model.transfer_tau == pytest.approx(0.02) and sim.rollout.solver.rate_f > 0
    sim0 = build_simulation(a, [])
    assert sim0.model.transfer_tau == 0.0 and sim0.rollout.solver.rate_f == 0.0


def test_a_negative_tau_is_one_line(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    code, out, err = run(["init", tmp_path / "s.usda", "--capture", cap, "--transfer-tau", "-1"], capsys)
    assert code == 2 and "--transfer-tau" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "s.usda").exists()


def test_synth_passes_it_to_the_truth(tmp_path):
    from physinteract_usd.synth.generate import SIZES, GroundTruth, generate
    from physinteract_usd.synth.scenes import SCENES

    with pytest.raises(InputError, match="--transfer-tau"):
        generate("foam_bar", tmp_path / "x", frames=4, transfer_tau=-0.1)
    gt = GroundTruth(SCENES["foam_bar"], SIZES["small"], 4)
    assert gt.model().transfer_tau == 0.0
    gt.transfer_tau = 0.01
    assert gt.model().transfer_tau == pytest.approx(0.01)


def test_info_shows_the_tau_when_set(tmp_path, capsys):
    """`info` prints the transfer tau (text and JSON) when the stage sets it, and says nothing of it for APIC."""
    cap = make_capture(tmp_path / "cap")
    for name, extra in (("a.usda", []), ("b.usda", ["--transfer-tau", "0.02"])):
        code, out, err = run(["init", tmp_path / name, "--capture", cap, "--grid", "12"] + extra, capsys)
        assert code == 0, err
    code, out, err = run(["info", tmp_path / "b.usda", "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)["simulation"]["transfer_tau_s"] == pytest.approx(0.02)
    code, out, err = run(["info", tmp_path / "b.usda"], capsys)
    assert code == 0 and "rate transfer tau 20 ms" in out, out
    code, out, err = run(["info", tmp_path / "a.usda", "--json"], capsys)
    assert json.loads(out)["simulation"]["transfer_tau_s"] == 0.0
    code, out, err = run(["info", tmp_path / "a.usda"], capsys)
    assert code == 0 and "rate transfer" not in out, out
