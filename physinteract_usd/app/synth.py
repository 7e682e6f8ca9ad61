"""`synth`: a synthetic capture with ground truth (scenes modelled on the paper's Table 1, hidden
effects, two sizes); the generator is `physinteract_usd.synth`."""

from __future__ import annotations

from ..synth import generate, list_scenes


def synth(name, out_dir, *, size="small", frames=None, hidden=None, strength=1.0, noise=None, blur=None, seed=0,
          device="cpu", force=False, log=print) -> dict:
    """Write the capture folder `out_dir` (object.ply, frames/, masks/, transforms.json, gt/);
    returns the ground truth's summary (gt/gt.json)."""
    return generate(name, out_dir, size=size, frames=frames, hidden=hidden, strength=strength, noise=noise,
                    blur=blur, seed=seed, device=device, force=force, log=log)


def synth_scenes() -> list:
    """[(name, paper name, interaction type, description)] of the scenes `synth` can make."""
    return list_scenes()
