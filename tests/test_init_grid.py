"""`init --grid auto`: the grid from the object's thinnest part, the caps, the line init prints and
the choice recorded on the stage's init layer."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture_factory import make_capture
from physinteract_usd.cli import main


def run(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:          # argparse's own errors
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def rod_capture(tmp_path_factory):
    """A capture whose object is a watertight capsule mesh: a rod 20 mm thick, 220 mm long."""
    import trimesh

    root = tmp_path_factory.mktemp("rod")
    cap = make_capture(root / "cap", object_kind="obj")
    mesh = trimesh.creation.capsule(height=0.2, radius=0.01, count=[24, 24])
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    mesh.apply_translation([0.0, 0.15, 0.0])
    (cap / "object.obj").unlink()
    mesh.export(cap / "object.obj")
    return cap


def grid_choice(stage, capsys):
    code, out, err = run(["info", stage, "--json"], capsys)
    assert code == 0, err
    return json.loads(out)["simulation"]


def test_auto_puts_four_cells_across_the_rod_and_records_why(rod_capture, tmp_path, capsys):
    st = tmp_path / "rod.usda"
    code, out, err = run(["init", st, "--capture", rod_capture, "--grid", "auto", "--padding", "0.3"], capsys)
    assert code == 0, err
    assert out.startswith("grid auto: ")
    sim = grid_choice(st, capsys)
    gc = sim["grid_choice"]
    assert gc["mode"] == "auto" and gc["limit"] == ""
    assert abs(gc["thinnestPart"] / 0.020 - 1) < 0.15, gc            # the rod's diameter
    assert 4.0 <= gc["cellsAcross"] < 4.5, gc
    assert max(sim["grid"]) == gc["grid"] and abs(sim["cell_size_m"] - gc["cellSize"]) < 1e-9
    assert f"{gc['cellsAcross']:.1f} cells across the thinnest part" in out


def test_the_cap_binds_with_one_plain_line(rod_capture, tmp_path, capsys):
    st = tmp_path / "rod.usda"
    code, out, err = run(["init", st, "--capture", rod_capture, "--grid", "auto", "--padding", "0.3",
                          "--max-grid", "24"], capsys)
    assert code == 0, err
    line = out.splitlines()[0]
    assert line.startswith("thinnest part ") and "at the cap of 24 cells" in line, line
    assert "bending stiffness of thin parts will be biased (use a GPU and --max-grid " in line
    gc = grid_choice(st, capsys)["grid_choice"]
    assert gc["grid"] == 24 and gc["limit"] == "grid" and gc["cellsAcross"] < 4
    code, out, err = run(["init", st, "--capture", rod_capture, "--grid", "auto", "--padding", "0.3",
                          "--max-particles", "500", "--force"], capsys)
    assert code == 0, err
    gc = grid_choice(st, capsys)["grid_choice"]
    assert gc["limit"] == "particles" and gc["particles"] <= 525, gc
    assert "at the cap of 500 particles" in out.splitlines()[0]


def test_a_fixed_grid_says_how_many_cells_cross_the_thinnest_part(rod_capture, tmp_path, capsys):
    st = tmp_path / "rod.usda"
    code, out, err = run(["init", st, "--capture", rod_capture, "--grid", "16"], capsys)
    assert code == 0, err
    assert out.startswith("grid 16 (fixed): ") and "--grid auto would choose" in out.splitlines()[0]
    gc = grid_choice(st, capsys)["grid_choice"]
    assert gc["mode"] == "fixed" and gc["grid"] == 16 and gc["cellsAcross"] < 2


def test_a_compact_object_gets_the_floor(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")                    # a Gaussian sphere, 200 mm across
    st = tmp_path / "ball.usda"
    code, out, err = run(["init", st, "--capture", cap, "--grid", "auto"], capsys)
    assert code == 0, err
    assert "the floor of 24 cells" in out
    assert grid_choice(st, capsys)["grid"] == [24, 24, 24]


@pytest.mark.parametrize("argv, says", [(["--grid", "fine"], "--grid: must be a whole number of cells or 'auto'"),
                                        (["--grid", "auto", "--max-grid", "4"], "--max-grid: must be"),
                                        (["--grid", "auto", "--max-particles", "10"], "--max-particles: must be")])
def test_bad_grid_flags_are_one_line(argv, says, tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    code, out, err = run(["init", tmp_path / "s.usda", "--capture", cap, *argv], capsys)
    assert code == 2 and says in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "s.usda").exists()


def test_a_batch_manifest_may_ask_for_auto(tmp_path):
    from physinteract_usd.batch.manifest import read_manifest

    for n in ("a", "b"):
        (tmp_path / n).mkdir()
    m = tmp_path / "m.csv"
    m.write_text("source,grid\na,auto\nb,32\n")
    a, b = read_manifest(m)
    assert a.options["grid"] == "auto" and b.options["grid"] == 32
    m.write_text("source,grid\na,fine\n")
    with pytest.raises(Exception, match="grid"):
        read_manifest(m)
