"""The stage codec of contacts: `PhysInteractContactSet` and `PhysInteractTrajectory` prims <->
`contacts.ContactSet`. The only place that knows how a contact is spelled in USD.

- A contact set is `/World/PhysInteract/<name>` with every attribute of the schema authored
  (particleIndices, contactType, graspTime, releaseTime, source, colliderRadius, contactPoint,
  contactNormal, friction, extentGuessed). "Never released" is `releaseTime = NEVER` (the schema's
  default); read back as `release_frame = None`.
- Its trajectories are `/World/PhysInteract/<name>_<stage>` (stage `initial`: T0 from extraction,
  the user or the ground truth; `fitted`: what a fit made of it), time-sampled position and velocity
  per frame, with `rel physinteract:contactSet` to the set.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Sdf, Usd, Vt

from ..contacts import ContactSet
from ..scene import Trajectory

CONTACT_TYPE = "PhysInteractContactSet"
TRAJECTORY_TYPE = "PhysInteractTrajectory"
NEVER = 1e9                       # releaseTime of a contact that is never released (the schema default)
INITIAL_STAGES = ("initial", "user", "groundTruth")   # trajectory stages that are a contact's T0


# ------------------------------------------------------------------------------------ write
def write_contact(stage: Usd.Stage, parent: Sdf.Path, c: ContactSet, x0: np.ndarray | None = None,
                  fps: float | None = None) -> Usd.Prim:
    """Define the contact set prim under `parent` and, if it has one, its initial trajectory."""
    p = stage.DefinePrim(parent.AppendChild(c.name), CONTACT_TYPE)
    a = lambda n, v: p.GetAttribute(f"physinteract:{n}").Set(v)  # noqa: E731
    a("particleIndices", Vt.IntArray.FromNumpy(np.asarray(c.indices, np.int32)))
    a("contactType", c.type)
    a("graspTime", float(c.grasp_frame))
    a("releaseTime", NEVER if c.release_frame is None else float(c.release_frame))
    a("source", c.source)
    a("colliderRadius", float(c.radius))
    a("contactPoint", Gf.Vec3f(*map(float, c.point(x0))))
    a("contactNormal", Gf.Vec3f(*map(float, c.normal)))
    a("friction", float(c.friction))
    a("extentGuessed", bool(c.guessed))
    if c.trajectory is not None and fps is not None:
        write_trajectory(stage, parent, c.name, c.trajectory, "initial", fps)
    return p


def write_trajectory(stage: Usd.Stage, parent: Sdf.Path, contact_name: str, traj: np.ndarray, stage_name: str,
                     fps: float) -> Usd.Prim:
    """A `<contact>_<stage_name>` trajectory prim: position and finite-difference velocity per frame."""
    tp = stage.DefinePrim(parent.AppendChild(f"{contact_name}_{stage_name}"), TRAJECTORY_TYPE)
    tp.GetAttribute("physinteract:stage").Set(stage_name)
    tp.GetRelationship("physinteract:contactSet").SetTargets([parent.AppendChild(contact_name)])
    traj = np.asarray(traj, np.float64)
    vel = np.vstack([np.diff(traj, axis=0) * fps, np.zeros((1, 3))])
    pa, va = tp.GetAttribute("physinteract:position"), tp.GetAttribute("physinteract:velocity")
    for k in range(len(traj)):
        pa.Set(Gf.Vec3f(*map(float, traj[k])), Usd.TimeCode(k))
        va.Set(Gf.Vec3f(*map(float, vel[k])), Usd.TimeCode(k))
    return tp


def remove_contacts(layer: Sdf.Layer, parent: Sdf.Path, names: set[str] | None = None,
                    keep: set[str] = frozenset()) -> list[str]:
    """Remove contact sets (and the trajectories that move them) from `layer`: those in `names`, or
    all but `keep` when `names` is None. Returns the names of the sets removed."""
    spec = layer.GetPrimAtPath(parent)
    if spec is None:
        return []
    gone = {c.name for c in spec.nameChildren if c.typeName == CONTACT_TYPE and c.name not in keep
            and (names is None or c.name in names)}
    for child in list(spec.nameChildren):
        if child.name in gone:
            del spec.nameChildren[child.name]
        elif child.typeName == TRAJECTORY_TYPE:
            rel = child.relationships.get("physinteract:contactSet")
            targets = [t.name for t in rel.targetPathList.GetAddedOrExplicitItems()] if rel is not None else []
            owner = targets[0] if targets else child.name.rsplit("_", 1)[0]
            if owner in gone:
                del spec.nameChildren[child.name]
    return sorted(gone)


# ------------------------------------------------------------------------------------ read
def read_contact(prim: Usd.Prim, trajectory: np.ndarray | None = None) -> ContactSet:
    g = lambda n: prim.GetAttribute(f"physinteract:{n}").Get()  # noqa: E731
    rel = g("releaseTime")
    rel = None if rel is None or not np.isfinite(rel) or rel >= NEVER else int(round(rel))
    src = str(g("source") or "user")
    return ContactSet(prim.GetName(), str(g("contactType")), np.array(g("particleIndices") or [], np.int64),
                      int(round(g("graspTime") or 0)), rel, trajectory, radius=float(g("colliderRadius") or 0.0),
                      normal=tuple(float(x) for x in g("contactNormal")), friction=float(g("friction")),
                      contact_point=np.array(g("contactPoint"), np.float64), source=src,
                      guessed=bool(g("extentGuessed")))


def read_trajectory(prim: Usd.Prim) -> Trajectory:
    pos_attr = prim.GetAttribute("physinteract:position")
    times = pos_attr.GetTimeSamples()
    pos = np.array([pos_attr.Get(tc) for tc in times], dtype=np.float64).reshape(-1, 3)
    vel_attr = prim.GetAttribute("physinteract:velocity")
    vel = (np.array([vel_attr.Get(tc) for tc in times], dtype=np.float64).reshape(-1, 3)
           if vel_attr.GetNumTimeSamples() == len(times) and times else None)
    targets = prim.GetRelationship("physinteract:contactSet").GetTargets()
    return Trajectory(prim.GetName(), targets[0].name if targets else "", np.array(times, dtype=np.float64), pos,
                      vel, str(prim.GetAttribute("physinteract:stage").Get()))


def read_contacts(scene_prim: Usd.Prim) -> tuple[list[ContactSet], list[Trajectory]]:
    """The composed stage's contact sets, each with its initial trajectory (T0) attached when it has
    one, and every trajectory prim (initial and fitted)."""
    trajs = [read_trajectory(ch) for ch in scene_prim.GetChildren() if ch.GetTypeName() == TRAJECTORY_TYPE]
    t0 = {t.contact_set: t.positions for t in trajs if t.stage in INITIAL_STAGES}
    contacts = [read_contact(ch, t0.get(ch.GetName())) for ch in scene_prim.GetChildren()
                if ch.GetTypeName() == CONTACT_TYPE]
    return contacts, trajs


def authored_contact_names(layer: Sdf.Layer | None, parent: Sdf.Path) -> list[str]:
    """Names of the contact sets a layer authors (defined, or overs that set particle indices)."""
    if layer is None:
        return []
    spec = layer.GetPrimAtPath(parent)
    if spec is None:
        return []
    return [ch.name for ch in spec.nameChildren
            if ch.typeName == CONTACT_TYPE or (ch.specifier == Sdf.SpecifierOver
                                               and "physinteract:particleIndices" in ch.attributes)]
