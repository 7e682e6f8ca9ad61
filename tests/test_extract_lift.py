"""Known answers for the lift of the 2D hand track to 3D (extract/lifting.py): the push direction
read in the image, the closed-form lift along a line, and the scene's bounds (#23, dev_0181)."""

import numpy as np
import pytest

from physinteract_usd.camera import Camera
from physinteract_usd.extract.lifting import (image_rate, keep_on_ray_in_box, lift_along, push_direction,
                                              segment_in_box)


def _cam():
    # looking down at 25 degrees, like the suite's cameras
    eye = np.array([0.0, 0.6 * np.sin(np.radians(25)), 0.6 * np.cos(np.radians(25))])
    return Camera.look_at(eye, [0.0, 0.0, 0.0], width=256, height=192, fov_y_deg=50.0)


def test_image_rate_is_the_projection_derivative():
    cam = _cam()
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = rng.uniform(-0.1, 0.1, 3)
        d = rng.normal(size=3)
        eps = 1e-6
        fd = (cam.project((p + eps * d)[None])[0][0] - cam.project((p - eps * d)[None])[0][0]) / (2 * eps)
        assert np.allclose(image_rate(cam, p, d), fd, rtol=1e-5, atol=1e-4)


def test_push_direction_moves_the_image_the_observed_way():
    """A target with a positive 3D component along the image's motion but a larger one away from
    the camera moves the image the other way (toward its vanishing point): not a push direction
    the video shows (dev_0181). The old 3D test accepted it; the image test refuses it and takes
    the fallback target (gravity for a palm), else the constant-depth lateral."""
    cam = _cam()
    c3 = np.array([0.05, -0.06, 0.02])   # below and right of the image centre: off axis
    # the observed motion: down the image, lifted at constant depth
    uv, z = cam.project(c3[None])
    lateral = cam.unproject(uv + np.array([[0.0, 5.0]]), z)[0] - c3
    lateral /= np.linalg.norm(lateral)
    ray = (c3 - cam.position) / np.linalg.norm(c3 - cam.position)
    r2 = ray - np.dot(ray, lateral) * lateral
    r2 /= np.linalg.norm(r2)
    assert abs(np.dot(ray, lateral)) > 0.05   # off axis: the ray has a component along the lateral
    a = 0.5 * abs(np.dot(ray, lateral))          # along the lateral, less than the ray's share
    bad = a * lateral + r2 * np.sign(np.dot(ray, lateral))
    seen = image_rate(cam, c3, lateral)
    assert np.dot(bad, lateral) > 0 and image_rate(cam, c3, bad) @ seen < 0   # the case
    d = push_direction(lateral, c3, cam, bad)
    assert np.allclose(d, lateral)
    g = np.array([0.0, -1.0, 0.0])
    d = push_direction(lateral, c3, cam, bad, g)
    assert image_rate(cam, c3, d) @ seen > 0
    assert d[1] < -0.9   # down, as gravity
    # a target the image agrees with is kept (its projection on the plane of the lateral and the ray)
    d = push_direction(lateral, c3, cam, g)
    assert image_rate(cam, c3, d) @ seen > 0 and d[1] < -0.9


def test_lift_along_recovers_a_line_path_exactly():
    cam = _cam()
    start = np.array([0.02, 0.03, -0.01])
    d = np.array([0.3, -0.8, -0.5])
    d /= np.linalg.norm(d)
    s_true = np.array([0, 0, 0, 0.01, 0.03, 0.06, 0.05, -0.02])
    path = start + s_true[:, None] * d
    track = cam.project(path)[0] + np.array([7.0, -3.0])   # the track's offset does not matter
    out = lift_along(cam, start, track, d, g=2)
    assert np.allclose(out, path, atol=1e-9)


def test_lift_along_stays_in_the_scene_past_the_vanishing_point():
    """A track that goes past the image of the line's point at infinity (a hand withdrawn the
    other way) has no point on the line: the lift goes as far as the scene's box allows, never
    metres out (dev_0181: y = -12.5 m); without a box it holds its last point."""
    cam = _cam()
    start = np.array([0.0, 0.0, 0.0])
    d = -(cam.position - start) / np.linalg.norm(cam.position - start) + np.array([0.0, -0.3, 0.0])
    d /= np.linalg.norm(d)                      # mostly away from the camera
    vp = cam.project((start + 1e6 * d)[None])[0][0]
    uv0 = cam.project(start[None])[0][0]
    steps = np.array([0, 0.2, 0.4, 0.6, 0.8, 1.2, 1.4, 1.6])[:, None]   # to 1.6x the way to the vanishing point
    track = uv0 + steps * (vp - uv0)
    box = (np.array([-0.3, -0.2, -0.3]), np.array([0.3, 0.2, 0.3]))
    out = lift_along(cam, start, track, d, 0, box)
    assert np.isfinite(out).all()
    assert (out >= box[0] - 1e-9).all() and (out <= box[1] + 1e-9).all()
    lo, hi = segment_in_box(start, d, box)
    assert np.allclose(out[-1], start + hi * d)         # at the box's face
    free = lift_along(cam, start, track, d, 0)
    assert np.isfinite(free).all() and np.allclose(free[5:], free[4])   # past it: held at its last point
    # before the vanishing point the path follows the track
    ok = steps[:, 0] < 1.0
    assert np.allclose(cam.project(free[ok])[0], track[ok], atol=1e-6)


def test_keep_on_ray_in_box_keeps_the_image():
    cam = _cam()
    box = (np.array([-0.2, -0.1, -0.2]), np.array([0.2, 0.1, 0.2]))
    inside = np.array([[0.05, 0.0, 0.01]])
    far = cam.position + 4.0 * (np.array([0.05, 0.02, -0.03]) - cam.position)   # behind the box
    near = cam.position + 0.3 * (np.array([0.05, 0.02, -0.03]) - cam.position)  # in front of it
    pts = np.concatenate([inside, far[None], near[None]])
    out = keep_on_ray_in_box(cam, pts, box)
    assert np.allclose(out[0], inside[0])
    assert (out >= box[0] - 1e-9).all() and (out <= box[1] + 1e-9).all()
    assert np.allclose(cam.project(out)[0], cam.project(pts)[0], atol=1e-6)
    # the nearest depth in the box: the far point on the box's far face, the near one on its near face
    assert np.linalg.norm(out[1] - cam.position) > np.linalg.norm(out[2] - cam.position)
