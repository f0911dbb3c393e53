"""The material that follows rigid bodies: their added mass, and its hand-over (``RigidBoundaries``).

For each body b the forecast model's engagement e_p of each particle p (``ForecastContact.engagement``)
weighs the particle's mass into the rigid-body inertia of the material that follows the body's twist
[omega; v] (about the body's origin, at the frame's end):

    A_b = sum_p m_p e_p J_p^T J_p,   J_p = [-[r_p]x, I]  (3D; 2D: [(-r_y, r_x)^T, I]),  r_p = x_p - pos_b

which is linear in the moments w = sum m_p e_p, c = sum m_p e_p r_p and S = sum m_p e_p r_p r_p^T:
A = [[tr(S) I - S, [c]x], [-[c]x, w I]] (2D: [[tr S, -c_y, c_x], [-c_y, w, 0], [c_x, 0, w]]). The kernel
sums the moments (a small reverse-mode program: Taichi's autodiff of the 6x6 sum took over ten minutes
to compile in 3D), the host assembles A through the fixed linear map ``ASSEMBLY`` and takes its
adjoint through the transpose. The hand-over (``cosim.couplers.handover``) gives each particle
e_p J_p dV_b.
"""

import numpy as np
import taichi as ti

from cosim.couplers.contact_rules import source_offset, surface_offset
from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented


def assembly(dim: int) -> np.ndarray:
    """(k*k, 1 + dim + dim*dim): vec(A) = ASSEMBLY @ [w, c, vec(S)] (module docstring), k = 3 (2D) or 6."""
    k = 3 if dim == 2 else 6
    columns = []
    for i in range(1 + dim + dim * dim):
        m = np.zeros(1 + dim + dim * dim)
        m[i] = 1.0
        w, c, S = m[0], m[1 : 1 + dim], m[1 + dim :].reshape(dim, dim)
        A = np.zeros((k, k))
        if dim == 2:
            A[0, 0] = np.trace(S)
            A[0, 1:] = A[1:, 0] = (-c[1], c[0])
            A[1:, 1:] = w * np.eye(2)
        else:
            cross = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
            A[:3, :3] = np.trace(S) * np.eye(3) - S
            A[:3, 3:], A[3:, :3] = cross, -cross
            A[3:, 3:] = w * np.eye(3)
        columns.append(A.reshape(-1))
    return np.stack(columns, axis=1)


@data_oriented
class RigidEngagement:
    """Added masses and hand-over of ``source``'s n bodies; ``source.engagement`` is the contact model."""

    def __init__(self, source, requires_grad: bool):
        self.source = source
        n, dim = max(source.n, 1), source.dim
        self.k = source.wdim + dim
        self.weight = field_pool.scalar(self, float, shape=(n,), needs_grad=requires_grad)
        self.first = field_pool.vector(self, dim, float, shape=(n,), needs_grad=requires_grad)
        self.second = field_pool.matrix(self, dim, dim, float, shape=(n,), needs_grad=requires_grad)
        self.handover_v = field_pool.vector(self, self.k, float, shape=(n,), needs_grad=requires_grad)
        self.substeps_now = field_pool.scalar(self, ti.i32, shape=())
        self.map = assembly(dim)

    def write(self, states: dict, K: int) -> None:
        """The step's substep count and its "handover" twists (n, k) (absent: zeros)."""
        full = np.zeros((self.handover_v.shape[0], self.k), dtype=self.source.real)
        if states.get("handover") is not None:
            full[: self.source.n] = states["handover"]
        self._write(full, K)

    @ti.kernel
    def _write(self, handover: ti.types.ndarray(), K: ti.i32):
        self.substeps_now[None] = K  # one launch for both: a step of a small scene is a few dozen launches
        for b in range(handover.shape[0]):
            for i in ti.static(range(self.k)):
                self.handover_v[b][i] = handover[b, i]

    def mass(self, src: int, K: int) -> np.ndarray:
        """(n, k, k) A_b of the particles in slot ``src`` against the bodies at substep K - 1."""
        self._moments(src, K - 1, K)
        dim = self.source.dim
        moments = np.zeros((self.weight.shape[0], 1 + dim + dim * dim), dtype=self.source.real)
        self._take_moments(moments)
        n = self.source.n
        return (moments[:n].astype(np.float64) @ self.map.T).reshape(n, self.k, self.k)

    @ti.kernel
    def _take_moments(self, out: ti.types.ndarray()):
        """Copy [w, c, vec(S)] per body into ``out`` and zero them for the next frame (the adjoint of their
        sums needs no primal values)."""
        d = ti.static(self.source.dim)
        for b in range(out.shape[0]):
            out[b, 0] = self.weight[b]
            for i in ti.static(range(d)):
                out[b, 1 + i] = self.first[b][i]
                for j in ti.static(range(d)):
                    out[b, 1 + d + d * i + j] = self.second[b][i, j]
            self.weight[b] = 0.0
            self.first[b] = ti.Vector.zero(float, d)
            self.second[b] = ti.Matrix.zero(float, d, d)

    def seed(self, g_mass: np.ndarray, src: int, K: int) -> None:
        """dL/dA_b (n, k, k) -> the moments' adjoints -> the particles' and the bodies' (after ``zero_grad``)."""
        n, dim = self.source.n, self.source.dim
        g = np.asarray(g_mass, dtype=np.float64).reshape(n, -1) @ self.map
        real = self.source.real
        for fld, values in (
            (self.weight, g[:, 0]),
            (self.first, g[:, 1 : 1 + dim]),
            (self.second, g[:, 1 + dim :].reshape(n, dim, dim)),
        ):
            full = np.zeros(fld.grad.shape + values.shape[1:], dtype=real)
            full[:n] = values
            fld.grad.from_numpy(full)
        self._moments.grad(src, K - 1, K)

    def state_grads(self) -> dict[str, np.ndarray]:
        n = self.source.n
        return {"handover": self.handover_v.grad.to_numpy()[:n].astype(np.float64)}

    def zero_grad(self) -> None:
        for fld in (self.weight, self.first, self.second, self.handover_v):
            fld.grad.fill(0)

    @ti.kernel
    def _moments(self, src: ti.i32, s: ti.i32, K: ti.i32):
        """w, c, S per body (module docstring) of the particles in slot ``src``, bodies at substep s."""
        b_src, contact = self.source, self.source.engagement
        e = contact.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            x = e.x[src, p]
            offset = surface_offset(e, ti.static(source_offset(b_src, contact.offset)), p)
            for b in ti.static(range(b_src.n)):
                share = contact.engagement(b_src, b_src.distance(s, b, x, p) - offset, K, p)
                if share > 0:
                    w = e.mass_of(p) * share
                    r = x - b_src.pos[s, b]
                    self.weight[b] += w
                    self.first[b] += w * r
                    self.second[b] += w * r.outer_product(r)

    @ti.func
    def handover(self, s, x, p):
        """[m/s] sum_b e_b (dv_b + dw_b x r): the velocity change particle p at x gets, e_b its engagement."""
        b_src, contact = self.source, self.source.engagement
        e = contact.engine
        dv = ti.Vector.zero(float, b_src.dim)
        offset = surface_offset(e, ti.static(source_offset(b_src, contact.offset)), p)
        for b in ti.static(range(b_src.n)):
            share = contact.engagement(b_src, b_src.distance(s, b, x, p) - offset, self.substeps_now[None], p)
            if share > 0:
                dv += share * self.twist_velocity(self.handover_v[b], x - b_src.pos[s, b])
        return dv

    @ti.func
    def twist_velocity(self, twist, r):
        """v + omega x r of a twist [omega; v] (2D: [omega_z, vx, vy]) at offset r [m]."""
        omega = ti.Vector([twist[i] for i in ti.static(range(self.source.wdim))])
        lin = ti.Vector([twist[self.source.wdim + i] for i in ti.static(range(self.source.dim))])
        return lin + self.source.spin(omega, r)
