"""`synth`: a synthetic capture with ground truth: the named scenes (modelled on the paper's Table 1,
hidden effects, two sizes) or a randomised world capture of the dev or validation split; the
generators are `physinteract_usd.synth` (`generate`, `world.generate_world`)."""

from __future__ import annotations

from ..errors import InputError
from ..synth import generate, list_scenes


def synth(name, out_dir, *, size="small", frames=None, hidden=None, strength=1.0, noise=None, blur=None, seed=0,
          device="cpu", force=False, log=print, random=None, split="dev", overrides=None, fit_grid=None,
          transfer_tau=0.0, calibrate="particles", truth_for_auto=None) -> dict:
    """Write the capture folder `out_dir` (object.ply, frames/ or video.mp4, masks/, transforms.json,
    gt/); returns the ground truth's summary (gt/gt.json).

    `random=SEED` (name None): world capture SEED of `split` ("dev", or "validation": never tuned
    on; its folders carry the split's marker, docs/benchmarks/world.md), everything drawn from the
    split's random stream; `frames` and `overrides` (drawn values by name) replace drawn values.
    `fit_grid` (named scenes): the init grid suggested instead of the size's; the truth's grid follows.
    `transfer_tau` (named scenes) [s]: the truth simulated with the rate transfer (docs/sim.md; 0: APIC).
    `calibrate` (named scenes, `hidden`): "particles" (default) or "frames", what `strength` measures
    (docs/synth.md). `truth_for_auto=N` (world captures): the truth also finer than the fit `init --grid auto
    --max-particles N` makes (beyond the CPU's budget on thin objects: a GPU's; docs/benchmarks/world_fits.md)."""
    if truth_for_auto is not None:
        if random is None:
            raise InputError("--truth-for-auto", "only for world captures (--random / --validation SEED)")
        if isinstance(truth_for_auto, bool) or int(truth_for_auto) != truth_for_auto or truth_for_auto < 100:
            raise InputError("--truth-for-auto", f"must be init's particle cap, a whole number >= 100, got {truth_for_auto}")
    if random is not None:
        from ..synth.world import generate_world

        if name is not None:
            raise InputError("synth", "give either a scene name or --random / --validation SEED, not both")
        for flag, v in (("--size", size != "small"), ("--hidden", hidden is not None), ("--noise", noise is not None),
                        ("--blur", blur is not None), ("--fit-grid", fit_grid is not None),
                        ("--transfer-tau", bool(transfer_tau)), ("--calibrate", calibrate != "particles")):
            if v:
                raise InputError(flag, "world captures draw it themselves (not with --random / --validation)")
        ov = dict(overrides or {})
        if frames is not None:
            if int(frames) < 3:
                raise InputError("--frames", "needs at least 3 frames")
            ov["frames"] = int(frames)
        if truth_for_auto is not None:
            ov["truth_for_auto"] = int(truth_for_auto)
        return generate_world(int(random), out_dir, split=split, overrides=ov, device=device, force=force, log=log)
    return generate(name, out_dir, size=size, frames=frames, hidden=hidden, strength=strength, noise=noise,
                    blur=blur, seed=seed, device=device, force=force, log=log, fit_grid=fit_grid,
                    transfer_tau=transfer_tau, calibrate=calibrate)


def synth_scenes() -> list:
    """[(name, paper name, interaction type, description)] of the scenes `synth` can make."""
    return list_scenes()
