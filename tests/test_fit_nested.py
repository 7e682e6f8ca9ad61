"""The nested field (`MaterialField.set_base`): log E = lo + (hi - lo) sigmoid(u_base + B theta), a
simpler model's per-particle E held fixed and a bumps offset from zero (the select schedule's field
step, fit/select.py; #24).

What is checked: the field starts exactly at its base (sharp part boundaries kept, which a
projection onto the bumps cannot represent), its smoothness term counts only the offsets, a warm
start reproduces a nested field's offsets exactly, and d loss / d offsets through the simulator and
renderer matches central finite differences in float64 on the tiny bar."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd.fit.material import MaterialField, neighbour_pairs

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _bar(n=(16, 4, 4), h=0.01):
    g = np.stack(np.meshgrid(*[np.arange(k) * h for k in n], indexing="ij"), -1).reshape(-1, 3)
    return g, h


def _two_parts(x):
    """A sharp 10x step along the bar (the two-part bar's parts)."""
    return np.where(x[:, 0] < 0.5 * x[:, 0].max(), 1e5, 1e4)


def test_nested_field_starts_at_its_base_which_a_projection_cannot_represent():
    x, h = _bar()
    E0 = _two_parts(x)
    mat = MaterialField(x, (1e3, 1e7), 0.45, dtype=torch.float64)
    mat.set_basis(8)
    # the old warm start: the parts projected onto 8 bumps blur the step
    mat.set_values(E0)
    blurred = mat.youngs().detach().numpy()
    assert np.max(np.abs(np.log(blurred / E0))) > 0.2
    # nested: exactly the base (within the range's clip), every offset zero
    mat.set_base(E0)
    assert float(mat.theta.detach().abs().max()) == 0.0
    np.testing.assert_allclose(mat.youngs().detach().numpy(), E0, rtol=1e-9)
    # its smoothness term measures the offsets only: zero at the start, across the step too
    pairs = torch.as_tensor(neighbour_pairs(x, 1.6 * h))
    assert float(mat.smoothness(pairs)) == 0.0
    with torch.no_grad():
        mat.theta.copy_(torch.linspace(-0.3, 0.3, mat.K, dtype=torch.float64))
    off = mat.smoothness(pairs)
    assert float(off) > 0
    # a warm start from the nested field's values on the same base gives back its offsets
    E1 = mat.youngs().detach().numpy()
    theta1 = mat.theta.detach().clone()
    mat2 = MaterialField(x, (1e3, 1e7), 0.45, dtype=torch.float64)
    mat2.set_basis(8)
    mat2.set_base(E0)
    mat2.set_values(E1)
    np.testing.assert_allclose(mat2.theta.detach().numpy(), theta1.numpy(), atol=1e-8)
    # refining keeps the base and projects the offsets; dropping the base keeps the values (projected)
    mat2.refine(4)
    assert mat2.base is not None and mat2.K == 4
    mat2.theta = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    np.testing.assert_allclose(mat2.youngs().detach().numpy(), E0, rtol=1e-9)
    mat2.set_base(None)
    assert mat2.base is None and mat2.K == 4
    # set_uniform is a plain (un-nested) field again
    mat2.set_base(E0)
    mat2.set_uniform(3e4)
    assert mat2.base is None
    np.testing.assert_allclose(mat2.youngs().detach().numpy(), 3e4, rtol=1e-9)


def test_nested_offsets_gradient_matches_finite_differences_float64(tmp_path):
    """d loss / d (the bump offsets of a field nested on two parts) through the simulator and the
    renderer (float64, the tiny bar) against central differences; the smoothness term's gradient
    too."""
    import fit_scene as fs
    from physinteract_usd.app.fit import prepare_fit
    from physinteract_usd.fit import FitProblem

    b = fs.build(tmp_path / "bar")
    job = prepare_fit(b["stage"], iterations=1, contact_from=b["gt"], joint=False, log=lambda *a: None)
    prob = FitProblem(job.scene, job.observations, job.contacts, dtype="float64")
    st = prob.scene.settings
    x = prob.x0
    E0 = np.where(x[:, 0] > np.median(x[:, 0]), 3e3, 8e3)
    mat = MaterialField(x, (st.youngs_min, st.youngs_max), st.poisson_max, dtype=torch.float64, seed=0)
    mat.set_uniform(4e3, 0.3)
    nu = mat.poisson().detach()
    mat.set_basis(3)
    mat.set_base(E0)
    with torch.no_grad():    # the base's own loss is the nested field's at zero offsets
        base_loss = float(prob.loss(torch.as_tensor(E0, dtype=torch.float64), nu)["rec"])
        assert float(prob.loss(mat.youngs(), nu)["rec"]) == pytest.approx(base_loss, rel=1e-9)
    pairs = torch.as_tensor(neighbour_pairs(x, 1.6 * st.particle_spacing))

    def loss(theta):
        mat.theta = theta
        return prob.loss(mat.youngs(), nu)["rec"] + 0.1 * mat.smoothness(pairs)

    th = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64, requires_grad=True)
    g, = torch.autograd.grad(loss(th), th)
    h = 1e-4
    for j in range(3):
        d = torch.zeros_like(th)
        d[j] = h
        with torch.no_grad():
            fd = (float(loss(th.detach() + d)) - float(loss(th.detach() - d))) / (2 * h)
        assert abs(float(g[j]) - fd) <= 1e-4 * max(abs(fd), 1e-6) + 1e-9, (j, float(g[j]), fd)
