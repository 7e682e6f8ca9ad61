"""The fit's material parameterisation: the RBF basis and the appearance prior (bumps and
smoothness that do not cross colour edges)."""

from __future__ import annotations

import numpy as np
import torch

from physinteract_usd.fit.material import (MaterialField, joint_space, neighbour_pairs, pair_weights,
                                           particle_appearance, rbf_basis)


def _two_colour_bar(n_side=6, spacing=0.01):
    """A bar along y, lower half orange, upper half blue, with Gaussians on its faces."""
    g = (np.arange(n_side) + 0.5) * spacing
    yy = (np.arange(4 * n_side) + 0.5) * spacing - 2 * n_side * spacing
    X, Y, Z = np.meshgrid(g, yy, g, indexing="ij")
    particles = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    rng = np.random.default_rng(0)
    means = particles + rng.normal(0, 0.2 * spacing, particles.shape)
    colors = np.where((means[:, 1] < 0)[:, None], [0.9, 0.5, 0.1], [0.2, 0.4, 0.8])
    colors = colors + rng.normal(0, 0.05, colors.shape)   # texture noise within a part
    return particles, means, colors


def test_basis_is_a_partition_of_unity():
    p, _, _ = _two_colour_bar()
    for k in (1, 4, 9):
        B, c = rbf_basis(p, k)
        assert B.shape == (len(p), k) and c.shape[0] == k
        np.testing.assert_allclose(B.sum(1), 1.0, atol=1e-12)
        assert (B >= 0).all()


def test_appearance_features_follow_the_local_colour():
    p, means, colors = _two_colour_bar()
    f = particle_appearance(p, means, colors, k=32)
    low, high = p[:, 1] < -0.03, p[:, 1] > 0.03
    np.testing.assert_allclose(f[low].mean(0), [0.9, 0.5, 0.1], atol=0.05)
    np.testing.assert_allclose(f[high].mean(0), [0.2, 0.4, 0.8], atol=0.05)


def test_bumps_stay_on_their_side_of_a_colour_edge():
    p, means, colors = _two_colour_bar()
    f = particle_appearance(p, means, colors, k=32)
    low = p[:, 1] < 0

    def cross_weight(appearance):
        B, c = rbf_basis(joint_space(p, f, appearance), 8)
        centre_low = c[:, 1] < 0
        # basis weight a particle receives from centres in the other part
        return float(np.mean(np.where(low, B[:, ~centre_low].sum(1), B[:, centre_low].sum(1))))

    plain, aware = cross_weight(0.0), cross_weight(1.0)
    assert plain > 0.03          # position-only bumps straddle the edge
    assert aware < 0.1 * plain   # appearance-aware bumps do not


def test_smoothness_pairs_are_weak_across_a_colour_edge():
    p, means, colors = _two_colour_bar()
    f = particle_appearance(p, means, colors, k=32)
    pairs = neighbour_pairs(p, 0.016)
    w = pair_weights(pairs, f, 1.0)
    across = (p[pairs[:, 0], 1] < 0) != (p[pairs[:, 1], 1] < 0)
    far = np.abs(p[pairs[:, 0], 1]) > 0.03
    assert across.any() and far.any()
    assert np.percentile(w[far], 5) > 0.8
    assert w[across].max() < 0.1
    np.testing.assert_array_equal(pair_weights(pairs, None, 1.0), 1.0)


def test_a_two_part_field_is_representable_only_with_the_prior():
    """Least-squares projection of a 5x step in E at the colour edge onto 8 bumps: with the
    appearance prior every particle lands within 20% of its value; without it the edge blurs."""
    p, means, colors = _two_colour_bar()
    f = particle_appearance(p, means, colors, k=32)
    E = np.where(p[:, 1] < 0, 2e3, 1e4)

    def share_within_20(appearance):
        field = MaterialField(p, (5e2, 5e4), 0.4, features=f, appearance=appearance)
        field.set_basis(8)
        field.set_values(E)
        with torch.no_grad():
            Ef = field.youngs().numpy()
        return float(np.mean(np.abs(Ef - E) / E <= 0.2))

    assert share_within_20(1.0) > 0.98
    assert share_within_20(0.0) < 0.95


def test_a_gaussian_at_an_edge_reports_its_own_parts_value():
    """Two particles, one per part; a Gaussian between them of the first part's colour takes the
    first particle's value, and the plain weights come back where no particle matches."""
    from physinteract_usd.fit.material import appearance_transfer_weights

    weight = np.array([[0.4, 0.6], [0.4, 0.6]])
    index = np.array([[0, 1], [0, 1]])
    particle_f = np.array([[0.9, 0.5, 0.1], [0.2, 0.4, 0.8]])
    gaussian_f = np.array([[0.88, 0.52, 0.12], [0.0, 1.0, 0.0]])   # orange; a colour no particle has
    w = appearance_transfer_weights(weight, index, gaussian_f, particle_f)
    assert w[0, 0] > 0.99
    np.testing.assert_allclose(w.sum(1), 1.0)
    np.testing.assert_allclose(w[1], weight[1])
