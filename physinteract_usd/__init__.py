"""physinteract-usd: fit a simulation-ready digital twin (material field + interaction) of a soft
object from a monocular video, through a differentiable MPM simulator and Gaussian-splat renderer,
and store it in OpenUSD.

Importing the package registers the PhysInteract USD schemas. The simulator (`physinteract_usd.sim`),
renderer (`physinteract_usd.render`) and optimiser (`physinteract_usd.fit`) know nothing of USD.
"""

__version__ = "0.1.0"

import os as _os
import sys as _sys


def _quiet_warp(wp) -> None:
    """Warp's greeting, module-load lines and "no CUDA driver" notice would clutter every command's
    output (and `--json`); PHYSINTERACT_WARP_LOG=info brings them back."""
    wp.config.log_level = {"debug": wp.LOG_DEBUG, "info": wp.LOG_INFO, "warning": wp.LOG_WARNING}.get(
        _os.environ.get("PHYSINTERACT_WARP_LOG", ""), wp.LOG_ERROR)


# more to run right after Warp is imported (devices.quiet_warp_init_on_load: the CLI's quiet init)
_ON_WARP: list = []


class _WhenWarpLoads:
    """Sets Warp's log level right after Warp is first imported, wherever that happens: importing
    the package does not import Warp (0.4 s of CPU that `info`, `versions`, `export` or a verb's
    `--help` do not need)."""

    @classmethod
    def find_spec(cls, fullname, path=None, target=None):
        if fullname != "warp":
            return None
        _sys.meta_path.remove(cls)
        import importlib.util

        spec = importlib.util.find_spec("warp")
        if spec is None or spec.loader is None:
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            for fn in [_quiet_warp] + _ON_WARP:
                fn(module)

        spec.loader.exec_module = exec_module
        return spec


if "warp" in _sys.modules:
    _quiet_warp(_sys.modules["warp"])
else:
    _sys.meta_path.insert(0, _WhenWarpLoads)

from . import usd as _usd  # noqa: E402,F401  (registers the schemas before any stage opens)
