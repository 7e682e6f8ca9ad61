"""Where learned models plug in.

Extraction calls three replaceable parts. The defaults are classical computer vision (OpenCV,
numpy, scipy) and need no weights and no GPU; a VLM / grounding model / SAM / 4D-Humans pipeline
can replace any of them by implementing the same call:

- `HandSegmenter`: frames (T, H, W, 3) float in [0, 1], object silhouettes (T, H, W) bool or None
  -> `segmentation.Segmentation` (hand and object masks per frame, background). Default:
  `segmentation.ColourMotionSegmenter` (background subtraction + learned colour models).
- `PointTracker`: `flows(frames) -> track.Flows` and `track(flows, points, start, stop) ->
  track.Tracks`. Default: `track.DenseFlowTracker` (DIS optical flow, chained, forward-backward
  checked). A learned point tracker only needs `track`; `flows` may return dense flow estimated
  from anything.
- `InteractionClassifier`: the evidence dict extraction computes (see docs/extract.md) ->
  (type, confidence). Default: `interaction_type.classify_interaction` (rules on the push/pull and
  surface evidence). A VLM that looks at the frames can implement it from the frames instead
  (the `frames` keyword is passed).

`Models()` holds the defaults; pass `Models(segmenter=MySAM())` to `extract(..., models=...)`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


class HandSegmenter(Protocol):
    name: str

    def __call__(self, frames: np.ndarray, masks: np.ndarray | None, *, masks_amodal: bool = False,
                 rest_alpha: np.ndarray | None = None, object_colors: np.ndarray | None = None):
        ...


class PointTracker(Protocol):
    name: str

    def flows(self, frames: np.ndarray):
        ...

    def track(self, flows, points: np.ndarray, start: int = 0, stop: np.ndarray | None = None):
        ...


class InteractionClassifier(Protocol):
    def __call__(self, evidence: dict, *, frames: np.ndarray | None = None) -> tuple[str, float]:
        ...


def _default_segmenter():
    from .segmentation import ColourMotionSegmenter

    return ColourMotionSegmenter()


def _default_tracker():
    from .track import DenseFlowTracker

    return DenseFlowTracker()


def _default_classifier():
    from .interaction_type import classify_interaction

    return classify_interaction


@dataclass
class Models:
    segmenter: HandSegmenter = field(default_factory=_default_segmenter)
    tracker: PointTracker = field(default_factory=_default_tracker)
    classifier: InteractionClassifier = field(default_factory=_default_classifier)

    def describe(self) -> dict:
        return {"segmenter": getattr(self.segmenter, "name", type(self.segmenter).__name__),
                "tracker": getattr(self.tracker, "name", type(self.tracker).__name__),
                "classifier": getattr(self.classifier, "__name__", type(self.classifier).__name__)}
