"""Two-way coupling of a cloth with the rigid bodies of one engine (DART links or kinematic bodies).

One macro step n (the cloth steps before DART, so the reaction acts in the same frame):

    boundary    the cloth's contact points (vertices, face centroids) at x^n within the contact
                thickness of a body (plus twice the farthest a vertex moves in the frame), asked of
                python-fcl at the bodies' poses at the step's start (``RigidObstacles``), become contact
                planes with the body's surface velocity under each point (friction is relative to it):
                the cloth's input "boundaries";
    cloth       steps with them as stiff penalties (``cosim.engines.cloth_contact``); its output
                "reactions" are the forces it exerts on the bodies at the plane points;
    forces      DART: per body the wrench [torque about the body origin o; force] of those forces;
                kinematic bodies (prescribed motions) take none.

Backward: ``forces_vjp`` turns dL/d(wrench) into the reactions' adjoints (the torque arms' part is
carried); the cloth's vjp returns the planes' adjoints (and takes the planes' dependence on its own
start positions through their Jacobians, ``RigidObstacles``); ``boundary_vjp`` takes them through
p = o + R p_l(x_l), n = R n_l(x_l), x_l = R^T (q - o) (q the queried point) to the bodies' poses and
DART's kinematics (dL/ds_D^n). Which points touch is decided at the step's start. A kinematic body
passes no gradient back (its motion is not a parameter, as with the MPM).
Conforms to ``cosim.engines.contract.Coupler`` with ``medium`` the cloth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.couplers.cloth_rigid import RigidObstacles
from cosim.engines.cloth_contact import ContactPlanes
from cosim.engines.contract import declares


@dataclass
class ClothRigidRecord:
    """One step's contacts as the vjp needs them."""

    state: np.ndarray | None  # the rigid engine's flat state at the step's start (DART), else None
    origin: np.ndarray  # (m, 3) [m] the coupled bodies' origins
    rotation: np.ndarray  # (m, 3, 3) body to world
    twist: np.ndarray  # (m, 2, 3) [m/s; rad/s] origin velocity and angular velocity
    query: np.ndarray  # (c, 3) [m] the queried contact points
    planes: ContactPlanes
    local_point: np.ndarray  # (c, 3) [m] each plane point in its body's frame
    local_normal: np.ndarray  # (c, 3)
    reactions: np.ndarray | None = None  # (c, 3) [N] the forces on the bodies, once ``forces`` ran


class ClothRigidCoupler:
    """Contact planes of ``rigid``'s bodies ``bodies`` (indices into its bodies: DART's ``body_names``
    or the kinematic motions) for ``cloth``, and the cloth's reactions back to DART."""

    capabilities = frozenset()

    def __init__(self, cloth, rigid, bodies: list[int], obstacles: RigidObstacles, thickness: float, name: str):
        self.cloth, self.rigid, self.obstacles = cloth, rigid, obstacles
        self.bodies = np.asarray(bodies, dtype=np.int64)
        self.thickness = float(thickness)  # [m] the cloth's contact thickness
        self.name = self.source = name
        self.medium, self.engine = cloth.name, rigid.name
        self.pushes = declares(rigid, "body_states")  # DART takes the reactions; prescribed bodies none

    def _poses(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(origins (m, 3), rotations (m, 3, 3), twists (m, 2, 3)) of the coupled bodies now."""
        if self.pushes:
            s = self.rigid.body_states()
            b = self.bodies
            return s["position"][b], s["rotation"][b], np.stack([s["linear_velocity"][b], s["angular_velocity"][b]], 1)
        poses, t = self.rigid.poses(), self.rigid.time
        twists = [self.rigid.motions[i].twist(t) for i in self.bodies]
        return (
            np.array([poses[i][0] for i in self.bodies]),
            np.array([poses[i][1] for i in self.bodies]),
            np.array([[np.asarray(v, float), np.broadcast_to(np.asarray(w, float), 3)] for v, w in twists]).reshape(
                -1, 2, 3
            ),
        )

    def boundary(self, dt: float, substeps: int) -> tuple[ContactPlanes, ClothRigidRecord]:
        """The contact planes of the cloth's current points against the bodies at their current poses."""
        origin, R, twist = self._poses()
        points = self.cloth.contact.points(self.cloth.x)
        # speculative: a point that may reach the contact layer within the frame gets its plane now, so the
        # implicit step stops it at the layer (without, it enters unopposed and is pushed back out at its
        # own speed the next frame: an elastic bounce)
        reach = 2.0 * dt * float(np.linalg.norm(self.cloth.v, axis=1).max(initial=0.0))
        planes = self.obstacles.planes(points, list(zip(origin, R)), self.thickness + reach)
        Rb, spin = R[planes.body], twist[planes.body, 1]
        arms = planes.point - origin[planes.body]
        planes.velocity = twist[planes.body, 0] + np.cross(spin, arms)  # the surface under each point
        planes.velocity_jacobian = np.cross(spin[:, :, None], planes.jacobians()[0], axis=1)  # [w]x dp/dq
        local_point = np.einsum("cji,cj->ci", Rb, arms)  # R^T (p - o)
        local_normal = np.einsum("cji,cj->ci", Rb, planes.normal)
        state = self.rigid.flat_state() if self.pushes else None
        record = ClothRigidRecord(state, origin, R, twist, points[planes.index], planes, local_point, local_normal)
        return planes, record

    def _arms(self, record: ClothRigidRecord) -> np.ndarray:
        return record.planes.point - record.origin[record.planes.body]

    def forces(self, record: ClothRigidRecord, reactions: dict) -> dict[str, np.ndarray]:
        """{"forces": per-body wrenches (DART's bodies, 6)} of the cloth's reactions {"force" (c, 3) [N],
        "point"}; {} for prescribed bodies."""
        record.reactions = np.asarray(reactions["force"], dtype=np.float64).reshape(-1, 3)
        if not self.pushes:
            return {}
        body = self.bodies[record.planes.body]
        wrenches = np.zeros((len(self.rigid.body_names), 6))
        np.add.at(wrenches[:, :3], body, np.cross(self._arms(record), record.reactions))
        np.add.at(wrenches[:, 3:], body, record.reactions)
        return {"forces": wrenches}

    def external_work(self, record: ClothRigidRecord, frame_dt: float) -> float:
        """[J] Work the bodies outside the energy budget (prescribed, or of a driven skeleton) did on the cloth
        over the frame: minus each reaction on the body times the body's velocity at the plane point."""
        outside = (
            ~self.rigid.passive_bodies()[self.bodies]
            if declares(self.rigid, "energy")
            else np.ones(len(self.bodies), bool)
        )
        at_plane = record.planes.velocities()  # the surface velocity under each point (``boundary``)
        return -frame_dt * float(
            np.sum(outside[record.planes.body] * np.einsum("ck,ck->c", record.reactions, at_plane))
        )

    def forces_vjp(self, record: ClothRigidRecord, grad_load: dict, grad_state: None = None) -> tuple:
        """dL/d(wrenches) -> (dL/d(reactions) {"force", "point"} (c, 3) each, dL/d(torque arms) carried to
        ``boundary_vjp`` for the origins, None)."""
        if not self.pushes or grad_load.get("forces") is None:
            return None, None, None
        g = np.asarray(grad_load["forces"], dtype=np.float64)[self.bodies[record.planes.body]]
        g_torque, g_force = g[:, :3], g[:, 3:]
        g_reactions = g_force + np.cross(g_torque, self._arms(record))  # d/dF of gt . (r x F) = gt x r
        g_arms = np.cross(record.reactions, g_torque)  # d/dr of gt . (r x F) = F x gt, r = p - o
        return {"force": g_reactions, "point": g_arms}, g_arms, None

    def boundary_vjp(self, record: ClothRigidRecord, grad_boundary: dict, carry) -> dict[str, np.ndarray]:
        """dL/d(planes) {"point", "normal", "velocity"} (c, 3) and the torque arms' adjoint -> dL/ds of the
        rigid engine."""
        if not self.pushes:
            return {"steps": np.zeros(1)}
        g_point = np.asarray(grad_boundary["point"], dtype=np.float64).reshape(-1, 3)
        g_normal = np.asarray(grad_boundary["normal"], dtype=np.float64).reshape(-1, 3)
        g_velocity = np.asarray(grad_boundary["velocity"], dtype=np.float64).reshape(-1, 3)
        body, m = self.bodies[record.planes.body], record.planes.body
        nb = len(self.rigid.body_names)
        g_pos, g_R, g_v, g_w = np.zeros((nb, 3)), np.zeros((nb, 3, 3)), np.zeros((nb, 3)), np.zeros((nb, 3))
        # v_s = v + w x (p - o): the twist, and the arm (the cloth took the arm's query-point part)
        arms = self._arms(record)
        np.add.at(g_v, body, g_velocity)
        np.add.at(g_w, body, np.cross(arms, g_velocity))
        along_arm = np.cross(g_velocity, record.twist[m, 1])
        g_point = g_point + along_arm
        np.add.at(g_pos, body, -along_arm)
        if carry is not None:  # the torque arms p - o: p's part came back through the cloth with the planes'
            np.add.at(g_pos, body, -carry)
        # p = o + R p_l(x_l), n = R n_l(x_l), x_l = R^T (q - o): the plane's feature moves with the query q
        J_p, J_n, _ = record.planes.jacobians()
        g_query = np.einsum("cki,ck->ci", J_p, g_point) + np.einsum("cki,ck->ci", J_n, g_normal)
        np.add.at(g_pos, body, g_point - g_query)
        g_local = np.einsum("cki,ck->ci", record.rotation[m], g_query)  # R^T g_query
        outer = (
            np.einsum("ci,cj->cij", g_point, record.local_point)
            + np.einsum("ci,cj->cij", g_normal, record.local_normal)
            + np.einsum("ci,cj->cij", record.query - record.origin[m], g_local)
        )
        np.add.at(g_R, body, outer)
        flat = self.rigid.body_states_vjp(g_pos, g_R, g_v, g_w, state=record.state)
        n = self.rigid.dofs
        return {"q": flat[:n], "qd": flat[n:]}
