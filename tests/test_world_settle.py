"""The world generator's truth settled before frame 0 (`draw_world(..., {"settle": True})`, #23): by default a world
object starts at its unsettled rest and sags before the toucher arrives (16 of 32 CPU dev captures by over 5% of their
size; dev_0534's glove drawn 6 cm from the sheet it pulls, so no hand is found); settled, the scan is the object at
rest on its supports and the hand's path starts at what it holds."""

import numpy as np


def _pre_contact(x, ref, arrive):
    size = float(np.ptp(ref, axis=0).max())
    return max(float(np.linalg.norm(x[k] - ref, axis=1).mean()) for k in range(arrive + 1)) / size


def test_a_settled_world_is_at_rest_before_the_toucher_arrives_and_the_hand_holds_where_it_is():
    from physinteract_usd.synth.world import World, draw_world

    # seed 658: a hanging object (400 truth particles, 29 frames): the smallest dev world with a grasp
    w0 = World(draw_world(658, "dev", {"settle": False}), device="cpu")     # its draw settles it: asked not to
    x0, _ = w0.run()
    assert _pre_contact(x0, w0.x0, w0.arrive) > 0.03              # the default: it sags before anything touches it
    w1 = World(draw_world(658, "dev", {"settle": True}), device="cpu")
    x1, _ = w1.run()
    assert np.allclose(x1[0], w1.x_scan) and np.allclose(x1[1], w1.x_scan)
    assert _pre_contact(x1, w1.x_scan, w1.arrive) < 0.002          # settled: still until the toucher comes
    assert np.linalg.norm(w1.x_scan - w1.x0, axis=1).mean() > 0.5 * _pre_contact(x0, w0.x0, w0.arrive) * float(
        np.ptp(w0.x0, axis=0).max())                                 # ... in the shape it sagged to, not at the old rest
    a, held = w1.arrive, w1.contact_indices
    assert np.linalg.norm(w1.trajectory[a] - x1[a][held].mean(0)) < 2.0 * w1.h   # the hand's path at what it holds


def test_synth_settle_is_for_world_captures_only(tmp_path, capsys):
    """`synth NAME OUT --settle`: one line naming the flag, exit 2, nothing written."""
    from physinteract_usd.cli import main

    out = tmp_path / "cap"
    assert main(["synth", "foam_bar", str(out), "--settle"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--settle" in err[0] and "world captures" in err[0]
    assert not out.exists()


def _ring(R=0.08, r=0.012, n=4000, seed=0):
    """Particles filling a torus in the x-y plane (a hanging ring), its hole's centre at the origin."""
    rng = np.random.default_rng(seed)
    u, v, rho = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n), r * np.sqrt(rng.uniform(0, 1, n))
    return np.stack([(R + rho * np.cos(v)) * np.cos(u), (R + rho * np.cos(v)) * np.sin(u), rho * np.sin(v)], 1)


def test_a_poke_on_a_rings_inner_rim_comes_in_only_as_far_as_its_path_is_clear():
    """dev_0542 (#23): a fingertip planned to come 18 cm along the inner rim's normal passed through the ring's far side
    and knocked it swinging before it arrived. `World._clear_approach` turns the direction toward the normal while that
    clears the particles and, where nothing does (across a ring's hole), shortens the approach to the clear stretch; a
    poke on the outer rim keeps its path."""
    import types

    from physinteract_usd.synth.world import World, _unit

    x = _ring()
    R, h = 0.012, 0.004
    for rim, n in (("inner", np.array([1.0, 0.0, 0.0])), ("outer", np.array([1.0, 0.0, 0.0]))):
        cp = np.array([0.08 - 0.012, 0.0, 0.0]) if rim == "inner" else np.array([0.08 + 0.012, 0.0, 0.0])
        if rim == "inner":
            n = -n                                         # the inner rim faces the hole: -x at +x
        w = types.SimpleNamespace(contact_normal=n, hand_dir=_unit(n + np.array([0.0, 0.3, 0.0])), h=h,
                                  w={"approach": 0.18, "look": "fingertip"})
        start = cp + n * (R + 0.2 * h)
        World._clear_approach(w, start, x, R)
        length = getattr(w, "approach_len", 0.18) + 0.06
        s = np.linspace(R / length, 1.0, 200)
        gap = np.linalg.norm((start + np.outer(s, length * w.hand_dir))[:, None] - x[None], axis=2).min(1) - R
        if rim == "outer":
            assert not hasattr(w, "approach_len") and w.approach_clearance >= 0.5 * h
        else:
            assert w.approach_clearance < 0 and 2 * R <= w.approach_len < 0.18    # shortened across the hole
        assert gap.min() > 0, (rim, gap.min())                                     # the swept path misses the ring


def test_a_settled_scans_splats_are_deformed_as_frame_0_shows_them():
    # the scan of a settled truth carries its splats as the truth renders frame 0 (F Sigma F^T), not the rest shapes
    import torch
    from physinteract_usd.gaussians import Gaussians
    from physinteract_usd.render import GaussianBinding, covariance_from_scales_quats
    from physinteract_usd.synth.world import settled_scan

    rng = np.random.default_rng(0)
    x0 = rng.uniform(0, 0.1, (60, 3))
    g = Gaussians.from_colors(x0[:20] + 0.001, np.full((20, 3), 0.5), 0.004)
    binding = GaussianBinding.knn(g.means, x0, k=4, dtype=torch.float32)
    F = np.tile(np.array([[1.3, 0.2, 0.0], [0.0, 0.8, 0.0], [0.0, 0.1, 1.0]]), (60, 1, 1))
    scan = settled_scan(g, binding, x0, F, g.means)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    got = covariance_from_scales_quats(t(scan.scales), t(scan.quats)).numpy()
    want = F[0] @ covariance_from_scales_quats(t(g.scales), t(g.quats)).numpy() @ F[0].T
    assert np.allclose(got, want, rtol=1e-4, atol=1e-10)
    assert not np.allclose(scan.scales, g.scales, rtol=0.05)


def test_three_of_four_worlds_settle_by_their_draw_and_no_settle_is_for_world_captures_only(tmp_path, capsys):
    from physinteract_usd.cli import main
    from physinteract_usd.synth.world import SETTLED_SHARE, draw_world

    share = np.mean([draw_world(s, "dev")["settle"] for s in range(200)])
    assert abs(share - SETTLED_SHARE) < 0.1
    assert draw_world(658, "dev", {"settle": False})["settle"] is False          # an override wins
    out = tmp_path / "cap"
    assert main(["synth", "foam_bar", str(out), "--no-settle"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--no-settle" in err[0] and "world captures" in err[0]
    assert not out.exists()
