"""The Python API: every verb of the command line as a function (see `physinteract_usd.app`, one
module per verb). The CLI, the Blender add-on's runner and the benchmarks use only these.

    from physinteract_usd import api
    api.init("scene.usda", "capture/")
    outcome = api.fit("scene.usda", iterations=60)
    api.evaluate("scene.usda", "capture/gt")
"""

import importlib
from typing import TYPE_CHECKING

# Each name is imported from its application module when first used (PEP 562), so a verb imports
# only what it needs: `info` or `versions list` no longer load torch, the simulator and the
# renderer through the other verbs' modules (~1.5-2 s of CPU at every start on a 2-core box).
_LAZY = {
    "load_observations": ("app.adapters", "load_observations"),
    "measured_tracks": ("app.adapters", "measured_tracks"),
    "read_scene": ("app.adapters", "read_scene"),
    "stage_contacts": ("app.adapters", "stage_contacts"),
    "true_contacts": ("app.adapters", "true_contacts"),
    "BatchResult": ("app.batch", "BatchResult"),
    "batch": ("app.batch", "batch"),
    "effects_add": ("app.effects", "add"),
    "effects_list": ("app.effects", "list_effects"),
    "effects_remove": ("app.effects", "remove"),
    "diagnose": ("app.diagnose", "diagnose"),
    "evaluate": ("app.evaluate", "evaluate"),
    "export": ("app.export", "export"),
    "extract": ("app.extract", "extract"),
    "FitJob": ("app.fit", "FitJob"),
    "FitOutcome": ("app.fit", "FitOutcome"),
    "fit": ("app.fit", "fit"),
    "prepare_fit": ("app.fit", "prepare_fit"),
    "run_fit": ("app.fit", "run_fit"),
    "info": ("app.info", "info"),
    "choose_sim_settings": ("app.init", "choose_sim_settings"),
    "init": ("app.init", "init"),
    "INTERACTION_DOC": ("app.interaction_spec", "INTERACTION_DOC"),
    "parse_interaction": ("app.interaction_spec", "parse_interaction"),
    "report": ("app.report", "report"),
    "simulate": ("app.simulate", "simulate"),
    "synth": ("app.synth", "synth"),
    "synth_scenes": ("app.synth", "synth_scenes"),
    "list_versions": ("app.versions", "list_versions"),
    "use_version": ("app.versions", "use"),
    "Hint": ("extract", "Hint"),
    "parse_hint": ("extract", "parse_hint"),
}

if TYPE_CHECKING:     # for readers and type checkers: the same names, imported eagerly
    from .app.adapters import load_observations, measured_tracks, read_scene, stage_contacts, true_contacts
    from .app.batch import BatchResult, batch
    from .app.effects import add as effects_add
    from .app.effects import list_effects as effects_list
    from .app.effects import remove as effects_remove
    from .app.diagnose import diagnose
    from .app.evaluate import evaluate
    from .app.export import export
    from .app.extract import extract
    from .app.fit import FitJob, FitOutcome, fit, prepare_fit, run_fit
    from .app.info import info
    from .app.init import choose_sim_settings, init
    from .app.interaction_spec import INTERACTION_DOC, parse_interaction
    from .app.report import report
    from .app.simulate import simulate
    from .app.synth import synth, synth_scenes
    from .app.versions import list_versions
    from .app.versions import use as use_version
    from .extract import Hint, parse_hint


def __getattr__(name):
    try:
        mod, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module("." + mod, __package__), attr)
    globals()[name] = value       # later look-ups skip this hook
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = ["init", "info", "extract", "fit", "prepare_fit", "run_fit", "FitJob", "FitOutcome", "simulate",
           "evaluate", "export", "synth", "synth_scenes", "choose_sim_settings", "INTERACTION_DOC",
           "parse_interaction", "load_observations", "read_scene", "stage_contacts", "true_contacts", "Hint",
           "parse_hint", "list_versions", "use_version", "report", "measured_tracks", "effects_add",
           "effects_remove", "effects_list", "diagnose", "batch", "BatchResult"]
