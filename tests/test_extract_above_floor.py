"""The toucher's path kept from going through the floor the object rests on (#23: dev_0568, a fingertip's poke on a
sheet on its floor read as a grasp diving 5.5 cm: the held particles dragged 3.7 cm under the floor, the fit
unstable at every uniform E). Known answers on a lattice slab, seen by a camera above and in front."""

import numpy as np

from physinteract_usd.camera import Camera
from physinteract_usd.contacts import ContactSet
from physinteract_usd.extract.supports import above_floor, resting_base


def _lattice(lo, hi, h):
    ax = [np.arange(a, b + 1e-9, h) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


H = 0.005
SLAB = _lattice((-0.08, 0.0, -0.05), (0.08, 0.02, 0.05), H)      # a 16 x 2 x 10 cm slab, its base at y = 0
FLOOR = resting_base(SLAB, H, [])


def _camera():
    return Camera.look_at((0.0, 0.30, 0.45), (0.0, 0.0, 0.0), width=128, height=128, fov_y_deg=50.0)


def _dive(start, frames=12, grasp=4, depth=0.08):
    """T0 at `start` until the grasp, then diving `depth` metres along the camera's ray away from it (a depth
    misread)."""
    eye = np.asarray(_camera().position)
    tr = np.repeat(np.asarray(start, float)[None], frames, 0)
    ray = (tr[0] - eye) / np.linalg.norm(tr[0] - eye)
    for k in range(grasp, frames):
        tr[k] = tr[0] + ray * depth * (k - grasp) / (frames - 1 - grasp)
    return tr


def test_the_floor_is_found_under_the_slab():
    assert FLOOR is not None and abs(FLOOR["height"] + 0.5 * H) < 1e-12


def test_a_grasp_diving_through_the_floor_is_kept_on_it_along_its_camera_rays():
    top = np.flatnonzero((SLAB[:, 1] > 0.02 - 1e-9) & (np.linalg.norm(SLAB[:, [0, 2]], axis=1) < 0.012))
    start = SLAB[top].mean(0)
    tr = _dive(start)
    c = ContactSet("hand", "pointAdherent", indices=top, grasp_frame=4, trajectory=tr)
    notes, ev = [], {}
    cam = _camera()
    out = above_floor(SLAB, c, FLOOR, notes, ev, cam)
    before = SLAB[top, 1].min() + (tr - tr[4])[:, 1]
    assert before.min() < -0.01                           # as read, the held particles went 1 cm+ under the base
    after = SLAB[top, 1].min() + (out.trajectory - out.trajectory[4])[:, 1]
    assert after[4:].min() >= -1e-9                       # kept on or above it
    assert abs(after.min()) < 1e-9                        # and no higher than that: on the floor
    np.testing.assert_array_equal(out.trajectory[:5], tr[:5])              # before the grasp (and at it): as read
    uv_in, z_in = cam.project(tr)
    uv_out, z_out = cam.project(out.trajectory)
    np.testing.assert_allclose(uv_out, uv_in, atol=1e-6)                  # what the image says is kept
    assert (z_out <= z_in + 1e-12).all() and (z_out < z_in - 1e-3).any()  # only the depth changed: nearer
    assert ev["path_above_floor"]["frames"] > 0 and ev["path_above_floor"]["raised_m"] > 0.01
    assert any("under what the floor allows" in n for n in notes)


def test_a_fingertip_through_the_floor_is_kept_on_it_and_one_pushing_beside_the_slab_is_untouched():
    """A fingertip (radius 6 mm) pressing down 5 cm from the slab's top, no camera (straight up): kept with its
    sphere on the floor; one pushing the slab's side with its centre 4 mm above the base (dev_0184's kind: a
    sideways push, its bottom 2 mm under the base but above the floor half a spacing lower) is left as read."""
    r = 0.006
    cp = np.array([0.0, 0.02, 0.0])
    tr = np.array([[0.0, 0.02 + r - 0.005 * k, 0.0] for k in range(11)])     # its bottom from 0.02 down to -0.03
    c = ContactSet("finger", "pointNonAdherent", trajectory=tr, radius=r, contact_point=cp)
    notes, ev = [], {}
    out = above_floor(SLAB, c, FLOOR, notes, ev)
    bottom = out.trajectory[:, 1] - r
    assert abs(bottom.min() - FLOOR["height"]) < 1e-12                    # on the floor, not under it
    np.testing.assert_array_equal(out.trajectory[:, [0, 2]], tr[:, [0, 2]])
    kept = tr[:, 1] - r >= FLOOR["height"]
    np.testing.assert_array_equal(out.trajectory[kept], tr[kept])
    assert ev["path_above_floor"]["frames"] == int((~kept).sum()) > 0
    side = np.array([[-0.08 - r - 0.01 + 0.002 * k, 0.004, 0.0] for k in range(8)])
    beside = ContactSet("finger", "pointNonAdherent", trajectory=side, radius=r,
                        contact_point=np.array([-0.08, 0.004, 0.0]))
    assert above_floor(SLAB, beside, FLOOR, [], {}) is beside


def test_without_a_floor_nothing_changes():
    tr = _dive(SLAB.mean(0))
    c = ContactSet("hand", "pointAdherent", indices=np.arange(10), grasp_frame=4, trajectory=tr)
    notes, ev = [], {}
    assert above_floor(SLAB, c, None, notes, ev, _camera()) is c and not notes and not ev
