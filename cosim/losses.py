"""Scalar losses on the final state of a coupled system, with their gradients (NumPy).

A loss takes the final state {engine name: state} (``CoupledSystem.state``) and returns
``(value, dL/dstate)`` of the same structure; entries a loss does not depend on get zeros.
"""

from __future__ import annotations

import numpy as np


def zeros_like(state: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, np.ndarray]]:
    """Zero adjoints of every engine's state (couplers' discrete states have none)."""
    return {name: {k: np.zeros_like(v) for k, v in s.items()} for name, s in state.items() if name != "couplers"}


class Loss:
    """The scene's loss (``loss:`` section), bound to the particles or joints it reads."""

    def __init__(self, spec, dim: int, seed: int, slices: dict[str, slice], mass: np.ndarray, rigid=None):
        n = len(mass)
        self.kind = spec.type
        if self.kind == "joint_target":
            self.dofs = rigid.dof_indices(spec.skeleton, spec.joint)
            self.rigid = rigid.name
        sl = slices[spec.body] if spec.body else slice(0, n)
        self.sel = np.arange(n)[sl]
        self.mass = mass[self.sel]
        self.target = None if spec.target is None else np.asarray(spec.target, float)
        rng = np.random.default_rng(seed + 7919)
        self.weights = rng.standard_normal((len(self.sel), dim))

    @classmethod
    def for_system(cls, system) -> Loss:
        """The loss of the scene ``system`` was built from."""
        scene = system.scene
        return cls(scene.loss, scene.dim, scene.seed, system.slices, system.mpm.mass, system.engines.get("dart"))

    def __call__(self, state: dict[str, dict[str, np.ndarray]]) -> tuple[float, dict]:
        grad = zeros_like(state)
        if self.kind == "joint_target":  # |q_joint - target|^2
            diff = state[self.rigid]["q"][self.dofs] - self.target
            grad[self.rigid]["q"][self.dofs] = 2.0 * diff
            return float(diff @ diff), grad
        x = state["mpm"]["x"][self.sel]
        gx = grad["mpm"]["x"]
        if self.kind == "weighted_positions":
            value = float((self.weights * x).sum() / len(x))
            gx[self.sel] = self.weights / len(x)
        else:  # com_target: |com - target|^2
            total = self.mass.sum()
            com = (self.mass[:, None] * x).sum(axis=0) / total
            diff = com - self.target
            value = float(diff @ diff)
            gx[self.sel] = 2.0 * diff[None, :] * (self.mass[:, None] / total)
        return value, grad
