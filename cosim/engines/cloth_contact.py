"""Cloth against rigid bodies inside the implicit step: a stiff penalty on per-step contact planes.

At the start of a step, every cloth contact point (each vertex, then each face centroid: a
rod thinner than the mesh's edges still meets the faces) near a rigid body gets a plane
through the body's nearest surface point p with unit normal n towards the cloth: the step's
input "boundaries" {source: ``ContactPlanes``}, one set per coupler (``cosim.couplers.cloth_rigid``
asks python-fcl).
The step then minimises, besides its incremental potential,

    E_c(x) = sum_i k_i / 2 * max(0, r - n_i . (sum_j w_ij x_j - p_i))^2,

with r the cloth's contact thickness [m], w_i the point's barycentric weights on its face
(a vertex: one weight 1) and k_i = kappa m_i / h^2, m_i = 1 / sum_j w_ij^2 / m_j the point's
effective mass: the penalty outweighs the point's inertia kappa times, so one step removes
all but 1 / (1 + kappa) of a penetration (kappa = 100: 1 %) and the step stays as well
conditioned as the inertia makes it. k_i uses the masses at attach time, so it is a
constant of the material parameters.

Friction (coefficient mu) is lagged Coulomb friction as a dissipation potential (as in IPC):
with the normal force lambda_i = k_i gap_i at the step's start and the point's tangential
slip relative to the body's surface under it (velocity v_s, from the plane's source),
u_i = T_i (x_i - x_i,n - h v_s,i), T_i = I - n_i n_i^T,

    D(x) = sum_i mu lambda_i f0(|u_i|),  f0(y) = y^2 / eps - y^3 / (3 eps^2) + eps / 3 (y < eps), y (else),

a smooth stick-slip law: slips below eps = v_eps h (v_eps = 1 mm/s) are resisted elastically,
faster ones by the full mu lambda. A towel hangs on a rod by it (without friction a draped
towel is in neutral balance and slides off on any asymmetry, measured).

The step's output "reactions" {source: (c, 3) [N]} is minus each contact point's force (normal
and friction): what the cloth exerts on the rigid body at the plane point p_i. Gradients
(``force_vjp``): a point's force f_i(y_i, p_i, n_i, s_i) depends on its position y_i = sum_j w_ij x_j
at the step's end, its plane, and (through the lagged normal force and the slip) on its position
s_i at the step's start; the cloth's adjoint takes the reactions' adjoints and returns the planes'
(``cosim.engines.cloth_adjoint``). Which points touch and the planes themselves are chosen by the
coupler at the step's start; it differentiates them as fixed in the body's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ContactPlanes:
    """Contact planes of one step from one source: point ``index`` (into the cloth's contact points,
    ``RigidContact.points``) touches ``body``; the plane passes through ``point`` [m] with unit
    ``normal`` towards the cloth. ``point_jacobian`` and ``normal_jacobian`` (c, 3, 3): how the plane
    point and normal move with the queried contact point (zero on a flat face; the cloth's adjoint
    carries them to its positions at the step's start)."""

    index: np.ndarray  # (c,) int
    body: np.ndarray  # (c,) int
    point: np.ndarray  # (c, 3)
    normal: np.ndarray  # (c, 3)
    point_jacobian: np.ndarray | None = None  # (c, 3, 3), None: zeros
    normal_jacobian: np.ndarray | None = None
    velocity: np.ndarray | None = None  # (c, 3) [m/s] the body's surface at the plane point, None: at rest
    velocity_jacobian: np.ndarray | None = None  # (c, 3, 3) how it moves with the queried point

    @staticmethod
    def empty() -> ContactPlanes:
        return ContactPlanes(np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)))

    def jacobians(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(point_jacobian, normal_jacobian, velocity_jacobian), zeros where not given."""
        return tuple(
            np.zeros((len(self.index), 3, 3)) if a is None else np.asarray(a, dtype=np.float64)
            for a in (self.point_jacobian, self.normal_jacobian, self.velocity_jacobian)
        )

    def velocities(self) -> np.ndarray:
        """(c, 3) [m/s] the surface velocities, zeros where not given."""
        return np.zeros((len(self.index), 3)) if self.velocity is None else np.asarray(self.velocity, dtype=np.float64)


@dataclass
class ContactSet:
    """The contacts of one step: point i lies on face ``face[i]`` with weights ``weight[i]`` (3,)."""

    face: np.ndarray  # (c,) int
    weight: np.ndarray  # (c, 3)
    point: np.ndarray  # (c, 3) [m] plane point on the rigid surface
    normal: np.ndarray  # (c, 3) unit, towards the cloth
    stiffness: np.ndarray  # (c,) [N/m]
    body: np.ndarray  # (c,) int, the rigid body of each contact
    start: np.ndarray  # (c, 3) [m] the contact points at the step's start
    normal_force: np.ndarray  # (c,) [N] lagged, for friction
    sources: dict[str, slice]  # the rows of each source's planes
    point_jacobian: np.ndarray  # (c, 3, 3) d(plane point)/d(start)
    normal_jacobian: np.ndarray  # (c, 3, 3) d(normal)/d(start)
    velocity_jacobian: np.ndarray  # (c, 3, 3) d(surface velocity)/d(start)
    surface_velocity: np.ndarray  # (c, 3) [m/s] the body's surface under each point (friction is relative to it)


class RigidContact:
    """Penalty contact of a cloth's vertices and face centroids with given planes; ``thickness`` r [m]."""

    def __init__(
        self,
        faces: np.ndarray,
        masses: np.ndarray,
        frame_dt: float,
        thickness: float,
        friction: float = 0.0,
        kappa: float = 100.0,
        slip_speed: float = 1e-3,
    ):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.thickness = float(thickness)
        self.friction = float(friction)
        self.eps = slip_speed * frame_dt  # [m] slip below which friction acts as a spring
        self.frame_dt = float(frame_dt)
        V = len(masses)
        # each vertex as a point of one face containing it: (face, slot of the vertex in it)
        owner = np.full(V, -1)
        slot = np.zeros(V, dtype=np.int64)
        for k in range(3):
            fresh = owner[self.faces[:, k]] < 0
            owner[self.faces[fresh, k]] = np.flatnonzero(fresh)
            slot[self.faces[fresh, k]] = k
        self.vertex_face = owner
        self.vertex_weight = np.eye(3)[slot]
        inv_mass = 1.0 / np.asarray(masses, dtype=np.float64)
        face_mass = 1.0 / (inv_mass[self.faces] / 9.0).sum(axis=1)  # weights 1/3 each
        self.point_stiffness = kappa * np.concatenate([masses, face_mass]) / frame_dt**2  # [N/m]

    def points(self, x: np.ndarray) -> np.ndarray:
        """(V + F, 3) [m]: the vertices, then the face centroids."""
        return np.concatenate([x, x.take(self.faces, axis=0).mean(axis=1)])  # take: x[faces] is slower

    def prepare(self, x_n: np.ndarray, planes: dict[str, ContactPlanes]) -> ContactSet:
        """The contacts of a step starting at positions x_n (V, 3) with each source's planes."""
        sources, start = {}, 0
        for name, p in planes.items():
            sources[name] = slice(start, start + len(p.index))
            start += len(p.index)
        idx = np.concatenate([np.asarray(p.index, dtype=np.int64) for p in planes.values()] or [np.zeros(0, int)])
        V = len(x_n)
        is_vertex = idx < V
        face = np.where(is_vertex, self.vertex_face[np.minimum(idx, V - 1)], idx - V)
        weight = np.where(is_vertex[:, None], self.vertex_weight[np.minimum(idx, V - 1)], 1.0 / 3.0)

        def rows(key: str, shape: tuple, dtype=np.float64) -> np.ndarray:
            parts = [np.asarray(getattr(p, key), dtype=dtype).reshape(-1, *shape) for p in planes.values()]
            return np.concatenate(parts) if parts else np.zeros((0, *shape), dtype=dtype)

        jacobians = [p.jacobians() for p in planes.values()] or [(np.zeros((0, 3, 3)),) * 3]
        c = ContactSet(
            face,
            weight.reshape(-1, 3),
            rows("point", (3,)),
            rows("normal", (3,)),
            self.point_stiffness[idx],
            rows("body", (), np.int64),
            np.zeros((len(idx), 3)),
            np.zeros(len(idx)),
            sources,
            *(np.concatenate(parts) for parts in zip(*jacobians)),
            np.concatenate([p.velocities() for p in planes.values()] or [np.zeros((0, 3))]),
        )
        c.start = self.contact_points(x_n, c)
        c.normal_force = c.stiffness * self.gaps(x_n, c)
        return c

    def spread(self, c: ContactSet, per_point: np.ndarray, n_vertices: int) -> np.ndarray:
        """(V, 3): per-point vectors (c, 3) spread onto the vertices with the points' weights (the
        adjoint of ``contact_points``)."""
        out = np.zeros((n_vertices, 3))
        np.add.at(out, self.faces[c.face], c.weight[:, :, None] * per_point[:, None, :])
        return out

    def gathered(self, c: ContactSet, per_vertex: np.ndarray) -> np.ndarray:
        """(c, 3): per-vertex vectors (V, 3) combined at each point with its weights."""
        return np.einsum("cj,cjk->ck", c.weight, per_vertex[self.faces[c.face]])

    def contact_points(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c, 3) [m] the contact points at positions x (V, 3)."""
        return np.einsum("cj,cjk->ck", c.weight, x[self.faces[c.face]])

    def gaps(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c,) [m] how far each point is inside its plane's band: max(0, r - n . (x_point - p))."""
        pts = self.contact_points(x, c)
        return np.maximum(0.0, self.thickness - np.einsum("ck,ck->c", c.normal, pts - c.point))

    def _moved(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c, 3) [m] each point's motion over the step relative to the body's surface under it."""
        return self.contact_points(x, c) - c.start - self.frame_dt * c.surface_velocity

    def _slip(self, x: np.ndarray, c: ContactSet) -> tuple[np.ndarray, np.ndarray]:
        """Tangential slips u (c, 3) [m] over the step, relative to the body, and their lengths y (c,)."""
        d = self._moved(x, c)
        u = d - np.einsum("ck,ck->c", d, c.normal)[:, None] * c.normal
        return u, np.linalg.norm(u, axis=1)

    def _f0(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The mollified slip norm f0 and its first two derivatives at y >= 0."""
        e = self.eps
        small = y < e
        f = np.where(small, y**2 / e - y**3 / (3 * e**2) + e / 3, y)
        df = np.where(small, 2 * y / e - y**2 / e**2, 1.0)
        d2f = np.where(small, 2 / e - 2 * y / e**2, 0.0)
        return f, df, d2f

    def energy(self, x: np.ndarray, c: ContactSet) -> float:
        penalty = 0.5 * float(np.sum(c.stiffness * self.gaps(x, c) ** 2))
        if self.friction == 0:
            return penalty
        return penalty + self.friction * float(np.sum(c.normal_force * self._f0(self._slip(x, c)[1])[0]))

    def forces(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c, 3) [N] the contact force on each point: the penalty along its normal plus friction."""
        f = (c.stiffness * self.gaps(x, c))[:, None] * c.normal
        if self.friction:
            f -= (self.friction * c.normal_force)[:, None] * self._friction_terms(x, c)[2]
        return f

    def gradient(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(V, 3) [N] grad E_c: minus each point's force spread with its weights."""
        return -self.spread(c, self.forces(x, c), len(x))

    def _friction_terms(self, x: np.ndarray, c: ContactSet, majorize: bool = False):
        """Slip u (c, 3), T = I - n n^T, the friction direction phi = f0'(y) u / y (friction force
        -mu lambda phi, y = |u|) and M = dphi/du (c, 3, 3); with ``majorize`` M = f0'(y)/y I, the
        curvature of the quadratic that bounds f0 from above at the current slip (``point_hessians``)."""
        u, y = self._slip(x, c)
        _, df, d2f = self._f0(y)
        safe = np.maximum(y, 1e-300)
        df_over_y = np.where(y < self.eps, 2 / self.eps - y / self.eps**2, df / safe)
        T = np.eye(3)[None] - np.einsum("ci,ck->cik", c.normal, c.normal)
        M = df_over_y[:, None, None] * np.eye(3)[None]
        if not majorize:  # d/du (df/y u) = df/y I + (d2f - df/y) t t^T; at y -> 0 both terms tend to (2/eps) I
            t = u / safe[:, None]
            M = M + (d2f - df_over_y)[:, None, None] * np.einsum("ci,ck->cik", t, t)
        return u, T, df_over_y[:, None] * u, M

    def point_hessians(self, x: np.ndarray, c: ContactSet, majorize: bool = False) -> np.ndarray:
        """(c, 3, 3) minus the derivative of each point's force with respect to its position; with
        ``majorize`` the friction's part is mu lambda f0'(y)/y T instead (the curvature of the quadratic
        that bounds f0 from above at the current slip, in every tangent direction): a Newton step with it
        cannot overshoot a sticking point past its stick (the exact Hessian has no curvature along a
        slip longer than eps, and its steps fly past and back)."""
        active = (self.gaps(x, c) > 0).astype(np.float64)
        K = np.einsum("c,ci,ck->cik", c.stiffness * active, c.normal, c.normal)
        if self.friction:
            _, T, _, M = self._friction_terms(x, c, majorize)
            K += (self.friction * c.normal_force)[:, None, None] * (M @ T)
        return K

    def face_hessians(self, x: np.ndarray, c: ContactSet, n_faces: int, majorize: bool = False) -> np.ndarray:
        """(F, 9, 9) the Hessian of E_c as blocks on each face's dofs: w_j w_l K_i for each point."""
        K = self.point_hessians(x, c, majorize)
        ww = np.einsum("cj,cl->cjl", c.weight, c.weight)  # (c, 3, 3)
        blocks = np.einsum("cjl,cik->cjilk", ww, K).reshape(-1, 9, 9)
        out = np.zeros((n_faces, 9, 9))
        np.add.at(out, c.face, blocks)
        return out

    def force_vjp(self, x: np.ndarray, c: ContactSet, g: np.ndarray) -> dict[str, np.ndarray]:
        """The adjoint of the points' forces f (c, 3) at positions x: dL/df = ``g`` (c, 3) ->
        dL/d(position y, start s, plane point p, plane normal n, surface velocity v_s), each (c, 3).

        f = k gap n [gap > 0] - mu lambda phi(u), gap = r - n . (y - p), u = T (y - s - h v_s),
        lambda = k max(0, r - n . (s - p)) (the lagged normal force)."""
        gap, stiffness = self.gaps(x, c), c.stiffness
        y_p = self.contact_points(x, c) - c.point
        g_gap = stiffness * (gap > 0) * np.einsum("ck,ck->c", c.normal, g)
        g_y = -g_gap[:, None] * c.normal
        g_p = g_gap[:, None] * c.normal
        g_n = (stiffness * gap)[:, None] * g - g_gap[:, None] * y_p
        g_s, g_v = np.zeros_like(g), np.zeros_like(g)
        if self.friction:
            _, _, phi, M = self._friction_terms(x, c)
            g_u = np.einsum("cik,ck->ci", M, -(self.friction * c.normal_force)[:, None] * g)
            n_dot = np.einsum("ck,ck->c", c.normal, g_u)
            d = self._moved(x, c)
            g_d = g_u - n_dot[:, None] * c.normal  # u = d - n (n . d)
            g_n -= np.einsum("ck,ck->c", c.normal, d)[:, None] * g_u + n_dot[:, None] * d
            g_y += g_d
            g_s -= g_d
            g_v -= self.frame_dt * g_d
            s_p = c.start - c.point
            g_gap0 = stiffness * (c.normal_force > 0) * (-self.friction * np.einsum("ck,ck->c", phi, g))
            g_s -= g_gap0[:, None] * c.normal
            g_p += g_gap0[:, None] * c.normal
            g_n -= g_gap0[:, None] * s_p
        return {"y": g_y, "start": g_s, "point": g_p, "normal": g_n, "velocity": g_v}
