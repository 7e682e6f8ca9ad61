"""The bumps schedule's opt-in levers for a fit that stops short (#24, foam_bar): the start from the
appearance parts (fit/parts_start.py) and the Gauss-Newton step (fit/gauss_newton.py), on the
two-part bar of tests/test_fit_select.py (left half 10x stiffer than the right, two colours; frames
rendered by the package's own model: the truth's loss is the floor). Slow: the 12-frame bar and
its probes, ~77 CPU s for both on the shared 2-core VM (2026-11-26)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import test_fit_select as tfs


class _MP:
    def setattr(self, obj, name, val):
        setattr(obj, name, val)


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    import fit_scene as fs

    saved = fs.bar_gaussians
    try:
        b, stiff = tfs._two_part_bar(tmp_path_factory.mktemp("two"), 1e4, _MP(), e_range=(3e3, 3e5))
    finally:
        fs.bar_gaussians = saved
    from physinteract_usd.app.fit import make_problem, prepare_fit

    job = prepare_fit(b["stage"], iterations=1, contact_from=b["gt"], log=lambda *a: None, progress=False,
                      settings_overrides={"schedule": "bumps"})
    return make_problem(job), job.settings, stiff


def _field_at_uniform(prob, s, e):
    from physinteract_usd.fit.material import MaterialField

    st = prob.scene.settings
    feats = prob.particle_appearance()
    mat = MaterialField(prob.x0, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=prob.tdtype, device=prob.tdev,
                        seed=s.seed, width=s.basis_width, features=feats, appearance=s.appearance,
                        centre_mask=~prob.held_particles())
    mat.set_uniform(e, 0.3)
    mat.refine(6)
    return mat


def _total(prob, mat):
    with torch.no_grad():
        return float(prob.loss(mat.youngs(), mat.poisson(), prob.initial_trajectories())["rec"])


@pytest.mark.slow
def test_parts_start_finds_the_stiff_half_from_the_uniform_e(bar):
    """From the best uniform E (the schedule's start search; truth 1e5 / 1e4), 30 forward probes
    over the two colour parts: the field the bumps start from renders better than the uniform one
    and its clamped half is stiffer than its lifted half by more than 3x (the truth: 10x; the
    uniform: 1x; measured 5.97 / 84.5 kPa in the whole fit, docs/benchmarks/fit.md)."""
    from physinteract_usd.fit.optimize import uniform_loss
    from physinteract_usd.fit.parts_start import parts_start

    prob, s, stiff = bar
    mat = _field_at_uniform(prob, s, uniform_loss(prob, s.search_evals)[0])
    before = _total(prob, mat)
    out = parts_start(prob, mat, s, [t.clone() for t in prob.initial_trajectories()], None,
                      lambda: _total(prob, mat), 30)
    assert out["parts"] == 2 and out["used"], out
    after = _total(prob, mat)
    assert after < 0.9 * before, (before, after)
    e = mat.youngs().detach().cpu().numpy()
    held = np.asarray(prob.held_particles(), bool)
    ratio = float(np.median(e[stiff & ~held]) / np.median(e[~stiff]))
    assert ratio > 3.0, (ratio, out)
    assert out["forwards"] <= 30 + 2


@pytest.mark.slow
def test_gauss_newton_step_never_raises_the_loss(bar):
    """A Gauss-Newton step keeps the coefficients where they were unless its try lowered the total
    loss (on this bar's tiny textured images its quadratic model overshoots: docs/benchmarks/fit.md),
    and reports what it cost."""
    from physinteract_usd.fit.gauss_newton import gauss_newton_step

    prob, s, _ = bar
    mat = _field_at_uniform(prob, s, 2e4)
    theta0 = mat.theta.detach().clone()
    out = gauss_newton_step(prob, mat, mat.poisson().detach(), [t.clone() for t in prob.initial_trajectories()],
                            None, lambda residuals=False: torch.zeros((0,) if residuals else (), dtype=prob.tdtype))
    assert out["forwards"] >= mat.K + 2
    if out["accepted"]:
        assert out["loss"] < out["loss0"] and not torch.equal(mat.theta.detach(), theta0)
    else:
        assert torch.equal(mat.theta.detach(), theta0)
