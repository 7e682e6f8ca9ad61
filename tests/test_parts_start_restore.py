"""A parts start that is not taken leaves the fit as it found it: the field and the adaptive substep's rung
(fit/parts_start.py). The probes simulate stiffer fields; the substep's hysteresis may keep their rung, and the
fit then goes on at another step (the H200's hemp_rope, 2026-11-26: a start not taken, MA 0.801 -> 0.485)."""

from __future__ import annotations

import types

import numpy as np
import torch

from physinteract_usd.fit import parts_start as ps
from physinteract_usd.fit import select


class _Sim:
    def __init__(self):
        self.e_bound, self.adaptive, self.used = 1.0e4, True, []

    def _use_bound(self, b):
        self.used.append(b)
        self.e_bound = b


class _Mat:
    lo, hi = np.log(1e3), np.log(6e4)

    def __init__(self):
        self.theta = torch.zeros(8, requires_grad=True)

    def log_e(self):
        return torch.full((6,), float(np.log(1e4)))

    def poisson(self):
        return torch.full((6,), 0.3)

    def set_values(self, e):
        with torch.no_grad():
            self.theta = torch.ones(8, requires_grad=True)


def _run(monkeypatch, losses):
    sim = _Sim()
    prob = types.SimpleNamespace(sim=sim, T=4)
    labels = np.array([0, 0, 0, 1, 1, 1])
    monkeypatch.setattr(select, "part_candidates", lambda *a: [{"kind": "appearance", "parts": 2, "labels": labels}])

    class Probe:
        def __init__(self, *a, **k):
            self.cache = {}

        def __call__(self, x):
            return 0.02

    def refine(f, start, lo, hi, n, step):
        sim.e_bound = 5.6e4          # the probes' stiff fields moved the rung (as prob.simulate's ensure_stable does)
        return {"log_e": [np.log(3e4), np.log(8e3)], "loss": 0.01}

    monkeypatch.setattr(select, "PartProbe", Probe)
    monkeypatch.setattr(select, "part_refine", refine)
    it = iter(losses)
    mat = _Mat()
    out = ps.parts_start(prob, mat, types.SimpleNamespace(select_sweep_batch=1), None, None, lambda: next(it), 20)
    return out, sim, mat


def test_a_start_not_taken_restores_the_rung_and_the_field(monkeypatch):
    out, sim, mat = _run(monkeypatch, [0.010, 0.012])      # the parts' field renders worse: not taken
    assert not out["used"]
    assert sim.e_bound == 1.0e4 and sim.used == [1.0e4]
    assert float(mat.theta.abs().max()) == 0.0


def test_a_start_taken_keeps_its_field(monkeypatch):
    out, sim, mat = _run(monkeypatch, [0.010, 0.004])      # better by more than half the parts' gain (0.01)
    assert out["used"]
    assert sim.used == [] and float(mat.theta.min()) == 1.0
