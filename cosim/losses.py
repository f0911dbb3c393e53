"""Scalar losses on the final MPM state, with their gradients (NumPy).

A loss returns ``(value, dL/dstate)`` where the gradient has the state's keys
(x, v, C, F, and "rigid" for scenes with DART skeletons); keys a loss does not
depend on get zeros.
"""

from __future__ import annotations

import numpy as np

from cosim.scene import Scene


def _zeros_like_state(state: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: np.zeros_like(v) for k, v in state.items()}


class Loss:
    """The scene's loss, bound to the particles it reads."""

    def __init__(self, scene: Scene, slices: dict[str, slice], mass: np.ndarray, rigid=None):
        spec = scene.loss
        n = len(mass)
        self.kind = spec.type
        if self.kind == "joint_target":
            self.dofs = rigid.dof_indices(spec.skeleton, spec.joint)
        sl = slices[spec.body] if spec.body else slice(0, n)
        self.sel = np.arange(n)[sl]
        self.mass = mass[self.sel]
        self.target = None if spec.target is None else np.asarray(spec.target, float)
        rng = np.random.default_rng(scene.seed + 7919)
        self.weights = rng.standard_normal((len(self.sel), scene.dim))

    def __call__(self, state: dict[str, np.ndarray]) -> tuple[float, dict[str, np.ndarray]]:
        grad = _zeros_like_state(state)
        x = state["x"][self.sel]
        if self.kind == "joint_target":  # |q_joint - target|^2
            diff = state["rigid"][self.dofs] - self.target
            grad["rigid"][self.dofs] = 2.0 * diff
            return float(diff @ diff), grad
        if self.kind == "weighted_positions":
            value = float((self.weights * x).sum() / len(x))
            grad["x"][self.sel] = self.weights / len(x)
        else:  # com_target: |com - target|^2
            total = self.mass.sum()
            com = (self.mass[:, None] * x).sum(axis=0) / total
            diff = com - self.target
            value = float(diff @ diff)
            grad["x"][self.sel] = 2.0 * diff[None, :] * (self.mass[:, None] / total)
        return value, grad
