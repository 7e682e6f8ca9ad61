"""Extraction's pieces on small hand-made inputs (no synthetic scene): back-projection, hand
segmentation, hint parsing and checking, the type rules, particle selection."""

from types import SimpleNamespace

import numpy as np
import pytest

import physinteract_usd  # noqa: F401
from physinteract_usd.camera import Camera
from physinteract_usd.errors import InputError
from physinteract_usd.extract import Hint, classify_interaction, parse_hint
from physinteract_usd.extract.geometry import back_project, particles_near, render_rest
from physinteract_usd.extract.hints import check_hint
from physinteract_usd.extract.segmentation import ColourMotionSegmenter, dilate
from physinteract_usd.extract.supports import components
from physinteract_usd.extract.timing import contact_period, release
from physinteract_usd.gaussians import Gaussians


def _camera(w=64, h=48):
    return Camera.look_at((0.2, 0.1, 1.2), (0.0, 0.0, 0.0), width=w, height=h, fov_y_deg=35.0)


def test_back_projection_is_exact_for_a_gaussian_at_a_known_point():
    cam = _camera()
    p = np.array([[0.05, -0.03, 0.1]])
    g = Gaussians.from_colors(p, np.array([[0.8, 0.2, 0.2]]), np.full((1, 3), 0.01), opacities=np.array([0.99]))
    view = render_rest(g, cam, p, 0.01)
    uv, z = cam.project(p)
    assert view.particle_visible[0]
    assert view.depth[int(uv[0, 1]), int(uv[0, 0])] == pytest.approx(z[0], abs=1e-5)
    x = back_project(view, uv)
    assert np.linalg.norm(x[0] - p[0]) < 1e-5
    # a pixel off the object takes the nearest rendered depth
    off = uv + np.array([[20.0, 0.0]])
    y = back_project(view, off)
    assert cam.world_to_camera(y)[0, 2] == pytest.approx(z[0], abs=1e-4)


def test_back_projection_of_a_surface_lands_on_it():
    cam = _camera()
    xs, ys = np.meshgrid(np.linspace(-0.1, 0.1, 30), np.linspace(-0.1, 0.1, 30))
    pts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 0.02)], 1)  # a plane z = 0.02
    g = Gaussians.from_colors(pts, np.tile([[0.2, 0.5, 0.8]], (len(pts), 1)), np.full((len(pts), 3), 0.006),
                              opacities=np.full(len(pts), 0.99))
    view = render_rest(g, cam, pts, 0.007)
    uv, _ = cam.project(np.array([[0.0, 0.0, 0.02], [0.05, -0.04, 0.02]]))
    x = back_project(view, uv)
    assert np.allclose(x[:, 2], 0.02, atol=3e-3)  # within half a Gaussian: the depth blends neighbours
    assert np.allclose(x[:, :2], [[0.0, 0.0], [0.05, -0.04]], atol=3e-3)


def _toy_video(T=8, W=64, H=48, seed=0, noise=0.01):
    """A static textured background, a static blue disc (the object, visible masks) and a
    skin-coloured disc (the hand) crossing it in front."""
    rng = np.random.default_rng(seed)
    bg = np.clip(0.55 + 0.08 * rng.standard_normal((H // 4, W // 4, 3)), 0, 1)
    bg = np.kron(bg, np.ones((4, 4, 1)))[:H, :W].astype(np.float32)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    obj = (xx - 28) ** 2 + (yy - 24) ** 2 <= 11 ** 2
    frames, masks, hands = [], [], []
    for k in range(T):
        cx = 58 - 4.0 * k
        hand = (xx - cx) ** 2 + ((yy - 22) / 0.8) ** 2 <= 8 ** 2
        f = bg.copy()
        f[obj] = [0.15, 0.3, 0.75]
        tex = 0.05 * np.sin(xx / 2.0)[..., None]
        f[hand] = (np.array([0.87, 0.66, 0.54]) + tex)[hand]
        f = np.clip(f + noise * rng.standard_normal(f.shape), 0, 1).astype(np.float32)
        frames.append(f)
        masks.append(obj & ~hand)
        hands.append(hand)
    return np.stack(frames), np.stack(masks), np.stack(hands)


def test_hand_segmentation_on_a_toy_video():
    frames, masks, hands = _toy_video()
    seg = ColourMotionSegmenter()(frames, masks, object_colors=np.tile([[0.15, 0.3, 0.75]], (10, 1)))
    iou = (seg.hand & hands).sum() / (seg.hand | hands).sum()
    # (the background next to the object is never seen free in this toy: inpainted, imperfectly)
    assert iou > 0.85
    assert not (seg.hand & masks).any()  # visible-only masks: the hand never takes object pixels


def test_hand_segmentation_with_amodal_masks_and_a_static_hand():
    frames, masks, hands = _toy_video()
    # the hand stays put for most of the video: the background median alone would be the hand
    frames[2:] = frames[2]
    hands[2:] = hands[2]
    amodal = np.repeat(((np.mgrid[0:48, 0:64][1] + 0.5 - 28) ** 2 + (np.mgrid[0:48, 0:64][0] + 0.5 - 24) ** 2
                        <= 11 ** 2)[None], len(frames), 0)
    seg = ColourMotionSegmenter()(frames, amodal, masks_amodal=True,
                                  object_colors=np.tile([[0.15, 0.3, 0.75]], (10, 1)))
    iou = (seg.hand & hands).sum() / (seg.hand | hands).sum()
    assert iou > 0.8


def test_parse_hint():
    h = parse_hint("3,10,20")
    assert h.frame == 3 and h.pixel == (10.5, 20.5) and h.particles is None
    h = parse_hint(particles="4, 7,9")
    assert list(h.particles) == [4, 7, 9]
    assert parse_hint() is None
    for bad in ("3,10", "a,1,2", "1,2,nan", "1,2,3,4"):
        with pytest.raises(InputError, match="--hint-pixel"):
            parse_hint(bad)
    for bad in ("1,x", ","):
        with pytest.raises(InputError, match="--hint-particles"):
            parse_hint(particles=bad)
    assert parse_hint(grasp_radius=0.02).grasp_radius == 0.02
    assert parse_hint(grasp_radius=0.02).is_empty  # a size, not a place
    for bad in (0.0, -0.01, float("nan"), float("inf")):
        with pytest.raises(InputError, match="--grasp-radius"):
            parse_hint(grasp_radius=bad)


def test_check_hint_names_the_problem():
    scene = SimpleNamespace(particles_positions=np.zeros((10, 3)), camera=_camera())
    with pytest.raises(InputError, match="frame 12 is outside the video"):
        check_hint(Hint(frame=12, pixel=(5.0, 5.0)), scene, 8)
    with pytest.raises(InputError, match="outside the 64x48 frame"):
        check_hint(Hint(frame=1, pixel=(70.0, 5.0)), scene, 8)
    with pytest.raises(InputError, match=r"must lie in \[0, 10\)"):
        check_hint(Hint(particles=np.array([3, 10])), scene, 8)
    with pytest.raises(InputError, match="integers"):
        check_hint(Hint(particles=np.array([1.5])), scene, 8)
    ok = check_hint(Hint(particles=np.array([3, 3, 1])), scene, 8)
    assert list(ok.particles) == [1, 3]


def test_type_rules():
    pull = {"push_cos": 0.4, "contact_motion_px": 12.0, "interface_span": 0.2}
    assert classify_interaction(pull)[0] == "pointAdherent"
    poke = {"push_cos": -0.95, "contact_motion_px": 8.0, "interface_span": 0.15}
    assert classify_interaction(poke)[0] == "pointNonAdherent"
    palm = {"push_cos": -0.9, "contact_motion_px": 8.0, "interface_span": 0.7}
    assert classify_interaction(palm)[0] == "surfaceNonAdherent"
    # seen pushed away from the hand, but the hand came in and went back out: a pull in depth
    back = dict(poke, approach_cos=-0.8, approach_speed_px=3.0)
    assert classify_interaction(back)[0] == "pointAdherent"
    still = {"push_cos": None, "contact_motion_px": 0.2}
    assert classify_interaction(still)[0] == "pointAdherent"
    # touched for a frame and parted, the object not following: a knock (dev_0012), a palm's press
    knock = dict(still, contact_frames=1, coupled_share=0.0)
    assert classify_interaction(knock)[0] == "pointNonAdherent"
    assert classify_interaction(dict(knock, interface_span=0.7))[0] == "surfaceNonAdherent"
    # a grasp that holds on for longer, or that the object followed, stays a grasp
    assert classify_interaction(dict(knock, contact_frames=6))[0] == "pointAdherent"
    assert classify_interaction(dict(pull, contact_frames=2, coupled_share=0.8))[0] == "pointAdherent"
    assert classify_interaction(dict(pull, contact_frames=None, coupled_share=0.0))[0] == "pointAdherent"


def test_particles_near_and_components():
    x = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(5)), -1).reshape(-1, 3) * 0.01
    idx = particles_near(np.array([[0.0, 0.0, 0.0]]), x, 0.0101)
    assert sorted(idx.tolist()) == sorted(np.where(np.linalg.norm(x, axis=1) <= 0.0101)[0].tolist())
    assert len(particles_near(np.array([[1.0, 1.0, 1.0]]), x, 0.001, min_count=3)) == 3
    a, b = x[x[:, 0] == 0], x[x[:, 0] == 0.04]
    comps = components(np.concatenate([a, b]), 0.015, np.arange(len(a) + len(b)))
    assert sorted(len(c) for c in comps) == [25, 25]


def test_contact_period_and_release():
    near = np.array([0, 1, 1, 0, 1, 1, 1, 1, 0, 0], bool)
    assert contact_period(near) == (1, 7)  # the one-frame gap is bridged
    coupled = np.array([-1, 1, 1, 1, 1, -1, -1, 0, 0], np.int8)
    near = np.ones(10, bool)
    assert release(coupled, near, 1) == 5
    assert release(np.ones(9, np.int8), near, 1) is None


def test_log_split_separates_held_particles_from_their_slowly_moving_neighbours():
    from physinteract_usd.extract.supports import log_split

    rng = np.random.default_rng(0)
    held = rng.uniform(0.005, 0.05, 60)        # at the tracking noise
    near = rng.uniform(0.3, 1.0, 40)           # a little motion next to the support
    t = log_split(np.concatenate([held, near]))
    assert held.max() < t < near.min()
    # the groups' sizes do not move the split out of the gap
    t2 = log_split(np.concatenate([held[:10], near]))
    assert held.max() < t2 < near.min()
    assert log_split(np.array([0.1, 0.2])) == 0.2    # too few to split: keep all


def test_contact_start_takes_the_stillest_frame_and_only_noise_level_ties():
    from physinteract_usd.extract.timing import contact_start

    vh = np.zeros((12, 2))
    near = np.ones(12, bool)
    # the hand arrives (3.6 px) and rests at frame 2; the pull starts slowly (0.56 px, then faster):
    # the start is frame 2, not the slowly moving frame after it (balloon's measured speeds)
    speed = np.array([np.nan, 3.56, 0.40, 0.56, 1.08, 1.49, 1.79, 1.94, 1.82, 1.46, 1.2, 1.0])
    coupled = np.array([0, -1, 1, -1, 1, 1, 1, 1, 1, 1, 1, 1])
    assert contact_start(speed, near, 1, 11, coupled, vh) == 2
    # two frames as still as each other (within the tracking noise): the later one
    speed2 = speed.copy()
    speed2[3] = 0.45
    assert contact_start(speed2, near, 1, 11, np.ones(12), vh) == 3


def test_grasp_centre_moves_onto_the_material_only_when_off_it():
    from physinteract_usd.extract.contact import onto_particles

    h = 0.01
    g = np.arange(-3, 4) * h
    x0 = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), -1).reshape(-1, 3)  # a sheet at z = 0
    # 4 spacings above the particle at (h, 0, 0): moved straight down to one spacing above it
    np.testing.assert_allclose(onto_particles(np.array([h, 0.0, 4 * h]), x0, h), [h, 0.0, h], atol=1e-12)
    # beyond the sheet's edge, diagonally: toward the corner particle, ending one spacing from it
    c = np.array([6 * h, 6 * h, 0.0])
    out = onto_particles(c, x0, h)
    np.testing.assert_allclose(np.linalg.norm(out - [3 * h, 3 * h, 0]), h, atol=1e-12)
    np.testing.assert_allclose(out[:2] - 3 * h, [h / np.sqrt(2)] * 2, atol=1e-12)
    # already within a spacing of the material: unchanged
    c = np.array([0.5 * h, 0.2 * h, 0.6 * h])
    np.testing.assert_array_equal(onto_particles(c, x0, h), c)


def test_support_core_keeps_the_still_core_and_only_the_hidden_part_of_its_shell():
    from physinteract_usd.extract.supports import support_core

    h = 0.01
    x0 = np.stack([np.zeros(8), np.arange(8) * h, np.zeros(8)], 1)      # a line of particles
    ids = np.arange(2, 8)                                                  # a still region: 2..7
    motion = np.array([0.01, 0.02, 0.03, 0.4, 0.5, 0.6])                  # 2..4 held, 5.. move a little
    keep, n = support_core(x0, ids, motion, limit=0.1, h=h)
    assert set(keep) == {2, 3, 4, 5} and n == 3                           # the core and its one shell
    visible = np.array([True, True, True, True, True, True])
    keep, n = support_core(x0, ids, motion, 0.1, h, visible=visible)
    assert set(keep) == {2, 3, 4}                                          # a seen shell is not held
    visible[3] = False                                                     # particle 5 hidden
    keep, _ = support_core(x0, ids, motion, 0.1, h, visible=visible)
    assert set(keep) == {2, 3, 4, 5}
    keep, n = support_core(x0, ids, np.full(6, 0.5), 0.1, h)               # nothing below the limit
    assert len(keep) >= 3 and n >= 1


def test_hand_coloured_spots_on_the_object_are_not_the_hand_without_masks():
    """No silhouettes (the object is where it rests): spots of the hand's colour on the object that
    never connect to the toucher coming in from outside are the object's own (#23: a pale sheet
    under a white glove was 'touched' from frame 0)."""
    frames, masks, hands = _toy_video()
    yy, xx = np.mgrid[0:48, 0:64] + 0.5
    spots = np.zeros((48, 64), bool)
    for cx, cy in ((19, 20), (21, 30), (26, 17)):
        spots |= (xx - cx) ** 2 + (yy - cy) ** 2 <= 2.2 ** 2
    tex = 0.05 * np.sin(xx / 2.0)[..., None]
    skin = (np.array([0.87, 0.66, 0.54]) + tex).astype(np.float32)
    for k in range(len(frames)):
        keep = spots & ~dilate(hands[k], 2)
        frames[k][keep] = skin[keep]
    rest = ((xx - 28) ** 2 + (yy - 24) ** 2 <= 11 ** 2).astype(np.float32)
    seg = ColourMotionSegmenter()(frames, None, rest_alpha=rest,
                                  object_colors=np.tile([[0.15, 0.3, 0.75]], (10, 1)))
    far = spots & ~dilate(hands.any(0), 3)
    assert far.any()
    assert not (seg.hand & far[None]).any()
    # the moving hand is still found where it is clear of the object
    clear = hands & ~dilate((xx - 28) ** 2 + (yy - 24) ** 2 <= 13 ** 2, 0)[None]
    assert (seg.hand & clear).sum() >= 0.8 * clear.sum()


def _lattice(lo, hi, h):
    ax = [np.arange(a, b + 1e-9, h) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


def test_a_floor_from_the_underside_not_its_deepest_trough():
    """resting_base: a 20 cm sheet lying still, with a few particles of a trough 2 spacings below
    the rest (a wavy sheet), rests on a floor (#23: dev_0002 got a fixed support); a bar clamped
    upright at its foot, and a bar hanging from a still region at its top, do not."""
    from physinteract_usd.extract.supports import resting_base

    h = 0.01
    sheet = _lattice((-0.1, 0.0, -0.06), (0.1, 0.01, 0.06), h)
    trough = np.array([[0.0, -0.02, 0.0], [0.01, -0.02, 0.0], [0.0, -0.02, 0.01]])
    x0 = np.concatenate([sheet, trough])
    still = np.flatnonzero(x0[:, 1] >= 0.0)            # the trough moved (poked), the rest lay still
    f = resting_base(x0, h, [still])
    assert f is not None and abs(f["height"] - (-0.02 - 0.5 * h)) < 1e-9   # under its lowest particle
    # the same sheet without the trough: a floor too (as before)
    assert resting_base(sheet, h, [np.arange(len(sheet))]) is not None
    # an upright bar clamped at its foot: the still region is as tall as it is wide, held
    bar = _lattice((-0.02, 0.0, -0.02), (0.02, 0.2, 0.02), h)
    foot = np.flatnonzero(bar[:, 1] <= 0.05)
    assert resting_base(bar, h, [foot]) is None
    # a bar hanging from its top: its still region does not touch the floor
    top = np.flatnonzero(bar[:, 1] >= 0.17)
    assert resting_base(bar, h, [top]) is None


def test_a_bar_on_a_floor_pushed_sideways_by_a_big_fingertip_rests_one_pushed_up_is_held():
    """lowest_toucher_y + resting_base (#23, dev_0184): a bar 3 cm tall lying on a floor, pushed
    sideways at mid-height by a round pusher of radius 2 cm (its bottom 1 cm under the bar's base,
    its centre above it), rests on the floor; the same pusher with its centre 2.5 cm under the base
    pushes the bar up (held, no floor); an adherent grasp below the base holds it too."""
    from physinteract_usd.extract.supports import lowest_toucher_y, resting_base

    h = 0.01
    bar = _lattice((-0.15, 0.0, -0.015), (0.15, 0.03, 0.015), h)
    end = np.flatnonzero(bar[:, 0] >= 0.09)               # the far end stays still, flat on the floor
    side = np.array([[0.0, 0.015, 0.04], [0.02, 0.012, 0.04], [0.04, 0.01, 0.04]])
    low = lowest_toucher_y(side, 0.02, "pointNonAdherent", float(bar[:, 1].min()))
    assert abs(low - 0.01) < 1e-12
    assert resting_base(bar, h, [end], low) is not None
    # the old reading (its bottom, centre - radius = -0.01 m, a spacing under the base) called it held
    assert resting_base(bar, h, [end], 0.01 - 0.02 - 1e-6) is None
    under = side - np.array([0.0, 0.035, 0.0])             # centre 2.5 cm under the base: pushes it up
    low = lowest_toucher_y(under, 0.02, "pointNonAdherent", float(bar[:, 1].min()))
    assert abs(low - (-0.025 - 0.02)) < 1e-12 and resting_base(bar, h, [end], low) is None
    assert abs(lowest_toucher_y(under, 0.02, "pointAdherent", 0.0) - (-0.025)) < 1e-12


def test_a_floor_under_two_still_corners_not_an_arch_on_its_piers():
    """resting_base with still regions at two places (#23, dev_0144): a block on a floor pressed
    from above, still at two corners of its bottom (3 spacings tall, 5 wide: flat), rests on the
    floor (its underside joins them on the floor's plane); an arch whose two feet are still is held
    at its feet (its underside leaves the plane between them); a strap sagging between two still
    ends is held (its ends are not its lowest points)."""
    from physinteract_usd.extract.supports import one_underside, resting_base

    h = 0.01
    block = _lattice((-0.1, 0.0, -0.06), (0.1, 0.12, 0.06), h)
    x, y, z = block.T
    c1 = np.flatnonzero((x <= -0.05 + 1e-9) & (y <= 0.03 + 1e-9) & (z <= -0.01 + 1e-9))
    c2 = np.flatnonzero((x >= 0.05 - 1e-9) & (y <= 0.03 + 1e-9) & (z >= 0.01 - 1e-9))
    f = resting_base(block, h, [c1, c2])
    assert f is not None and abs(f["height"] + 0.5 * h) < 1e-9
    # an arch: two 4 cm feet, a deck 6 cm above the floor between them
    feet = _lattice((-0.1, 0.0, -0.02), (-0.06, 0.08, 0.02), h)
    arch = np.concatenate([feet, feet + [0.16, 0.0, 0.0], _lattice((-0.05, 0.06, -0.02), (0.05, 0.08, 0.02), h)])
    ax, ay = arch[:, 0], arch[:, 1]
    left = np.flatnonzero((ax <= -0.06 + 1e-9) & (ay <= 0.02 + 1e-9))
    right = np.flatnonzero((ax >= 0.06 - 1e-9) & (ay <= 0.02 + 1e-9))
    assert resting_base(arch, h, [left, right]) is None
    base = ay <= ay.min() + 1.5 * h
    assert not one_underside(arch, h, base, [left, right])
    assert one_underside(block, h, block[:, 1] <= 1.5 * h, [c1, c2])
    # a strap sagging 3 cm between two still ends
    s = np.linspace(-0.1, 0.1, 21)
    strap = np.concatenate([np.stack([s, 0.03 * (s / 0.1) ** 2 + dy, np.full_like(s, dz)], 1)
                            for dy in (0.0, h) for dz in (-h, 0.0, h)])
    ends = [np.flatnonzero(strap[:, 0] <= -0.08 + 1e-9), np.flatnonzero(strap[:, 0] >= 0.08 - 1e-9)]
    assert resting_base(strap, h, ends) is None


def test_a_still_hand_coloured_prop_is_not_the_hand():
    """A post the object hangs on, as brown as skin and touching the object, never moves: it is
    background, not the toucher, though the hand passes next to it (a guard: this toy passed before
    #23's dev_0011 fix too; `drop_still_props` below is what changed)."""
    frames, masks, hands = _toy_video()
    yy, xx = np.mgrid[0:48, 0:64] + 0.5
    post = (np.abs(xx - 28) <= 3) & (yy >= 34)          # below the object, touching its silhouette
    tex = 0.05 * np.sin(xx / 2.0)[..., None]
    brown = (np.array([0.62, 0.42, 0.30]) + tex).astype(np.float32)
    for k in range(len(frames)):
        keep = post & ~hands[k] & ~masks[k]
        frames[k][keep] = brown[keep]
        hands[k] &= ~post  # (the hand never crosses it in this toy)
    seg = ColourMotionSegmenter()(frames, masks, object_colors=np.tile([[0.15, 0.3, 0.75]], (10, 1)))
    inner = post & ~dilate(masks.any(0) | hands.any(0), 2)
    assert inner.sum() >= 20
    assert not (seg.hand & inner[None]).any()
    iou = (seg.hand & hands).sum() / (seg.hand | hands).sum()
    assert iou > 0.8  # the moving hand is still found


def test_drop_still_props_keeps_a_resting_hand_and_drops_a_prop_the_hand_never_meets():
    from physinteract_usd.extract.segmentation import drop_still_props

    T, H, W = 6, 30, 40
    hand = np.zeros((T, H, W), bool)
    seeds = np.zeros((T, H, W), bool)
    hand[:, 20:28, 2:6] = True                     # a still prop, "hand" in every frame, never moving
    for k in range(T):                              # the toucher comes in, then rests at x 20..26
        x = max(30 - 4 * k, 20)
        hand[k, 5:12, x:x + 6] = True
        if k < 3:
            seeds[k, 5:12, x:x + 6] = True           # it moved in the first frames only
    out = drop_still_props(hand, seeds)
    assert not out[:, 20:28, 2:6].any()
    assert out[3:, 5:12, 20:26].all()                # the resting hand stays, where it moved to rest
    prop = np.zeros((H, W), bool)
    prop[20:28, 2:6] = True
    assert (out == (hand & ~prop[None])).all()       # nothing else taken away



def test_a_fixed_piece_apart_from_the_toucher_at_the_start_is_dropped_though_the_toucher_passes_over_it():
    """#23, dev_0542: a drawn support's foot of the hand's colour beside the object, "hand" in every frame; the toucher
    starts away, passes over it while it pokes and leaves. `drop_still_props` keeps a still place the moving toucher
    meets, so the foot stayed hand and the grasp was read at frame 0; `fixed_pieces` drops it (a piece of the first
    frame's hand that is not its largest and is there in nearly every frame). A hand resting from the first frame
    (its largest piece) stays."""
    from physinteract_usd.extract.segmentation import drop_still_props, fixed_pieces

    T, H, W = 10, 30, 40
    hand = np.zeros((T, H, W), bool)
    seeds = np.zeros((T, H, W), bool)
    hand[:, 12:16, 14:18] = True                    # the foot, in every frame
    for k in range(T):                              # the toucher: away, over the foot in frames 3..6, away again
        x = 30 if k < 3 or k > 6 else 12
        hand[k, 10:20, x:x + 8] = True
        seeds[k, 10:20, x:x + 8] = True
    foot = np.zeros((H, W), bool)
    foot[12:16, 14:18] = True
    assert (fixed_pieces(hand) == foot).all()
    out = drop_still_props(hand, seeds)
    assert not out[:, 12:16, 14:18].any()
    assert out[0, 10:20, 30:38].all() and out[4, 10:20, 12:14].all()   # the toucher stays, less the foot's pixels
    # a hand resting on the object from the first frame is its largest piece: kept
    rest = np.zeros((T, H, W), bool)
    rest[:, 5:15, 5:20] = True
    rest[:, 20:23, 30:33] = True                     # and a fixed speck apart from it: dropped
    speck = np.zeros((H, W), bool)
    speck[20:23, 30:33] = True
    assert (fixed_pieces(rest) == speck).all()
    moved = np.zeros_like(rest)
    moved[-1, 5:15, 5:20] = True                     # (the hand moves off at the end)
    kept = drop_still_props(rest, moved)
    assert kept[:, 5:15, 5:20].all() and not kept[:, 20:23, 30:33].any()
    # one piece in the first frame: nothing to tell apart, nothing dropped
    assert not fixed_pieces(hand[:, :, 25:]).any()

def test_a_colliders_retreat_is_not_the_motion_supports_are_judged_against():
    """A palm presses a still sheet by a pixel and then lifts off 20 px: the supports' stillness is
    judged against the pixel it moved while acting, not the retreat (#23, dev_0009: the whole sheet
    on a floor was 'held'); a grasp keeps its whole track over the contact period."""
    from physinteract_usd.extract.lifting import HandTrack
    from physinteract_usd.extract.pipeline import acting_motion

    uv = np.zeros((12, 2))
    uv[3:7, 1] = [0.0, 0.5, 1.0, 0.5]      # the press, frames 3..6
    uv[7:, 1] = [-5.0, -10.0, -15.0, -20.0, -20.0]   # the lift-off after the release at 6
    hand = HandTrack(uv, 20.0, 8, uv[8] - uv[3])
    assert acting_motion(hand, 3, 6, "surfaceNonAdherent") == pytest.approx(1.0)
    assert acting_motion(hand, 3, 6, "pointNonAdherent") == pytest.approx(1.0)
    assert acting_motion(hand, 3, 6, "pointAdherent") == 20.0
    assert acting_motion(hand, 3, None, "pointNonAdherent") == 20.0


def test_grasp_of_a_slow_press_is_its_onset_above_the_toucher_noise_floor():
    """A palm approaches, rests (noise ~0.1 px), presses slowly (0.3-0.5 px a frame) and retreats
    fast (6-8 px): the grasp is the last frame at rest before the press, not the stillest frame of
    everything slower than 30% of the retreat (#23, dev_0009: found 24, truly 13)."""
    from physinteract_usd.extract.timing import contact_start, rest_onset

    rng = np.random.default_rng(1)
    speed = np.array([0.3, 0.5, 1.2, 1.7, 1.4, 1.2, 0.34, 0.17, 0.06, 0.15, 0.04,     # approach, rest 7..10
                      0.46, 0.43, 0.30, 0.34, 0.24, 0.31, 0.02,                         # the press, 11..16; turn
                      1.5, 5.9, 7.7, 7.2, 3.1, 0.2])                                   # the retreat
    ang = np.where(np.arange(len(speed)) < 11, rng.uniform(0, 2 * np.pi, len(speed)), 1.2)   # noise has no direction
    vh = speed[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
    near = np.ones(len(speed) + 1, bool)
    coupled = np.zeros(len(speed), np.int8)
    assert rest_onset(speed, vh, 0, len(speed)) == 10
    assert contact_start(speed, near, 0, len(speed), coupled, vh) == 10
    # no onset soon after the rest (a hand holding a stiff block barely moves): no answer here,
    # the caller's rule (the stillest frame) decides
    flat = np.array([4.2, 3.9, 2.6, 1.3, 0.10, 0.22, 0.07, 0.14, 0.08, 0.04, 0.13, 0.10, 0.2, 0.25, 0.17])
    vflat = flat[:, None] * np.stack([np.cos(np.arange(15.0) * 2.1), np.sin(np.arange(15.0) * 2.1)], 1)
    assert rest_onset(flat, vflat, 0, 15) is None
    # one slow frame at the start of the video is the approach's start, not a rest
    assert rest_onset(speed, vh, 0, len(speed)) != 0
    # a rest of three slow frames (0.27, 0.03, 0.28 px) before a pull that starts slowly (glove,
    # the named suite): its floor is its stillest frames', not its last one's
    sg = np.array([2.25, 0.27, 0.03, 0.28, 0.54, 0.81, 0.91, 0.94, 0.87, 0.56, 5.4])
    vg = sg[:, None] * np.array([[1.0, 0.1]])
    vg[2] = [0.03, -0.02]
    assert rest_onset(sg, vg, 0, len(sg) - 1) == 2


def test_the_type_reads_the_toucher_while_it_acts_not_its_retreat():
    """A finger presses a bar 2 px away from its body and withdraws 14 px toward it: the first
    main motion is the press (#23, dev_0010 read as a pull); a toucher that moves under 2 px while
    it acts and parts without the object following is a press (dev_0009)."""
    from physinteract_usd.extract.lifting import track_hand
    from physinteract_usd.extract.timing import Timing

    T1 = 20
    vh = np.zeros((T1, 2))
    vh[5:9, 1] = -0.5           # the press, up
    vh[9:13, 1] = 0.5           # back
    vh[14:19] = [-2.0, 2.0]     # the retreat, down-left, after the release at 14
    t = Timing(vh, np.zeros((T1, 2)), np.zeros(T1, np.int8), np.ones(T1 + 1, bool), (0, 19),
               np.linalg.norm(vh, axis=1), 4, 14)
    hand = track_hand(t, np.array([50.0, 50.0]))
    assert hand.first_move[1] < 0 and abs(hand.first_move[0]) < 1e-9     # the press, not the retreat
    assert hand.acting == pytest.approx(2.0)
    assert hand.motion > 10
    press = {"push_cos": 0.75, "contact_motion_px": 26.0, "acting_motion_px": 1.7, "interface_span": 0.7,
             "coupled_share": 0.25, "contact_frames": 12}
    assert classify_interaction(press)[0] == "surfaceNonAdherent"
    assert classify_interaction(dict(press, interface_span=0.2))[0] == "pointNonAdherent"
    # a grasp that moves the hand, or that the object follows, stays a grasp
    assert classify_interaction(dict(press, acting_motion_px=9.8, push_cos=1.0))[0] == "pointAdherent"
    assert classify_interaction(dict(press, coupled_share=0.8))[0] == "pointAdherent"



def test_supports_that_would_pin_the_object_against_the_interaction_are_shrunk_or_dropped():
    """(#23) a support next to the grasp, one the grasp's path would tear the object off, and one a
    fingertip's path sweeps through are shrunk or dropped, and the notes say so; a support clear of
    a modest pull is kept whole."""
    from physinteract_usd.contacts import ContactSet
    from physinteract_usd.extract.supports import unpin

    h = 0.01
    x0 = np.stack([np.arange(21) * h, np.zeros(21), np.zeros(21)], 1)       # a 20 cm rod along x
    held = np.arange(16, 21)                                               # the grasp at the right end
    T = 6
    pull = np.tile(x0[held].mean(0), (T, 1))
    pull[:, 1] = np.linspace(0.0, 0.05, T)                                 # lifted 5 cm: a modest stretch
    grasp = ContactSet("hand", "pointAdherent", held, trajectory=pull)
    clamp = ContactSet("support", "fixed", np.arange(0, 4))
    notes, ev = [], {}
    out = unpin(x0, h, grasp, [clamp], notes, ev)
    assert len(out) == 1 and len(out[0].indices) == 4 and not notes
    # a support reaching the grasp: the particles within two spacings of it go
    wide = ContactSet("support", "fixed", np.arange(0, 16))
    out = unpin(x0, h, grasp, [wide], notes, ev)
    assert out[0].indices.max() <= 13 and "next to the grasp" in notes[-1]
    # pulled 40 cm away from a clamp 14 cm off: torn off, not held; dropped
    tear = pull.copy()
    tear[:, 0] += np.linspace(0.0, 0.4, T)
    notes = []
    assert unpin(x0, h, ContactSet("hand", "pointAdherent", held, trajectory=tear),
                 [ContactSet("support", "fixed", np.arange(0, 4))], notes, ev) == []
    assert "stretch" in notes[0] and "--support-pixel" in notes[0]
    # a fingertip of 2 cm pushed along the rod from its right end sweeps through the particles there
    path = np.stack([np.linspace(0.22, 0.10, T), np.zeros(T), np.zeros(T)], 1)
    poke = ContactSet("finger", "pointNonAdherent", trajectory=path, radius=0.02)
    notes = []
    out = unpin(x0, h, poke, [ContactSet("support", "fixed", np.arange(5, 21))], notes, ev)
    assert out[0].indices.max() < 10 and "inside the fingertip's path" in notes[0]


def test_a_sphere_that_comes_in_and_pulls_back_rests_for_an_instant_at_its_turn():
    """(#23, dev_0020) a sphere approaches fast (6 px a frame) leftward, the object not following,
    stops for an instant (0.36 px) and pulls back rightward with the object: the grasp is the turn;
    a pull that reverses mid-way with the object following both ways (dev_0013) is no rest."""
    from physinteract_usd.extract.timing import rest_onset

    sp = np.array([0.55, 2.7, 5.0, 6.0, 5.9, 4.7, 3.7, 1.8, 0.8, 0.36, 1.0, 1.7, 2.2, 2.8, 3.2, 3.4])
    vh = np.zeros((len(sp), 2))
    vh[:9, 0] = -sp[:9]
    vh[9] = [0.30, 0.20]
    vh[10:, 0] = sp[10:]
    coupled = np.where(np.arange(len(sp)) < 9, -1, 1).astype(np.int8)
    assert rest_onset(sp, vh, 0, len(sp) - 1, coupled) == 9
    # the same speeds, the object following before the turn too: a pull reversing, no rest
    assert rest_onset(sp, vh, 0, len(sp) - 1, np.ones(len(sp), np.int8)) is None


def test_a_colliders_contact_is_its_pushing_edge():
    """(#23) a fingertip seen over the object as a 4 x 16 px strip, pushing down the image: its
    contact is the strip's lower end (the part that pushes), not the strip's middle."""
    from physinteract_usd.extract.contact import GraspContact, pushing_edge

    an = SimpleNamespace(R=4.0)
    region = np.zeros((40, 40), bool)
    region[10:26, 18:22] = True
    g = GraspContact(np.array([20.0, 18.0]), region)
    e = pushing_edge(an, g, np.array([0.0, 1.0]))
    assert e.uv[1] > 23.0 and abs(e.uv[0] - 20.0) < 1e-9
    assert e.region.sum() < region.sum() and (e.region <= region).all()
    up = pushing_edge(an, g, np.array([0.0, -2.0]))
    assert up.uv[1] < 13.0
    assert pushing_edge(an, g, np.zeros(2)) is g           # no push seen: the region as it is


def test_a_held_end_with_noisy_frames_is_grown_from_its_still_core():
    """A bar held at one end bends away (displacement ~ distance from the clamp); the held end's
    particles read a 3 px spike in one small-motion frame (noise), so their largest motion is not
    still, but against the object's own motion frame by frame they stay put: the support grown
    from the still core takes them, and not the first particle that moves, nor the grasp (#23)."""
    from physinteract_usd.extract.supports import grow_supports, particle_motion, relative_motion

    x0 = np.stack([np.arange(12.0), np.zeros(12), np.zeros(12)], 1)     # spacing 1
    T = 8
    amp = np.linspace(0.0, 2.0, T)                                       # px per spacing from the clamp
    D = np.zeros((T, 12, 2))
    D[:, :, 0] = amp[:, None] * np.clip(np.arange(12.0) - 2.0, 0, None)[None]
    D[1, 1:3, 1] = 3.0                                                   # a spike while little moves
    D[5, 7, :] = np.nan                                                  # a lost seed
    assert particle_motion(x0, x0, D, 1.0)[1:3].min() > 1.5          # "still" by its largest motion: no
    rel = relative_motion(x0, x0, D, 1.0)
    assert rel[:3].max() < 0.03 and rel[3] > 0.04
    grown = grow_supports(x0, [np.array([0])], rel, 1.0, 0.04)
    assert grown[0].tolist() == [0, 1, 2]
    assert grow_supports(x0, [np.array([0])], rel, 1.0, 0.04, exclude=np.array([1]))[0].tolist() == [0]
    # only through the particles the camera does not see, where asked: the seen one stops it
    seen = np.zeros(12, bool)
    seen[1] = True
    assert grow_supports(x0, [np.array([0])], rel, 1.0, 0.04, visible=seen)[0].tolist() == [0]
    seen[1] = False
    seen[2] = True
    assert grow_supports(x0, [np.array([0])], rel, 1.0, 0.04, visible=seen)[0].tolist() == [0, 1]


def _release_of(vh, vo, near, g):
    """find_timing's release steps on given velocities (frame pairs), as the pipeline runs them."""
    from physinteract_usd.extract.timing import contact_run, contact_share, coupling, part_by_ratio, release

    eps = 0.35
    coupled = coupling(vh, vo, eps)
    run = contact_run(coupled, near, vh, vo, eps)
    share = 0.0
    if run is not None:
        coupled = part_by_ratio(coupled, vh, vo, run, eps)
        share = contact_share(coupled, vh, vo, run, eps)
    speed = np.linalg.norm(vh, axis=1)
    return release(coupled, near, g, speed, vh=vh, vo=vo, share=share, eps=eps), coupled


def test_a_release_is_where_toucher_and_object_stay_apart_not_one_odd_frame_pair():
    """(#23, fifth pass) a hand pulls (the object next to it following at 0.9 of its speed) and
    lets go at frame 10: the object springs back while the hand moves off; in the pair after,
    the object's flow next to the fast-moving hand reads as following it (the hand's flow smeared
    onto it), then apart again. One odd pair mid-pull (pair 6: the object's flow lags, noise) is no
    release; the release is frame 10, where their relative motion grows and stays."""
    T1 = 14
    vh = np.zeros((T1, 2))
    vh[2:10, 0] = [0.8, 1.6, 2.2, 2.4, 2.4, 2.2, 1.4, 0.6]      # the pull, slowing at its end
    vh[10:, 0] = [4.0, 12.0, 16.0, 10.0]                         # the hand moves off after letting go
    vo = 0.9 * vh.copy()
    vo[6] = [0.4, 0.5]                                             # one odd pair: lags, turned
    vo[10] = [-3.0, 0.5]                                           # springs back
    vo[11] = [6.0, 0.0]                                            # the hand's flow smeared onto it
    vo[12] = [-1.0, 0.2]
    vo[13] = [0.5, 0.0]
    near = np.ones(T1 + 1, bool)
    r, coupled = _release_of(vh, vo, near, 2)
    assert coupled[6] < 0 and coupled[11] > 0     # the per-pair coupling sees both odd pairs
    assert r == 10
    # no odd pairs: the same release
    vo2 = 0.9 * vh.copy()
    vo2[10:] = [[-3.0, 0.5], [-1.0, 0.0], [0.0, 0.3], [0.2, 0.0]]
    assert _release_of(vh, vo2, near, 2)[0] == 10
    # held on to the end (the object follows throughout): none
    assert _release_of(vh, 0.9 * vh, near, 2)[0] is None


def test_a_toucher_never_seen_in_contact_releases_where_it_leaves_and_says_so():
    """(#23, dev_0002) a white finger on a pale sheet: the grasp is put on its approach (pair 2:
    it slows, then moves fast into the sheet, the sheet not following), then the finger and the sheet next
    to it are hidden until it moves off (pairs 22, 23) and leaves (frame 24). The approach is not
    the release: nothing in the video shows the contact, so only the leaving ends it, and the
    confidence says so."""
    from physinteract_usd.extract.timing import Timing, timing_confidence

    T1 = 26
    vh = np.full((T1, 2), np.nan)
    vo = np.full((T1, 2), np.nan)
    vh[2], vo[2] = [-0.37, 0.12], [-0.04, -0.07]
    vh[3], vo[3] = [-2.8, 6.7], [0.02, 0.05]
    vh[22], vo[22] = [2.1, -4.5], [0.07, -0.05]
    vh[23], vo[23] = [0.6, -1.2], [-0.03, 0.01]
    near = np.zeros(T1 + 1, bool)
    near[1:24] = True
    r, coupled = _release_of(vh, vo, near, 2)
    assert r == 24
    speed = np.linalg.norm(vh, axis=1)
    t = Timing(vh, vo, coupled, near, (1, 23), speed, 2, r)
    ev, notes = {}, []
    assert timing_confidence(t, 0.35, ev, notes) == "low"
    assert any(n.startswith("release uncertain: the video never shows the object moving with the hand") for n in notes)
    # once the finger is seen resting on the sheet (pair 5: both still), a parting after it counts
    vh[5], vo[5] = [0.05, 0.02], [0.01, 0.0]
    vh[8], vo[8] = [3.0, -5.0], [0.0, 0.02]
    vh[9], vo[9] = [4.0, -6.0], [0.01, 0.0]
    assert _release_of(vh, vo, near, 2)[0] == 8


def test_the_object_next_to_the_contact_is_measured_clear_of_the_toucher_in_both_frames():
    """(#23, fifth pass) the object stands still while a toucher (a disc) moves 6 px across it: the
    object pixels the disc moves onto in the second frame are hidden there, and their flow is the
    disc's. The object's velocity next to the contact leaves them out: still."""
    from physinteract_usd.extract.timing import velocities

    H = W = 48
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    disc = [(xx - cx) ** 2 + (yy - 24) ** 2 <= 7 ** 2 for cx in (16, 22)]
    hand = np.stack(disc)
    obj = np.stack([~d for d in disc])                  # the object fills the frame behind the disc
    fl = np.zeros((1, H, W, 2), np.float32)
    fl[0][disc[0] | disc[1]] = [6.0, 0.0]               # the disc's flow, and the pixels it moves onto
    an = SimpleNamespace(T=2, H=H, W=W, R=4.0, clear=2, hand=hand, obj=obj, flows=SimpleNamespace(forward=fl))
    vh, vo = velocities(an, [np.array([22.0, 24.0]), None])
    assert np.allclose(vh[0], [6.0, 0.0])
    assert np.linalg.norm(vo[0]) < 0.05


def test_a_grasp_read_after_the_objects_motion_moves_to_where_the_object_starts_to_follow():
    """(#23, fifth pass; dev_9224) tongs pull an anchored bar straight from the approach (no rest
    before), hold it still for four frames and let go: the rest-onset rule reads the hold as the
    rest and the withdrawal as the onset (grasp 18). The object followed the toucher over pairs
    5..14 before that: the grasp is frame 5. A grasp before the motion is kept."""
    from physinteract_usd.extract.timing import not_after_the_motion

    T1 = 22
    coupled = np.zeros(T1, np.int8)
    coupled[5:15] = 1
    coupled[19:] = -1
    vo = np.zeros((T1, 2))
    vo[5:15, 1] = -np.array([0.8, 1.7, 2.4, 3.1, 3.7, 3.6, 3.3, 2.8, 1.9, 0.6])
    run = (4, 18)
    assert not_after_the_motion(18, coupled, vo, run) == 5
    assert not_after_the_motion(4, coupled, vo, run) == 4
    assert not_after_the_motion(7, coupled, vo, run) == 7     # a grasp a little into the motion stays
    assert not_after_the_motion(18, coupled, vo, None) == 18


def test_a_fingertips_front_hidden_over_the_object_is_found_from_the_notch_in_its_silhouette():
    """(#23, fifth pass; dev_0014) a fingertip pushes down into a sheet; its pixels over the sheet
    are not segmented (a similar colour), but the frame's silhouette has a notch where it hides the
    sheet: the contact's pushing edge is the notch's far end. A band along the silhouette's edge
    (the object moved), speckles of a ragged mask, or no visible masks give nothing."""
    from physinteract_usd.extract.contact import GraspContact, hidden_front, pushing_edge

    H, W = 60, 60
    rest = np.zeros((H, W), bool)
    rest[20:50, 5:55] = True                                   # the sheet at rest
    obj = rest.copy()
    obj[20:30, 26:34] = False                                  # the notch: the fingertip down to row 29
    hand = np.zeros((H, W), bool)
    hand[5:20, 26:34] = True                                   # the fingertip seen above the sheet
    region = hand & (np.arange(H)[:, None] >= 17)              # the contact region next to the silhouette
    an = SimpleNamespace(R=6.0, H=H, W=W, hand=hand[None], obj=obj[None], visible_masks=True,
                         rest=SimpleNamespace(silhouette=rest))
    d = np.array([0.0, 1.0])
    front = hidden_front(an, 0, region, d)
    assert front.any() and np.nonzero(front)[0].max() == 29
    assert np.nonzero(front)[1].min() == 26 and np.nonzero(front)[1].max() == 33
    edge = pushing_edge(an, GraspContact(np.array([30.0, 18.5]), region), d, 0)
    assert 27.0 <= edge.uv[1] <= 30.0 and 29.0 <= edge.uv[0] <= 31.0
    # without the frame index (or without visible masks) the region as before
    assert pushing_edge(an, GraspContact(np.array([30.0, 18.5]), region), d).uv[1] < 20.0
    an.visible_masks = False
    assert not hidden_front(an, 0, region, d).any()
    an.visible_masks = True
    # a band along the silhouette's edge (the sheet moved down by 3 px) is not a notch
    moved = np.zeros((H, W), bool)
    moved[23:53, 5:55] = True
    an.obj = moved[None]
    assert not hidden_front(an, 0, region, d).any()
    # speckles of a ragged mask ahead of the region are no front either
    ragged = rest.copy()
    ragged[21, 28] = ragged[23, 30] = ragged[22, 31] = False
    an.obj = ragged[None]
    assert not hidden_front(an, 0, region, d).any()


def test_an_object_lagging_behind_a_toucher_that_keeps_pulling_is_not_released():
    """(#23, fifth pass; dev_9217) a glove pulls a stiff anchored bar at about 2 px a frame; the
    bar next to it reads 0.8-1.1 px a frame, then 0.0-0.4 px for eight frames (a plain bar's flow
    next to the hand) while the glove keeps pulling the same way, slowing at the pull's end; it
    lets go at frame 25 and moves off across. The lag is no release (the toucher neither turns
    nor speeds up, the bar does not spring back); the release is frame 25."""
    T1 = 30
    vh = np.zeros((T1, 2))
    vh[9:25, 0] = [0.6, 0.9, 1.1, 1.6, 1.8, 2.0, 2.2, 2.2, 2.3, 2.4, 2.0, 2.0, 1.6, 1.3, 1.0, 0.4]
    vh[25:] = [[3.5, 2.1], [8.5, 6.0], [12.1, 7.6], [10.4, 5.7], [4.0, 2.0]]
    vo = np.zeros((T1, 2))
    vo[9:15, 0] = [0.2, 0.8, 0.9, 0.9, 1.1, 0.9]
    vo[15:25, 0] = [0.4, 0.36, 0.16, 0.0, 0.1, 0.16, 0.07, 0.16, 0.47, 0.17]
    vo[25:] = [[-0.7, 1.2], [-2.7, 0.0], [-0.1, 0.1], [0.1, 0.0], [0.0, 0.0]]
    near = np.ones(T1 + 1, bool)
    r, coupled = _release_of(vh, vo, near, 8)
    assert (coupled[15:23] < 0).all()            # every pair of the lag reads as parting
    assert r == 25
    # the same lag with the toucher turning off at frame 15: released there (moved back to the
    # frame after its slowest pair before, as a hand slows before it lets go)
    vh2 = vh.copy()
    vh2[15:18] = [[0.5, 2.5], [0.2, 4.0], [0.0, 5.0]]
    assert _release_of(vh2, vo, near, 8)[0] in (14, 15)


def test_a_grasp_read_on_the_approach_moves_to_where_the_object_starts_to_follow():
    """(#23, fifth pass; dev_9229) a glove comes in over a bar (its image touching the bar from the
    first frame) at 9-11 px a frame and pulls with no rest before: every pair from the grasp read
    at frame 0 to the first the bar follows (5) has the toucher moving and the bar not following,
    some fast: its approach. A slow press before the object gives (no fast pair) is kept."""
    from physinteract_usd.extract.timing import past_the_approach

    coupled = np.array([-1, -1, -1, -1, -1, 1, 1, 1, 1, 1, 1, 1, -1], np.int8)
    speed = np.array([9.1, 10.9, 3.3, 11.4, 0.8, 1.0, 1.7, 2.2, 2.5, 2.8, 3.3, 3.3, 8.0])
    assert past_the_approach(0, coupled, speed, (5, 11)) == 5
    assert past_the_approach(0, coupled, speed, None) == 0
    slow = np.array([0.5, 0.6, 0.6, 0.7, 0.8, 1.0, 1.7, 2.2, 2.5, 2.8, 3.3, 3.3, 8.0])
    assert past_the_approach(0, coupled, slow, (5, 11)) == 0
    still = coupled.copy()
    still[2] = 0                                              # a rest on the way: not an approach
    assert past_the_approach(0, still, speed, (5, 11)) == 0


def _toucher_scene(hand: np.ndarray, obj: np.ndarray, R: float = 4.0):
    """A one-frame analysis stand-in: the toucher's and the object's masks."""
    return SimpleNamespace(hand=hand[None], obj=obj[None], R=R, T=1, H=hand.shape[0], W=hand.shape[1])


def test_a_ball_touching_an_object_is_a_point_contact_however_long_its_interface():
    """(#23, sixth pass) a plain sphere pressed into a ring or a bar meets it along an arc, which
    the interface span read as a palm. A ball's free outline is one circle whose radius is half
    its extent; a palm's (a flat ellipse with fingers) is not."""
    from physinteract_usd.extract.analysis import disk_mask
    from physinteract_usd.extract.interaction_type import circle_fit, is_ball, toucher_roundness

    # the circle fit recovers a known circle
    t = np.linspace(0, 1.5 * np.pi, 40)
    c, r, rms = circle_fit(np.stack([3 + 7 * np.cos(t), -2 + 7 * np.sin(t)], 1))
    assert np.allclose(c, [3, -2]) and r == pytest.approx(7) and rms < 1e-9
    H = W = 80
    obj = np.zeros((H, W), bool)
    obj[40:, 10:70] = True                                     # the object, below
    ball = disk_mask((H, W), (40, 30), 11.0) & ~obj            # a ball sunk into it, its lower part hidden
    rnd = toucher_roundness(_toucher_scene(ball, obj), 0, np.array([40.0, 40.0]), 0)
    assert rnd is not None and is_ball(rnd)
    yy, xx = np.mgrid[0:H, 0:W]
    palm = (((xx + 0.5 - 40) / 30) ** 2 + ((yy + 0.5 - 35) / 5) ** 2 <= 1) & ~obj
    palm |= (xx >= 62) & (xx < 66) & (yy >= 20) & (yy < 36)   # a finger
    rnd_p = toucher_roundness(_toucher_scene(palm, obj), 0, np.array([40.0, 40.0]), 0)
    assert rnd_p is not None and not is_ball(rnd_p)
    # the rules: the same long interface is a palm's unless the toucher is a ball
    press = {"push_cos": -0.9, "contact_motion_px": 8.0, "interface_span": 0.7}
    assert classify_interaction(press)[0] == "surfaceNonAdherent"
    assert classify_interaction(dict(press, toucher_round=rnd))[0] == "pointNonAdherent"
    assert classify_interaction(dict(press, toucher_round=rnd_p))[0] == "surfaceNonAdherent"


def test_a_toucher_that_arrives_and_presses_on_at_once_rests_for_one_frame():
    """(#23, sixth pass; dev_9301) a sphere comes down onto a stiff sheet (2.2 .. 0.36 px a frame),
    slows to 0.27 px for one frame and presses on the same way: it arrived there (grasp 11, truly
    11), not at the turn at the bottom of the press (18..22, read before)."""
    from physinteract_usd.extract.timing import rest_onset

    sp = np.array([2.2, 1.74, 1.27, 0.87, 0.36, 0.27, 0.38, 0.55, 0.83, 0.69, 0.91, 0.52, 0.33, 0.34,
                   0.02, 0.33, 0.31, 0.82, 0.9, 0.65])
    vh = np.zeros((len(sp), 2))
    vh[:14, 1] = sp[:14]                        # down: the approach, then the press
    vh[14:, 1] = -sp[14:]                       # back up
    assert rest_onset(sp, vh, 0, len(sp) - 1) in (5, 6)
    # one slow frame without an approach before it is no arrival (a pull's jitter)
    calm = np.array([0.6, 0.5, 0.6, 0.5, 0.36, 0.27, 0.38, 0.55, 0.83, 0.69, 0.91, 0.52, 0.6, 0.7])
    vc = np.zeros((len(calm), 2))
    vc[:, 1] = calm
    assert rest_onset(calm, vc, 0, len(calm) - 1) is None
    # a toucher that slows after coming in and settles (tongs, dev_9205: 3.7, 0.12, 0.6, 0.21,
    # 0.19, 0 px) has not arrived at its first slow frame: its rest is where it settles
    st = np.array([3.72, 0.12, 0.60, 0.21, 0.19, 0.01, 0.54, 1.46, 0.9, 1.9, 2.4, 2.2])
    vs = np.zeros((len(st), 2))
    vs[:6, 0] = st[:6]
    vs[6:] = -st[6:, None] * np.array([[0.85, 0.5]])
    assert rest_onset(st, vs, 0, len(st) - 1) == 5


def test_a_collider_pressing_on_into_a_stiff_object_has_not_let_go():
    """(#23, sixth pass; dev_9301) a sphere presses a stiff sheet: the sheet next to it moves at a
    quarter of its speed (pairs 2..5 read apart), then it turns and the sheet springs back with it,
    then it leaves. Moving on into the object it cannot have parted from it: the release is where
    it leaves, not the press. A block knocked away faster than the toucher follows is released."""
    from physinteract_usd.extract.timing import Timing, collider_release, coupling

    T1 = 16
    vh = np.zeros((T1, 2))
    vo = np.zeros((T1, 2))
    vh[0:2, 1] = [0.5, 0.8]
    vo[0:2, 1] = [0.3, 0.5]                     # the object gives at first
    vh[2:6, 1] = [0.8, 0.7, 0.9, 0.5]
    vo[2:6, 1] = [0.1, 0.05, 0.0, 0.05]         # then barely: stiff
    vh[6:8, 1] = [0.1, -0.1]
    vh[8:12, 1] = [-0.8, -0.9, -0.6, -0.4]
    vo[8:12, 1] = [-0.4, -0.5, -0.4, -0.3]      # it springs back with the toucher
    vh[12:, 1] = [-5.0, -6.0, -6.0, -5.0]       # the toucher leaves
    vo[12:, 1] = [-0.2, 0.0, 0.0, 0.0]
    near = np.ones(T1 + 1, bool)
    coupled = coupling(vh, vo, 0.35)
    speed = np.linalg.norm(vh, axis=1)
    tm = Timing(vh, vo, coupled, near, (0, T1), speed, 0, release(coupled, near, 0, speed, vh=vh, vo=vo, eps=0.35))
    # (eighth pass) the press is no parting even before the collider's rule: the toucher carries on
    # its motion into the object (no new motion of its own, the object not running ahead of it)
    assert tm.release is not None and tm.release >= 11
    assert collider_release(tm, np.array([0.0, 1.0])) >= 11
    # the same pairs read as parting (the rule before the eighth pass): the collider's rule undoes it
    tm0 = Timing(vh, vo, coupled, near, (0, T1), speed, 0, 2)
    assert collider_release(tm0, np.array([0.0, 1.0])) >= 11
    # knocked: the object moves on along the push faster than the toucher
    vo2 = vo.copy()
    vo2[2:6, 1] = [3.0, 4.0, 4.0, 3.0]
    c2 = coupling(vh, vo2, 0.35)
    tm2 = Timing(vh, vo2, c2, near, (0, T1), speed, 0, release(c2, near, 0, speed, vh=vh, vo=vo2, eps=0.35))
    assert collider_release(tm2, np.array([0.0, 1.0])) == tm2.release


def test_an_object_carrying_on_its_own_motion_is_not_following_the_toucher():
    """(#23, sixth pass; dev_9331) a plush toy still sliding sideways on the floor (2.1 px a frame)
    as a palm lands on it: its motion next to the contact in the first pairs carries on what it did
    before the palm came, so it is no evidence the palm moves it; from where it turns (the press,
    down) it is. An object at rest before the contact: nothing is discounted."""
    from physinteract_usd.extract.timing import carried_on

    vo = np.array([[2.24, 1.23], [1.61, 0.65], [1.12, 0.17], [-0.07, 0.25], [-0.22, 0.66], [-0.4, 0.6]])
    coupled = np.ones(len(vo), np.int8)
    before = np.array([2.06, 0.93])
    assert carried_on(coupled, vo, 0, before, 0.35) == [0, 1, 2]
    assert carried_on(coupled, vo, 0, np.array([0.1, 0.05]), 0.35) == []
    assert carried_on(coupled, vo, 0, None, 0.35) == []
    # faster than it was moving (1.5x): the toucher drives it
    assert carried_on(coupled, vo * 2.0, 0, before, 0.35) == []


def test_a_flat_face_moved_along_its_normal_into_the_object_is_a_press():
    """(#23, sixth pass; dev_9331, dev_9332) a palm pressing a plush toy from above: its long
    straight interface moves along its own normal into the object, while its body lies beside
    the contact (push_cos near 0, which read as a pull). A long interface pulled out of the
    object (a pinch round a ring, dev_0004) or moved along the face is no press."""
    palm = {"push_cos": -0.13, "into_cos": 0.42, "contact_motion_px": 13.0, "interface_span": 0.59,
            "face_normal_cos": 0.86}
    assert classify_interaction(palm)[0] == "surfaceNonAdherent"
    assert classify_interaction(dict(palm, face_normal_cos=None))[0] == "pointAdherent"     # as before
    assert classify_interaction(dict(palm, into_cos=-0.21))[0] == "pointAdherent"           # pulled out
    assert classify_interaction(dict(palm, face_normal_cos=0.36))[0] == "pointAdherent"     # along the face
    assert classify_interaction(dict(palm, toucher_round=[0.03, 0.97]))[0] != "surfaceNonAdherent"  # a ball


def _still_glove_clip(T=16, W=64, H=48, seed=0, noise=0.01, arrive=3, leave=None):
    """A textured background, an orange disc (the object, visible masks) and a blue glove (not
    skin-coloured) that comes in fast from the right, stops on the object's edge at `arrive` and
    sits still there (until `leave`, then goes back out)."""
    rng = np.random.default_rng(seed)
    bg = np.clip(0.55 + 0.08 * rng.standard_normal((H // 4, W // 4, 3)), 0, 1)
    bg = np.kron(bg, np.ones((4, 4, 1)))[:H, :W].astype(np.float32)
    yy, xx = np.mgrid[0:H, 0:W] + 0.5
    obj = (xx - 24) ** 2 + (yy - 24) ** 2 <= 11 ** 2
    frames, masks, hands = [], [], []
    for k in range(T):
        cx = 44.0 + 8.0 * max(arrive - k, 0) + (8.0 * max(k - leave, 0) if leave is not None else 0.0)
        hand = ((xx - cx) / 1.2) ** 2 + (yy - 24) ** 2 <= 8 ** 2
        f = bg.copy()
        f[obj] = [0.85, 0.55, 0.2]
        f[hand] = [0.15, 0.25, 0.8]
        frames.append(np.clip(f + noise * rng.standard_normal(f.shape), 0, 1).astype(np.float32))
        masks.append(obj & ~hand)
        hands.append(hand)
    return np.stack(frames), np.stack(masks), np.stack(hands), bg


@pytest.mark.parametrize("arrive, leave", [(3, None), (0, 10)])
def test_a_glove_sitting_still_is_not_the_background(arrive, leave):
    """A toucher that sits still on the object for most of the clip is what the per-pixel median
    shows where it sits (#23's dev_9398: a glove on a rope, hand IoU 0.27). The background there is
    what the pixel showed before it arrived (or after it left): the side of the pixel's one lasting
    change that looks like the background elsewhere, not like the toucher."""
    from physinteract_usd.extract.segmentation import step_changes
    from physinteract_usd.render import estimate_background

    frames, masks, hands, bg = _still_glove_clip(arrive=arrive, leave=leave)
    sat = (hands.sum(0) >= 9) & ~masks.any(0)          # where the glove sits for most of the clip
    median = estimate_background(frames, masks, dilate=2)
    assert np.median(np.abs(median - bg).max(-1)[sat]) > 0.3       # the median is the glove there
    seg = ColourMotionSegmenter()(frames, masks, object_colors=np.tile([[0.85, 0.55, 0.2]], (10, 1)))
    assert np.median(np.abs(seg.background - bg).max(-1)[sat]) < 0.03
    iou = (seg.hand & hands).sum() / (seg.hand | hands).sum()
    assert iou > 0.9
    # the change itself: one lasting step from the background to the glove's colour (or back)
    before, after, step, rms = step_changes(frames, ~masks)
    assert np.median(step[sat]) > 0.3 and np.median(rms[sat]) < 0.05
    glove_side = before if leave is not None else after
    assert np.median(np.abs(glove_side[sat] - [0.15, 0.25, 0.8]).max(-1)) < 0.05


def _pairs(*runs):
    """Velocities per frame pair from (count, (vx, vy)) runs."""
    return np.array([v for n, v in runs for _ in range(n)], float)


def test_a_press_pushes_along_the_inward_normal_and_the_object_never_follows_out():
    """A fingertip press: the object next to the contact moves only along the inward normal and
    comes back at most to its rest surface as the toucher withdraws (#23 (d): a finger press typed
    a grasp). Its first main motion may still read as a pull (push_cos -0.1: the withdrawal, or the
    toucher's body beside the contact), which alone types it a grasp."""
    from physinteract_usd.extract.interaction_type import normal_motion

    into = np.array([1.0, 0.0])
    # the toucher comes in (3 pairs), presses 4 pairs (the object gives 0.4 px a pair), withdraws
    # 5 pairs (the object springs back 0.4 px a pair for 4, then rests at its rest surface)
    vh = _pairs((3, (1.0, 0.0)), (4, (0.5, 0.05)), (5, (-1.5, 0.0)), (2, (0.0, 0.0)))
    vo = _pairs((3, (0.0, 0.0)), (4, (0.4, 0.03)), (4, (-0.4, 0.0)), (3, (0.0, 0.0)))
    ev = normal_motion(vh, vo, into, start=0, g=3, end=12)
    assert ev["pressed_in_px"] == pytest.approx(1.6, abs=1e-6)
    assert ev["pulled_out_px"] < 0.05 and ev["tension_px"] < 0.05
    assert ev["press_cos"] > 0.99
    base = {"push_cos": -0.1, "contact_motion_px": 3.0, "interface_span": 0.2, "approach_cos": 0.5,
            "approach_speed_px": 1.0, "contact_frames": 9, "coupled_share": 0.6}
    assert classify_interaction(base)[0] == "pointAdherent"          # the evidence before: a grasp
    assert classify_interaction({**base, **ev})[0] == "pointNonAdherent"
    # a grasp dragging the contact region along the surface with the toucher is no press
    drag = normal_motion(_pairs((6, (0.1, 1.0))), _pairs((6, (0.05, 0.7))), into, start=0, g=0, end=6)
    assert drag["press_cos"] < 0.2
    assert classify_interaction({**base, **drag})[0] == "pointAdherent"
    # an object pressed in and overshooting out past its rest surface while the toucher withdraws
    # (a rebound, not held): still no tension to speak of
    over = normal_motion(vh, _pairs((3, (0.0, 0.0)), (4, (0.4, 0.0)), (5, (-0.4, 0.0)), (2, (0.0, 0.0))),
                         into, start=0, g=3, end=12)
    assert over["pulled_out_px"] == pytest.approx(0.4, abs=1e-6) and over["tension_px"] < 0.5


def test_a_grasp_holds_the_object_as_the_toucher_moves_away_from_the_surface():
    """A grasp: the object follows the toucher out past its rest surface (tension), which a palm or
    a board cannot do, however long and straight the interface and however much the motion runs
    along its normal (#23 (d): a glove typed a surface press)."""
    from physinteract_usd.extract.interaction_type import normal_motion

    into = np.array([0.0, -1.0])
    # the glove comes in and rests (4 pairs), then moves out 1 px a pair, the object following at 0.6
    vh = _pairs((2, (0.0, -1.0)), (2, (0.0, 0.0)), (6, (0.0, 1.0)))
    vo = _pairs((4, (0.0, 0.0)), (6, (0.0, 0.6)))
    ev = normal_motion(vh, vo, into, start=0, g=3, end=10)
    assert ev["tension_px"] == pytest.approx(3.6, abs=1e-6) and ev["pulled_out_px"] == pytest.approx(3.6, abs=1e-6)
    assert ev["press_cos"] < -0.99 and ev["pressed_in_px"] == 0.0
    # a long straight face moved along its normal: the face rule alone says a press
    base = {"push_cos": 0.3, "contact_motion_px": 6.0, "interface_span": 0.6, "face_normal_cos": 0.95,
            "into_cos": 0.4, "approach_cos": 0.2, "approach_speed_px": 1.0, "contact_frames": 7,
            "coupled_share": 0.9}
    assert classify_interaction(base)[0] == "surfaceNonAdherent"
    assert classify_interaction({**base, **ev})[0] == "pointAdherent"
    # the same toucher moving out with the object staying at its rest surface holds nothing
    free = normal_motion(vh, np.zeros_like(vo), into, start=0, g=3, end=10)
    assert free["tension_px"] == 0.0
    assert classify_interaction({**base, **free})[0] == "surfaceNonAdherent"



def test_the_press_rule_needs_a_surface_normal_and_a_toucher_that_moved_out():
    """The inward normal is the silhouette's signed-distance gradient: across a bar at its side,
    along it at its end, none on its ridge (under a hand over a thin rope "inward" is both ways).
    And a toucher that only pushes (never moves out) leaves the press untested: a grasp that drags
    the object into itself looks the same until it pulls (dev_9372: a glove dragging a rope)."""
    from physinteract_usd.extract.interaction_type import inward_normal, normal_motion

    yy, xx = np.mgrid[0:40, 0:60]
    bar = (np.abs(yy + 0.5 - 20.5) <= 3.5) & (xx > 10) & (xx < 50)
    assert inward_normal(bar, (30.5, 20.5)) is None                       # the ridge
    assert np.allclose(inward_normal(bar, (30.5, 16.5)), [0.0, 1.0], atol=0.05)   # its upper side
    assert np.allclose(inward_normal(bar, (30.5, 14.5)), [0.0, 1.0], atol=0.05)   # just off it
    assert np.allclose(inward_normal(bar, (9.5, 20.5)), [1.0, 0.0], atol=0.05)    # its left end
    into = np.array([1.0, 0.0])
    push = normal_motion(_pairs((8, (1.0, 0.0))), _pairs((8, (0.8, 0.0))), into, start=0, g=0, end=8)
    assert push["press_cos"] > 0.99 and push["withdrawn_px"] == 0.0
    base = {"push_cos": 0.5, "contact_motion_px": 8.0, "interface_span": 0.1, "approach_cos": 0.5,
            "approach_speed_px": 1.0, "contact_frames": 8, "coupled_share": 0.9}
    assert classify_interaction({**base, **push})[0] == "pointAdherent"


def test_an_object_moving_on_while_the_toucher_rests_is_not_released_until_the_toucher_moves_off():
    """(#23, eighth pass; the fresh dev captures' commonest failure: a release 3-5 frames early) a
    hand pulls a ball (the object next to it following at 0.9 of its speed), then holds still for
    four frames while the held ball rolls on (2.5 px a frame, slowing: the elastic object about a
    still hold), then moves off fast (pair 14) while the ball does not follow. A still toucher
    says nothing about the hold: the release is frame 14, where the toucher's own motion is not
    followed, and the confidence says the object moved alone before it. An object that stays
    still while the hand moves off is released the same."""
    from physinteract_usd.extract.timing import Timing, moved_alone, timing_confidence

    T1 = 18
    vh = np.zeros((T1, 2))
    vh[2:10, 0] = [0.8, 1.6, 2.2, 2.4, 2.4, 2.2, 1.4, 0.9]      # the pull
    vh[10:14] = [[0.1, 0.0], [0.2, 0.05], [0.05, 0.1], [0.1, 0.0]]  # the hand holds still
    vh[14:, 1] = [-4.0, -9.0, -12.0, -8.0]                       # and moves off (up), letting go
    vo = 0.9 * vh.copy()
    vo[10:14] = [[2.5, 0.4], [2.0, 0.6], [1.4, 0.5], [1.0, 0.3]]  # the ball rolls on by itself
    vo[14:] = [[0.3, 0.2], [0.1, 0.0], [0.0, 0.1], [0.0, 0.0]]   # and stays when the hand lifts off
    near = np.ones(T1 + 1, bool)
    r, coupled = _release_of(vh, vo, near, 2)
    assert (coupled[10:14] < 0).any()       # the per-pair coupling sees the ball moving alone
    assert r == 14
    # the same pull with no rolling: the same release
    vo2 = vo.copy()
    vo2[10:14] = 0.9 * vh[10:14]
    assert _release_of(vh, vo2, near, 2)[0] == 14
    # the confidence states the disagreement: the object moved on its own from pair 10
    t = Timing(vh, vo, coupled, near, (0, T1), np.linalg.norm(vh, axis=1), 2, r)
    assert moved_alone(t, 0.35)[:2] == (10, 13)
    ev, notes = {"timing_source": {}}, []
    timing_confidence(t, 0.35, ev, notes)
    assert any("moves on its own" in n and "frames 10..14" in n and "--release-frame" in n for n in notes)
    assert ev["timing_confidence"] in ("medium", "low")
    # the object following the still hand (no motion of its own): nothing to state
    t2 = Timing(vh, vo2, _release_of(vh, vo2, near, 2)[1], near, (0, T1), np.linalg.norm(vh, axis=1), 2, 14)
    assert moved_alone(t2, 0.35) is None


def test_a_grasp_is_where_the_object_starts_to_follow_just_after_the_toucher_starts():
    """(#23, eighth pass) the toucher's onset against its noise floor comes at frame 5; the object
    next to the contact follows visibly (>= eps, two pairs running) from pair 6 (a smooth start
    moves it by less than eps in the first pair): the grasp is frame 6, the last frame before the
    object moves. An object that follows only 4 pairs later (it was not the toucher's start), or
    one that never visibly follows (a stiff object, hidden), leaves the toucher's onset."""
    from physinteract_usd.extract.timing import coupling, following_onset

    T1 = 16
    vh = np.zeros((T1, 2))
    vh[5:12, 0] = [0.5, 1.2, 2.0, 2.4, 2.0, 1.2, 0.5]
    vo = 0.8 * vh.copy()
    vo[5] = [0.2, 0.0]                       # under eps: not yet visible
    c = coupling(vh, vo, 0.35)
    assert following_onset(5, c, vo, 0.35) == 6
    assert following_onset(6, c, vo, 0.35) == 6       # already there: unchanged
    late = np.zeros((T1, 2))
    late[9:12, 0] = [2.0, 1.2, 0.5]
    assert following_onset(5, coupling(vh, late, 0.35), late, 0.35) == 5
    stiff = 0.1 * vh                          # follows, but never by eps
    assert following_onset(5, coupling(vh, stiff, 0.35), stiff, 0.35) == 5


def _pull(T1=24, g=6, r=16, dwell=3, share=0.8, hold=0, off=(0.0, -6.0), seed=0, noise=0.08):
    """Velocities (frame pairs) of a toucher that comes in, rests `dwell` pairs, pulls smoothly
    from frame g (the last frame at rest) to r - `hold` and holds still to r, then moves off
    (`off` px a frame) while the object next to the contact springs back; flow noise `noise` px."""
    rng = np.random.default_rng(seed)
    vh = np.zeros((T1, 2))
    vh[: g - dwell] = [3.0, 1.0]                               # the approach
    n = r - hold - g
    s = np.arange(n + 1) / n
    pos = 3 * s ** 2 - 2 * s ** 3                              # a smooth start and stop
    vh[g:r - hold, 0] = 30.0 * np.diff(pos)
    vh[r:] = off
    vo = share * vh
    vo[: g - dwell] = 0.0                                      # the object rests while it comes in
    vo[r:] = [-2.0, 0.5]                                       # let go: it springs back
    vh += rng.normal(0, noise, vh.shape)
    vo += rng.normal(0, noise, vo.shape)
    return vh, vo


def test_the_held_window_is_where_the_object_moves_with_the_toucher():
    """(#23, ninth pass) one likelihood model for every toucher: per frame pair, "the object next to
    the contact moves with the toucher at its share" against "it moves by itself"; the grasp is
    where the run of most evidence starts (a toucher coming in or resting on the object is no
    hold yet), the release the first pair after it in which the toucher moves off unfollowed. The
    truth's frames are recovered for pulls with and without a rest, a still hold before letting go,
    any share, and under noise; held to the end is None."""
    from physinteract_usd.extract.timing import held_window

    near = np.ones(25, bool)
    for seed in range(5):
        for dwell, hold, share in [(3, 0, 0.8), (1, 0, 0.4), (3, 4, 0.8), (2, 3, 0.3)]:
            vh, vo = _pull(dwell=dwell, hold=hold, share=share, seed=seed)
            g, r, _ = held_window(vh, vo, near)
            assert abs(g - 6) <= 1 and r == 16, (seed, dwell, hold, share, g, r)
    # held to the end: the toucher never moves off
    vh, vo = _pull(r=24)
    assert held_window(vh, vo, near)[1] is None
    # nothing follows the toucher: no window
    vh, vo = _pull()
    assert held_window(vh, np.zeros_like(vo), near) is None


def test_the_held_window_ignores_the_object_moving_by_a_still_toucher_and_a_lag_behind_a_pull():
    """A still toucher says nothing about the hold (the held ball rolls on under a still hand:
    released where the hand moves off, pair 16, not where the ball moved alone); an object's flow
    lagging behind a toucher that carries on pulling is no release (letting go is a motion of the
    toucher's own); a toucher that leaves the object's image ends the hold there."""
    from physinteract_usd.extract.timing import held_window

    near = np.ones(25, bool)
    vh, vo = _pull(hold=4)
    vo[12:16] = [[2.5, 0.4], [2.0, 0.6], [1.4, 0.5], [1.0, 0.3]]   # rolls on while the hand holds still
    assert held_window(vh, vo, near)[1] == 16
    vh, vo = _pull()
    vo[11:16] *= 0.05                                               # the flow next to it lags the pull
    assert held_window(vh, vo, near)[1] == 16
    vh, vo = _pull()
    vh[16:] = 0.0                                                   # the toucher rests ...
    vo[16:] = 0.0
    near[19:] = False                                               # ... and is gone from frame 19
    assert held_window(vh, vo, near)[1] == 19


def test_the_held_window_starts_after_the_toucher_arrives_and_at_the_onset_of_its_motion():
    """A palm comes down onto a block that is still settling under gravity (its flow next to the
    palm points the palm's way: it reads as following), rests two pairs on it and presses from
    frame 13: the pairs before the rest were the approach, and the grasp is 13, not 9. A slow pull
    whose first pairs are under the noise level (0.15-0.3 px a frame, the object's following not yet
    visible) starts where its speed ramp starts (at most 3 pairs back), not where the following
    shows."""
    from physinteract_usd.extract.timing import held_window

    T1 = 30
    vh = np.full((T1, 2), np.nan)
    vo = np.full((T1, 2), np.nan)
    near = np.zeros(T1 + 1, bool)
    near[6:] = True
    vh[6:11] = [[0.0, 7.4], [0.0, 6.4], [0.0, 5.1], [0.0, 3.3], [0.0, 1.1]]     # coming down
    vo[6:11] = [[0.0, 1.2], [0.0, 0.1], [0.0, 0.8], [0.0, 1.0], [0.0, 0.7]]     # the block settling
    vh[11:13] = vo[11:13] = [[0.0, 0.02], [0.02, -0.03]]                         # at rest on it
    vh[13:22] = 0.0
    vh[13:22, 1] = [0.35, 0.7, 0.95, 1.1, 1.3, 1.5, 1.1, 0.9, 0.4]                # the press
    vo[13:22] = 0.8 * vh[13:22]
    vh[22:] = [0.0, -8.0]                                                       # lifted off
    vo[22:] = [0.0, -0.3]
    g, r, _ = held_window(vh, vo, near)
    assert g == 13 and r == 22
    # the slow pull: 0.15, 0.2, 0.3 px before the object's following shows (pair 17)
    vh2 = np.zeros((T1, 2))
    vo2 = np.zeros((T1, 2))
    vh2[:14] = [0.05, -0.03]
    vh2[14:25, 0] = [0.15, 0.2, 0.3, 0.8, 1.2, 1.4, 1.4, 1.2, 0.9, 0.6, 0.4]
    vo2[17:25] = 0.8 * vh2[17:25]
    vh2[25:] = [0.0, 6.0]
    vo2[25:] = [-1.0, 0.0]
    g, r, _ = held_window(vh2, vo2, np.ones(T1 + 1, bool))
    assert g == 14 and r == 25


def test_a_collider_touches_until_it_is_back_out_where_it_first_touched():
    """A stick presses a block 9 px in and withdraws over four pairs while the block springs back
    slower (it reads as left behind from the withdrawal's first pair); the stick is back where it
    first touched at frame 19, then moves off: the release is 19, not the withdrawal's start. A
    toucher that never comes back (a knocked object) keeps the held window's release; a toucher
    that leaves the object's image first is released there."""
    from physinteract_usd.extract.timing import collider_back_out

    T1 = 26
    vh = np.zeros((T1, 2))
    vh[8:14, 1] = [-0.5, -0.7, -2.4, -3.0, -1.8, -0.8]        # in: 9.2 px
    vh[15:19, 1] = [2.0, 3.1, 2.9, 1.4]                        # back out: 9.4 px
    vh[19:, 0] = 6.0                                           # and away
    near = np.ones(T1 + 1, bool)
    assert collider_back_out(8, 15, vh, near) == 19
    knock = vh.copy()
    knock[15:] = [4.0, 0.0]                                    # it goes on sideways
    assert collider_back_out(8, 15, knock, near) == 15
    near[17:] = False
    assert collider_back_out(8, 15, vh, near) == 17


def test_the_grasp_at_the_foot_of_the_toucher_s_speed_ramp():
    """timing.ramp_start (#23, tenth pass): a hand at rest on the object (tracker noise 0.03 px a
    frame, random directions) starts to pull at frame 4 with a constant acceleration (0.2 px per
    frame^2), so its speed per pair is 0.1, 0.3, 0.5, ... from pair 4: an onset seen at the noise
    level 0.35 (pair 6) is 2 frames late; the ramp's foot gives frame 4, the truth. A grasp whose
    pair is at rest, or a toucher not seen before it, stays."""
    from physinteract_usd.extract.timing import Timing, ramp_start

    rng = np.random.default_rng(3)
    T = 14
    x = np.array([0.0 if t <= 4 else 0.5 * 0.2 * (t - 4) ** 2 for t in range(T)])
    vh = np.zeros((T - 1, 2))
    vh[:, 0] = np.diff(x)
    ang = rng.uniform(0, 2 * np.pi, T - 1)
    vh += 0.03 * np.stack([np.cos(ang), np.sin(ang)], 1)
    vh[0] = [3.0, 0.0]                         # the arrival
    sp = np.linalg.norm(vh, axis=1)
    near = np.ones(T - 1, bool)
    tm = Timing(vh, np.zeros_like(vh), np.zeros(T - 1), near, (0, T - 1), sp, 6, None, 0.0)
    assert sp[6] > 0.35 and sp[5] < 0.35
    assert ramp_start(tm, 0.35) == 4
    tm.grasp = 3                               # a grasp at rest stays
    assert ramp_start(tm, 0.35) == 3
    near2 = near.copy()
    near2[:6] = False                          # the toucher not seen at the object before pair 6
    tm2 = Timing(vh, np.zeros_like(vh), np.zeros(T - 1), near2, (6, T - 1), sp, 6, None, 0.0)
    assert ramp_start(tm2, 0.35) == 6


def test_a_still_speck_off_the_floor_holds_nothing_up_a_hook_region_does():
    """resting_base (#23: dev_0204, 0206, 0218): a block on a floor still at one corner of its
    bottom and at a 4-particle speck on its top (the tracking's noise, a hand passing by) rests on
    the floor: a hold of 4 particles of 3549 (0.017 of V^(2/3)) cannot carry its weight; a hook's
    region on its top of 30 particles (0.13, as the world suite's held objects read, 0.11-0.8)
    holds it, with or without the still corner; a speck alone leaves (a) and (c) to decide."""
    from physinteract_usd.extract.supports import resting_base

    h = 0.01
    block = _lattice((-0.1, 0.0, -0.06), (0.1, 0.12, 0.06), h)
    x, y, z = block.T
    corner = np.flatnonzero((x <= -0.07 + 1e-9) & (y <= 0.01 + 1e-9) & (z <= -0.03 + 1e-9))
    top = np.flatnonzero(y >= 0.12 - 1e-9)
    speck = top[np.argsort(np.linalg.norm(block[top] - [0.05, 0.12, 0.03], axis=1))[:4]]
    hook = top[np.argsort(np.linalg.norm(block[top] - [0.0, 0.12, 0.0], axis=1))[:30]]
    assert resting_base(block, h, [corner]) is not None
    assert resting_base(block, h, [corner, speck]) is not None
    assert resting_base(block, h, [speck]) is not None
    assert resting_base(block, h, [corner, hook]) is None
    assert resting_base(block, h, [hook]) is None
    # the share is the lever: at 0 every region counts, as before
    assert resting_base(block, h, [corner, speck], hold_share=0.0) is None


def test_the_image_windows_do_not_shrink_with_a_finer_particle_cap():
    """`window_radius`: 2.5 particle spacings, but no finer than the spacing at WINDOW_PARTICLES: the same object
    (volume P h^3 fixed) sampled at 1500, 12000 and 96000 particles keeps one window; at 190 particles (twice the
    spacing of 1500) the window is twice as wide; the quarter-object cap and the 4 px floor still bound it."""
    from physinteract_usd.extract.analysis import WINDOW_PARTICLES, window_radius

    size = 400.0
    h1500 = 8.0                                   # px at WINDOW_PARTICLES
    r = [window_radius(h1500 * (WINDOW_PARTICLES / P) ** (1 / 3), P, size) for P in (1500, 12000, 96000)]
    assert r[0] == pytest.approx(20.0) and r[1] == pytest.approx(r[0]) and r[2] == pytest.approx(r[0])
    assert window_radius(2 * h1500, WINDOW_PARTICLES // 8, size) == pytest.approx(40.0)
    assert window_radius(60.0, 100, size) == pytest.approx(0.25 * size + 4.0)
    assert window_radius(0.5, 100, size) == 4.0
