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
    rigid       s_D^{n+1} = DART step(s_D^n, a^n, F^n, A^n).

The strong coupling (``added_mass``, as ``cosim.couplers.mpm_cloth`` does for a cloth; why
there): the material that follows each body over the frame enters DART's step as an inertia
A^n (6x6 per body on its twist V = [omega; v] about its origin, ``RigidBoundaries``'s "mass",
``cosim.engines.rigid_added_mass``), so a light body under heavy material moves with the
material instead of being kicked by it one frame late, and the next step's MPM hands that
material the body's twist change V^{n+1} - V^n (``cosim.couplers.handover``). The coupler's
state carries V_b^{n-1} (m, 6), the twist the previous step's MPM met (None at the start).

Backward, per step, exactly the paper's chain rule: the rigid vjp gives dL/ds_D^n
(own dynamics), dL/da^n and dL/dF^n; ``forces_vjp`` turns dL/dF^n into reaction
adjoints, which the MPM vjp takes as an argument and returns dL/ds_M^n with both the
direct path and the path through F^{n+1}, and dL/d(boundary states), which carries the
force path and the boundary path into s_M^{n+1}; ``boundary_vjp`` takes the boundary
adjoint back through the substep motion and DART's kinematics to dL/ds_D^n. The added
mass: DART's dL/dA^n goes to the MPM as the reactions' "mass" adjoint; the hand-over's
adjoint dL/d(V^n - V_b^{n-1}) to the twist V^n and, negated, to this coupler's state before
the step; dL/d(the carried V_b^n = V^n) to V^n.

2D scenes: DART is 3D; bodies move in the xy-plane (planar or z-axis joints) and the
MPM sees (x, y), the 2x2 rotation and the z angular velocity; the reactions come back
as (fx, fy, 0) and (0, 0, tz).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.engines import so3


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
    R = so3.exp(k * b.w[None]) @ b.R[None]
    return BodyStates(pos, R, np.broadcast_to(b.v, pos.shape).copy(), np.broadcast_to(b.w, pos.shape).copy())


def substep_origins(b: BodyStates, dt: float, K: int) -> np.ndarray:
    """The body origins p + k dt v of substeps k = 0..K-1, (K, m, 3)."""
    return b.pos[None] + (np.arange(K) * dt)[:, None, None] * b.v[None]


def substep_states_vjp(g: BodyStates, b: BodyStates, dt: float) -> BodyStates:
    """Adjoint of ``substep_states``: per-substep gradients (K, m, ...) -> gradients of ``b``."""
    k = (np.arange(len(g.pos)) * dt)[:, None, None]
    phi = k * b.w[None]
    E = so3.exp(phi)
    R_k = E @ b.R[None]
    gR = (np.swapaxes(E, -1, -2) @ g.R).sum(axis=0)
    # R_k = exp(phi) R with exp(phi + d) = exp(J_l(phi) d) exp(phi): dR_k = [J_l d]x R_k
    spin = so3.axial(g.R @ np.swapaxes(R_k, -1, -2))
    gw = g.w.sum(axis=0) + (k * (np.swapaxes(so3.left_jacobian(phi), -1, -2) @ spin[..., None])[..., 0]).sum(axis=0)
    gv = g.v.sum(axis=0) + (k * g.pos).sum(axis=0)
    return BodyStates(g.pos.sum(axis=0), gR, gv, gw)


def to_mpm(s: BodyStates, dim: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(pos, rot, vel, omega) as the MPM's boundary states: 3D as is; 2D the xy-plane and the z spin."""
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
    """Substep reactions (impulse, angular impulse) from the MPM's boundary source as 3D vectors."""
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


TWIST_2D = slice(2, 5)  # the 2D MPM's twist [omega_z, vx, vy] within DART's [omega; v]


def lift_mass(mass: np.ndarray, dim: int) -> np.ndarray:
    """(m, k, k) added masses from the MPM's boundary source (k = 3 in 2D, 6 in 3D) as DART's (m, 6, 6)."""
    if dim == 3:
        return np.array(mass, dtype=np.float64)
    out = np.zeros((len(mass), 6, 6))
    out[:, TWIST_2D, TWIST_2D] = mass
    return out


def lift_twist(twist: np.ndarray, dim: int) -> np.ndarray:
    """(m, k) twists in the MPM's layout as DART's (m, 6) [omega; v]."""
    if dim == 3:
        return np.asarray(twist, dtype=np.float64)
    out = np.zeros((len(twist), 6))
    out[:, TWIST_2D] = twist
    return out


def lower_mass(grad: np.ndarray, dim: int) -> np.ndarray:
    """Adjoint of ``lift_mass``."""
    return grad if dim == 3 else grad[:, TWIST_2D, TWIST_2D]


@dataclass
class CoupledRecord:
    """One coupled step as the coupler's vjp needs it: filled by ``boundary``, completed by ``forces``."""

    state: np.ndarray  # the rigid engine's flat state at s_D^n
    bodies: BodyStates  # coupled bodies at s_D^n
    dt: float
    substeps: int
    J: np.ndarray | None = None  # (K, m, 3) reaction impulses per substep
    pos_k: np.ndarray | None = None  # (K, m, 3) body origins per substep
    handover: bool = False  # whether this step's MPM hands over a twist change (not at the start)

    @property
    def frame(self) -> float:
        return self.dt * self.substeps


class MPMRigidCoupler:
    """Moves DART bodies' SDFs through the MPM and hands the averaged reactions back to DART.

    ``coupled``: indices into ``rigid.body_names`` of the bodies the MPM sees, in the order of
    the bodies of boundary source ``source`` (a ``RigidBoundaries``). Bodies not listed (a
    floor, a fixed palm) cost nothing in the MPM. ``added_mass=False`` exchanges explicitly (the
    choice for bodies whose every dof a velocity command drives: no inertia of theirs to add to).
    Conforms to ``cosim.engines.contract.Coupler``.
    """

    def __init__(self, rigid, coupled: list[int], dim: int, name: str = "dart", added_mass: bool = True):
        self.rigid = rigid
        self.coupled = list(coupled)
        self.dim = dim
        self.name = self.source = name
        self.engine = rigid.name
        self.medium = "mpm"
        self.added_mass = bool(added_mass)
        self.capabilities = frozenset({"carried_state", "exchange_limit"}) if self.added_mass else frozenset()
        # a thin plate at r = 1-5 on an elastic block jitters at 8 substeps per exchange (docs/bench/coupling.md)
        self.exchange_substeps = 4
        self._boundary_v: np.ndarray | None = None  # V_b^{n-1}, None at the start

    def state(self) -> dict:
        """{"boundary_v": (m, 6) V_b^{n-1} [rad/s; m/s] or None (fresh)}: what the next step reads."""
        return {"boundary_v": None if self._boundary_v is None else self._boundary_v.copy()}

    def set_state(self, state: dict | None) -> None:
        """Restore a state from ``state()`` (None: fresh, as at the start of a run)."""
        v_b = (state or {}).get("boundary_v")
        self._boundary_v = None if v_b is None else np.array(v_b, dtype=np.float64)

    def budgeted(self) -> np.ndarray:
        """(m,) bool: which coupled bodies' energy is in the system's budget (no action drives their
        skeleton), so that their contact work on the material is internal."""
        return self.rigid.passive_bodies()[self.coupled]

    def current_bodies(self) -> BodyStates:
        s = self.rigid.body_states()
        c = self.coupled
        return BodyStates(s["position"][c], s["rotation"][c], s["linear_velocity"][c], s["angular_velocity"][c])

    def boundary(self, dt: float, substeps: int) -> tuple[dict, CoupledRecord]:
        """The coupled bodies at the engine's current state, moved with their twists through the substeps."""
        bodies = self.current_bodies()
        pos, rot, vel, omega = to_mpm(substep_states(bodies, dt, substeps), self.dim)
        record = CoupledRecord(self.rigid.flat_state(), bodies, dt, substeps)
        states = {"pos": pos, "rot": rot, "vel": vel, "omega": omega}
        record.handover = self.added_mass and self._boundary_v is not None
        if record.handover:
            change = np.concatenate([bodies.w, bodies.v], axis=1) - self._boundary_v
            states["handover"] = change if self.dim == 3 else change[:, TWIST_2D]
        return states, record

    def forces(self, record: CoupledRecord, reactions: dict) -> dict[str, np.ndarray]:
        """{"forces": per-body wrenches (len(body_names), 6) for DART: the substep reactions averaged over the
        frame; with the added mass, "added_mass" (len(body_names), 6, 6) A^n}; keeps V_b^n for the next step."""
        K, dt = record.substeps, record.dt
        record.J, L = lift_reactions(reactions["impulse"], reactions["angular_impulse"], self.dim)
        record.pos_k = substep_origins(record.bodies, dt, K)
        nb = len(self.rigid.body_names)
        wrenches = np.zeros((nb, 6))
        wrenches[self.coupled] = average_wrench(record.J, L, record.pos_k, record.bodies.pos, K * dt)
        if not self.added_mass or "mass" not in reactions:  # no engagement (not the forecast model): explicit
            return {"forces": wrenches}
        b = record.bodies
        self._boundary_v = np.concatenate([b.w, b.v], axis=1)
        full = np.zeros((nb, 6, 6))
        full[self.coupled] = lift_mass(reactions["mass"], self.dim)
        return {"forces": wrenches, "added_mass": full}

    def forces_vjp(self, record: CoupledRecord, grad_load: dict, grad_state: dict | None = None) -> tuple:
        """dL/d(wrenches, added masses) and dL/d(this coupler's state after the step) -> dL/d(reactions) in
        the MPM's layout, the carry to ``boundary_vjp`` (the torque arms' dL/dp_k (K, m, 3), dL/dp (m, 3),
        the twists' dL/dV^n (m, 6), the state's adjoint before the step) and dL/d(this coupler's state
        before the step) (None without a state; ``boundary_vjp`` completes it)."""
        gW = grad_load["forces"][self.coupled]
        gJ, gL, gpk, gp = average_wrench_vjp(gW, record.J, record.pos_k, record.bodies.pos, record.frame)
        if self.dim == 2:
            gJ, gL = gJ[..., :2], gL[..., 2:]
        reactions = {"impulse": gJ, "angular_impulse": gL}
        m = len(self.coupled)
        g_twist = np.zeros((m, 6))
        if not self.added_mass:
            return reactions, (gpk, gp, g_twist, None), None
        if grad_state and grad_state.get("boundary_v") is not None:
            g_twist += grad_state["boundary_v"]  # the carried V_b^n is V^n
        if grad_load.get("added_mass") is not None:
            reactions["mass"] = lower_mass(grad_load["added_mass"][self.coupled], self.dim)
        before = {"boundary_v": np.zeros((m, 6))}
        return reactions, (gpk, gp, g_twist, before), before

    def boundary_vjp(self, record: CoupledRecord, grad_boundary: dict, carry: tuple) -> dict[str, np.ndarray]:
        """dL/ds_D^n (the engine's state layout) through the boundary states, the torque arms and the hand-over;
        the hand-over's share of dL/d(this coupler's state before the step) goes into ``carry``."""
        per_substep = from_mpm(grad_boundary, self.dim)
        per_substep.pos = per_substep.pos + carry[0]
        g = substep_states_vjp(per_substep, record.bodies, record.dt)
        g_twist = carry[2]
        if record.handover:  # the hand-over V^n - V_b^{n-1}
            g_change = lift_twist(grad_boundary["handover"], self.dim)
            g_twist = g_twist + g_change
            carry[3]["boundary_v"] = -g_change
        g.w, g.v = g.w + g_twist[:, :3], g.v + g_twist[:, 3:]
        nb = len(self.rigid.body_names)
        full = [np.zeros((nb, 3)), np.zeros((nb, 3, 3)), np.zeros((nb, 3)), np.zeros((nb, 3))]
        full[0][self.coupled] = g.pos + carry[1]
        full[1][self.coupled], full[2][self.coupled], full[3][self.coupled] = g.R, g.v, g.w
        flat = self.rigid.body_states_vjp(*full, state=record.state)
        n = self.rigid.dofs
        return {"q": flat[:n], "qd": flat[n:]}
