"""`init` and `info` through the CLI, and every kind of bad input: one line naming the file,
exit code 2, and no partial stage left behind."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from capture_factory import make_capture
from physinteract_usd.cli import main


def run(argv, capsys):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_init_and_info(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    code, out, err = run(["init", tmp_path / "scene.usda", "--capture", cap, "--grid", "16"], capsys)
    assert code == 0, err
    assert "800 Gaussians" in out and "4 at 24 fps" in out
    code, out, err = run(["info", tmp_path / "scene.usda", "--json"], capsys)
    assert code == 0
    d = json.loads(out)
    assert d["frames"]["count"] == 4 and d["frames"]["masks"] == 4
    assert d["particles"]["count"] > 100
    assert d["fits"] == [] and d["contacts"] == []
    assert d["simulation"]["grid"][0] == 16


def test_init_from_video_and_per_file_flags(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap", video=True, fps_in_json=False, masks=False)
    code, out, err = run(["init", tmp_path / "s.usda", "--object", cap / "object.ply", "--video",
                          cap / "video.mp4", "--camera", cap / "transforms.json", "--grid", "16"], capsys)
    assert code == 0, err
    d = json.loads(run(["info", tmp_path / "s.usda", "--json"], capsys)[1])
    assert d["frames"]["fps"] == pytest.approx(24.0)  # from the video
    assert d["frames"]["source"].endswith("video.mp4")


def test_python_dash_m(tmp_path):
    cap = make_capture(tmp_path / "cap")
    r = subprocess.run([sys.executable, "-m", "physinteract_usd", "init", str(tmp_path / "a.usda"),
                        "--capture", str(cap), "--grid", "16"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_existing_stage_is_not_overwritten_and_force_keeps_the_root(tmp_path, capsys):
    cap = make_capture(tmp_path / "cap")
    stage = tmp_path / "scene.usda"
    assert run(["init", stage, "--capture", cap, "--grid", "16"], capsys)[0] == 0
    # the user authors something in their root layer
    text = stage.read_text().rstrip() + '\n\nover "World"\n{\n    custom string userNote = "mine"\n}\n'
    stage.write_text(text)
    code, _, err = run(["init", stage, "--capture", cap, "--grid", "16"], capsys)
    assert code == 2 and "already exists" in err and str(stage) in err
    assert stage.read_text() == text
    code, _, err = run(["init", stage, "--capture", cap, "--grid", "12", "--force"], capsys)
    assert code == 0, err
    assert stage.read_text() == text  # the user's layer survives
    d = json.loads(run(["info", stage, "--json"], capsys)[1])
    assert d["simulation"]["grid"][0] == 12


def _corrupt(kind, cap):
    if kind == "missing object":
        (cap / "object.ply").unlink()
        return cap, "no object file"
    if kind == "ply without gaussians":
        pts = np.random.default_rng(0).random((10, 3)).astype("<f4")
        hdr = "ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
        (cap / "object.ply").write_bytes(hdr.encode() + pts.tobytes())
        return cap / "object.ply", "neither the 3D Gaussian properties"
    if kind in ("ply cut in its header", "ply cut in its data"):
        b = (cap / "object.ply").read_bytes()
        cut = b.find(b"end_header") - 20 if kind == "ply cut in its header" else len(b) - 13
        (cap / "object.ply").write_bytes(b[:cut])
        return cap / "object.ply", ("header ends before end_header" if kind == "ply cut in its header"
                                    else "the PLY is truncated: its header declares")
    if kind == "video cannot be decoded":
        shutil.rmtree(cap / "frames")
        (cap / "video.mp4").write_bytes(b"this is not a video" * 100)
        return cap / "video.mp4", "cannot be decoded"
    if kind == "transforms without intrinsics":
        tj = json.loads((cap / "transforms.json").read_text())
        for k in ("fl_x", "fl_y", "cx"):
            tj.pop(k)
        (cap / "transforms.json").write_text(json.dumps(tj))
        return cap / "transforms.json", "intrinsics missing: fl_x, fl_y, cx"
    if kind == "mask count differs":
        (cap / "masks" / "000003.png").unlink()
        return cap / "masks", "3 masks for 4 frames"
    if kind == "mask size differs":
        from physinteract_usd.frames import write_mask

        write_mask(cap / "masks" / "000002.png", np.zeros((10, 12), bool))
        return cap / "masks" / "000002.png", "mask is 12x10 but frames are 64x48"
    if kind == "no fps":
        tj = json.loads((cap / "transforms.json").read_text())
        tj.pop("fps")
        (cap / "transforms.json").write_text(json.dumps(tj))
        return cap / "transforms.json", "no fps anywhere"
    if kind == "frame of another size":
        from physinteract_usd.frames import write_image

        write_image(cap / "frames" / "000001.png", np.zeros((20, 20, 3)))
        return cap / "frames" / "000001.png", "frame is 20x20"
    if kind == "corrupt json":
        (cap / "transforms.json").write_text("{not json")
        return cap / "transforms.json", "not valid JSON"
    raise KeyError(kind)


BAD = ["missing object", "ply without gaussians", "ply cut in its header", "ply cut in its data", "video cannot be decoded", "transforms without intrinsics",
       "mask count differs", "mask size differs", "no fps", "frame of another size", "corrupt json"]


@pytest.mark.parametrize("kind", BAD)
def test_bad_capture(tmp_path, capsys, kind):
    cap = make_capture(tmp_path / "cap")
    culprit, message = _corrupt(kind, cap)
    stage = tmp_path / "out" / "scene.usda"
    stage.parent.mkdir()
    code, out, err = run(["init", stage, "--capture", cap], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert str(culprit) in lines[0], lines[0]
    assert message in lines[0], lines[0]
    assert list(stage.parent.iterdir()) == []  # no partial stage, no temp files


def test_missing_capture_folder(tmp_path, capsys):
    code, _, err = run(["init", tmp_path / "s.usda", "--capture", tmp_path / "nope"], capsys)
    assert code == 2 and "nope: capture folder not found" in err
    assert not (tmp_path / "s.usda").exists()


def test_info_on_a_stage_from_another_tool(tmp_path, capsys):
    from pxr import Usd, UsdGeom

    p = tmp_path / "other.usda"
    st = Usd.Stage.CreateNew(str(p))
    UsdGeom.Xform.Define(st, "/World")
    st.Save()
    code, _, err = run(["info", p], capsys)
    assert code == 2
    assert err.strip().count("\n") == 0
    assert str(p) in err and "not a physinteract-usd stage" in err
    code, _, err = run(["info", tmp_path / "missing.usda"], capsys)
    assert code == 2 and "missing.usda: file not found" in err
    (tmp_path / "junk.usda").write_text("#usda 1.0\n(\n garbage")
    code, _, err = run(["info", tmp_path / "junk.usda"], capsys)
    assert code == 2 and "junk.usda" in err and err.strip().count("\n") == 0


def test_a_device_that_is_not_there_is_a_one_line_error(capsys):
    import torch

    from physinteract_usd import cli

    assert cli.main(["fit", "missing.usda", "--device", "tpu"]) == 2
    assert "--device: must be cpu or cuda" in capsys.readouterr().err
    if not torch.cuda.is_available():
        assert cli.main(["extract", "missing.usda", "--device", "cuda"]) == 2
        err = capsys.readouterr().err
        assert "no usable CUDA GPU" in err and len(err.strip().splitlines()) == 1


def test_a_corrupt_stage_file_says_where_it_is_broken(tmp_path, capsys):
    bad = tmp_path / "scene.usda"
    bad.write_text("#usda 1.0\n( garbage\n")
    assert main(["info", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "scene.usda:2" in err and "Expected" in err and "()" not in err
    assert bad.read_text() == "#usda 1.0\n( garbage\n"    # nothing the user wrote is touched


@pytest.mark.parametrize("argv, says", [
    (["extract", "s.usda", "--grasp-radius", "abc"], "argument --grasp-radius: invalid float value: 'abc'"),
    (["fit", "s.usda", "--iterations", "x"], "argument --iterations: invalid int value: 'x'"),
    (["extract"], "the following arguments are required: stage"),
    (["bogus"], "invalid choice: 'bogus'"),
])
def test_a_malformed_flag_is_one_line(argv, says, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1 and "-h)" in err
