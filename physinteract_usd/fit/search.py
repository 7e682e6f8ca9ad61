"""One-dimensional searches the fit's start-ups share (no gradients)."""

from __future__ import annotations

import math

from ..errors import SimulationError

GOLDEN = (math.sqrt(5) - 1) / 2


def golden_section(f, a: float, b: float, evals: int) -> tuple[float, float]:
    """Golden-section search for a minimum of `f` on [a, b] with `evals` evaluations of `f` (the
    caller's `f` keeps what it saw); a non-finite value loses to a finite one. Returns the final
    bracket. Where `f` has a `prefetch(points, maybe)` (`UniformProbe` with a `many`: two probes at once
    on the CPU's second core), the search hands it the first two points together, and then each point
    with the one most likely to follow it (`_likely_next`): the same points, values and decisions, in
    the same order, whatever prefetch does."""
    ahead = getattr(f, "prefetch", None)
    n = max(int(evals) - 2, 0)
    c, d = b - GOLDEN * (b - a), a + GOLDEN * (b - a)
    if ahead is not None:
        ahead([c, d])
    fc, fd = f(c), f(d)
    known = {c: fc, d: fd}
    for i in range(n):
        left = _goes_left(fc, fd)
        if left:
            b, d, fd = d, c, fc
            c = b - GOLDEN * (b - a)
        else:
            a, c, fc = c, d, fd
            d = a + GOLDEN * (b - a)
        if ahead is not None:
            ahead([c if left else d], _likely_next(known, a, b, c, d, fc, fd, left) if i + 1 < n else None)
        if left:
            fc = known[c] = f(c)
        else:
            fd = known[d] = f(d)
    return a, b


def _goes_left(fc: float, fd: float) -> bool:
    return fc < fd or (math.isfinite(fc) and not math.isfinite(fd))


def _predict(known: dict, x: float) -> float:
    """f(x) from the finite values seen: the parabola through the three nearest, the line through two."""
    pts = sorted(((k, v) for k, v in known.items() if math.isfinite(v)), key=lambda kv: abs(kv[0] - x))[:3]
    if len(pts) < 2:
        return pts[0][1] if pts else float("inf")
    if len(pts) == 2:
        (x0, y0), (x1, y1) = pts
        return y0 + (y1 - y0) * (x - x0) / (x1 - x0) if x1 != x0 else y0
    (x0, y0), (x1, y1), (x2, y2) = pts
    try:
        return (y0 * (x - x1) * (x - x2) / ((x0 - x1) * (x0 - x2)) + y1 * (x - x0) * (x - x2) / ((x1 - x0) * (x1 - x2))
                + y2 * (x - x0) * (x - x1) / ((x2 - x0) * (x2 - x1)))
    except ZeroDivisionError:
        return y0


def _likely_next(known: dict, a, b, c, d, fc, fd, left: bool) -> float:
    """The point `golden_section` evaluates after the pending one (c if `left`, else d), with the pending
    value predicted from those seen (`_predict`): a guess, only ever computed ahead, never used unchecked."""
    if left:
        fc = _predict(known, c)
    else:
        fd = _predict(known, d)
    if _goes_left(fc, fd):
        b, d = d, c
        return b - GOLDEN * (b - a)
    a, c = c, d
    return a + GOLDEN * (b - a)


def no_finite_uniform_probe(errors=(), ground: bool | None = None) -> SimulationError:
    """The error of a start-up whose every uniform-E probe went unstable or left the grid. `errors`: the probes'
    SimulationErrors (`UniformProbe.errors`), `ground`: whether the model has the ground effect (None: unknown).
    Where most probes left through the grid's bottom (`SimulationError.face` "-y": the object falls) it says so, and
    with no ground that nothing holds the object up (#23: world dev_0510, a rope on a floor that extract did not
    find, fell at every E)."""
    errors = list(errors)
    down = sum(getattr(e, "face", "") == "-y" for e in errors)
    if errors and 2 * down >= len(errors):
        what = f"went unstable or left the grid at every uniform E tried ({down} of {len(errors)} fell out of its bottom)"
        if ground is False:
            return SimulationError(what, frame=None, advice=(
                "nothing holds the object up: the stage has no ground. If it rests on a floor in the video, switch the "
                "ground on (physinteract-usd effects add SCENE ground; extract looks for it) and fit again; else check "
                "the supports extract found"))
        return SimulationError(what, frame=None, advice=(
            "it falls through its support or the ground: check the supports (extract) and the ground's height "
            "(physinteract-usd effects list SCENE); a deeper grid below it (init --padding) if it sags that far"))
    what, advice = "went unstable or left the grid at every uniform E tried", (
        "check the contacts (extract) and the Young's modulus range (init --youngs-range); a wider grid padding "
        "(init --padding) if the object leaves the domain")
    said = probe_errors_said(errors)
    unstable = sum(getattr(e, "kind", "") == "unstable" for e in errors)
    faces = [getattr(e, "face", "") for e in errors if getattr(e, "kind", "") == "domain"]
    face = max(set(faces), key=faces.count) if faces else ""
    if errors and unstable == len(errors) and len(errors) >= 3:
        # soft and stiff alike: not the material, the interaction (#23: dev_0568, a grasp whose path dived through
        # the floor it rests on)
        advice = ("unstable at the softest E tried as at the stiffest, so not for the material: the interaction is "
                  "likely impossible (a grasp dragging the object into the floor or against a support, or a path "
                  "faster than the grid allows): check the contacts and the path (the preview image extract wrote), "
                  "the supports and the ground (physinteract-usd effects list SCENE)")
    elif len(errors) >= 3 and face and 4 * faces.count(face) >= 3 * len(errors):
        # out through one face at every E (#23: validation_0009, a clamped bar pulled up out of its grid by a grasp
        # where extract found no support near the true one)
        advice = (f"it leaves through the same ({face}) face at the softest E tried as at the stiffest, so the "
                  "interaction carries it there rather than the material: check the contacts, the path and the "
                  "supports (the preview image extract wrote); a wider grid padding (init --padding) only if the "
                  "video shows it going that far")
    return SimulationError(what + (f" ({said})" if said else ""), frame=None, advice=advice)


def probe_errors_said(errors) -> str:
    """The failed probes' errors in a few words: how many went unstable, how many left the grid through which face,
    and the frames where they did ("" where there are none)."""
    errors = list(errors)
    if not errors:
        return ""
    parts = []
    unstable = [e for e in errors if getattr(e, "kind", "") == "unstable"]
    if unstable:
        parts.append(f"{len(unstable)} of {len(errors)} unstable{_frames(unstable)}")
    faces: dict = {}
    for e in errors:
        if getattr(e, "kind", "") == "domain":
            faces.setdefault(getattr(e, "face", "") or "?", []).append(e)
    for face, es in sorted(faces.items(), key=lambda kv: -len(kv[1])):
        where = f" through its {face} face" if face != "?" else ""
        parts.append(f"{len(es)} of {len(errors)} left the grid{where}{_frames(es)}")
    other = len(errors) - len(unstable) - sum(len(es) for es in faces.values())
    if other:
        parts.append(f"{other} of {len(errors)} failed otherwise")
    return "; ".join(parts)


def _frames(errors) -> str:
    fr = sorted(int(e.frame) for e in errors if getattr(e, "frame", None) is not None)
    if not fr:
        return ""
    return f" at frame {fr[0]}" if fr[0] == fr[-1] else f" at frames {fr[0]}-{fr[-1]}"


def has_ground(prob) -> bool | None:
    """Whether a fit problem's simulation has the ground effect (None: it cannot tell)."""
    eff = getattr(getattr(prob, "sim", None), "effects", None)
    return None if eff is None else "ground" in eff


class UniformProbe:
    """The reconstruction loss at one uniform E, called with log E (no gradients) and cached per
    log E in `cache`. `loss_of(E)` takes the (P,) tensor of that E and returns the loss. A probe
    that goes unstable, leaves the grid or gives a non-finite loss is inf: it is logged and its E
    appended to `skipped`, so a search moves away from it and never returns it.

    `many` (optional): `many([E1, E2])` simulates two probes at once (the CPU's second core) and returns
    one callable per probe, called in order when the search asks for that probe, giving what `loss_of`
    would give there (or raising its error); `prefetch` uses it. What was computed ahead and not asked
    for next is dropped: the values, the log and `skipped` are those of the one-at-a-time search."""

    def __init__(self, loss_of, n: int, dtype, device, log=None, skipped: list | None = None, many=None):
        self.loss_of, self.n, self.dtype, self.device = loss_of, int(n), dtype, device
        self.log, self.skipped = log, skipped
        self.many = many
        self.cache: dict[float, float] = {}
        self._ahead: dict = {}         # log E -> the callable `many` gave for it, in the order asked
        self.ahead_used = 0            # probes answered from what `many` computed
        self.ahead_wasted = 0          # guesses computed ahead and not asked for
        self.errors: list = []         # the SimulationErrors of the probes that failed

    def _E(self, le: float):
        import torch

        return torch.full((self.n,), math.exp(le), dtype=self.dtype, device=self.device)

    def prefetch(self, points, maybe=None) -> None:
        """Compute `points` (asked for next, in this order) ahead, two at a time with `many`, and where only
        one is new, `maybe` (perhaps asked for after it) beside it. Without `many`: nothing."""
        if self.many is None:
            return
        pending = lambda le: le in self.cache or le in self._ahead  # noqa: E731
        les: list[float] = []
        for p in points:
            le = float(p)
            if not pending(le) and le not in les:
                les.append(le)
        if len(les) == 1 and maybe is not None and not pending(float(maybe)) and float(maybe) != les[0]:
            les.append(float(maybe))
        if len(les) < 2:
            return
        les = les[:2]
        for le, run in zip(les, self.many([self._E(le) for le in les])):
            self._ahead[le] = run

    def __call__(self, le) -> float:
        import torch

        le = float(le)
        if le in self.cache:
            return self.cache[le]
        run = self._ahead.pop(le, None)
        if run is None:
            self.ahead_wasted += len(self._ahead)
            self._ahead.clear()            # guesses made for another order of probes
        else:
            self.ahead_used += 1
        E = self._E(le)
        why = ""
        try:
            with torch.no_grad():
                v = float(run() if run is not None else self.loss_of(E))
            if not math.isfinite(v):
                why = f"loss {v}"
        except SimulationError as exc:
            v, why = float("inf"), exc.kind or "unstable"
            self.errors.append(exc)
        if why:
            v = float("inf")
            if self.skipped is not None:
                self.skipped.append(math.exp(le))
            if self.log:
                self.log(f"uniform E {math.exp(le):.4g} Pa: the simulation went unstable or left the grid ({why}): "
                         "skipped")
        elif self.log:
            self.log(f"uniform E {math.exp(le):.4g} Pa: loss {v:.5f}")
        self.cache[le] = v
        return v
