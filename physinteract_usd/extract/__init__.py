"""Interaction extraction from a video: the algorithm on plain arrays (no USD).

    result = extract_interaction(scene, frames, masks, hint=Hint(frame=5, pixel=(61.5, 40.5)))

The `extract` verb (read the stage, apply the user's contact sets, write the fit layer) is
`physinteract_usd.app.extract`. Classical computer vision by default; learned models plug in
through `models.Models` (docs/extract.md). One module per question: `pipeline` (the steps in
order), `analysis`, `contact`, `timing`, `interaction_type`, `lifting`, `supports`, `hints`.
"""

from __future__ import annotations

from .hints import parse_hint
from .interaction_type import classify_interaction
from .models import Models
from .pipeline import extract_interaction
from .result import INTERACTION_TYPES, ExtractionResult, Hint

__all__ = ["extract_interaction", "parse_hint", "Hint", "Models", "ExtractionResult", "INTERACTION_TYPES",
           "classify_interaction"]
