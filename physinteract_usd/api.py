"""The Python API: every verb of the command line as a function (see `physinteract_usd.app`, one
module per verb). The CLI, the Blender add-on's runner and the benchmarks use only these.

    from physinteract_usd import api
    api.init("scene.usda", "capture/")
    outcome = api.fit("scene.usda", iterations=60)
    api.evaluate("scene.usda", "capture/gt")
"""

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

__all__ = ["init", "info", "extract", "fit", "prepare_fit", "run_fit", "FitJob", "FitOutcome", "simulate",
           "evaluate", "export", "synth", "synth_scenes", "choose_sim_settings", "INTERACTION_DOC",
           "parse_interaction", "load_observations", "read_scene", "stage_contacts", "true_contacts", "Hint",
           "parse_hint", "list_versions", "use_version", "report", "measured_tracks", "effects_add",
           "effects_remove", "effects_list", "diagnose", "batch", "BatchResult"]
