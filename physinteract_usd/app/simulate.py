"""`simulate`: re-simulate the fitted object under a new interaction (a JSON spec, see
`interaction_spec`), with the effects the stage switches on at the values its last fit found;
written as its own layer and a small view stage over the fitted one (the user's root untouched)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..simulation import build_simulation
from ..usd.fit_io import write_simulation_layer
from .adapters import effects_with_fitted, read_scene
from .interaction_spec import parse_interaction


def simulate(stage_path, interaction, *, name=None, device="cpu", log=print) -> dict:
    """Returns {"layer", "stage", "frames"}: the simulation layer, its view stage, the frame count."""
    sd = read_scene(stage_path)
    if not sd.reports:
        log("note: the stage has no fit yet; simulating with its current (initial) material")
    spec, n, contacts = parse_interaction(interaction, sd)
    name = name or spec.get("name") or Path(interaction).stem
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name):
        raise InputError(name, "simulation name may hold letters, digits, '_' and '-' only")
    sd_n = dataclasses.replace(sd, end_frame=sd.start_frame + n - 1)
    try:
        sim = build_simulation(sd_n, contacts, n, effects=effects_with_fitted(sd), device=device)
    except ValueError as exc:  # what the spec's checks did not catch (the simulator's own)
        raise InputError(interaction, str(exc)) from None
    st = sd.settings
    E = torch.as_tensor(sd.youngs_modulus, dtype=sim.tdtype).clamp(st.youngs_min, st.youngs_max)
    nu = torch.as_tensor(np.minimum(sd.poisson_ratio, st.poisson_max), dtype=sim.tdtype)
    with torch.no_grad():
        x, F = sim.simulate(E, nu)
        means, covs = zip(*[sim.gaussians_at(x[k], F[k]) for k in range(n)])
    out = write_simulation_layer(stage_path, sd, name, x.cpu().numpy(), np.stack([m.cpu().numpy() for m in means]),
                                 np.stack([c.cpu().numpy() for c in covs]), sd.fps, spec)
    out["frames"] = n
    return out
