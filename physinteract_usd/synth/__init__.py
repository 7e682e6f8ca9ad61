"""Synthetic benchmark suite with ground truth: scenes modelled on the PhysInteract paper's Table 1,
hidden-effect variants, two sizes (see docs/synth.md)."""

from .generate import NOISE_PX, SIZES, generate, list_scenes
from .scenes import SCENES, SceneSpec, get_scene

__all__ = ["generate", "list_scenes", "SCENES", "SceneSpec", "get_scene", "SIZES", "NOISE_PX"]
