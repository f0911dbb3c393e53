"""Cloth against rigid bodies inside the implicit step: a stiff penalty on per-step contact planes.

At the start of a step, every cloth contact point (each vertex, then each face centroid: a
rod thinner than the mesh's edges still meets the faces) near a rigid body gets a plane
through the body's nearest surface point p with unit normal n towards the cloth (the
planes come from ``planes_fn``; the scene wires python-fcl in, ``cosim.couplers.cloth_rigid``).
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
slip u_i = T_i (x_i - x_i,n), T_i = I - n_i n_i^T,

    D(x) = sum_i mu lambda_i f0(|u_i|),  f0(y) = y^2 / eps - y^3 / (3 eps^2) + eps / 3 (y < eps), y (else),

a smooth stick-slip law: slips below eps = v_eps h (v_eps = 1 mm/s) are resisted elastically,
faster ones by the full mu lambda. A towel hangs on a rod by it (without friction a draped
towel is in neutral balance and slides off on any asymmetry, measured).

The planes and the lagged normal forces are data of the step: the adjoint (exact Hessian of
E + E_c + D at the converged state) is exact for them, but does not follow how they move with
the rigid pose or the cloth's previous positions. The reaction on rigid body b is minus the
contact forces (normal and friction) of its points, applied at the plane points p_i.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


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


class RigidContact:
    """Penalty contact of a cloth's vertices and face centroids with planes from ``planes_fn``.

    ``planes_fn(points (P, 3)) -> planes`` with ``index`` (into the points: vertices first,
    then face centroids), ``body``, ``point`` and ``normal`` arrays; ``thickness`` r [m].
    """

    def __init__(
        self,
        faces: np.ndarray,
        masses: np.ndarray,
        frame_dt: float,
        thickness: float,
        planes_fn: Callable,
        friction: float = 0.0,
        kappa: float = 100.0,
        slip_speed: float = 1e-3,
    ):
        self.faces = np.asarray(faces, dtype=np.int64)
        self.thickness = float(thickness)
        self.planes_fn = planes_fn
        self.friction = float(friction)
        self.eps = slip_speed * frame_dt  # [m] slip below which friction acts as a spring
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
        return np.concatenate([x, x[self.faces].mean(axis=1)])

    def prepare(self, x_n: np.ndarray) -> ContactSet:
        """The contact planes of a step starting at positions x_n (V, 3)."""
        planes = self.planes_fn(self.points(x_n))
        idx = np.asarray(planes.index, dtype=np.int64)
        V = len(x_n)
        is_vertex = idx < V
        face = np.where(is_vertex, self.vertex_face[np.minimum(idx, V - 1)], idx - V)
        weight = np.where(is_vertex[:, None], self.vertex_weight[np.minimum(idx, V - 1)], 1.0 / 3.0)
        c = ContactSet(
            face,
            weight,
            np.asarray(planes.point, dtype=np.float64).reshape(-1, 3),
            np.asarray(planes.normal, dtype=np.float64).reshape(-1, 3),
            self.point_stiffness[idx],
            np.asarray(planes.body, dtype=np.int64),
            np.zeros((len(idx), 3)),
            np.zeros(len(idx)),
        )
        c.start = self.contact_points(x_n, c)
        c.normal_force = c.stiffness * self.gaps(x_n, c)
        return c

    def contact_points(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c, 3) [m] the contact points at positions x (V, 3)."""
        return np.einsum("cj,cjk->ck", c.weight, x[self.faces[c.face]])

    def gaps(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(c,) [m] how far each point is inside its plane's band: max(0, r - n . (x_point - p))."""
        pts = self.contact_points(x, c)
        return np.maximum(0.0, self.thickness - np.einsum("ck,ck->c", c.normal, pts - c.point))

    def _slip(self, x: np.ndarray, c: ContactSet) -> tuple[np.ndarray, np.ndarray]:
        """Tangential slips u (c, 3) [m] since the step's start and their lengths y (c,)."""
        d = self.contact_points(x, c) - c.start
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
            u, y = self._slip(x, c)
            df_over_y = np.where(y < self.eps, 2 / self.eps - y / self.eps**2, 1.0 / np.maximum(y, 1e-300))
            f -= (self.friction * c.normal_force * df_over_y)[:, None] * u
        return f

    def gradient(self, x: np.ndarray, c: ContactSet) -> np.ndarray:
        """(V, 3) [N] grad E_c: minus each point's force spread with its weights."""
        g = np.zeros_like(x)
        f = self.forces(x, c)
        np.add.at(g, self.faces[c.face], -c.weight[:, :, None] * f[:, None, :])
        return g

    def face_hessians(self, x: np.ndarray, c: ContactSet, n_faces: int) -> np.ndarray:
        """(F, 9, 9) the Hessian of E_c as blocks on each face's dofs: k w_j w_l n n^T for active points."""
        active = (self.gaps(x, c) > 0).astype(np.float64)
        K = np.einsum("c,ci,ck->cik", c.stiffness * active, c.normal, c.normal)  # (c, 3, 3) point Hessians
        if self.friction:
            u, y = self._slip(x, c)
            _, df, d2f = self._f0(y)
            small = y < self.eps
            safe = np.maximum(y, 1e-300)
            df_over_y = np.where(small, 2 / self.eps - y / self.eps**2, df / safe)
            t = u / safe[:, None]
            T = np.eye(3)[None] - np.einsum("ci,ck->cik", c.normal, c.normal)
            tt = np.einsum("ci,ck->cik", t, t)
            # d/dx (df/y u) = df/y T + (d2f - df/y) t t^T (T t = t); at y -> 0 both terms tend to (2/eps) T
            K += (self.friction * c.normal_force)[:, None, None] * (
                df_over_y[:, None, None] * T + (d2f - df_over_y)[:, None, None] * tt
            )
        ww = np.einsum("cj,cl->cjl", c.weight, c.weight)  # (c, 3, 3)
        blocks = np.einsum("cjl,cik->cjilk", ww, K).reshape(-1, 9, 9)
        out = np.zeros((n_faces, 9, 9))
        np.add.at(out, c.face, blocks)
        return out

    def wrenches(self, x: np.ndarray, c: ContactSet, origins: np.ndarray) -> np.ndarray:
        """(bodies, 6) [torque about each body origin; force] [N m; N] the cloth exerts on the rigid bodies."""
        on_body = -self.forces(x, c)
        out = np.zeros((len(origins), 6))
        np.add.at(out[:, 3:], c.body, on_body)
        np.add.at(out[:, :3], c.body, np.cross(c.point - origins[c.body], on_body))
        return out
