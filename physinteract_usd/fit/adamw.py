"""The fit's optimisers, AdamW and Rprop: torch's own, less their import of `torch._dynamo` (#26).

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
_RPROP_STEP = _body(torch.optim.Rprop.step)


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


class Rprop(torch.optim.Rprop):
    """`torch.optim.Rprop` whose construction, `zero_grad` and `step` never import torch._dynamo (as
    `AdamW`). Resilient backpropagation: each coefficient's step grows (x1.2) while its gradient keeps
    its sign and halves when it flips; the gradient's size is never used. A full-batch method, which
    the fit is (every iteration sees every frame): the material's coefficients travel as far as their
    gradients agree, where Adam moves each about its learning rate an iteration (#24)."""

    def add_param_group(self, param_group):
        return _ADD_PARAM_GROUP(self, param_group)

    def zero_grad(self, set_to_none: bool = True):
        return _ZERO_GRAD(self, set_to_none)

    def step(self, closure=None):
        if self.defaults.get("differentiable"):
            return super().step(closure)
        with torch.no_grad():
            return _RPROP_STEP(self, closure)


class Chained:
    """Several optimisers stepped as one (the material's `Rprop` beside the path's `AdamW`): their
    parameter groups as one list and their states as one mapping, so a schedule's loop rescales rates,
    clears moments and steps as it does for one optimiser."""

    def __init__(self, *optimizers):
        self.optimizers = [o for o in optimizers if o is not None]

    @property
    def param_groups(self) -> list:
        return [g for o in self.optimizers for g in o.param_groups]

    @property
    def state(self) -> dict:
        out: dict = {}
        for o in self.optimizers:
            out.update(o.state)
        return out

    def zero_grad(self, set_to_none: bool = True):
        for o in self.optimizers:
            o.zero_grad(set_to_none)

    def step(self, closure=None):
        for o in self.optimizers:
            o.step()


def make_optimizer(groups: list, material_optimizer: str = "adam", weight_decay: float = 0.0,
                   max_step: float = 1.0, growth: float = 1.2):
    """The optimiser of one level: AdamW on every group, or (`material_optimizer` "rprop") Rprop on the
    first group (the material's coefficients, its "lr" the first step) and AdamW on the rest. Rprop's
    steps stay within [max_step / 1000, max_step], grow by `growth` while a gradient keeps its sign and halve
    when it flips."""
    if material_optimizer == "adam":
        return AdamW(groups, weight_decay=weight_decay)
    if material_optimizer != "rprop":
        raise ValueError(f"material_optimizer must be 'adam' or 'rprop', got {material_optimizer!r}")
    first = Rprop([groups[0]], lr=groups[0]["lr"], step_sizes=(max_step * 1e-3, max_step), etas=(0.5, growth))
    rest = AdamW(groups[1:], weight_decay=weight_decay) if len(groups) > 1 else None
    return Chained(first, rest)


def shrink_steps(opt, factor: float) -> None:
    """Every group's rate times `factor`, and an Rprop's learnt step sizes too (its rate is only its
    first step)."""
    for g in opt.param_groups:
        g["lr"] *= factor
    for st in opt.state.values():
        if "step_size" in st:
            st["step_size"].mul_(factor)


def forget_direction(opt, step_factor: float = 0.5) -> None:
    """After a restore to an earlier iterate: no momentum back into the overshoot (Adam's first moment
    cleared; the step sizes Adam learnt stay), and Rprop's last gradient forgotten (no sign comparison
    across the jump) with its step sizes times `step_factor`."""
    for st in opt.state.values():
        if "exp_avg" in st:
            st["exp_avg"].zero_()
        if "prev" in st:
            st["prev"].zero_()
            st["step_size"].mul_(step_factor)
