"""World.check_held: a world capture whose held object tears off its supports and falls is not generated (dev_0485:
a 1.9 kPa block fell off a 35-particle clamp, 600 mm from rest by its last frame; docs/benchmarks/world_fits.md)."""

from __future__ import annotations

from types import SimpleNamespace as NS

import numpy as np
import pytest

from physinteract_usd.errors import SimulationError
from physinteract_usd.synth.world import HELD_FALL, HeldObjectFell, World


def _world(supports=True, extent=0.2):
    return NS(supports=[{"centre": [0, 0, 0], "radius": 0.02, "label": "clamp"}] if supports else [],
              extent=extent, w={"scenario": "clamped"})


def _frames(shift):
    rest = np.random.default_rng(0).uniform(-0.1, 0.1, (50, 3))
    return np.stack([rest, rest + np.array([0.0, -shift, 0.0])])


def test_a_held_object_that_stays_passes_and_one_that_falls_is_refused():
    World.check_held(_world(), _frames(0.5 * HELD_FALL * 0.2))            # swung or pulled: fine
    with pytest.raises(HeldObjectFell, match="tore the object off its clamped support") as e:
        World.check_held(_world(), _frames(3.0 * 0.2))                    # fell 0.6 m, three times its size
    assert isinstance(e.value, SimulationError) and "take another seed" in str(e.value)
    # the CLI keeps the generator's advice (the simulator's "unstable" advice, a shorter step, would mislead)
    from physinteract_usd.cli import CLI_ADVICE
    assert "take another seed" in e.value.message(CLI_ADVICE.get(e.value.kind))
    World.check_held(_world(supports=False), _frames(3.0 * 0.2))          # a free object may go where it goes
