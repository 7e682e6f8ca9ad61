"""Stage camera == cv2.projectPoints from transforms.json, within 0.01 px."""

import json

import cv2
import numpy as np
import pytest

from capture_factory import make_capture
from physinteract_usd import api
from physinteract_usd.camera import Camera
from physinteract_usd.capture import read_transforms
from physinteract_usd.usd.stage import project_with_usd_camera, read_stage
from pxr import Usd


def _cv2_project(tj_path, points, frame=None):
    tj = json.loads(tj_path.read_text())
    K = np.array([[tj["fl_x"], 0, tj["cx"]], [0, tj["fl_y"], tj["cy"]], [0, 0, 1]], dtype=np.float64)
    c2w = np.array(tj["transform_matrix"] if frame is None else tj["frames"][frame]["transform_matrix"])
    c2w_cv = c2w @ np.diag([1, -1, -1, 1])  # nerfstudio/OpenGL -> OpenCV axes
    w2c = np.linalg.inv(c2w_cv)
    rvec, _ = cv2.Rodrigues(w2c[:3, :3])
    uv, _ = cv2.projectPoints(points.reshape(-1, 1, 3), rvec, w2c[:3, 3], K, None)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("fx,fy,cx,cy", [(80.0, 80.0, 32.0, 24.0), (95.0, 70.0, 29.3, 26.8)])
def test_stage_camera_matches_cv2(tmp_path, fx, fy, cx, cy):
    cap = make_capture(tmp_path / "cap")
    tj = json.loads((cap / "transforms.json").read_text())
    tj.update(fl_x=fx, fl_y=fy, cx=cx, cy=cy)
    (cap / "transforms.json").write_text(json.dumps(tj))
    lp = api.init(tmp_path / "scene.usda", cap, grid=16)
    stage = Usd.Stage.Open(str(lp.root))
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.15, 0.15, size=(60, 3)) + [0, 0.15, 0]
    uv_usd = project_with_usd_camera(stage, pts, 64, 48)
    uv_cv = _cv2_project(cap / "transforms.json", pts)
    assert np.abs(uv_usd - uv_cv).max() < 0.01
    # our Camera read back from the stage agrees too
    cam = read_stage(lp.root).camera
    uv_ours, depth = cam.project(pts)
    assert np.abs(uv_ours - uv_cv).max() < 0.01
    assert (depth > 0).all()
    # back-projection inverts projection
    assert np.allclose(cam.unproject(uv_ours, depth), pts, atol=1e-9)


def test_per_frame_camera_is_time_sampled(tmp_path):
    cap = make_capture(tmp_path / "cap", per_frame_camera=True)
    tj = json.loads((cap / "transforms.json").read_text())
    for k, f in enumerate(tj["frames"]):
        m = np.array(f["transform_matrix"])
        m[0, 3] += 0.05 * k
        f["transform_matrix"] = m.tolist()
    (cap / "transforms.json").write_text(json.dumps(tj))
    lp = api.init(tmp_path / "scene.usda", cap, grid=16)
    stage = Usd.Stage.Open(str(lp.root))
    pts = np.array([[0.0, 0.15, 0.0], [0.05, 0.2, -0.03]])
    for k in range(4):
        uv_usd = project_with_usd_camera(stage, pts, 64, 48, time=Usd.TimeCode(k))
        assert np.abs(uv_usd - _cv2_project(cap / "transforms.json", pts, frame=k)).max() < 0.01
    cam = read_stage(lp.root).camera
    assert not cam.is_static and len(cam.c2w) == 4


def test_look_at_and_rvec():
    cam = Camera.look_at((0, 0, 2), (0, 0, 0), width=100, height=80, fov_y_deg=50)
    uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]]))
    assert uv[0] == pytest.approx([50, 40])
    assert uv[1, 1] < 40  # +Y world is up in the image
    assert z[0] == pytest.approx(2.0)
    rvec, tvec = cam.rvec_tvec()
    uv2, _ = cv2.projectPoints(np.array([[0.0, 0.1, 0.0]]), rvec, tvec, cam.K, None)
    assert np.allclose(uv2.reshape(2), uv[1])


def test_transforms_without_intrinsics(tmp_path):
    (tmp_path / "t.json").write_text(json.dumps({"transform_matrix": np.eye(4).tolist(), "w": 10, "h": 10}))
    from physinteract_usd.errors import InputError

    with pytest.raises(InputError, match="intrinsics missing: fl_x, fl_y, cx, cy"):
        read_transforms(tmp_path / "t.json")
