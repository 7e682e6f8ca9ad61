"""physinteract-usd: fit a simulation-ready digital twin (material field + interaction) of a soft
object from a monocular video, through a differentiable MPM simulator and Gaussian-splat renderer,
and store it in OpenUSD.

Importing the package registers the PhysInteract USD schemas. The simulator (`physinteract_usd.sim`),
renderer (`physinteract_usd.render`) and optimiser (`physinteract_usd.fit`) know nothing of USD.
"""

__version__ = "0.1.0"

from . import usd as _usd  # noqa: F401  (registers the schemas before any stage opens)
