"""The fit's AdamW: torch's own, less its import of `torch._dynamo` (#26).

`torch.optim.Optimizer` wraps `add_param_group` and `zero_grad` in `torch._disable_dynamo` and
`Adam.step` in `_use_grad_for_differentiable`; each imports `torch._dynamo` on its first call (with
sympy, torch.fx, torch.distributed, ...: ~820 modules, 1.0 s of CPU per process with compiled
bytecode, 3.8 s without, measured on the 2-core dev VM; docs/benchmarks/gpu.md, session 16), only to
step aside when torch.compile is tracing. The fit never compiles, so `AdamW` here calls the same
methods' undecorated bodies: the same `_init_group` and the same functional `adam(...)` with the same
arguments, under `torch.no_grad()` (what the wrapper sets for `differentiable=False`), so the
iterates are torch's own, bitwise (tests/test_adamw.py). A torch whose methods are not wrapped this
way (no `__wrapped__`) gets its methods as they are.
"""

from __future__ import annotations

import inspect

import torch


def _body(fn):
    """`fn` without its decorators (functools.wraps chains; the step's profiling hook too)."""
    return inspect.unwrap(fn)


_ADD_PARAM_GROUP = _body(torch.optim.Optimizer.add_param_group)
_ZERO_GRAD = _body(torch.optim.Optimizer.zero_grad)
_STEP = _body(torch.optim.Adam.step)


class AdamW(torch.optim.AdamW):
    """`torch.optim.AdamW` whose construction, `zero_grad` and `step` never import torch._dynamo."""

    def add_param_group(self, param_group):
        return _ADD_PARAM_GROUP(self, param_group)

    def zero_grad(self, set_to_none: bool = True):
        return _ZERO_GRAD(self, set_to_none)

    def step(self, closure=None):
        if self.defaults.get("differentiable"):
            return super().step(closure)
        with torch.no_grad():
            return _STEP(self, closure)
