"""The USD layer: schema registration and stage I/O. The only part of the package that imports pxr.

Importing `physinteract_usd` imports this module, which registers the codeless PhysInteract
schemas with USD's plugin registry. That must happen before the first stage is opened.
"""

from __future__ import annotations

from pathlib import Path

from pxr import Plug, Usd

SCHEMA_DIR = Path(__file__).resolve().parent.parent / "schemas"

SCHEMA_TYPES = ("PhysInteractScene", "PhysInteractContactSet", "PhysInteractTrajectory",
                "PhysInteractFitReport")
API_SCHEMAS = ("PhysInteractMaterialFieldAPI", "PhysInteractDampingAPI", "PhysInteractPlasticityAPI",
               "PhysInteractGroundAPI", "PhysInteractViscoelasticityAPI")
EFFECT_APIS = {"damping": "PhysInteractDampingAPI", "plasticity": "PhysInteractPlasticityAPI",
               "ground": "PhysInteractGroundAPI", "viscoelasticity": "PhysInteractViscoelasticityAPI"}


def register_schemas() -> None:
    """Register the PhysInteract codeless schemas (idempotent)."""
    if Plug.Registry().GetPluginWithName("physInteract") is not None:
        return
    if not (SCHEMA_DIR / "plugInfo.json").exists():
        raise RuntimeError(f"{SCHEMA_DIR}: PhysInteract schema plugin (plugInfo.json) not found")
    Plug.Registry().RegisterPlugins(str(SCHEMA_DIR))
    if Usd.SchemaRegistry().FindConcretePrimDefinition("PhysInteractScene") is None:
        raise RuntimeError(f"{SCHEMA_DIR}: PhysInteract schemas did not register; was a stage opened "
                           "before `import physinteract_usd`?")


register_schemas()
