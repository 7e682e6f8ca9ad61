"""(#23, fifteenth pass) A collider's release is not read against its own departure: a collider comes
into contact moving into the object, so a "push" (the first main motion) that points against its
approach is its leaving, and its leaving pairs part it from the object (dev_0322, dev_0307, dev_0149)."""
import numpy as np

from physinteract_usd.extract.timing import Timing, approach, collider_release, coupling, release


def _palm(seen_coming_in=True):
    """A palm comes down onto a stiff object at 5 px a frame (pairs 0..3), rests on it pressing a
    few tenths of a pixel (4..12: the object next to it gives 0.1 px), then lifts off back the way
    it came at 5 px a frame (13..16) while the object stays; it is out of contact from frame 17."""
    T1 = 20
    vh = np.zeros((T1, 2))
    vo = np.zeros((T1, 2))
    vh[0:4, 1] = 5.0                        # the approach, down into the object
    vh[4:13, 1] = 0.2                       # the press
    vo[4:13, 1] = 0.1
    vh[13:17, 1] = -5.0                     # the departure, back up; the object stays
    near = np.zeros(T1 + 1, bool)
    near[(0 if seen_coming_in else 4):17] = True
    c = coupling(vh, vo, 0.35)
    speed = np.linalg.norm(vh, axis=1)
    g = 4
    r = release(c, near, g, speed, vh=vh, vo=vo, eps=0.35)
    p0 = 0 if seen_coming_in else 4
    return Timing(vh, vo, c, near, (p0, 16), speed, g, r)


def test_the_release_of_a_resting_palm_is_its_lift_off():
    tm = _palm()
    assert tm.release == 13                                   # the motion rule reads the lift-off
    assert np.allclose(approach(tm) / np.linalg.norm(approach(tm)), [0.0, 1.0])
    # its first main motion read as far as a late release is the departure itself (up): a push
    # against the approach is no pressing on, the lift-off still parts them (before: 17, the
    # frame it was no longer seen touching; on the world suite: held to the end)
    assert collider_release(tm, np.array([0.0, -1.0])) == 13
    # a push read along the approach: the same
    assert collider_release(tm, np.array([0.0, 1.0])) == 13


def test_without_a_seen_approach_the_push_is_the_first_main_motion():
    # never seen coming in (touching from the grasp on): no approach, the rule as before (the
    # departure read as a push into the object is not parting: the end of the contact)
    tm = _palm(seen_coming_in=False)
    assert approach(tm) is None
    assert collider_release(tm, np.array([0.0, -1.0])) == 17
    assert collider_release(tm, np.array([0.0, 1.0])) == 13


def test_a_fingertip_back_out_past_where_it_touched_presses_nothing():
    """(#23, 28th session, dev_0543) A fingertip presses into the object (pairs 2..5), comes back out with the object
    springing back after it (6..10), moves off fast while the object stays (11: the release), and on its way out makes
    one pair down and aside (13) before it is out of contact (14). That pair points along the push, but the toucher
    is already farther out than where it first touched: it presses nothing, and must not hide the parting at 11 (it
    did: read as pressing on, the parting's window lost its majority and the release went to 14, the contact's end)."""
    T1 = 16
    vh = np.zeros((T1, 2))
    vo = np.zeros((T1, 2))
    vh[2:6] = [0.0, 1.5]
    vo[2:6] = [0.0, 0.5]
    vh[6:11] = [0.0, -1.5]
    vo[6:11] = [0.0, -0.6]
    vh[11] = [0.0, -3.0]
    vh[12] = [0.0, -1.0]
    vo[12] = [0.0, -0.3]
    vh[13] = [1.0, 1.4]
    near = np.zeros(T1 + 1, bool)
    near[0:14] = True
    c = coupling(vh, vo, 0.35)
    assert c[11] < 0 and c[13] < 0
    speed = np.linalg.norm(vh, axis=1)
    g = 2
    r = release(c, near, g, speed, vh=vh, vo=vo, eps=0.35)
    assert r is not None and 9 <= r <= 11
    tm = Timing(vh, vo, c, near, (0, 13), speed, g, r)
    assert collider_release(tm, np.array([0.0, 1.0])) == r


def test_a_collider_acts_from_when_the_object_gives_aside():
    """(#23, 28th session, dev_0545) A fingertip rests on a rope lying on its floor (pairs 11..12), then presses down
    and aside (13..): the rope next to it is squeezed out sideways, 60-70 deg off the fingertip's way, so `coupling`
    reads those pairs decoupled and the grasp went to the first coupled pair (15, truly 12). The object giving within
    90 deg of the push is the press's start; an object moving against the toucher, or a still one, is not."""
    from physinteract_usd.extract.timing import collider_start, gives

    T1 = 18
    vh = np.zeros((T1, 2))
    vo = np.zeros((T1, 2))
    vh[13:16] = [0.7, 0.9]
    vo[13:15] = [0.5, -0.05]
    vo[15] = [0.7, 0.8]
    near = np.ones(T1 + 1, bool)
    c = coupling(vh, vo, 0.35)
    assert c[13] < 0 and c[14] < 0 and c[15] > 0
    speed = np.linalg.norm(vh, axis=1)
    tm = Timing(vh, vo, c, near, (0, T1 - 1), speed, 12, None)
    assert collider_start(tm) == 13
    assert gives(np.array([0.7, 0.9]), np.array([0.5, -0.05]))
    assert not gives(np.array([0.7, 0.9]), np.array([-0.5, -0.3]))      # against the push
    assert not gives(np.array([0.7, 0.9]), np.array([0.1, 0.0]))        # the object barely moves
    assert not gives(np.array([0.1, 0.1]), np.array([0.5, 0.0]))        # the toucher at rest
    vo2 = vo.copy()
    vo2[13:15] = [-0.5, 0.05]                                          # squeezed the other way: not the press
    tm2 = Timing(vh, vo2, coupling(vh, vo2, 0.35), near, (0, T1 - 1), speed, 12, None)
    assert collider_start(tm2) == 15


def test_a_collider_arriving_in_motion_acts_from_the_first_pair_the_object_follows():
    """(#23, 33rd session, dev_0539) A sphere comes in decelerating (3.5 ... 0.7 px a frame) and presses on without a
    stop (0.46, 0.63, 0.88 ...); the object next to the contact follows its way from the arrival's pair at 0.25 px
    (below eps), then at 0.38, 0.57 ...: the grasp is the first pair it follows (16), not the first two above eps (17,
    where the rules had put it). Not back over a pair it does not follow, nor more than `back` pairs, nor where the
    toucher is not at the contact."""
    from physinteract_usd.extract.timing import collider_start

    vh = np.array([[-3.44, -0.65], [-2.88, -0.35], [-2.31, -0.38], [-1.47, -0.1], [-0.89, 0.01], [-0.52, -0.46],
                   [-0.46, -0.05], [-0.55, 0.3], [-0.87, 0.08], [-0.7, 0.37], [-0.96, 0.0], [-0.87, 0.02]])
    vo = np.array([[0.18, 0.15], [0.52, 0.03], [0.18, -0.29], [-0.04, 0.0], [-0.17, 0.14], [-0.09, -0.05],
                   [-0.22, -0.11], [-0.36, 0.12], [-0.56, 0.08], [-0.53, 0.1], [-0.69, 0.04], [-0.69, 0.0]])
    pad = 10                                   # frames 10.. as on the capture
    vh = np.vstack([np.zeros((pad, 2)), vh])
    vo = np.vstack([np.zeros((pad, 2)), vo])
    T1 = len(vh)
    c = coupling(vh, vo, 0.35)
    assert c[15] < 0 and c[16] > 0 and c[17] > 0
    speed = np.linalg.norm(vh, axis=1)
    near = np.ones(T1 + 1, bool)
    assert collider_start(Timing(vh, vo, c, near, (9, T1 - 1), speed, 17, None)) == 16
    assert collider_start(Timing(vh, vo, c, near, (9, T1 - 1), speed, 17, None), back=0) == 17
    off = near.copy()
    off[16] = False                            # the toucher not at the contact there: not walked over
    assert collider_start(Timing(vh, vo, c, off, (9, T1 - 1), speed, 17, None)) == 17
    c2 = c.copy()
    c2[16] = -1                                # the object not following there: not walked over
    assert collider_start(Timing(vh, vo, c2, near, (9, T1 - 1), speed, 17, None)) == 17


def test_a_hand_faintly_seen_at_the_contact_for_two_frames_has_not_let_go():
    """(#23, 33rd session, dev_0530) A pinch pulls a ring out and back; in frames 19-20 its hand shows 2 px at the
    contact (under the touching's 3 px floor), then touches again to 25: the gap is bridged and the contact period runs
    on past it. Not a gap where the hand is gone (0 px), nor one longer than FAINT_GAP frames."""
    from physinteract_usd.extract.timing import FAINT_GAP, bridge_faint, contact_period

    touch = np.array([0, 0, 0, 0, 11, 9, 9, 8, 9, 7, 6, 8, 6, 5, 3, 3, 9, 8, 5, 2, 2, 7, 6, 8, 7, 7, 0, 0, 0])
    near = touch >= 3
    assert contact_period(near) == (4, 18)
    bridged = bridge_faint(near, touch)
    assert bridged[19] and bridged[20] and contact_period(bridged) == (4, 25)
    gone = touch.copy()
    gone[20] = 0                                            # the hand gone from the contact in one frame of the gap
    assert contact_period(bridge_faint(gone >= 3, gone)) == (4, 18)
    long_gap = touch.copy()
    long_gap[19:19 + FAINT_GAP + 1] = 2                     # longer than FAINT_GAP
    assert not bridge_faint(long_gap >= 3, long_gap)[19]
    assert np.array_equal(bridge_faint(near, None), near)  # no counts: unchanged
    assert not bridge_faint(near, touch)[26]               # the end of the clip is not a gap
