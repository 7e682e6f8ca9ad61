"""The confidence estimate (fit/optimize.py `confidence`) simulates once for all its probes: the
probes differ only in their random signs, so each is a backward of the same graph. Checked against
the estimate with one simulation per probe (what it did before, docs/benchmarks/cpu.md "Levers,
session 9") on the tiny cantilever of tests/fit_scene.py: the same numbers (to float32 rounding), one
simulation."""

import math

import numpy as np
import pytest
import torch

import fit_scene as fs
from physinteract_usd import api
from physinteract_usd.fit import FitProblem
from physinteract_usd.fit.material import MaterialField
from physinteract_usd.fit.optimize import confidence, residual_correlation
from physinteract_usd.usd.stage import read_stage


def _reference(prob, mat, probes, seed=0, tol=math.log(1.2)):
    """One simulation per probe (the estimator as it was before)."""
    gen = torch.Generator(device="cpu").manual_seed(seed + 11)
    theta = mat.theta.detach().clone().requires_grad_(True)
    mat.theta = theta
    diag = torch.zeros_like(theta)
    rss, count, residuals = 0.0, 0, []
    nu = mat.poisson().detach()
    for p in range(probes):
        x, F = prob.simulate(mat.youngs(), nu, None, None)
        acc = 0.0
        for k in range(1, prob.T):
            out = prob.render_frame(k, x[k], F[k])
            w = prob.weight[k] if prob.weight is not None else torch.ones_like(out["alpha"])
            r = (out["rgb"] - prob.frames[k]) * w[..., None]
            acc = acc + ((torch.randint(0, 2, r.shape, generator=gen) * 2 - 1).to(r) * r).sum()
            if prob.masks is not None:
                rm = (out["alpha"] - prob.masks[k]) * w
                acc = acc + ((torch.randint(0, 2, rm.shape, generator=gen) * 2 - 1).to(rm) * rm).sum()
                if p == 0:
                    rss += float((rm.detach() ** 2).sum())
                    count += rm.numel()
            if p == 0:
                rss += float((r.detach() ** 2).sum())
                count += r.numel()
                residuals.append(r.detach().float().mean(-1).cpu().numpy())
        g, = torch.autograd.grad(acc, theta)
        diag += g ** 2
    diag /= probes
    noise_var = max(rss / max(count, 1), 1e-8) * residual_correlation(residuals)
    sigma_theta = torch.sqrt(noise_var / diag.clamp_min(1e-30))
    with torch.no_grad():
        s = torch.sigmoid(mat.u())
        sigma_p = (mat.B * sigma_theta[None, :]).sum(1) * (mat.hi - mat.lo) * s * (1 - s)
        return torch.erf(tol / (sigma_p * math.sqrt(2.0)).clamp_min(1e-12)).cpu().numpy()


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    sc = fs.build(tmp_path_factory.mktemp("conf") / "base")
    sd = read_stage(sc["stage"])
    return FitProblem(sd, api.load_observations(sd), api.true_contacts(sd, sc["gt"])), sd


def _field(prob, sd):
    st = sd.settings
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype, device=prob.tdev)
    mat.set_uniform(1.5 * fs.E_TRUE, fs.NU_TRUE)   # off the truth: residuals everywhere
    mat.refine(4)
    with torch.no_grad():                           # a varying field
        mat.theta += torch.linspace(-0.3, 0.3, mat.K, dtype=mat.theta.dtype)
    return mat


def test_one_simulation_for_all_probes_same_estimate(problem):
    prob, sd = problem
    calls = []
    sim = prob.simulate

    def counted(*a, **kw):
        calls.append(1)
        return sim(*a, **kw)

    prob.simulate = counted
    try:
        got = confidence(prob, _field(prob, sd), [], probes=3, seed=0, method="probes", exposure_floor=0)
        assert len(calls) == 1
        want = _reference(prob, _field(prob, sd), probes=3, seed=0)
        assert len(calls) == 4
    finally:
        prob.simulate = sim
    assert got.shape == want.shape and np.ptp(want) > 0          # not a constant: the test can tell
    # float32 simulation: the same up to its rounding (measured: 3.3e-7 relative at most)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-9)
    # the probes are not all alike: another seed gives another (equally valid) estimate
    other = confidence(prob, _field(prob, sd), [], probes=3, seed=5, method="probes", exposure_floor=0)
    assert not np.allclose(other, got, rtol=1e-3, atol=1e-9)


def _probe_samples(prob, mat, n, seed=3, outer=False):
    """n Hutchinson samples (J^T s)^2 of diag(J^T J) (`outer`: (J^T s)(J^T s)^T of the whole J^T J),
    one simulation."""
    gen = torch.Generator(device="cpu").manual_seed(seed)
    theta = mat.theta.detach().clone().requires_grad_(True)
    mat.theta = theta
    x, F = prob.simulate(mat.youngs(), mat.poisson().detach(), None, None)
    res = []
    for k in range(1, prob.T):
        out = prob.render_frame(k, x[k], F[k])
        w = prob.weight[k] if prob.weight is not None else torch.ones_like(out["alpha"])
        res.append((out["rgb"] - prob.frames[k]) * w[..., None])
        if prob.masks is not None:
            res.append((out["alpha"] - prob.masks[k]) * w)
    out = []
    for p in range(n):
        acc = sum(((torch.randint(0, 2, r.shape, generator=gen) * 2 - 1).to(r) * r).sum() for r in res)
        g, = torch.autograd.grad(acc, theta, retain_graph=p < n - 1)
        g = g.detach().double().numpy()
        out.append(np.outer(g, g) if outer else g ** 2)
    return np.array(out)


def test_finite_differences_give_the_gauss_newton_diagonal(problem):
    """The finite-difference estimator (one simulation per coefficient) against the mean of 80
    Hutchinson probes: within 4 of the probes' standard errors plus 10% (the one-sided difference's
    truncation at a 1% step in E); the confidence it gives within 0.06 of 32 probes' (measured: 0.04
    at most, confidences 0.06-0.58; the 4 probes the fit used before scatter more); "auto" picks
    it for 4 coefficients against 4 probes and the probes for 4 coefficients against 1 probe."""
    prob, sd = problem
    conf_fd, d_fd, used = confidence(prob, _field(prob, sd), [], probes=4, return_diag=True, exposure_floor=0)
    assert used == "fd"
    samples = _probe_samples(prob, _field(prob, sd), 80)
    mean, se = samples.mean(0), samples.std(0, ddof=1) / np.sqrt(len(samples))
    assert np.all(d_fd > 0)
    assert np.all(np.abs(d_fd - mean) < 4 * se + 0.1 * mean), (d_fd, mean, se)
    conf_p, d_p, used_p = confidence(prob, _field(prob, sd), [], probes=1, return_diag=True, exposure_floor=0)
    assert used_p == "probes"
    conf_fd = confidence(prob, _field(prob, sd), [], probes=4, covariance="diag", exposure_floor=0)  # same rule
    conf_many = confidence(prob, _field(prob, sd), [], probes=32, method="probes", exposure_floor=0)
    assert np.abs(conf_fd - conf_many).max() < 0.06, np.abs(conf_fd - conf_many).max()


def test_the_finite_difference_columns_give_the_whole_gauss_newton_matrix(problem):
    """The Laplace covariance (#24): J^T J's off-diagonal terms from the finite-difference columns
    against the mean of 80 Hutchinson outer products (J^T s)(J^T s)^T, within 4 standard errors plus
    10% of the diagonal's scale; the confidence then follows sigma_p^2 = dlogE_p^2 B_p Sigma B_p^T,
    Sigma = noise x (J^T J)^-1, recomputed here from the same matrix."""
    from physinteract_usd.fit import optimize as O

    prob, sd = problem
    mat = _field(prob, sd)
    theta = mat.theta.detach().clone()
    captured = {}
    lv = O.laplace_variance

    def spy(B, g, *a, **kw):
        captured["gram"] = g.clone()
        return lv(B, g, *a, **kw)

    O.laplace_variance = spy
    try:
        conf_full, sigma_full = confidence(prob, mat, [], probes=4, return_sigma=True, exposure_floor=0)
    finally:
        O.laplace_variance = lv
    G = captured["gram"].numpy()
    K = G.shape[0]
    samples = _probe_samples(prob, _field(prob, sd), 80, outer=True)
    mean, se = samples.mean(0), samples.std(0, ddof=1) / np.sqrt(len(samples))
    scale = np.sqrt(np.outer(np.diag(G), np.diag(G)))
    assert np.abs(G - G.T).max() <= 1e-9 * np.abs(G).max()
    off = ~np.eye(K, dtype=bool)
    assert np.abs(G[off]).max() > 0.05 * np.diag(G).min()          # the coefficients do overlap: a real test
    assert np.all(np.abs(G - mean) < 4 * se + 0.1 * scale), (G, mean, se)
    # the confidence from that matrix, by hand
    conf_diag, sigma_diag = confidence(prob, _field(prob, sd), [], probes=4, return_sigma=True, covariance="diag",
                                        exposure_floor=0)
    mat.theta = theta
    with torch.no_grad():
        s_ = torch.sigmoid(mat.u()).double().numpy()
    dlog = (mat.hi - mat.lo) * s_ * (1 - s_)
    B = mat.B.detach().double().numpy()
    Ginv = np.linalg.inv(G)
    quad = np.einsum("pk,kl,pl->p", B, Ginv, B)
    ratio = sigma_full / (np.sqrt(quad) * dlog)
    assert np.ptp(ratio) < 1e-3 * ratio.mean()                      # sigma_p proportional to the quadratic form
    assert not np.allclose(sigma_full, sigma_diag, rtol=1e-2)       # and not the diagonal's rule
    want = np.array([math.erf(math.log(1.2) / (sg * math.sqrt(2.0))) for sg in sigma_full])
    np.testing.assert_allclose(conf_full, want, rtol=1e-5, atol=1e-7)


def test_laplace_variance_treats_an_unpinned_direction_as_unknown():
    """Two coefficients whose columns are equal: only their sum is pinned. The sum's variance is
    finite (1 / |column|^2 per unit), each one alone is unknown (a huge variance: confidence 0); an
    invertible matrix gives b G^-1 b exactly."""
    from physinteract_usd.fit.optimize import laplace_variance

    G = torch.tensor([[1.0, 1.0], [1.0, 1.0]], dtype=torch.float64)
    v = laplace_variance(torch.tensor([[1.0, 1.0], [1.0, 0.0]], dtype=torch.float64), G).numpy()
    assert v[0] == pytest.approx(1.0, rel=1e-6)                    # (b . v1)^2 / lambda1 = 2 / 2
    assert v[1] > 1e6
    G = torch.tensor([[2.0, 0.5], [0.5, 1.0]], dtype=torch.float64)
    B = torch.tensor([[1.0, 0.0], [0.3, -0.7]], dtype=torch.float64)
    want = np.einsum("pk,kl,pl->p", B.numpy(), np.linalg.inv(G.numpy()), B.numpy())
    np.testing.assert_allclose(laplace_variance(B, G).numpy(), want, rtol=1e-12)


def test_what_the_video_cannot_see_gets_confidence_zero(problem):
    """The tiny cantilever (clamped at one end, pulled at the other): its clamped particles and the
    ones that barely strain in the fit's rollout (`select.unconstrained_particles`, the same rollout
    the estimate simulates) get confidence 0 whatever the curvature says; the others keep the
    Laplace value exactly; `exposure_floor=0` turns it off."""
    from physinteract_usd.fit.select import EXPOSURE_FLOOR, strain_exposure, unconstrained_particles

    prob, sd = problem
    mat = _field(prob, sd)
    off = confidence(prob, mat, [], probes=4, exposure_floor=0)
    on = confidence(prob, _field(prob, sd), [], probes=4)
    held = np.asarray(prob.held_particles(), bool)
    expo = strain_exposure(prob, mat.youngs().detach().numpy(), mat.poisson().detach().numpy())
    unseen = unconstrained_particles(expo, held, EXPOSURE_FLOOR)
    assert held.any() and (unseen & ~held).any() and (~unseen).sum() > len(unseen) // 2
    assert np.all(on[unseen] == 0.0) and np.all(off[unseen] > 0.0)
    np.testing.assert_allclose(on[~unseen], off[~unseen], rtol=1e-6)


def test_the_sandwich_is_zero_where_the_frames_agree_and_their_spread_where_they_do_not():
    """The frame-clustered sandwich (opt-in `covariance="sandwich"`): G^-1 M G^-1 with M the frames'
    gradients' spread. Frames that agree (equal gradients) give 0; two halves pulling a coefficient
    apart by +-a give b G^-1 M G^-1 b with M = T/(T-1) x T a^2 (the sum over the frames), by hand."""
    from physinteract_usd.fit.optimize import sandwich_variance

    G = torch.tensor([[4.0, 1.0], [1.0, 2.0]], dtype=torch.float64)
    B = torch.tensor([[1.0, 0.0], [0.5, 0.5]], dtype=torch.float64)
    same = torch.tensor([[0.3, -0.1]] * 6, dtype=torch.float64)
    assert torch.all(sandwich_variance(B, G, same) < 1e-24)
    a = 0.7
    split = torch.tensor([[a, 0.0]] * 3 + [[-a, 0.0]] * 3, dtype=torch.float64)
    M = np.array([[a * a, 0.0], [0.0, 0.0]]) * 6 * 6 / 5
    Gi = np.linalg.inv(G.numpy())
    want = np.einsum("pk,kl,lm,mn,pn->p", B.numpy(), Gi, M, Gi, B.numpy())
    np.testing.assert_allclose(sandwich_variance(B, G, split).numpy(), want, rtol=1e-12)


def test_the_sandwich_option_widens_the_interval_by_the_frames_spread(problem):
    """On the tiny cantilever off its truth (the frames disagree about E), `covariance="sandwich"`
    never narrows the Laplace interval, widens it somewhere, and equals the larger of the two."""
    from physinteract_usd.fit import optimize as O

    prob, sd = problem
    conf_full, sig_full = confidence(prob, _field(prob, sd), [], probes=4, return_sigma=True, exposure_floor=0)
    seen = {}
    sv = O.sandwich_variance

    def spy(B, G, g, *a, **kw):
        out = sv(B, G, g, *a, **kw)
        seen["v"] = out.clone()
        return out

    O.sandwich_variance = spy
    try:
        conf_sw, sig_sw = confidence(prob, _field(prob, sd), [], probes=4, return_sigma=True, exposure_floor=0,
                                     covariance="sandwich")
    finally:
        O.sandwich_variance = sv
    assert np.all(sig_sw >= sig_full * (1 - 1e-6)) and np.any(sig_sw > 1.05 * sig_full)
    assert np.all(conf_sw <= conf_full + 1e-7)
    mat = _field(prob, sd)
    with torch.no_grad():
        s_ = torch.sigmoid(mat.u()).double().numpy()
    dlog = (mat.hi - mat.lo) * s_ * (1 - s_)
    wider = sig_sw > 1.01 * sig_full
    np.testing.assert_allclose(sig_sw[wider], np.sqrt(seen["v"].numpy()[wider]) * dlog[wider], rtol=1e-5)


def test_columns_too_large_to_keep_fall_back_to_the_diagonals_rule(problem, monkeypatch):
    """Where the K columns would not fit `GRAM_COLUMNS_BYTES`, the estimate is the diagonal's (the same
    as `covariance="diag"`), not a quadratic form of a diagonal matrix."""
    from physinteract_usd.fit import optimize as O

    prob, sd = problem
    want = confidence(prob, _field(prob, sd), [], probes=4, covariance="diag", exposure_floor=0)
    full = confidence(prob, _field(prob, sd), [], probes=4, exposure_floor=0)
    monkeypatch.setattr(O, "GRAM_COLUMNS_BYTES", 0)
    got = confidence(prob, _field(prob, sd), [], probes=4, covariance="sandwich", exposure_floor=0)
    np.testing.assert_allclose(got, want, rtol=1e-6)
    assert not np.allclose(full, want, rtol=1e-3)


def test_the_batched_finite_differences_give_the_solo_gauss_newton_matrix(problem, monkeypatch):
    """On CUDA the K stepped fields go as tiled copies in one rollout, the unstepped field as copy 0 (#26). Forced
    here on the CPU: the Gauss-Newton matrix agrees with the one-rollout-per-column path within 1% (the confidence 0.02)
    (the columns are differences of the same 1% step; a copy's tiled arithmetic is not bitwise a solo rollout's)."""
    from physinteract_usd.fit import optimize as O

    prob, sd = problem
    grams = {}
    lv = O.laplace_variance

    def spy(tag):
        def f(B, g, *a, **kw):
            grams[tag] = g.clone().numpy()
            return lv(B, g, *a, **kw)
        return f

    calls = []
    real = O._fd_columns_batched

    def counted(*a, **kw):
        calls.append(1)
        return real(*a, **kw)

    if "simulate" in vars(prob):     # an earlier test's counter left on the shared problem: the plain path
        monkeypatch.delattr(prob, "simulate")
    monkeypatch.setattr(O, "laplace_variance", spy("solo"))
    conf_solo = confidence(prob, _field(prob, sd), [], probes=4, exposure_floor=0, method="fd")
    monkeypatch.setattr(O, "fd_batched", lambda sim: True)   # the batched path (CUDA's), on the CPU
    monkeypatch.setattr(O, "_fd_columns_batched", counted)
    monkeypatch.setattr(O, "laplace_variance", spy("batched"))
    conf_b = confidence(prob, _field(prob, sd), [], probes=4, exposure_floor=0, method="fd")
    assert calls, "the batched path did not run"
    G0, G1 = grams["solo"], grams["batched"]
    assert np.abs(G1 - G0).max() <= 0.01 * np.abs(np.diag(G0)).max(), (G0, G1)   # 0.3% here
    np.testing.assert_allclose(conf_b, conf_solo, atol=0.02)


def test_the_callers_rollout_is_not_simulated_again(problem, monkeypatch):
    """#26: with the finite differences the confidence takes the final pass's rollout of the same field (`simulated`)
    instead of its own first simulation: the same confidence, one simulation fewer."""
    prob, sd = problem
    mat = _field(prob, sd)
    want = confidence(prob, mat, [], probes=4, exposure_floor=0, method="fd")
    with torch.no_grad():
        x, F = prob.simulate(mat.youngs().detach(), mat.poisson().detach(), None, None)
    calls = []
    real = prob.simulate
    monkeypatch.setattr(prob, "simulate", lambda *a, **k: calls.append(1) or real(*a, **k))
    got = confidence(prob, _field(prob, sd), [], probes=4, exposure_floor=0, method="fd", simulated=(x, F))
    n_with = len(calls)
    calls.clear()
    confidence(prob, _field(prob, sd), [], probes=4, exposure_floor=0, method="fd")
    assert n_with == len(calls) - 1
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
