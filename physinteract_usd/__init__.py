"""physinteract-usd: fit a simulation-ready digital twin (material field + interaction) of a soft
object from a monocular video, through a differentiable MPM simulator and Gaussian-splat renderer,
and store it in OpenUSD.

Importing the package registers the PhysInteract USD schemas. The simulator (`physinteract_usd.sim`),
renderer (`physinteract_usd.render`) and optimiser (`physinteract_usd.fit`) know nothing of USD.
"""

__version__ = "0.1.0"

import os as _os

import warp as _wp

# Warp's greeting, module-load lines and "no CUDA driver" notice would clutter every command's
# output (and `--json`); PHYSINTERACT_WARP_LOG=info brings them back.
_wp.config.log_level = {"debug": _wp.LOG_DEBUG, "info": _wp.LOG_INFO, "warning": _wp.LOG_WARNING}.get(
    _os.environ.get("PHYSINTERACT_WARP_LOG", ""), _wp.LOG_ERROR)

from . import usd as _usd  # noqa: E402,F401  (registers the schemas before any stage opens)
