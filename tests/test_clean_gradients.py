"""fit.optimize.clean_gradients: the trajectories' rest row zeroed, a non-finite gradient entry zeroed, a
finite gradient bitwise unchanged, and no host read (no device sync on a GPU, #26)."""

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from physinteract_usd.fit.adamw import AdamW
from physinteract_usd.fit.optimize import clean_gradients


class _Reads(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.n = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.__name__.split(".")[0] in ("_local_scalar_dense", "is_nonzero"):
            self.n += 1
        return func(*args, **(kwargs or {}))


def test_clean_gradients_without_host_reads():
    g = torch.Generator().manual_seed(0)
    theta = torch.randn(8, generator=g, requires_grad=True)
    w = torch.randn(3, generator=g, requires_grad=True)
    traj = torch.randn(5, 3, generator=g, requires_grad=True)
    unused = torch.randn(2, requires_grad=True)               # no gradient: left as None
    opt = AdamW([{"params": [theta, unused]}, {"params": [w]}, {"params": [traj]}])
    theta.grad = torch.randn(8, generator=g) * 1e-30          # tiny, -0.0 and denormal-ish values kept bitwise
    theta.grad[2] = -0.0
    finite_theta = theta.grad.clone()
    w.grad = torch.tensor([1.0, float("nan"), float("-inf")])
    traj.grad = torch.randn(5, 3, generator=g)
    traj.grad[3, 1] = float("inf")
    expect_traj = traj.grad.clone()
    expect_traj[0] = 0
    expect_traj[3, 1] = 0
    with _Reads() as reads:
        clean_gradients(opt, [traj])
    assert reads.n == 0
    assert torch.equal(theta.grad, finite_theta) and torch.signbit(theta.grad[2])
    assert torch.equal(w.grad, torch.tensor([1.0, 0.0, 0.0]))
    assert torch.equal(traj.grad, expect_traj)
    assert unused.grad is None
