"""The floor's test (c) reads the toucher only where it acts on the object (#23, the sixteenth
extraction pass: dev_0390 and dev_0402 were given supports on a floor): known answers on lattices."""

import numpy as np

from physinteract_usd.extract.supports import lowest_toucher_y, resting_base, toucher_acting


def _lattice(lo, hi, h):
    ax = [np.arange(a, b + 1e-9, h) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)


H = 0.005
BLOCK = _lattice((-0.05, 0.0, -0.025), (0.05, 0.04, 0.025), H)      # a 10 x 4 x 5 cm block, its base at y = 0


def _low(tr, radius, itype, x0=BLOCK, grasp=0, release=None):
    act = toucher_acting(tr, itype, radius, x0, H, grasp, release)
    return lowest_toucher_y(tr, radius, itype, float(x0[:, 1].min()), act)


def test_a_fingertip_that_leaves_down_and_away_does_not_hold_a_block_up():
    """A fingertip (radius 6 mm) comes in level, pokes the block's side at mid-height, then leaves
    down and away, its centre 2.5 cm under the base 4 cm clear of the block (dev_0390's glove
    finger after its release): nothing still on the block, it stands: a floor. Read over every
    frame (the old rule), the leaving's low point called it held."""
    r = 0.006
    x = [-0.05 - r - 0.03, -0.05 - r - 0.01, -0.05 - r + 0.002, -0.05 - r + 0.004, -0.05 - r - 0.02, -0.05 - r - 0.04]
    y = [0.02, 0.02, 0.02, 0.02, -0.01, -0.025]
    tr = np.stack([x, y, np.zeros(6)], 1)
    act = toucher_acting(tr, "pointNonAdherent", r, BLOCK, H, 0, None)
    assert act.tolist() == [False, False, True, True, False, False]
    low = _low(tr, r, "pointNonAdherent")
    assert abs(low - 0.02) < 1e-12
    assert resting_base(BLOCK, H, [], low) is not None
    assert resting_base(BLOCK, H, [], lowest_toucher_y(tr, r, "pointNonAdherent", 0.0)) is None   # every frame: held


def test_a_sphere_that_never_reaches_the_object_holds_nothing_up():
    """A sphere put 1.5 cm clear under the block's base that never moves (dev_0402's, placed on the
    far side of a contact read on the underside): it touches nothing, so (c) has nothing to read."""
    r = 0.016
    tr = np.tile([0.0, -0.015 - r, 0.0], (8, 1))
    assert not toucher_acting(tr, "pointNonAdherent", r, BLOCK, H, 0, None).any()
    assert _low(tr, r, "pointNonAdherent") is None
    assert resting_base(BLOCK, H, [], None) is not None
    assert resting_base(BLOCK, H, [], lowest_toucher_y(tr, r, "pointNonAdherent", 0.0)) is None   # every frame: held


def test_a_strap_on_its_anchors_pushed_down_past_them_stays_held():
    """Recall: a strap anchored flat at both ends (still there, its underside one piece on the
    anchors' plane, which alone reads as lying on a floor), pushed down in the middle by a fingertip
    whose centre goes 1 cm under the strap's base while touching it (dev_0142's class): held."""
    strap = _lattice((-0.15, 0.0, -0.01), (0.15, 0.01, 0.01), H)
    ends = [np.flatnonzero(strap[:, 0] <= -0.12), np.flatnonzero(strap[:, 0] >= 0.12)]
    r = 0.008
    y = [0.04, 0.02, 0.01 + r, 0.01, 0.0, -0.01, 0.0, 0.03]
    tr = np.stack([np.zeros(8), y, np.zeros(8)], 1)
    act = toucher_acting(tr, "pointNonAdherent", r, strap, H, 0, None)
    assert act[2:7].all() and not act[0]
    low = _low(tr, r, "pointNonAdherent", x0=strap)
    assert abs(low - (-0.01 - r)) < 1e-12
    assert resting_base(strap, H, ends, None) is not None        # the ends alone read as a floor
    assert resting_base(strap, H, ends, low) is None              # pushed past them: held


def test_a_grasp_counts_from_its_grasp_to_its_release():
    """A grasp acts from its grasp frame to its release: a hand below the base before it takes
    hold does not count (a floor), one pulling the block under its base while holding it does
    (held)."""
    y = np.array([-0.03, -0.03, 0.02, 0.025, 0.03, 0.03])        # under the base before the grasp at 2
    tr = np.stack([np.zeros(6), y, np.zeros(6)], 1)
    low = _low(tr, 0.0, "pointAdherent", grasp=2, release=4)
    assert abs(low - 0.02) < 1e-12 and resting_base(BLOCK, H, [], low) is not None
    assert resting_base(BLOCK, H, [], lowest_toucher_y(tr, 0.0, "pointAdherent", 0.0)) is None   # every frame: held
    pulled = tr.copy()
    pulled[3, 1] = -0.02                                           # held and pulled 2 cm under the base
    low = _low(pulled, 0.0, "pointAdherent", grasp=2, release=4)
    assert abs(low + 0.02) < 1e-12 and resting_base(BLOCK, H, [], low) is None
    assert toucher_acting(tr, "pointAdherent", 0.0, BLOCK, H, 2, None)[2:].all()   # never released: to the end
    assert not toucher_acting(tr, "pointAdherent", 0.0, BLOCK, H, 2, 3)[4:].any()


def test_a_grasp_read_below_the_base_only_by_its_scale_still_stands_on_its_floor():
    """A pinch lifts the block's top edge 3 cm; the hand's apparent scale misread (a tool leaving the
    frame: dev_0510) puts the path 2 cm under the base at its end. At the grasp depth the path
    rises: the test (c) takes the higher reading and the block rests on a floor; where both
    readings go under the base (a grasp pulling the object down), it is held."""
    from physinteract_usd.extract.supports import toucher_low

    T = 6
    flat = np.zeros((T, 3))
    flat[:, 1] = 0.04 + np.linspace(0, 0.03, T)
    scaled = flat.copy()
    scaled[:, 1] = 0.04 - np.linspace(0, 0.06, T)
    act = toucher_acting(scaled, "pointAdherent", 0.0, BLOCK, H, 1, 4)
    ev = {}
    low = toucher_low(scaled, flat, 0.0, "pointAdherent", 0.0, act, ev)
    assert abs(low - flat[1, 1]) < 1e-12 and ev["toucher_low_m"]["scaled"] < -0.005
    assert resting_base(BLOCK, H, [], low) is not None
    assert resting_base(BLOCK, H, [], lowest_toucher_y(scaled, 0.0, "pointAdherent", 0.0, act)) is None
    down = flat.copy()
    down[:, 1] = 0.04 - np.linspace(0, 0.07, T)
    assert resting_base(BLOCK, H, [], toucher_low(scaled, down, 0.0, "pointAdherent", 0.0, act)) is None
    assert toucher_low(scaled, None, 0.0, "pointAdherent", 0.0, act) == lowest_toucher_y(scaled, 0.0, "pointAdherent", 0.0, act)
