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
    """The scene's loss (``loss:`` section), bound to the points or joints it reads.

    The points are an MPM body's particles (``state["mpm"]["x"]``, all bodies when ``body`` is
    unset) or a cloth's vertices (``state[cloth]["x"]``, when ``body`` names a cloth).
    """

    def __init__(self, spec, dim: int, seed: int, slices: dict[str, slice], mass: np.ndarray, rigid=None, cloths=None):
        self.kind = spec.type
        if self.kind == "joint_target":
            self.dofs = rigid.dof_indices(spec.skeleton, spec.joint)
            self.rigid = rigid.name
        cloths = {c.name: c for c in (cloths or [])}
        if spec.body in cloths:
            cloth = cloths[spec.body]
            self.engine, self.sel = cloth.name, np.arange(cloth.mesh.n_vertices)
            self.mass, rest = cloth.masses(), cloth.mesh.vertices
        else:
            sl = slices[spec.body] if spec.body else slice(0, len(mass))
            self.engine, self.sel = "mpm", np.arange(len(mass))[sl]
            self.mass, rest = mass[self.sel], None
        self.target = None if spec.target is None else np.asarray(spec.target, float)
        if self.kind == "pose_target":
            self.goal = pose_goal(rest if rest is not None else spec.rest_positions, spec)
        rng = np.random.default_rng(seed + 7919)
        self.weights = rng.standard_normal((len(self.sel), dim))

    @classmethod
    def for_system(cls, system) -> Loss:
        """The loss of the scene ``system`` was built from."""
        scene = system.scene
        cloths = [e for e in system.engines.values() if hasattr(e, "mesh")]
        loss = scene.loss
        if loss.type == "pose_target" and loss.body not in {c.name for c in cloths}:
            loss = loss.model_copy(update={"rest_positions": system.initial["mpm"]["x"][system.slices[loss.body]]})
        return cls(loss, scene.dim, scene.seed, system.slices, system.mpm.mass, system.engines.get("dart"), cloths)

    def __call__(self, state: dict[str, dict[str, np.ndarray]]) -> tuple[float, dict]:
        grad = zeros_like(state)
        if self.kind == "joint_target":  # |q_joint - target|^2
            diff = state[self.rigid]["q"][self.dofs] - self.target
            grad[self.rigid]["q"][self.dofs] = 2.0 * diff
            return float(diff @ diff), grad
        x = state[self.engine]["x"][self.sel]
        gx = grad[self.engine]["x"]
        if self.kind == "weighted_positions":
            value = float((self.weights * x).sum() / len(x))
            gx[self.sel] = self.weights / len(x)
        elif self.kind == "pose_target":  # mean squared distance to the goal positions
            diff = x - self.goal
            value = float((diff * diff).sum() / len(x))
            gx[self.sel] = 2.0 * diff / len(x)
        else:  # com_target: |com - target|^2
            total = self.mass.sum()
            com = (self.mass[:, None] * x).sum(axis=0) / total
            diff = com - self.target
            value = float(diff @ diff)
            gx[self.sel] = 2.0 * diff[None, :] * (self.mass[:, None] / total)
        return value, grad


def pose_goal(rest: np.ndarray, spec) -> np.ndarray:
    """The body's start positions (n, 3) moved rigidly: rotated by ``spec.rotation`` (rotation vector
    [rad]) about ``spec.pivot`` [m], then shifted by ``spec.target`` [m] (defaults: none)."""
    from cosim.engines import so3

    pivot = np.zeros(rest.shape[1]) if spec.pivot is None else np.asarray(spec.pivot, float)
    R = so3.exp(np.asarray(spec.rotation or [0.0, 0.0, 0.0], float))[: rest.shape[1], : rest.shape[1]]
    shift = np.zeros(rest.shape[1]) if spec.target is None else np.asarray(spec.target, float)
    return (rest - pivot) @ R.T + pivot + shift
