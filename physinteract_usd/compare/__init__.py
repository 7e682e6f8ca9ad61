"""Compare a model's animation with the measurements and say where it fails (the `report`
verb's analysis). Arrays in, a `Comparison` out; no USD, no file paths.

- `core`: `compare(model, measurements, scene)`: per-frame PSNR (full, masked), SSIM, silhouette
  IoU and 2D track error (measured point tracks against the model's projected Gaussians), the
  phases, the noise floor, the residual motion split along velocity / gravity / contact normal,
  whiteness and correlation with the input, the per-particle residual map, the verdict.
- `phases`: rest / load / hold / release / free from the contacts and the hand's path.
- `noise`: the noise floor measured from the video itself.
- `tracks`, `residuals`: the pieces (reusable by diagnose).
- `verdict`: the headline's logic; `figures`, `html`: the side-by-side frames, plots and page.
"""

from .core import Comparison, Measurements, ModelAnimation, SceneInfo, compare, render_frames, track_start
from .tracks import GaussianTracks, background_points
from .noise import NoiseFloor, noise_floor, pixel_noise
from .phases import PHASE_COLORS, PHASES, frame_phases

__all__ = ["compare", "render_frames", "track_start", "GaussianTracks", "background_points", "Comparison", "Measurements", "ModelAnimation", "SceneInfo",
           "NoiseFloor", "noise_floor", "pixel_noise", "PHASES", "PHASE_COLORS", "frame_phases"]
