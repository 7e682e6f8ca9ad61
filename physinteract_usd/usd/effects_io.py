"""`effects add | remove`: an effect's API schema (`PhysInteractDampingAPI` ...) applied to, or
removed from, `/World/PhysInteract` in the user's ROOT layer (scene.usda), with its start values
and `fit` flag; nothing else of the root is touched and the generated sublayers never are. The
composed effects are read by `usd.stage.read_stage` (SceneData.effects): the one reader.

The root is edited as a copy (`Sdf.Layer.OpenAsAnonymous`) and written back atomically; an effect
applied in a weaker layer (not ours to edit) is removed by a `deletedItems` entry in the root.
"""

from __future__ import annotations

from pathlib import Path

from pxr import Sdf, Usd

from ..errors import InputError
from . import EFFECT_APIS
from .layout import SCENE, WORLD, check_our_root, remove_prim_spec, save_layer
from .stage import open_stage


def _prefix(effect: str) -> str:
    return f"physinteract:{effect}:"


def _list_op(spec: Sdf.PrimSpec) -> Sdf.TokenListOp:
    op = spec.GetInfo("apiSchemas") if spec.HasInfo("apiSchemas") else None
    return op if op is not None else Sdf.TokenListOp()


def _set_list_op(spec: Sdf.PrimSpec, op: Sdf.TokenListOp) -> None:
    empty = (not op.isExplicit and not op.prependedItems and not op.appendedItems and not op.deletedItems
             and not op.addedItems and not op.orderedItems)
    if empty:
        if spec.HasInfo("apiSchemas"):
            spec.ClearInfo("apiSchemas")
    else:
        spec.SetInfo("apiSchemas", op)


def _attr_type(api: str, name: str) -> Sdf.ValueTypeName:
    d = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(api)
    spec = d.GetSchemaAttributeSpec(name) if d is not None else None
    return spec.typeName if spec is not None else (Sdf.ValueTypeNames.Bool if name.endswith(":fit")
                                                   else Sdf.ValueTypeNames.Float)


def composed_effects(stage_path) -> set[str]:
    """The effects the composed stage switches on."""
    scene = open_stage(stage_path).GetPrimAtPath(SCENE)
    return {e for e, api in EFFECT_APIS.items() if scene.HasAPI(api)}


def root_values(stage_path, effect: str) -> dict:
    """{attribute name without prefix: value} the root layer itself authors for `effect`."""
    layer = Sdf.Layer.OpenAsAnonymous(str(stage_path))
    spec = layer.GetPrimAtPath(SCENE) if layer is not None else None
    if spec is None:
        return {}
    return {n[len(_prefix(effect)):]: a.default for n, a in spec.attributes.items()
            if n.startswith(_prefix(effect)) and a.HasDefaultValue()}


def apply_effect(stage_path, effect: str, values: dict, fit: bool, *, keep_authored: bool = True) -> dict:
    """Apply `effect`'s API to /World/PhysInteract in the root layer with `values` ({parameter:
    float}) and `physinteract:<effect>:fit`. A value the root already authors for a parameter not in
    `values` is kept (`keep_authored`). Returns {parameter: value} as authored."""
    path = Path(stage_path)
    api = EFFECT_APIS[effect]
    check_our_root(path)
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    if layer is None:
        raise InputError(path, "cannot be opened as a USD layer")
    spec = Sdf.CreatePrimInLayer(layer, SCENE)   # `over`s for /World and /World/PhysInteract if absent
    op = _list_op(spec)
    if op.isExplicit:
        items = list(op.explicitItems)
        if api not in items:
            op.explicitItems = items + [api]
    else:
        op.deletedItems = [x for x in op.deletedItems if x != api]
        if api not in op.prependedItems and api not in op.appendedItems:
            op.prependedItems = list(op.prependedItems) + [api]
    _set_list_op(spec, op)
    authored = {}
    for name, v in list(values.items()) + [("fit", bool(fit))]:
        full = _prefix(effect) + name
        attr = spec.attributes.get(full)
        if attr is not None and keep_authored and name not in values and name != "fit":
            authored[name] = attr.default
            continue
        if attr is None:
            attr = Sdf.AttributeSpec(spec, full, _attr_type(api, full))
        attr.default = v
        authored[name] = v
    save_layer(layer, path)
    return authored


def remove_effect(stage_path, effect: str) -> list[str]:
    """Remove `effect`'s API (and the root's values of its parameters) from the root layer; an
    effect applied by a weaker layer gets a `delete` entry. Empty `over`s this leaves are removed.
    Returns the attribute names removed."""
    path = Path(stage_path)
    api = EFFECT_APIS[effect]
    check_our_root(path)
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    if layer is None:
        raise InputError(path, "cannot be opened as a USD layer")
    removed = []
    spec = layer.GetPrimAtPath(SCENE)
    if spec is not None:
        op = _list_op(spec)
        if op.isExplicit:
            op.explicitItems = [x for x in op.explicitItems if x != api]
        else:
            op.prependedItems = [x for x in op.prependedItems if x != api]
            op.appendedItems = [x for x in op.appendedItems if x != api]
        _set_list_op(spec, op)
        for name in [n for n in spec.attributes.keys() if n.startswith(_prefix(effect))]:
            spec.RemoveProperty(spec.attributes[name])
            removed.append(name)
    # still applied by a weaker layer? then the root says delete
    weaker = [Sdf.Layer.FindOrOpen(str((path.parent / s).resolve())) if not Path(s).is_absolute()
              else Sdf.Layer.FindOrOpen(s) for s in layer.subLayerPaths]
    if any(_applies(w, api) for w in weaker if w is not None):
        spec = Sdf.CreatePrimInLayer(layer, SCENE)
        op = _list_op(spec)
        if not op.isExplicit and api not in op.deletedItems:
            op.deletedItems = list(op.deletedItems) + [api]
        _set_list_op(spec, op)
    _prune(layer)
    save_layer(layer, path)
    return removed


def _applies(layer: Sdf.Layer, api: str) -> bool:
    spec = layer.GetPrimAtPath(SCENE)
    if spec is None or not spec.HasInfo("apiSchemas"):
        return False
    op = spec.GetInfo("apiSchemas")
    return api in op.explicitItems or api in op.prependedItems or api in op.appendedItems


def _is_bare_over(spec: Sdf.PrimSpec) -> bool:
    """An `over` with nothing in it (what `apply_effect` created and `remove_effect` emptied)."""
    keys = set(spec.ListInfoKeys()) - {"specifier"}
    return (spec.specifier == Sdf.SpecifierOver and not keys and not spec.properties
            and not spec.nameChildren)


def _prune(layer: Sdf.Layer) -> None:
    for p in (SCENE, WORLD):
        spec = layer.GetPrimAtPath(p)
        if spec is not None and _is_bare_over(spec):
            remove_prim_spec(layer, p)
