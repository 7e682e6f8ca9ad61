"""SimState: the particle state at one instant (x, v, C, F and the Maxwell branch's Fv)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .kernels import get_kernels


@dataclass
class SimState:
    """Warp arrays of one particle state, in the model's dtype and on its device.

    x (P, 3) positions, v (P, 3) velocities, C (P, 3, 3) APIC affine velocity, F (P, 3, 3)
    deformation gradient (after the plastic return mapping), Fv (P, 3, 3) the elastic
    deformation of the viscoelastic (Maxwell) branch (identity while that effect is off).
    """

    x: wp.array
    v: wp.array
    C: wp.array
    F: wp.array
    Fv: wp.array

    FIELDS = ("x", "v", "C", "F", "Fv")

    @classmethod
    def zeros(cls, n: int, dtype: str, device: str, requires_grad: bool = False) -> "SimState":
        K = get_kernels(dtype)
        return cls(*(wp.zeros(n, dtype=t, device=device, requires_grad=requires_grad)
                     for t in (K.vec3, K.vec3, K.mat33, K.mat33, K.mat33)))

    @classmethod
    def rest(cls, model, v0=None, block_dim: int = 256) -> "SimState":
        """The state at frame 0: rest positions, F = Fv = I, C = 0, velocity v0 (default 0)."""
        s = cls.zeros(model.n_particles, model.dtype, model.device)
        s.set_rest(model, v0, block_dim)
        return s

    def set_rest(self, model, v0=None, block_dim: int = 256) -> None:
        """`block_dim`: the launch's threads per block, the solver's (`MPMSolver.block_dim`: one compiled variant of
        the simulator's modules on CUDA; the CPU ignores it)."""
        K = get_kernels(model.dtype)
        dev = model.device_arrays()
        if v0 is None:
            v0a = wp.zeros_like(self.v)
        elif isinstance(v0, wp.array):
            v0a = v0
        else:
            v0a = wp.array(np.broadcast_to(np.asarray(v0, dtype=model.np_dtype), (model.n_particles, 3)).copy(),
                           dtype=K.vec3, device=model.device)
        wp.launch(K.set_rest, model.n_particles, [dev["x0"], v0a], [self.x, self.v, self.C, self.F, self.Fv],
                  device=model.device, block_dim=int(block_dim))

    def assign(self, other: "SimState") -> None:
        for f in self.FIELDS:
            wp.copy(getattr(self, f), getattr(other, f))

    def zero_(self) -> None:
        for f in self.FIELDS:
            getattr(self, f).zero_()

    def numpy(self) -> dict[str, np.ndarray]:
        return {f: getattr(self, f).numpy().copy() for f in self.FIELDS}
