"""The synthetic suite, modelled on the PhysInteract paper's Table 1: eight synthetic scenes and
stand-ins for its three real ones. Each scene is procedural geometry (analytic SDF parts),
a spatially varying ground-truth Young's modulus (mostly >= 5x range: a stiff part and soft ones),
realistic Poisson ratios, one interaction of the paper's type, supports the camera does not see,
and an oblique static camera.

Units: metres, Pa, kg/m^3. Y is up. Rest shapes sit around the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .geometry import Box, Capsule, Ellipsoid, Shape, Tube, helix

# ------------------------------------------------------------------------------ textures


def _hash3(c: np.ndarray) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per integer cell."""
    c = c.astype(np.int64)
    h = (c[:, 0] * 73856093) ^ (c[:, 1] * 19349663) ^ (c[:, 2] * 83492791)
    return ((h * 2654435761) % 2 ** 32) / 2 ** 32


def value_noise(p: np.ndarray, scale: float) -> np.ndarray:
    """Smooth 3D value noise in [0, 1) with features of size ~scale."""
    q = p / scale
    i = np.floor(q)
    f = q - i
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(p))
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * (f[:, 2] if dz else 1 - f[:, 2])
                out += w * _hash3(i + np.array([dx, dy, dz]))
    return out


def pattern_color(p, base, accent, scale, kind="noise", axis=(0, 1, 0), freq=40.0):
    """Base colour mixed with an accent by a solid pattern: noise blotches, stripes or dots."""
    base = np.asarray(base, float)
    accent = np.asarray(accent, float)
    if kind == "stripes":
        t = 0.5 + 0.5 * np.sin(freq * (p @ np.asarray(axis, float)) + 3.0 * value_noise(p, scale))
    elif kind == "dots":
        q = p / scale
        d = np.linalg.norm(q - np.floor(q) - 0.5, axis=1)
        t = (d < 0.3).astype(float)
    elif kind == "checker":
        c = np.floor(p / scale).astype(int)
        t = ((c[:, 0] + c[:, 1] + c[:, 2]) % 2).astype(float)
    else:
        t = value_noise(p, scale)
        t = np.clip((t - 0.35) * 2.5, 0, 1)
    shade = 0.85 + 0.3 * value_noise(p, scale * 0.37)
    return np.clip((base[None] * (1 - t[:, None]) + accent[None] * t[:, None]) * shade[:, None], 0, 1)


# ------------------------------------------------------------------------------ scene spec
@dataclass
class Support:
    """Particles within `radius` of `centre` (rest) are held still: a hook, a clamp, a table."""

    centre: tuple
    radius: float
    label: str = "support"


@dataclass
class SceneSpec:
    name: str
    paper_name: str
    origin: str                              # "synthetic" or "real" (a stand-in for a real capture)
    interaction: str                         # contact type
    description: str
    shape: Callable[[], Shape]
    youngs: Callable[[np.ndarray, np.ndarray], np.ndarray]   # (points, part index) -> E [Pa]
    poisson: dict                            # part label -> nu
    density: float
    texture: Callable[[np.ndarray, np.ndarray], np.ndarray]  # (points, part index) -> RGB
    contact_point: tuple                     # rest position of the contact (surface)
    contact_radius: float                    # grasp region radius / collider radius
    path: Callable[[np.ndarray], np.ndarray]  # s in [0, 1] -> displacement of the contact (m)
    hand_dir: tuple                          # direction from the contact to the hand's body
    supports: list = field(default_factory=list)
    camera_eye: tuple = (0.45, 0.35, 0.75)
    camera_target: tuple = (0.0, 0.0, 0.0)
    fov_y: float = 40.0
    plane_normal: tuple = (0.0, -1.0, 0.0)   # surfaceNonAdherent: side the object is on
    collider_shape: str = "sphere"
    friction: float = 0.5                    # collider / surface friction
    phases: tuple = (0.12, 0.6)              # grasp, release as fractions of the clip
    hidden_effects: tuple = ("damping",)

    @property
    def labels(self) -> list[str]:
        return self.shape().labels


def _smooth(s):
    s = np.clip(s, 0.0, 1.0)
    return s * s * (3 - 2 * s)


def _by_part(values: dict, labels: list[str]):
    def f(p, part):
        return np.array([values[labels[i]] for i in part], dtype=np.float64)
    return f


# ------------------------------------------------------------------------------ scenes
def _hemp_rope():
    pts = np.stack([0.012 * np.sin(np.linspace(0, 3, 9)), np.linspace(0.16, -0.16, 9), np.zeros(9)], 1)
    return Shape([Tube("rope", pts, 0.022)])


def _hemp_rope_E(p, part):
    # stiff, tightly twisted top grading log-linearly into a soft frayed end: 5x over the length
    s = np.clip((0.16 - p[:, 1]) / 0.32, 0, 1)
    return np.exp(np.log(STIFF) + s * (np.log(SOFT) - np.log(STIFF)))


def _tow_rope():
    return Shape([Box("strap", (0, 0, 0), (0.17, 0.012, 0.03), rounding=0.006),
                  Box("hook_left", (-0.19, 0, 0), (0.03, 0.018, 0.035), rounding=0.008),
                  Box("hook_right", (0.19, 0, 0), (0.03, 0.018, 0.035), rounding=0.008)])


def _glove():
    """Hanging from a clip at the wrist, fingers down."""
    parts = [Box("palm", (0, 0, 0), (0.06, 0.07, 0.022), rounding=0.015)]
    xs = [-0.045, -0.015, 0.015, 0.045]
    lens = [0.06, 0.07, 0.068, 0.055]
    for i, (x, L) in enumerate(zip(xs, lens)):
        # fanned out a little, so that the fingers are apart (not a mitten) in the frames
        parts.append(Capsule(f"finger{i}", (x, -0.06, 0), (1.45 * x, -0.06 - L, 0), 0.014))
    parts.append(Capsule("thumb", (-0.055, 0.0, 0), (-0.1, -0.05, 0), 0.017))
    return Shape(parts)


def _balloon_dog():
    r = 0.022
    return Shape([
        Capsule("body", (-0.08, 0.0, 0), (0.08, 0.0, 0), r),
        Capsule("leg_fl", (0.07, 0.0, 0.025), (0.07, -0.09, 0.035), r),
        Capsule("leg_fr", (0.07, 0.0, -0.025), (0.07, -0.09, -0.035), r),
        Capsule("leg_bl", (-0.07, 0.0, 0.025), (-0.07, -0.09, 0.035), r),
        Capsule("leg_br", (-0.07, 0.0, -0.025), (-0.07, -0.09, -0.035), r),
        # neck near upright and a short, raised head: a longer, level head on this soft neck sagged
        # ~7 cm under its own weight, more than the hand's pull
        Capsule("neck", (0.08, 0.0, 0), (0.095, 0.085, 0), r),
        Capsule("head", (0.095, 0.085, 0), (0.145, 0.1, 0), r),
        Capsule("tail", (-0.08, 0.0, 0), (-0.12, 0.06, 0), 0.017),
        Ellipsoid("knot_front", (0.08, 0.0, 0), (0.028, 0.028, 0.028)),
        Ellipsoid("knot_back", (-0.08, 0.0, 0), (0.028, 0.028, 0.028)),
    ])


def _balloon():
    """Hanging from its knot (the neck up)."""
    return Shape([Ellipsoid("balloon", (0, -0.02, 0), (0.1, 0.125, 0.1)),
                  Ellipsoid("neck", (0, 0.11, 0), (0.022, 0.03, 0.022))])


def _balloon_E(p, part):
    # thicker, stiffer rubber near the neck grading to a thin soft bottom: 5x
    s = np.clip((0.14 - p[:, 1]) / 0.28, 0, 1)
    return np.exp(np.log(STIFF) + s * (np.log(SOFT) - np.log(STIFF)))


def _flower():
    # the stem is thick enough to hold the head up: at 18 mm radius the head's weight was near the
    # stem's Euler buckling load and the flower fell over after the pull
    parts = [Capsule("stem", (0, -0.09, 0), (0, 0.04, 0), 0.024),
             Ellipsoid("centre", (0, 0.05, 0), (0.028, 0.018, 0.028))]
    for i in range(5):
        a = 2 * np.pi * i / 5 + 0.3
        d = np.array([np.cos(a), 0.0, np.sin(a)])
        R = np.stack([d, np.array([0.0, 1.0, 0.0]), np.cross(d, [0.0, 1.0, 0.0])], 1)
        parts.append(Ellipsoid(f"petal{i}", tuple(np.array([0, 0.055, 0]) + 0.058 * d), (0.045, 0.012, 0.028), R))
    return Shape(parts)


def _basketball():
    return Shape([Ellipsoid("shell", (0, 0, 0), (0.11, 0.11, 0.11))])


def _basketball_E(p, part):
    # a rubber shell over a soft core (1.5e4); the shell is worn soft where it is pressed: 3.75e4
    # where it sits on the stand grading log-linearly to 7.5e3 at the top. The grading is what
    # makes the field vary over the surface, where the Gaussians (and MA) are: a shell of one E
    # would let a uniform E score MA 1.
    r = np.linalg.norm(p, axis=1)
    s = np.clip((p[:, 1] + 0.11) / 0.22, 0, 1)
    shell = np.exp(np.log(STIFF) + s * (np.log(SOFT) - np.log(STIFF)))
    return np.where(r > 0.08, shell, MID)


def _knit_cap():
    # a thick hemispherical shell (the cap) with a rib band at the rim and a pompom on top
    parts = []
    cap_pts = []
    for k, phi in enumerate(np.linspace(0.15, np.pi / 2 - 0.05, 5)):
        ring = [(0.1 * np.cos(t) * np.cos(phi), 0.1 * np.sin(phi) - 0.03, 0.1 * np.sin(t) * np.cos(phi))
                for t in np.linspace(0, 2 * np.pi, 25)]
        cap_pts.append(np.array(ring))
    for k, ring in enumerate(cap_pts):
        parts.append(Tube("body" if k else "rib", ring, 0.02 if k else 0.022))
    parts.append(Ellipsoid("pompom", (0, 0.095, 0), (0.035, 0.035, 0.035)))
    return Shape(parts)


def _toy_rope():
    pts = np.stack([0.015 * np.sin(np.linspace(0, 5, 11)), np.linspace(0.2, -0.2, 11), 0.012 * np.cos(np.linspace(0, 3, 11))], 1)
    parts = [Tube("rope", pts, 0.018)]
    for i, j in enumerate((0, 5, 10)):
        parts.append(Ellipsoid(f"knot{i}", tuple(pts[j]), (0.03, 0.03, 0.03)))
    return Shape(parts)


# The coil is a helical spring of soft foam (E / rho = 50 m^2/s^2): its sag under its own weight
# between the two held plugs grows as D^4 n^2 / d^2 (coil diameter D, n turns, wire diameter d).
# A phone-cord-like 9 cm coil of 5 turns of 22 mm wire would sag metres: it collapses, its turns
# collide and the ground truth goes non-finite. 3 turns of 6 cm over 28 mm wire sag ~1 cm, and the
# wire is ~4.5 ground-truth particles thick.
COIL_TOP, COIL_R, COIL_PITCH, COIL_TURNS, COIL_WIRE, PLUG_LEN = 0.07, 0.03, 0.045, 3.0, 0.014, 0.05


def _coil_points(t=None):
    if t is None:
        return helix((0, COIL_TOP, 0), COIL_R, COIL_PITCH, COIL_TURNS, n_per_turn=20)
    return np.array([COIL_R * np.cos(t), COIL_TOP - COIL_PITCH * t / (2 * np.pi), COIL_R * np.sin(t)])


def _telephone_cable():
    pts = _coil_points()
    return Shape([Tube("coil", pts, COIL_WIRE),
                  Capsule("plug_top", tuple(pts[0]), tuple(pts[0] + [0, PLUG_LEN, 0]), 0.016),
                  Capsule("plug_bottom", tuple(pts[-1]), tuple(pts[-1] + [0, -PLUG_LEN, 0]), 0.016)])


_POKE_T = 4 * np.pi - 0.4   # the poked point: mid-height, the coil's outer side facing the image's right
_POKE_AT = _coil_points(_POKE_T) + COIL_WIRE * np.array([np.cos(_POKE_T), 0.0, np.sin(_POKE_T)])


PULL = 0.6  # all hand paths are scaled by this: soft parts stretch a lot already at 60%


def _arc(d1, d2):
    d1, d2 = PULL * np.asarray(d1, float), PULL * np.asarray(d2, float)
    return lambda s: np.outer(_smooth(s), d1) + np.outer(np.sin(np.pi * np.clip(s, 0, 1)), d2)


def _press(depth_vec):
    d = PULL * np.asarray(depth_vec, float)
    return lambda s: np.outer(np.sin(np.pi * np.clip(s, 0, 1)) ** 2, d)


def _bow_tie_shape():
    return Shape([
        Ellipsoid("knot", (0, 0, 0), (0.03, 0.035, 0.028)),
        Ellipsoid("lobe_left", (-0.07, 0, 0), (0.06, 0.045, 0.02)),
        Ellipsoid("lobe_right", (0.07, 0, 0), (0.06, 0.045, 0.02)),
    ])


# Materials: light foam/fabric-like objects. Elastic wave speed sets the substep, gravity sets the
# sag: with E/rho >= 50 m^2/s^2 for the soft parts the objects do not collapse under their weight,
# and with E/rho <= 250 for the stiff parts the CFL substep stays coarse enough for CPU fits.
RHO = 150.0
SOFT, MID, STIFF = 7.5e3, 1.5e4, 3.75e4

SCENES: dict[str, SceneSpec] = {}


def _add(spec: SceneSpec):
    SCENES[spec.name] = spec


_add(SceneSpec(
    name="hemp_rope", paper_name="hemp rope", origin="synthetic", interaction="pointAdherent",
    description="a hemp rope hanging from a hook; the hand grabs its lower end, swings it aside and lets go",
    shape=_hemp_rope, youngs=_hemp_rope_E, poisson={"rope": 0.3}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.72, 0.58, 0.36), (0.42, 0.3, 0.16), 0.02, "stripes",
                                          axis=(0.5, 0.85, 0.0), freq=90.0),
    contact_point=(0.0, -0.13, 0.02), contact_radius=0.03, path=_arc((0.1, 0.05, 0.04), (0.0, 0.02, 0.03)),
    hand_dir=(0.3, -0.4, 1.0), supports=[Support((0.0, 0.17, 0.0), 0.035, "hook")],
    camera_eye=(0.25, 0.1, 0.75), camera_target=(0.03, 0.0, 0.0), hidden_effects=("damping", "viscoelasticity")))

_add(SceneSpec(
    name="bow_tie", paper_name="bow tie", origin="synthetic", interaction="pointAdherent",
    description="a bow tie clamped at its knot; the hand pulls the right lobe outward and lets go",
    shape=_bow_tie_shape,
    youngs=lambda p, part: np.array([STIFF, SOFT, SOFT])[part],
    poisson={"knot": 0.35, "lobe_left": 0.3, "lobe_right": 0.3}, density=RHO,
    texture=lambda p, part: np.where((part == 0)[:, None], pattern_color(p, (0.1, 0.1, 0.35), (0.8, 0.8, 0.9), 0.01, "dots"),
                                     pattern_color(p, (0.55, 0.08, 0.12), (0.95, 0.85, 0.3), 0.018, "dots")),
    contact_point=(0.12, 0.0, 0.01), contact_radius=0.025, path=_arc((0.05, 0.05, 0.04), (0.0, 0.0, 0.02)),
    hand_dir=(1.0, 0.2, 0.6), supports=[Support((0.0, 0.0, -0.02), 0.03, "clamp")],
    camera_eye=(0.12, 0.3, 0.6), camera_target=(0.02, 0.0, 0.0), hidden_effects=("plasticity", "damping")))

_add(SceneSpec(
    name="tow_rope", paper_name="tow rope", origin="synthetic", interaction="pointAdherent",
    description="a tow strap hooked between two anchors; the hand lifts its middle and lets go",
    shape=_tow_rope,
    youngs=lambda p, part: np.array([SOFT, STIFF, STIFF])[part],
    poisson={"strap": 0.3, "hook_left": 0.4, "hook_right": 0.4}, density=RHO,
    texture=lambda p, part: np.where((part == 0)[:, None], pattern_color(p, (0.9, 0.5, 0.05), (0.2, 0.2, 0.2), 0.02, "stripes", axis=(1, 0, 0.3), freq=120.0),
                                     pattern_color(p, (0.25, 0.25, 0.28), (0.7, 0.7, 0.7), 0.012, "checker")),
    contact_point=(0.02, 0.0, 0.03), contact_radius=0.03, path=_arc((0.0, 0.06, 0.06), (0.02, 0.0, 0.0)),
    hand_dir=(0.2, 0.5, 1.0), supports=[Support((-0.2, 0.0, 0.0), 0.045, "anchor"), Support((0.2, 0.0, 0.0), 0.045, "anchor")],
    camera_eye=(0.1, 0.35, 0.7), camera_target=(0.0, 0.02, 0.0), hidden_effects=("damping", "ground")))

_add(SceneSpec(
    name="glove", paper_name="glove", origin="synthetic", interaction="pointAdherent",
    description="a knit glove hanging from a clip at the wrist; the hand pulls a finger aside and lets go",
    shape=_glove,
    youngs=lambda p, part: np.where(part == 0, STIFF, SOFT),
    poisson={"palm": 0.35, **{f"finger{i}": 0.3 for i in range(4)}, "thumb": 0.3}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.2, 0.45, 0.7), (0.9, 0.9, 0.85), 0.012, "checker"),
    contact_point=(0.021, -0.12, 0.014), contact_radius=0.025, path=_arc((0.06, 0.03, 0.06), (0.0, 0.01, 0.02)),
    hand_dir=(0.3, -0.5, 1.0), supports=[Support((0.0, 0.075, 0.0), 0.05, "wrist clip")],
    camera_eye=(0.35, 0.2, 0.65), camera_target=(0.0, 0.05, 0.0), hidden_effects=("plasticity", "damping")))

_add(SceneSpec(
    name="balloon_dog", paper_name="balloon dog", origin="synthetic", interaction="pointAdherent",
    description="a balloon dog standing on an unseen table (feet held); the hand pulls its head up and lets go",
    shape=_balloon_dog,
    youngs=lambda p, part: np.where(part >= 8, STIFF, np.where((part == 5) | (part == 6), MID, SOFT)),
    poisson={**{k: 0.4 for k in ("body", "leg_fl", "leg_fr", "leg_bl", "leg_br", "neck", "head", "tail")},
             "knot_front": 0.4, "knot_back": 0.4}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.9, 0.15, 0.45), (1.0, 0.7, 0.85), 0.03, "noise"),
    contact_point=(0.165, 0.105, 0.015), contact_radius=0.025, path=_arc((0.04, 0.07, 0.03), (0.0, 0.0, 0.03)),
    hand_dir=(1.0, 0.5, 0.6),
    supports=[Support((0.07, -0.1, 0.035), 0.02, "foot"), Support((0.07, -0.1, -0.035), 0.02, "foot"),
              Support((-0.07, -0.1, 0.035), 0.02, "foot"), Support((-0.07, -0.1, -0.035), 0.02, "foot")],
    camera_eye=(0.2, 0.25, 0.7), camera_target=(0.02, 0.0, 0.0), hidden_effects=("viscoelasticity", "damping")))

_add(SceneSpec(
    name="balloon", paper_name="balloon", origin="synthetic", interaction="pointAdherent",
    description="a balloon hanging from a string at its neck; the hand grabs its side, pulls it aside and lets go",
    shape=_balloon, youngs=_balloon_E, poisson={"balloon": 0.4, "neck": 0.4}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.15, 0.55, 0.9), (0.95, 0.95, 1.0), 0.025, "dots"),
    contact_point=(0.099, -0.04, 0.0), contact_radius=0.035, path=_arc((0.07, 0.03, 0.02), (0.0, 0.02, 0.04)),
    hand_dir=(1.0, 0.1, 0.5), supports=[Support((0.0, 0.14, 0.0), 0.03, "string")],
    camera_eye=(0.35, 0.2, 0.7), camera_target=(0.02, 0.0, 0.0), hidden_effects=("damping", "viscoelasticity")))

_add(SceneSpec(
    name="flower", paper_name="flower", origin="synthetic", interaction="pointAdherent",
    description="a flower with a stiff stem planted in an unseen pot; the hand pulls a petal down and lets go",
    shape=_flower,
    youngs=lambda p, part: np.where(part == 0, STIFF, np.where(part == 1, MID, SOFT)),
    poisson={"stem": 0.35, "centre": 0.3, **{f"petal{i}": 0.3 for i in range(5)}}, density=RHO,
    texture=lambda p, part: np.where((part == 0)[:, None], pattern_color(p, (0.2, 0.55, 0.15), (0.1, 0.3, 0.05), 0.015, "stripes", freq=150.0),
                                     np.where((part == 1)[:, None], pattern_color(p, (0.95, 0.8, 0.1), (0.5, 0.3, 0.05), 0.006, "dots"),
                                              pattern_color(p, (0.95, 0.45, 0.6), (1.0, 0.9, 0.95), 0.012, "stripes", axis=(1, 0, 1), freq=160.0))),
    contact_point=(0.095, 0.06, 0.03), contact_radius=0.022, path=_arc((0.03, -0.05, 0.03), (0.0, 0.0, 0.02)),
    hand_dir=(1.0, 0.6, 0.7), supports=[Support((0.0, -0.1, 0.0), 0.045, "pot")],
    camera_eye=(0.3, 0.35, 0.6), camera_target=(0.02, -0.01, 0.0), hidden_effects=("plasticity", "damping")))

_add(SceneSpec(
    name="basketball", paper_name="basketball", origin="synthetic", interaction="surfaceNonAdherent",
    description="a soft basketball on an unseen stand; a flat palm presses it down from above and lifts off",
    shape=_basketball, youngs=_basketball_E, poisson={"shell": 0.4}, density=RHO,
    texture=lambda p, part: np.where((np.abs(p[:, 0]) < 0.006)[:, None] | (np.abs(p[:, 2]) < 0.006)[:, None]
                                     | (np.abs(np.linalg.norm(p[:, [0, 1]], axis=1) - 0.085) < 0.006)[:, None],
                                     np.array([[0.1, 0.05, 0.02]]),
                                     pattern_color(p, (0.85, 0.38, 0.08), (0.6, 0.25, 0.05), 0.008, "dots")),
    contact_point=(0.0, 0.112, 0.0), contact_radius=0.0, path=_press((0.0, -0.05, 0.0)),
    hand_dir=(0.0, 1.0, 0.0), supports=[Support((0.0, -0.115, 0.0), 0.035, "stand")],
    camera_eye=(0.3, 0.3, 0.6), camera_target=(0.0, 0.0, 0.0), plane_normal=(0.0, -1.0, 0.0),
    phases=(0.1, 0.7), hidden_effects=("damping", "viscoelasticity")))

_add(SceneSpec(
    name="knit_cap", paper_name="knit cap (real)", origin="real", interaction="pointAdherent",
    description="stand-in for the real knit cap: a cap on an unseen mannequin (rim held); the hand pulls the pompom aside",
    shape=_knit_cap,
    youngs=lambda p, part: np.array([STIFF, SOFT, SOFT, SOFT, SOFT, MID])[part],
    poisson={"rib": 0.3, "body": 0.25, "pompom": 0.3}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.7, 0.1, 0.1), (0.95, 0.95, 0.9), 0.015, "stripes", axis=(0, 1, 0), freq=140.0),
    contact_point=(0.0, 0.13, 0.0), contact_radius=0.03, path=_arc((0.08, 0.02, 0.04), (0.0, 0.02, 0.02)),
    hand_dir=(0.5, 1.0, 0.6), supports=[Support((0.0, -0.02, -0.1), 0.06, "mannequin"), Support((-0.1, -0.02, 0.0), 0.05, "mannequin"),
                                        Support((0.1, -0.02, 0.0), 0.05, "mannequin")],
    camera_eye=(0.3, 0.3, 0.6), camera_target=(0.0, 0.03, 0.0), hidden_effects=("plasticity", "damping")))

_add(SceneSpec(
    name="toy_rope", paper_name="toy rope (real)", origin="real", interaction="pointAdherent",
    description="stand-in for the real toy rope: a knotted dog rope hanging from a hand at its top knot; the other hand swings the bottom knot",
    shape=_toy_rope,
    youngs=lambda p, part: np.where(part == 0, SOFT, STIFF),
    poisson={"rope": 0.3, "knot0": 0.35, "knot1": 0.35, "knot2": 0.35}, density=RHO,
    texture=lambda p, part: pattern_color(p, (0.1, 0.5, 0.2), (0.95, 0.9, 0.2), 0.02, "stripes", axis=(1, 0.3, 0.5), freq=100.0),
    contact_point=(0.0, -0.2, 0.03), contact_radius=0.032, path=_arc((0.1, 0.05, 0.05), (0.0, 0.02, 0.03)),
    hand_dir=(0.4, -0.5, 1.0), supports=[Support((0.0, 0.2, 0.0), 0.035, "hand")],
    camera_eye=(0.05, 0.35, 0.7), camera_target=(0.0, 0.0, 0.0), hidden_effects=("damping", "ground")))

_add(SceneSpec(
    name="telephone_cable", paper_name="telephone cable (real)", origin="real", interaction="pointNonAdherent",
    description="stand-in for the real telephone cable: a coiled cord between socket and handset; a fingertip pokes the coil sideways and withdraws",
    shape=_telephone_cable,
    youngs=lambda p, part: np.where(part == 0, SOFT, STIFF),
    poisson={"coil": 0.4, "plug_top": 0.4, "plug_bottom": 0.4}, density=RHO,
    texture=lambda p, part: np.where((part == 0)[:, None], pattern_color(p, (0.9, 0.82, 0.62), (0.45, 0.38, 0.25), 0.01, "noise"),
                                     pattern_color(p, (0.15, 0.15, 0.15), (0.4, 0.4, 0.4), 0.01, "checker")),
    contact_point=tuple(_POKE_AT), contact_radius=0.015, path=_press((-0.055, 0.0, 0.024)),
    hand_dir=(0.92, 0.1, -0.39), supports=[Support(tuple(_coil_points(0.0) + [0, PLUG_LEN, 0]), 0.03, "socket"),
                                        Support(tuple(_coil_points()[-1] + [0, -PLUG_LEN, 0]), 0.03, "handset")],
    camera_eye=(0.3, 0.1, 0.7), camera_target=(0.0, 0.0, 0.0), phases=(0.05, 0.75),
    hidden_effects=("damping", "viscoelasticity")))


def get_scene(name: str) -> SceneSpec:
    if name not in SCENES:
        raise KeyError(name)
    return SCENES[name]


# ------------------------------------------------------------------------------ the bundled sample
def _foam_bar():
    """A thick foam bar: a stiff upper half (held by a clip at the top) over a soft lower half."""
    return Shape([Capsule("stiff", (0, 0.08, 0), (0, 0.0, 0), 0.035),
                  Capsule("soft", (0, 0.0, 0), (0, -0.08, 0), 0.035)])


_add(SceneSpec(
    name="foam_bar", paper_name="(bundled sample)", origin="synthetic", interaction="pointAdherent",
    description="a thick foam bar clipped at its top: stiff upper half, soft lower half; the hand pulls "
                "its lower end aside and lets go (small and compact: the CPU demo)",
    shape=_foam_bar, youngs=lambda p, part: np.where(part == 0, STIFF, SOFT),
    poisson={"stiff": 0.3, "soft": 0.3}, density=RHO,
    texture=lambda p, part: np.where((part == 0)[:, None],
                                     pattern_color(p, (0.15, 0.35, 0.75), (0.9, 0.9, 0.4), 0.014, "dots"),
                                     pattern_color(p, (0.9, 0.5, 0.15), (0.35, 0.15, 0.05), 0.012, "stripes",
                                                   axis=(0.3, 1.0, 0.2), freq=180.0)),
    contact_point=(0.03, -0.09, 0.018), contact_radius=0.03, path=_arc((0.06, 0.03, 0.04), (0.0, 0.01, 0.02)),
    hand_dir=(0.5, -0.6, 0.8), supports=[Support((0.0, 0.115, 0.0), 0.04, "clip")],
    camera_eye=(0.2, 0.1, 0.6), camera_target=(0.01, -0.01, 0.0), phases=(0.1, 0.55),
    hidden_effects=("damping", "plasticity")))
