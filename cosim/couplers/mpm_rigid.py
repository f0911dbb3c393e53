"""Two-way coupling of the MPM with DART rigid bodies (the paper's "Differentiable Simulation Design").

One macro step n (rigid dt = K x MPM dt = the frame):

    boundary    every coupled body's pose and twist at s_D^n, moved with that twist
                through the K substeps (p_k = p + k dt v, R_k = exp(k dt w) R), become
                the MPM's moving boundaries (SDFs in ``RigidBoundaries``);
    MPM         K substeps under the scene's contact model: s_M^{n+1}; the contact
                reactions per substep (impulse, angular impulse about p_k);
    force       F^n = the reaction averaged over the K substeps: force sum_k J_k / T,
                torque about the body origin p, sum_k (L_k + (p_k - p) x J_k) / T,
                with T = K dt the frame;
    rigid       s_D^{n+1} = DART step(s_D^n, a^n, F^n).

Backward, per step, exactly the paper's chain rule: the rigid vjp gives dL/ds_D^n
(own dynamics), dL/da^n and dL/dF^n; dL/dF^n is seeded on the reaction adjoints, so
the MPM vjp returns dL/ds_M^n with both the direct path and the path through F^{n+1},
and dL/d(boundary states), which carries the force path and the boundary path into
s_M^{n+1}; the boundary adjoint goes back through the substep motion and DART's
kinematics to dL/ds_D^n.

2D scenes: DART is 3D; bodies move in the xy-plane (planar or z-axis joints) and the
MPM sees (x, y), the 2x2 rotation and the z angular velocity; the reactions come back
as (fx, fy, 0) and (0, 0, tz).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _hat(phi: np.ndarray) -> np.ndarray:
    """[phi]x for a batch of vectors (..., 3) -> (..., 3, 3)."""
    z = np.zeros(phi.shape[:-1])
    x, y, w = phi[..., 0], phi[..., 1], phi[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def _series(phi: np.ndarray):
    """|phi|, [phi]x, [phi]x^2 and a safe |phi| (1 where it is ~0) for batched SO(3) formulas."""
    t = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = _hat(phi)
    return t, K, K @ K, np.where(t < 1e-6, 1.0, t)


def _exp(phi: np.ndarray) -> np.ndarray:
    """exp([phi]x) (Rodrigues) for a batch (..., 3) -> (..., 3, 3); a Taylor series near 0."""
    t, K, K2, ts = _series(phi)
    a = np.where(t < 1e-6, 1.0 - t**2 / 6, np.sin(ts) / ts)
    b = np.where(t < 1e-6, 0.5 - t**2 / 24, (1 - np.cos(ts)) / ts**2)
    return np.eye(3) + a * K + b * K2


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(phi) with exp(phi + d) = exp(J_l d) exp(phi) to first order, batched."""
    t, K, K2, ts = _series(phi)
    a = np.where(t < 1e-6, 0.5 - t**2 / 24, (1 - np.cos(ts)) / ts**2)
    b = np.where(t < 1e-6, 1 / 6 - t**2 / 120, (ts - np.sin(ts)) / ts**3)
    return np.eye(3) + a * K + b * K2


def _axial(M: np.ndarray) -> np.ndarray:
    """a with <M, [a]x> = a . axial(M), batched (..., 3, 3) -> (..., 3)."""
    return np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)


@dataclass
class BodyStates:
    """World-frame states of the coupled bodies (3D): origin ``pos`` (m, 3), rotation ``R`` body to
    world (m, 3, 3), origin velocity ``v`` (m, 3), angular velocity ``w`` (m, 3)."""

    pos: np.ndarray
    R: np.ndarray
    v: np.ndarray
    w: np.ndarray


def substep_states(b: BodyStates, dt: float, K: int) -> BodyStates:
    """Per-substep states (K, m, ...): each body moves with its twist, p_k = p + k dt v, R_k = exp(k dt w) R."""
    k = (np.arange(K) * dt)[:, None, None]
    pos = substep_origins(b, dt, K)
    R = _exp(k * b.w[None]) @ b.R[None]
    return BodyStates(pos, R, np.broadcast_to(b.v, pos.shape).copy(), np.broadcast_to(b.w, pos.shape).copy())


def substep_origins(b: BodyStates, dt: float, K: int) -> np.ndarray:
    """The body origins p + k dt v of substeps k = 0..K-1, (K, m, 3)."""
    return b.pos[None] + (np.arange(K) * dt)[:, None, None] * b.v[None]


def substep_states_vjp(g: BodyStates, b: BodyStates, dt: float) -> BodyStates:
    """Adjoint of ``substep_states``: per-substep gradients (K, m, ...) -> gradients of ``b``."""
    k = (np.arange(len(g.pos)) * dt)[:, None, None]
    phi = k * b.w[None]
    E = _exp(phi)
    R_k = E @ b.R[None]
    gR = (np.swapaxes(E, -1, -2) @ g.R).sum(axis=0)
    # R_k = exp(phi) R with exp(phi + d) = exp(J_l(phi) d) exp(phi): dR_k = [J_l d]x R_k
    spin = _axial(g.R @ np.swapaxes(R_k, -1, -2))
    gw = g.w.sum(axis=0) + (k * (np.swapaxes(_left_jacobian(phi), -1, -2) @ spin[..., None])[..., 0]).sum(axis=0)
    gv = g.v.sum(axis=0) + (k * g.pos).sum(axis=0)
    return BodyStates(g.pos.sum(axis=0), gR, gv, gw)


def to_mpm(s: BodyStates, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What ``RigidBoundaries.set_states`` takes: 3D as is; 2D the xy-plane and the z spin."""
    if dim == 3:
        return s.pos, s.R, s.v, s.w
    return s.pos[..., :2], s.R[..., :2, :2], s.v[..., :2], s.w[..., 2:]


def from_mpm(grads: dict[str, np.ndarray], dim: int) -> BodyStates:
    """Adjoint of ``to_mpm``: MPM-side gradients embedded in 3D (zeros off the plane)."""
    pos, rot, vel, omega = grads["pos"], grads["rot"], grads["vel"], grads["omega"]
    if dim == 3:
        return BodyStates(pos, rot, vel, omega)
    lead = pos.shape[:-1]
    out = BodyStates(np.zeros((*lead, 3)), np.zeros((*lead, 3, 3)), np.zeros((*lead, 3)), np.zeros((*lead, 3)))
    out.pos[..., :2], out.R[..., :2, :2], out.v[..., :2], out.w[..., 2:] = pos, rot, vel, omega
    return out


def lift_reactions(impulse: np.ndarray, angular: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Substep reactions from ``RigidBoundaries.reactions`` as 3D vectors."""
    if dim == 3:
        return impulse, angular
    lead = impulse.shape[:-1]
    J, L = np.zeros((*lead, 3)), np.zeros((*lead, 3))
    J[..., :2], L[..., 2:] = impulse, angular
    return J, L


def average_wrench(J: np.ndarray, L: np.ndarray, pos_k: np.ndarray, pos: np.ndarray, frame: float) -> np.ndarray:
    """(m, 6) [torque about the body origin p; force]: the reactions J_k, L_k (about p_k) of the K
    substeps (K, m, 3) averaged over the frame T."""
    torque = (L + np.cross(pos_k - pos[None], J)).sum(axis=0) / frame
    return np.concatenate([torque, J.sum(axis=0) / frame], axis=1)


def average_wrench_vjp(gW: np.ndarray, J: np.ndarray, pos_k: np.ndarray, pos: np.ndarray, frame: float):
    """Adjoint of ``average_wrench``: (dL/dJ_k, dL/dL_k, dL/dp_k, dL/dp)."""
    gt, gf = gW[:, :3] / frame, gW[:, 3:] / frame
    r = pos_k - pos[None]
    gJ = gf[None] + np.cross(gt[None], r)  # d/dJ of gt . (r x J) = gt x r
    gL = np.broadcast_to(gt, J.shape).copy()
    gpk = np.cross(J, gt[None])  # d/dr of gt . (r x J) = J x gt
    return gJ, gL, gpk, -gpk.sum(axis=0)


@dataclass
class CoupledRecord:
    """What the backward pass needs about one coupled step besides the MPM's own record."""

    rigid: object  # the rigid engine's StepRecord
    bodies: BodyStates  # coupled bodies at s_D^n
    J: np.ndarray  # (K, m, 3) reaction impulses per substep
    pos_k: np.ndarray  # (K, m, 3) body origins per substep
    dt: float
    substeps: int


class MPMRigidCoupler:
    """Moves DART bodies' SDFs through the MPM and hands the averaged reactions back to DART.

    ``coupled``: indices into ``rigid.body_names`` of the bodies the MPM sees, in the order of
    their ``RigidBoundaries`` slots ``first_slot, first_slot + 1, ...`` (kinematic bodies take
    the slots before). Bodies not listed (a floor, a fixed palm) cost nothing in the MPM.
    """

    def __init__(self, rigid, boundaries, coupled: list[int], first_slot: int, dim: int):
        self.rigid = rigid
        self.boundaries = boundaries
        self.coupled = list(coupled)
        self.first = first_slot
        self.dim = dim
        self.slots = slice(first_slot, first_slot + len(coupled))

    def current_bodies(self) -> BodyStates:
        s = self.rigid.body_states()
        c = self.coupled
        return BodyStates(
            s["position"][c], s["rotation"][c], s["linear_velocity"][c], s["angular_velocity"][c]
        )

    def boundary_arrays(self, bodies: BodyStates, dt: float, K: int):
        """(pos, rot, vel, omega) per substep (K, m, ...) in the MPM's dimension."""
        return to_mpm(substep_states(bodies, dt, K), self.dim)

    def finish_step(self, bodies: BodyStates, action: np.ndarray | None, dt: float, K: int) -> CoupledRecord:
        """After the MPM's K substeps: average the reactions and step DART."""
        if not self.coupled:  # nothing touches the MPM
            zero = np.zeros((K, 0, 3))
            return CoupledRecord(self.rigid.step(action, None), bodies, zero, zero, dt, K)
        impulse, angular = self.boundaries.reactions(K)
        J, L = lift_reactions(impulse[:, self.slots], angular[:, self.slots], self.dim)
        pos_k = substep_origins(bodies, dt, K)
        wrenches = np.zeros((len(self.rigid.body_names), 6))
        wrenches[self.coupled] = average_wrench(J, L, pos_k, bodies.pos, K * dt)
        record = self.rigid.step(action, wrenches)
        return CoupledRecord(record, bodies, J, pos_k, dt, K)

    def seed_reaction_grads(self, rec: CoupledRecord, grad_wrenches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Put dL/dF on the reaction adjoints of the coupled slots; returns the torque-arm gradients
        (dL/dp_k (K, m, 3), dL/dp (m, 3))."""
        if not self.coupled:
            return np.zeros((rec.substeps, 0, 3)), np.zeros((0, 3))
        gJ, gL, gpk, gp = average_wrench_vjp(
            grad_wrenches[self.coupled], rec.J, rec.pos_k, rec.bodies.pos, rec.substeps * rec.dt
        )
        K, n = rec.substeps, self.boundaries.n
        gi, ga = np.zeros((K, n, self.dim)), np.zeros((K, n, self.boundaries.wdim))
        if self.dim == 3:
            gi[:, self.slots], ga[:, self.slots] = gJ, gL
        else:
            gi[:, self.slots], ga[:, self.slots] = gJ[..., :2], gL[..., 2:]
        self.boundaries.seed_reaction_grads(gi, ga)
        return gpk, gp

    def boundary_vjp(self, rec: CoupledRecord, arm_grads: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """dL/ds_D^n through the boundary states (after the MPM vjp filled their adjoints)."""
        if not self.coupled:
            return np.zeros(2 * self.rigid.dofs)
        grads = self.boundaries.state_grads(rec.substeps)
        per_substep = from_mpm({k: v[:, self.slots] for k, v in grads.items()}, self.dim)
        per_substep.pos = per_substep.pos + arm_grads[0]
        g = substep_states_vjp(per_substep, rec.bodies, rec.dt)
        nb = len(self.rigid.body_names)
        full = [np.zeros((nb, 3)), np.zeros((nb, 3, 3)), np.zeros((nb, 3)), np.zeros((nb, 3))]
        full[0][self.coupled] = g.pos + arm_grads[1]
        full[1][self.coupled], full[2][self.coupled], full[3][self.coupled] = g.R, g.v, g.w
        return self.rigid.body_states_vjp(*full, state=rec.rigid.state)
