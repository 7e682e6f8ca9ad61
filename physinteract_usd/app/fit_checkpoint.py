"""A running fit's checkpoint: the optimiser's best iterate so far, on disk every N iterations
(`<stem>.versions/checkpoint.npz`, written atomically), so that `fit --resume` goes on after a
kill -9, a power cut or a scheduler's SIGKILL; and in memory, so that a stop that lands after the
optimiser's loop (in its last pass or the confidence estimate) still writes the best iterate.

`FitTracker` is the optimiser's `on_iteration` callback. The optimiser calls it after each step
with the loss of the iterate it just evaluated and the field already stepped past it, so the
tracker pairs each loss with the field it saved one call earlier (same basis, consecutive
iterations): its best is an iterate the optimiser evaluated, with that iterate's loss.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from .. import stopping
from ..errors import InputError
from ..usd.versions import now_utc

FORMAT = 1


class FitTracker:
    def __init__(self, path: Path | None, fingerprint: dict, budget: int, names: list[str], *, every: int = 5,
                 history: list | None = None, resumed_from: str = ""):
        self.path = None if path is None else Path(path)
        self.fingerprint = fingerprint
        self.budget = int(budget)
        self.names = list(names)
        self.every = int(every)
        self.prior = list(history or [])    # a resumed checkpoint's history: this fit goes on from it
        self.history: list[float] = []
        self.resumed_from = resumed_from
        self.best: dict | None = None
        self.best_loss = math.inf
        self.pending: dict | None = None
        self.last_it = -1
        self.loop_done = False
        self.saved_at = 0

    def __call__(self, it, loss, mat, trajs) -> None:
        loss = float(loss)
        p = self.pending
        if p is not None and it == self.last_it + 1 and p["K"] == mat.K and math.isfinite(loss) \
                and loss < self.best_loss:
            self.best, self.best_loss = p, loss
        self.history.append(loss)
        import torch

        with torch.no_grad():
            self.pending = {"youngs": mat.youngs().detach().cpu().numpy().astype(np.float64),
                            "poisson": mat.poisson().detach().cpu().numpy().astype(np.float64),
                            "trajectories": {n: t.detach().cpu().numpy().astype(np.float64)
                                             for n, t in zip(self.names, trajs)},
                            "K": int(mat.K)}
        self.last_it = it
        if it >= self.budget:
            self.loop_done = True
            stopping.finishing()   # the optimiser's last pass and the write run to their end
        if self.path is not None and self.every > 0 and it % self.every == 0:
            self.save(it)

    @property
    def iterations(self) -> int:
        return max(self.last_it, 0)

    def start(self) -> dict | None:
        """The best iterate as a fit's `start` ({"youngs", "poisson", "trajectories"}), else the
        latest one, else None."""
        s = self.best or self.pending
        return None if s is None else {k: s[k] for k in ("youngs", "poisson", "trajectories")}

    def save(self, it: int) -> None:
        s = self.best or self.pending
        if s is None:
            return
        self.path.parent.mkdir(exist_ok=True)
        meta = {"format": FORMAT, "iteration": int(it), "budget": self.budget, "loss": self.best_loss
                if self.best is not None else None, "history": self.prior + self.history,
                "fingerprint": self.fingerprint, "created": now_utc(), "resumed_from": self.resumed_from}
        arrays = {"youngs": s["youngs"], "poisson": s["poisson"]}
        for i, n in enumerate(s["trajectories"]):
            arrays[f"traj_{i}"] = s["trajectories"][n]
        meta["trajectories"] = list(s["trajectories"])
        tmp = self.path.with_name(f".{self.path.stem}.tmp{os.getpid()}.npz")
        try:
            with open(tmp, "wb") as fh:
                np.savez(fh, meta=np.array(json.dumps(meta)), **arrays)
            os.replace(tmp, self.path)
        finally:
            if tmp.exists():
                tmp.unlink()
        self.saved_at = it


def load_checkpoint(path: Path) -> dict | None:
    """{"start", "iteration", "budget", "loss", "history", "fingerprint", "created"} or None when
    there is none; InputError for a damaged file."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            start = {"youngs": np.asarray(z["youngs"], np.float64), "poisson": np.asarray(z["poisson"], np.float64),
                     "trajectories": {n: np.asarray(z[f"traj_{i}"], np.float64)
                                      for i, n in enumerate(meta.get("trajectories", []))}}
    except Exception as exc:  # noqa: BLE001  (truncated, not an npz, missing keys)
        raise InputError(path, f"fit checkpoint cannot be read ({exc.__class__.__name__}): delete it to start "
                         "afresh") from None
    if not (np.isfinite(start["youngs"]).all() and (start["youngs"] > 0).all()):
        raise InputError(path, "fit checkpoint holds non-finite or non-positive E: delete it to start afresh")
    return {"start": start, **{k: meta.get(k) for k in ("iteration", "budget", "loss", "history", "fingerprint",
                                                        "created", "resumed_from")}}


def fingerprint(scene, contacts) -> dict:
    """What a checkpoint must match to be resumed on a stage."""
    return {"particles": int(len(scene.particles_positions)), "frames": int(scene.n_frames),
            "contacts": sorted(c.name for c in contacts)}


def remove_checkpoint(path: Path) -> None:
    try:
        Path(path).unlink()
    except FileNotFoundError:
        pass
