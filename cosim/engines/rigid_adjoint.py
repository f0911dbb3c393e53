"""The one-step vector-Jacobian product of ``RigidEngine`` (DART), a mixin for readability.

Which blocks are closed form and which use central differences over DART's own
step, and why, is written in ``vjp_flat``. The mixin reads the engine's
``dt``, ``dofs``, ``skeletons``, ``controls``, ``_offsets``, ``_kinematic``,
``_rotation_blocks`` and ``_bodies``, and calls its ``flat_state`` /
``set_flat_state`` / ``_advance`` / ``_body_jacobian`` / ``_joint_jacobian`` /
``body_states``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.engines import rigid_added_mass
from cosim.engines.so3 import left_jacobian, left_jacobian_inv
from cosim.errors import InputError, SimulationError

FD_EPS = 1e-6  # central-difference step for the state blocks (relative error ~1e-9 at unit scales)


@dataclass
class StepRecord:
    """What ``vjp`` needs about one step: the state before and after, and the inputs."""

    state: np.ndarray
    action: np.ndarray
    wrenches: np.ndarray
    next_state: np.ndarray
    step: int = 0  # 1 for the engine's first step
    clamped: np.ndarray | None = None  # (action_size,) bool: velocity commands clipped to the joint limits
    constraint: tuple[str, float] | None = None  # ("skeleton/dof", force) when a limit or contact acted
    added: np.ndarray | None = None  # (bodies, 6, 6) the coupling's added masses (``rigid_added_mass``)


# ------------------------------------------------------------------------------- joint integration Jacobian


def position_step_jacobian(kind: str, q_next: np.ndarray, qd_next: np.ndarray, R0: np.ndarray, dt: float) -> np.ndarray:
    """d q'/d qd' of DART's integration for a free (6x6) or ball (3x3) joint, closed form.

    Measured conventions (DART 6.20), R0 = rotation of the joint origin in the parent frame:
    free joint, qd = [w; v] in the parent frame: q_rot' = log(exp(dt R0^T w) exp(q_rot)), q_pos' = q_pos + dt R0^T v,
      so d q_rot'/d w = J_l^-1(q_rot') J_l(dt R0^T w) dt R0^T;
    ball joint, w in the child body frame: q' = log(exp(q) exp(dt w)) -> J_r^-1(q') J_r(dt w) dt, J_r(x) = J_l(-x).
    """
    if kind == "BallJoint":
        return left_jacobian_inv(-q_next) @ left_jacobian(-dt * qd_next) * dt
    w = R0.T @ qd_next[:3]
    B = np.zeros((6, 6))
    B[:3, :3] = left_jacobian_inv(q_next[:3]) @ left_jacobian(dt * w) @ R0.T * dt
    B[3:, 3:] = dt * R0.T
    return B


class RigidAdjoint:
    """``vjp_flat`` and ``body_states_vjp`` of the rigid engine."""

    def vjp_flat(self, record: StepRecord, grad_next_state: np.ndarray) -> tuple:
        """(grad_state, grad_action, grad_wrenches, grad_added_mass or None) of one step for the adjoint
        ``grad_next_state``.

        Action and wrench blocks: closed form from DART's M, damping D and Jacobians at the step's start.
        Per skeleton, with F the force-driven dofs, K the velocity-controlled ones and A = M_FF + dt D_FF:
        qd'_F = qd_F + dt A^-1 (tau_F + (J^T F)_F - C_F - D qd_F - M_FK (target - qd_K)/dt), qd'_K = target;
        with added masses M + A_hat in place of M (``rigid_added_mass``), and dL/dA_b in closed form.
        Positions: q' = q + dt qd' except free/ball joints (closed form,
        ``position_step_jacobian``). These blocks are exact for DART's unconstrained step; a step in which a
        joint limit or a contact acted (a non-zero constraint force, ``StepRecord.constraint``) raises
        ``SimulationError`` instead of returning a gradient that omits the impulse. Velocity commands clipped
        to joint limits (``StepRecord.clamped``) have a zero action gradient, which is exact.
        State block: central differences over DART's own deterministic step (set_state, perturb, step): the
        closed form needs the derivatives of the Coriolis/gravity terms, M(q) and J(q), which DART does not
        expose; the differences include contacts and limits. Cost: 4 * dofs steps.
        """
        if record.constraint is not None:
            where, force = record.constraint
            raise SimulationError(
                f"rigid step {record.step}: a joint limit or a rigid contact acted on '{where}' (generalised "
                f"constraint force {force:.3g}); the gradient of DART's step leaves constraint impulses out, so "
                "it would be wrong here. Keep torque/wrench-driven joints inside their limits (bound the actions) "
                "or use velocity control (its commands are clipped to the limits, and differentiated), or switch "
                "rigid collisions off"
            )
        g = np.asarray(grad_next_state, dtype=np.float64)
        if g.shape != (2 * self.dofs,):
            raise InputError(f"grad_next_state must have length {2 * self.dofs}, got {g.shape}")
        current = self.flat_state()
        self.set_flat_state(record.state)
        grad_v = self._velocity_adjoint(g, record.next_state)
        A_hat = None
        if record.added is not None:
            jacobians = rigid_added_mass.body_jacobians(self, record.added)
            A_hat = rigid_added_mass.generalised(self, record.added, jacobians)
        grad_tau, grad_cmd = self._force_adjoints(grad_v, A_hat)
        grad_action = self._action_adjoint(grad_tau, grad_cmd)
        if record.clamped is not None:
            grad_action[record.clamped] = 0.0  # a clipped command does not depend on its action
        grad_wrenches = (
            np.stack([self._body_jacobian(k, body) @ grad_tau[k] for k, body in self._bodies])
            if self._bodies
            else np.zeros((0, 6))
        )
        grad_added = None
        if record.added is not None:
            change = record.next_state[self.dofs :] - record.state[self.dofs :]
            y = [t / self.dt for t in grad_tau]
            grad_added = rigid_added_mass.added_mass_adjoint(self, record.added, y, change)
        grad_state = self._state_vjp_fd(record, g)
        self.set_flat_state(current)
        return grad_state, grad_action, grad_wrenches, grad_added

    def _velocity_adjoint(self, g: np.ndarray, next_state: np.ndarray) -> np.ndarray:
        """Adjoint of qd' (total): g_qd + (d q'/d qd')^T g_q."""
        n = self.dofs
        g_q, g_qd = g[:n], g[n:]
        grad_v = g_qd + self.dt * g_q
        for kind, idx, R0 in self._rotation_blocks:
            B = position_step_jacobian(kind, next_state[idx], next_state[n + idx], R0, self.dt)
            grad_v[idx] = g_qd[idx] + B.T @ g_q[idx]
        return grad_v

    def _force_adjoints(self, grad_v: np.ndarray, A_hat: list | None = None) -> tuple[list, list]:
        """Per skeleton: adjoints of the generalised forces and of the velocity targets (at the current q),
        with the added masses ``A_hat`` (per skeleton, dofs x dofs; None: none)."""
        grad_tau, grad_cmd = [], []
        for k in range(len(self.skeletons)):
            gv = grad_v[self._offsets[k] : self._offsets[k + 1]]
            kin = self._kinematic[k]
            free = ~kin
            M = rigid_added_mass.inertia(self, k) + (0.0 if A_hat is None else A_hat[k])  # M + dt D (+ A_hat)
            y = np.zeros_like(gv)
            if free.any():
                y[free] = np.linalg.solve(M[np.ix_(free, free)].T, gv[free])
            cmd = np.zeros_like(gv)
            cmd[kin] = gv[kin] - M[np.ix_(kin, free)] @ y[free]
            grad_tau.append(self.dt * y)
            grad_cmd.append(cmd)
        return grad_tau, grad_cmd

    def _action_adjoint(self, grad_tau: list[np.ndarray], grad_cmd: list[np.ndarray]) -> np.ndarray:
        out = np.zeros(self.action_size)
        for c in self.controls:
            if c.mode == "torque":
                out[c.slice] = grad_tau[c.skel][c.dofs]
            elif c.mode == "wrench":
                out[c.slice] = self._joint_jacobian(c) @ grad_tau[c.skel][c.dofs]
            elif c.mode == "velocity":
                out[c.slice] = grad_cmd[c.skel][c.dofs]
            else:
                out[c.slice] = np.linalg.solve(self._joint_jacobian(c).T, grad_cmd[c.skel][c.dofs])
        return out

    def _state_vjp_fd(self, record: StepRecord, g: np.ndarray) -> np.ndarray:
        out = np.zeros(2 * self.dofs)
        for i in range(2 * self.dofs):
            e = np.zeros(2 * self.dofs)
            e[i] = FD_EPS
            plus = self._advance(record.state + e, record.action, record.wrenches, record.added)
            minus = self._advance(record.state - e, record.action, record.wrenches, record.added)
            out[i] = g @ (plus - minus) / (2 * FD_EPS)
        return out

    def body_states_vjp(self, grad_pos=None, grad_R=None, grad_v=None, grad_w=None, state=None) -> np.ndarray:
        """Gradient w.r.t. the state (positions, velocities) of sum <grad, body_states()> at ``state``
        (default: the current state). None means a zero gradient.

        d/d qd closed form: [w; v] = J(q) qd, so grad_qd = sum_b J_b^T [grad_w; grad_v]. d/d q: central
        differences over DART's forward kinematics (a closed form needs dJ/dq and the rotation-vector
        chart of free/ball joints, which DART does not expose); cost 2 * dofs kinematics evaluations.
        """
        nb = len(self._bodies)
        grads = [
            np.zeros(shape) if g is None else np.asarray(g, dtype=np.float64).reshape(shape)
            for g, shape in ((grad_pos, (nb, 3)), (grad_R, (nb, 3, 3)), (grad_v, (nb, 3)), (grad_w, (nb, 3)))
        ]
        current = self.flat_state()
        s = current if state is None else np.asarray(state, dtype=np.float64)
        self.set_flat_state(s)
        n = self.dofs
        out = np.zeros(2 * n)
        for i, (k, body) in enumerate(self._bodies):
            J = self._body_jacobian(k, body)
            out[n + self._offsets[k] : n + self._offsets[k + 1]] += J.T @ np.concatenate([grads[3][i], grads[2][i]])
        for i in range(n):
            e = np.zeros(2 * n)
            e[i] = FD_EPS
            out[i] = (self._body_state_dot(s + e, grads) - self._body_state_dot(s - e, grads)) / (2 * FD_EPS)
        self.set_flat_state(current)
        return out

    def _body_state_dot(self, s: np.ndarray, grads: list[np.ndarray]) -> float:
        self.set_flat_state(s)
        b = self.body_states()
        keys = ("position", "rotation", "linear_velocity", "angular_velocity")
        return float(sum(np.sum(g * b[key]) for g, key in zip(grads, keys)))
