"""The loss terms: each maps a state to its value and adds weight x its gradient into a gradient
state (``zeros_like``). See ``cosim.scene.schema.LossTermSpec`` for what each one measures."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.errors import SceneError


def zeros_like(state: dict[str, dict[str, np.ndarray]]) -> dict[str, dict[str, np.ndarray]]:
    """Zero adjoints of every engine's state (couplers' discrete states have none)."""
    return {name: {k: np.zeros_like(v) for k, v in s.items()} for name, s in state.items() if name != "couplers"}


Term = Callable[[dict, dict, float], float]  # (state, grad to add into, weight) -> value


def make_term(spec, dim, seed, slices, mass, rigid, cloths, dx, source_dir, key: str) -> Term:
    """The term ``spec`` (a ``LossTermSpec``) bound to the system's bodies."""
    if spec.type == "joint_target":
        dofs, engine, target = joint_dofs(spec, rigid, key), rigid.name, np.asarray(spec.target, float)
        quantity = "qd" if spec.velocity else "q"

        def joint(state, grad, weight):  # |q_joint - target|^2 (or its velocities)
            diff = state[engine][quantity][dofs] - target
            grad[engine][quantity][dofs] += weight * 2.0 * diff
            return float(diff @ diff)

        return joint
    cloths = {c.name: c for c in (cloths or [])}
    if spec.body in cloths:
        cloth = cloths[spec.body]
        engine, sel, masses, rest = cloth.name, np.arange(cloth.mesh.n_vertices), cloth.masses(), cloth.mesh.vertices
    else:
        sl = slices[spec.body] if spec.body else slice(0, len(mass))
        engine, sel = "mpm", np.arange(len(mass))[sl]
        masses, rest = mass[sel], spec.rest_positions
    points_fn = _points_term(spec, dim, seed, len(sel), masses, rest, dx, source_dir, key)

    def on_points(state, grad, weight):
        value, g = points_fn(state[engine]["x"][sel])
        grad[engine]["x"][sel] += weight * g
        return value

    return on_points


def joint_dofs(spec, rigid, key: str) -> np.ndarray:
    """The coordinates (indices into the DART engine ``rigid``'s positions) a joint_target term ``spec``
    at ``key`` reads: its skeleton's joint, ``components`` of it if given; refused naming the key, the
    value and what the skeletons have when the skeleton, joint, components or target do not fit."""
    if rigid is None:
        raise SceneError(f"{key}.type: joint_target needs an articulated: section")
    skeletons = [s.name for s in rigid.specs]
    if spec.skeleton not in skeletons:
        raise SceneError(f"{key}.skeleton: no skeleton '{spec.skeleton}'; skeletons: {skeletons}")
    joints = [j.getName() for j in rigid.skeletons[skeletons.index(spec.skeleton)].getJoints()]
    if spec.joint not in joints:
        raise SceneError(f"{key}.joint: skeleton '{spec.skeleton}' has no joint '{spec.joint}'; joints: {joints}")
    dofs = rigid.dof_indices(spec.skeleton, spec.joint)
    if spec.components is not None:
        if max(spec.components) >= len(dofs):
            raise SceneError(
                f"{key}.components: joint '{spec.joint}' has {len(dofs)} coordinates "
                f"({'0..' + str(len(dofs) - 1) if len(dofs) else 'none'}), got {spec.components}"
            )
        dofs = dofs[spec.components]
    if len(spec.target) != len(dofs):
        raise SceneError(f"{key}.target: {len(dofs)} numbers (the joint's coordinates read), got {len(spec.target)}")
    return dofs


def _points_term(spec, dim, seed, n, masses, rest, dx, source_dir, key):
    """value, d/dx of a term on n points x (n, dim) [m]."""
    if spec.type == "weighted_positions":  # mean w_p . x_p, fixed seeded weights
        weights = np.random.default_rng(seed + 7919).standard_normal((n, dim))
        return lambda x: (float((weights * x).sum() / n), weights / n)
    if spec.type == "pose_target":  # mean squared distance to the goal positions
        goal = pose_goal(rest, spec)
        return lambda x: (float(((x - goal) ** 2).sum() / n), 2.0 * (x - goal) / n)
    if spec.type == "chamfer":
        from cosim.losses.chamfer import Chamfer, target_points

        if spec.points is None:
            raise SceneError(f"{key}.points: chamfer needs its target point set (file, shape or rollout)")
        return Chamfer(target_points(spec.points, spec.body, dim, dx, seed, source_dir, f"{key}.points"))
    # com_target: |com - target|^2
    share, target = masses[:, None] / masses.sum(), np.asarray(spec.target, float)

    def com(x):
        diff = (share * x).sum(axis=0) - target
        return float(diff @ diff), 2.0 * diff[None, :] * share

    return com


def pose_goal(rest: np.ndarray, spec) -> np.ndarray:
    """The body's start positions (n, 3) moved rigidly: rotated by ``spec.rotation`` (rotation vector
    [rad]) about ``spec.pivot`` [m], then shifted by ``spec.target`` [m] (defaults: none)."""
    from cosim.engines import so3

    pivot = np.zeros(rest.shape[1]) if spec.pivot is None else np.asarray(spec.pivot, float)
    R = so3.exp(np.asarray(spec.rotation or [0.0, 0.0, 0.0], float))[: rest.shape[1], : rest.shape[1]]
    shift = np.zeros(rest.shape[1]) if spec.target is None else np.asarray(spec.target, float)
    return (rest - pivot) @ R.T + pivot + shift
