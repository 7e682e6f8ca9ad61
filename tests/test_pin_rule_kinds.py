"""A pin rule per contact kind (#24): the supports (fixed contacts) take their own rule at the grid nodes they hold
(SimModel.support_rule; the environment's PHYSINTERACT_SUPPORT_RULE in the stage's simulation), the grasps keep
theirs. A node that only a grasp or only a support reaches gets exactly that contact's rule; one both reach mixes
the two by the supports' share of its pinned mass (its gradient: tests/test_sim_gradients.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from physinteract_usd import simulation as S
from physinteract_usd.errors import InputError
from physinteract_usd.sim import Contact, Control, GridSpec, Rollout, SimModel
from sim_helpers import block

DX = 0.05
SP = DX / 2
T = 4


def _positions(contacts, **rules):
    pts = block((6, 3, 3), SP, (0.2, 0.2, 0.25))
    m = SimModel.create(pts, SP ** 3, 1000.0, 2e3, 0.3, grid=GridSpec((0, 0, 0), DX, (16, 14, 14)), fps=15,
                        substeps=10, E_max=2e4, dtype="float64", **rules)
    ctrl = Control(contacts(pts), n_frames=T)
    with torch.no_grad():
        x, _ = Rollout(m, ctrl)(torch.full((len(pts),), 2e3, dtype=torch.float64),
                                torch.full((len(pts),), 0.3, dtype=torch.float64))
    return x.numpy()


def _grasp(pts):
    right = np.nonzero(pts[:, 0] > pts[:, 0].max() - 1e-9)[0]
    tr = np.repeat(pts[right].mean(0)[None], T + 1, 0)
    tr[:, 1] += np.linspace(0.0, 0.02, T + 1)
    return [Contact("pointAdherent", indices=right, trajectory=tr)]


def _clamp(pts):
    left = np.nonzero(pts[:, 0] < pts[:, 0].min() + 2.5 * SP)[0]     # three layers: the band holds a node from 40%
    return [Contact("fixed", indices=left)]


def test_a_support_takes_the_support_rule_and_a_grasp_keeps_its_own():
    band = dict(pin_gain=S.CLAMP_BAND[0], pin_floor=S.CLAMP_BAND[1])
    # a clamp alone (a bar sagging under gravity): the support rule is the rule
    held = _positions(_clamp, support_rule=S.CLAMP_BAND)
    assert np.array_equal(held, _positions(_clamp, **band))
    assert not np.array_equal(held, _positions(_clamp))        # and the rule matters here: the default holds more
    # a grasp alone: the support rule changes nothing
    pulled = _positions(_grasp)
    assert np.array_equal(pulled, _positions(_grasp, support_rule=S.CLAMP_BAND))
    assert not np.array_equal(pulled, _positions(_grasp, pin_gain=2.0))     # (under the band it would let go)


def test_the_support_rule_setting():
    assert S.support_rule(None) is None and S.support_rule(" ") is None
    assert S.support_rule("band") == S.CLAMP_BAND and S.support_rule("2,0.1") == (2.0, 0.1)
    for bad in ("clamp", "0,0", "2,1"):
        with pytest.raises(InputError, match="PHYSINTERACT_SUPPORT_RULE"):
            S.support_rule(bad)
    with pytest.raises(ValueError, match="support rule"):
        SimModel.create(block((2, 2, 2), SP), SP ** 3, grid=GridSpec((0, 0, 0), DX, (16, 14, 14)), fps=15,
                        substeps=2, support_rule=(0.0, 0.2))
    m = SimModel.create(block((2, 2, 2), SP), SP ** 3, grid=GridSpec((0, 0, 0), DX, (16, 14, 14)), fps=15, substeps=2)
    assert m.support_rule == (m.pin_gain, m.pin_floor) == S.DEFAULT_PIN_RULE
