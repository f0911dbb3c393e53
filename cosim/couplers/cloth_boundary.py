"""A cloth as an MPM boundary source (``cosim.couplers.boundary``): unsigned distance plus traced sign.

One body (n = 1) per cloth. The cloth is frozen during the MPM substeps of a macro
step, so everything per vertex is per macro step, not per substep: positions
``verts`` (V, 3) [m], velocities ``vel`` (V, 3) [m/s] and the reaction ``impulse``
(V, 3) [N s], summed over the macro step (minus the momentum the contact gave the
material). All three carry adjoints with gradients.

What a contact model sees at a point x:

- particle p (p >= 0; also its forecast look-ahead point x + dt v): its contact frame
  for the substep, blended at its traced position x_p (``_blend``, right after the
  trace) and used to first order about it: distance d_p + n_p . (x - x_p), normal n_p.
  Per candidate face k (the traced face and the faces within ``CUTOFF`` tau of the
  nearest distance, ``PenetrationTracer``): the signed distance d_k, positive on p's
  legal side (in a face's interior the plane distance, smooth through the sheet; on
  an edge or corner side(x) |x - c_k| with side(x) from the closest-point pseudo-normal,
  p's stored side on the open boundary), the normal n_k towards the legal side and the
  closest point's barycentrics. The frame is their softmin blend, weights
  exp(-(|d_k| - |d_0|) / tau) normalised, tau = ``BLEND`` bands: d_p, n_p (renormalised)
  and the vertex weights are weighted means. Why: the nearest face of a point on the
  concave side of a bent sheet jumps between faces whose closest points and normals
  differ, and with one face the contact frame jumped with it: finite differences of a
  loss through contact did not converge (measured, towel_squash). The blend changes
  continuously, a face entering or leaving the candidates weighs at most e^-30, and the
  distance exceeds the exact one by at most about tau (3e-5 m at the default band).
- grid node (p = -1; the grid model): the node's nearest face from a query at
  ``write`` (nodes are fixed and the cloth frozen), two-sided: distance |x - c| and
  the normal from the closest point towards the node, so approaching velocity is
  removed on either side. (A node's nearest face can still switch between steps.)
- nothing within the band: distance ``FAR`` [m], no reaction.

The contact velocity is the blend of the candidate faces' vertex velocities with the
frame's vertex weights, and the reaction -dp is split over the same vertices with the
same weights (which sum to one), so momentum balances between particles and cloth to
round-off.

Boundary states (``write``): {"x": (V, 3) [m], "v": (V, 3) [m/s], "tracking": {face,
side, inside} (N,) int or None (fresh)}; reactions (``reactions(K)``): {"impulse":
(V, 3) [N s] over the macro step, "tracking": the state after the step (not
differentiable)}. The tracking state at the start of a step is an input, so the
MPM's vjp, which writes the recorded states again and recomputes the substeps,
replays the tracing bit for bit.
"""

import numpy as np
import taichi as ti

from cosim.couplers.boundary import NODE, at_node
from cosim.couplers.cloth_mesh_query import INTERIOR, MeshQuery, closest_point_on_triangle
from cosim.couplers.cloth_topology import build_topology
from cosim.couplers.cloth_tracing import CANDIDATES, ERRORS, TRACKING_KEYS, PenetrationTracer
from cosim.engines import field_pool
from cosim.engines.contract import ContactTraits
from cosim.engines.data_oriented import data_oriented

FAR = 1e30  # [m] the distance reported where no face is within the band
TINY = 1e-30  # [m^2] keeps |x - c| differentiable at x = c
BLEND = 1e-3  # blend width tau of the candidate faces, in bands
CUTOFF = 30.0  # candidates lie within CUTOFF tau of the nearest: a face entering there weighs e^-30


@data_oriented
class ClothBoundary:
    """The cloth ``faces`` (F, 3) with rest vertices ``verts`` (V, 3) [m] as a boundary of ``engine`` (3D).

    ``band`` [m] (default one cell): faces are found within it; it must be at least the
    contact model's threshold (forecast) or band (grid), and it is the largest distance
    a particle or the sheet may move relative to each other between two traces
    (``max_step_travel``). ``radius`` [m] (default 4 band): the geodesic radius of each
    face's neighbourhood; consecutive closest points of a particle moving less than the
    band lie within 3 bands of each other. ``trace=False`` turns tracing off (every
    particle is legal on its current side; for comparisons only).
    """

    n = 1
    capabilities = frozenset({"substep_hooks", "node_queries", "added_mass"})

    def __init__(
        self,
        engine,
        verts: np.ndarray,
        faces: np.ndarray,
        band: float | None = None,
        radius: float | None = None,
        requires_grad: bool | None = None,
        trace: bool = True,
        max_neighbours: int = 4096,
    ):
        if engine.dim != 3:
            raise ValueError("a cloth boundary needs a 3D MPM engine")
        self.engine = engine
        self.band = float(engine.dx if band is None else band)
        # a light sheet without volume, coupled explicitly (``ContactTraits`` says why each); the grid model
        # constrains nodes within the band on either side
        self.contact_traits = ContactTraits(
            offset=False, blend_all=True, liquid_support=False, forecast_alpha=0.8, grid_band=self.band
        )
        self.radius = float(4.0 * self.band if radius is None else radius)
        grad = engine.cfg.requires_grad if requires_grad is None else bool(requires_grad)
        self.topology = build_topology(verts, faces, self.radius, max_neighbours)
        self.query = MeshQuery(self.topology.faces, len(verts), self.band, requires_grad=grad)
        self.slots = engine.cfg.grad_substeps if engine.cfg.requires_grad else 2
        self.tracer = PenetrationTracer(engine, self.query, self.topology, self.slots, enabled=trace)
        self.tracer.neighbour_radius = self.radius
        V = len(verts)
        self.vel = field_pool.vector(self, 3, float, shape=V, needs_grad=grad)
        self.impulse = field_pool.vector(self, 3, float, shape=V, needs_grad=grad)
        self.contact_mass = field_pool.scalar(self, float, shape=V, needs_grad=grad)
        self.handover_v = field_pool.vector(self, 3, float, shape=V, needs_grad=grad)  # ``handover``
        self.substeps_now = field_pool.scalar(self, ti.i32, shape=())
        self.engagement = None  # the contact model that says how much material follows the sheet (forecast)
        self._substeps = 1  # K of the step written last
        self.node_face = field_pool.scalar(self, ti.i32, shape=engine.nodes)
        # whether a contact model asks about grid nodes (p = -1; the grid model sets it): only then is each
        # node's nearest face queried in ``write`` (a cost the particle and forecast models need not pay)
        self.queries_nodes = False
        # each traced particle's blended contact frame per substep slot (``_blend``)
        self.blend_width = BLEND * self.band
        self.tracer.cutoff = CUTOFF * self.blend_width
        S, N = self.slots, engine.capacity
        self.frame_d = field_pool.scalar(self, float, shape=(S, N), needs_grad=grad)
        self.frame_n = field_pool.vector(self, 3, float, shape=(S, N), needs_grad=grad)
        self.frame_x = field_pool.vector(self, 3, float, shape=(S, N), needs_grad=grad)
        self.frame_w = field_pool.vector(self, 3, float, shape=(S, N, CANDIDATES), needs_grad=grad)
        self.real = self.query.real

    def set_tracing(self, enabled: bool) -> None:
        """Turn tracing on or off (off: every particle is legal on its current side; for comparisons)."""
        self.tracer.enabled[None] = int(enabled)

    def max_step_travel(self) -> float:
        """[m] the bound on relative particle-cloth motion between traces: |v| dt of every particle near the
        cloth, and the cloth's vertex displacement per macro step, must stay below it."""
        return self.band

    @property
    def max_neighbours(self) -> int:
        """Length of the padded neighbourhood lists (the largest neighbourhood, in faces)."""
        return self.topology.max_neighbours

    # ------------------------------------------------------------------ geometry
    @ti.func
    def _face_geometry(self, f, x, legal, side: ti.template()):
        """Signed distance [m] of x to face f, the unit normal towards the legal side and the closest
        point's barycentrics. ``legal``: +1 / -1, the legal side in f's winding; ``side`` the stored
        side in f's winding (used on the open boundary, never 0), or ``NODE`` for a grid node, two-sided (a
        Python int: the node's path and a particle's compile apart, as with ``at_node``)."""
        a, b, c = self.query.corners(f)
        point, w, region = closest_point_on_triangle(x, a, b, c)
        diff = x - point
        d, n = FAR, ti.Vector([0.0, 1.0, 0.0])
        if region == INTERIOR:
            nf = (b - a).cross(c - a)
            nf = nf / ti.sqrt(nf.norm_sqr())
            h = nf.dot(diff)
            if ti.static(at_node(side)):  # two-sided: towards the node
                legal = ti.select(h >= 0, 1, -1)
            d, n = legal * h, legal * nf
        else:
            dist = ti.sqrt(diff.norm_sqr() + TINY)
            sign = 1
            if ti.static(not at_node(side)):
                geo = self.tracer.side_of(f, region, diff)
                if geo == 0 or self.tracer.on_open_boundary(f, region):
                    geo = side
                sign = legal * geo
            d, n = sign * dist, (sign / dist) * diff
        return d, n, w

    @ti.kernel
    def _blend(self, src: ti.i32, slot: ti.i32):
        """Each traced particle's contact frame for this substep (see the module docstring)."""
        t = self.tracer
        ti.loop_config(serialize=self.engine.serial_particle_loops)
        for p in range(self.engine.count[None]):
            f = t.face_s[slot, p]
            if f >= 0:
                x = self.engine.x[src, p]
                side = t.side_s[slot, p]
                legal = side * (1 - 2 * t.inside_s[slot, p])
                d0, n0, w0 = self._face_geometry(f, x, legal, side)
                total, d, n = 1.0, d0, n0
                shares = ti.Vector([1.0] + [0.0] * (CANDIDATES - 1))
                bary = ti.Matrix.zero(float, CANDIDATES, 3)
                for i in ti.static(range(3)):
                    bary[0, i] = w0[i]
                for k in ti.static(range(1, CANDIDATES)):
                    g, flag = t.candidate_s[slot, p, k], t.candidate_flag_s[slot, p, k]
                    if g >= 0:
                        dk, nk, wk = self._face_geometry(g, x, legal * flag, side * flag)
                        share = ti.exp((ti.abs(d0) - ti.abs(dk)) / self.blend_width)
                        shares[k] = share
                        for i in ti.static(range(3)):
                            bary[k, i] = wk[i]
                        total += share
                        d += share * dk
                        n += share * nk
                self.frame_d[slot, p] = d / total
                self.frame_n[slot, p] = n / ti.sqrt(n.norm_sqr() + TINY)
                self.frame_x[slot, p] = x
                for k in ti.static(range(CANDIDATES)):
                    self.frame_w[slot, p, k] = ti.Vector([bary[k, 0], bary[k, 1], bary[k, 2]]) * (shares[k] / total)

    def before_substep_grad(self, src: int, s: int) -> None:
        """Adjoint of ``before_substep`` (the blend), after the adjoint of substep s."""
        self._blend.grad(src, s % self.slots)

    # ------------------------------------------------------------------ what a contact model asks
    # p is a template (``cosim.couplers.boundary.at_node``): a grid node's path and a particle's compile apart
    @ti.func
    def _geometry(self, s, x, p: ti.template()):
        """(face or -1, signed distance [m], unit normal towards the legal side) at x: a particle's
        blended frame (first order about the particle's traced position, exact there), or a grid
        node's nearest face, two-sided."""
        if ti.static(at_node(p)):  # (a conditional expression would build both calls)
            return self._node_geometry(x)
        else:
            return self._particle_geometry(s, x, p)

    @ti.func
    def _particle_geometry(self, s, x, p):
        k = s % self.slots
        f, d, n = self.tracer.face_s[k, p], FAR, ti.Vector([0.0, 1.0, 0.0])
        if f >= 0:
            n = self.frame_n[k, p]
            d = self.frame_d[k, p] + n.dot(x - self.frame_x[k, p])
        return f, d, n

    @ti.func
    def _node_geometry(self, x):
        f, d, n = self._node_face(x), FAR, ti.Vector([0.0, 1.0, 0.0])
        if f >= 0:
            d, n, _w = self._face_geometry(f, x, 1, NODE)
        return f, d, n

    @ti.func
    def distance(self, s, b: ti.template(), x, p: ti.template()):
        _f, d, _n = self._geometry(s, x, p)
        return d

    @ti.func
    def distance_normal(self, s, b: ti.template(), x, p: ti.template()):
        _f, d, n = self._geometry(s, x, p)
        return d, n

    @ti.func
    def _vertex_weights(self, s, x, p: ti.template()):
        """(faces (CANDIDATES,) or -1, weights (CANDIDATES, 3)) spreading a contact at x over cloth vertices:
        a particle's blended frame, or a grid node's nearest face (row 0). The weights sum to one."""
        if ti.static(at_node(p)):
            return self._node_weights(x)
        else:
            return self._particle_weights(s, p)

    @ti.func
    def _particle_weights(self, s, p):
        faces = ti.Vector([-1] * CANDIDATES)
        weights = ti.Matrix.zero(float, CANDIDATES, 3)
        k = s % self.slots
        for j in ti.static(range(CANDIDATES)):
            faces[j] = self.tracer.candidate_s[k, p, j]
            w = self.frame_w[k, p, j]
            for i in ti.static(range(3)):
                weights[j, i] = w[i]
        return faces, weights

    @ti.func
    def _node_weights(self, x):
        faces = ti.Vector([-1] * CANDIDATES)
        weights = ti.Matrix.zero(float, CANDIDATES, 3)
        f = self._node_face(x)
        if f >= 0:
            _d, _n, w = self._face_geometry(f, x, 1, NODE)
            faces[0] = f
            for i in ti.static(range(3)):
                weights[0, i] = w[i]
        return faces, weights

    @ti.func
    def contact_velocity(self, s, b: ti.template(), x, p: ti.template()):
        faces, weights = self._vertex_weights(s, x, p)
        v = ti.Vector.zero(float, 3)
        for j in ti.static(range(CANDIDATES)):
            if faces[j] >= 0:
                tri = self.query.faces[faces[j]]
                for i in ti.static(range(3)):
                    v += weights[j, i] * self.vel[tri[i]]
        return v

    @ti.func
    def add_reaction(self, s, b: ti.template(), x, dp, p: ti.template()):
        faces, weights = self._vertex_weights(s, x, p)
        for j in ti.static(range(CANDIDATES)):
            if faces[j] >= 0:
                tri = self.query.faces[faces[j]]
                for i in ti.static(range(3)):
                    self.impulse[tri[i]] -= weights[j, i] * dp

    @ti.func
    def _node_face(self, x):
        """The nearest face of the grid node at x (queried at ``write``), or -1."""
        return self.node_face[ti.cast(x * self.engine.inv_dx + 0.5, ti.i32)]

    # ------------------------------------------------------------------ the MPM engine's side
    def write(self, states: dict) -> None:
        """The cloth for this macro step: x (V, 3) [m], v (V, 3) [m/s], handover (V, 3) [m/s] or None, tracking
        (or None); clears the reactions, rebuilds the face hash and queries the grid nodes. One launch takes it
        all (``_write_step``). The mesh motion is traced before the first substep (``before_substep(src, 0)``),
        when the particles' slot is known."""
        x = np.asarray(states["x"], dtype=np.float64)
        V = len(x)
        hashed, inv_h = self.query.packed_hash(x)
        rows = np.zeros((3 * V + 2, 3), dtype=self.real)  # positions, velocities, handover, the mesh's box
        rows[:V], rows[V : 2 * V] = x, states["v"]
        if states.get("handover") is not None:
            rows[2 * V : 3 * V] = states["handover"]
        rows[3 * V], rows[3 * V + 1] = x.min(axis=0) - self.query.band, x.max(axis=0) + self.query.band
        packed = np.concatenate([hashed, self.tracer.packed_tracking(states.get("tracking")).reshape(-1)])
        self._substeps = int(states.get("substeps", 1))
        self._write_step(rows, packed, inv_h, self._substeps)
        if self.queries_nodes:
            self._query_nodes()

    @ti.kernel
    def _write_step(self, rows: ti.types.ndarray(), packed: ti.types.ndarray(), inv_h: float, substeps: ti.i32):
        """``write``'s arrays in one launch (on a GPU each is a copy and a wait): ``rows`` (3 V + 2, 3) positions,
        velocities, handover velocities, the grown box; ``packed`` the face hash, the tracking state."""
        self.substeps_now[None] = substeps
        self.query.load(rows, packed, inv_h)
        V = self.query.n_verts
        ti.loop_config(serialize=self.query.serial_copies)
        for v in range(V):
            self.vel[v] = ti.Vector([rows[V + v, k] for k in ti.static(range(3))])
            self.handover_v[v] = ti.Vector([rows[2 * V + v, k] for k in ti.static(range(3))])
            self.impulse[v] = ti.Vector.zero(float, 3)
            self.contact_mass[v] = 0.0
        self.tracer.load(rows, 3 * V, packed, self.query.table + 1 + 8 * self.query.n_faces)

    def before_substep(self, src: int, s: int) -> None:
        """Trace the particles in slot ``src`` for substep s (s = 0: the mesh moved, the particles not),
        then blend their contact frames."""
        self.tracer.trace(src, s, first=s == 0, record=True)
        self._blend(src, s % self.slots)

    @staticmethod
    def work(states: dict, reactions: dict) -> np.ndarray:
        """(1,) [J] Work the cloth did on the material over a macro step: -sum impulse . v over its vertices
        (their velocities are held over the step)."""
        return np.array([-float(np.sum(reactions["impulse"] * np.asarray(states["v"])))])

    def reactions(self, K: int) -> dict:
        """{"impulse": (V, 3) [N s] over the macro step, "tracking": the state after its last substep,
        "mass": (V,) [kg] the material that follows each vertex over the frame (``_contact_mass``; zeros
        unless the contact model says how much: the forecast model)}. Raises ``ClothTracingError`` for what
        the step's traces met, read with the rest in one launch (``_read_step``)."""
        self.tracer.trace(self.engine.slot, K, first=False, record=False)  # the last substep's motion
        if self.engagement is not None:
            self._contact_mass(K - 1, (K - 1) % self.slots, K)
        rows = np.empty((self.query.n_verts, 4), dtype=self.real)
        packed = np.empty(len(ERRORS) + len(TRACKING_KEYS) * self.engine.n_particles, dtype=np.int32)
        self._read_step(rows, packed)
        self.tracer.check(packed[: len(ERRORS)], end=K)
        return {
            "impulse": rows[:, :3].astype(np.float64),
            "tracking": self.tracer.unpacked_tracking(packed[len(ERRORS) :]),
            "mass": rows[:, 3].astype(np.float64),
        }

    @ti.kernel
    def _read_step(self, rows: ti.types.ndarray(), packed: ti.types.ndarray()):
        """``reactions``' arrays in one launch: ``rows`` (V, 4) impulse and added mass, ``packed`` the tracer's
        ``errors`` then the tracking state."""
        for i in ti.static(range(len(ERRORS))):
            packed[i] = self.tracer.errors[i]
        ti.loop_config(serialize=self.query.serial_copies)
        for v in range(self.query.n_verts):
            for k in ti.static(range(3)):
                rows[v, k] = self.impulse[v][k]
            rows[v, 3] = self.contact_mass[v]
        self.tracer.tracking_pass(packed, ti.static(len(ERRORS)), False)

    @ti.kernel
    def _contact_mass(self, s: ti.i32, k: ti.i32, K: ti.i32):
        """Each particle traced to the sheet in the last substep s adds its mass times the share the
        contact model moves with the sheet over the frame (``engagement``) to the vertices of its contact
        frame, with the frame's vertex weights: the added mass A (V,) [kg] of ``cosim.couplers.mpm_cloth``,
        a smooth function of the particles' and the sheet's positions (its adjoint runs in the MPM's vjp)."""
        ti.loop_config(serialize=self.engine.serial_particle_loops)
        for p in range(self.engine.count[None]):  # k = s % slots (a statement outside the loop breaks autodiff)
            if self.tracer.face_s[k, p] >= 0:
                share = self.engagement.engagement(self, self.frame_d[k, p], K, p)
                if share > 0:
                    faces, weights = self._vertex_weights(s, self.frame_x[k, p], p)
                    m = self.engine.mass_of(p) * share
                    for j in ti.static(range(CANDIDATES)):
                        if faces[j] >= 0:
                            tri = self.query.faces[faces[j]]
                            for i in ti.static(range(3)):
                                self.contact_mass[tri[i]] += weights[j, i] * m

    @ti.func
    def handover(self, s, x, p):
        """[m/s] The velocity change particle p gets from the sheet at substep s: its engaged share times the
        vertices' "handover" velocity changes under its contact frame (``cosim.couplers.handover``)."""
        dv = ti.Vector.zero(float, 3)
        k = s % self.slots
        if self.tracer.face_s[k, p] >= 0:
            share = self.engagement.engagement(self, self.frame_d[k, p], self.substeps_now[None], p)
            if share > 0:
                faces, weights = self._vertex_weights(s, self.frame_x[k, p], p)
                for j in ti.static(range(CANDIDATES)):
                    if faces[j] >= 0:
                        tri = self.query.faces[faces[j]]
                        for i in ti.static(range(3)):
                            dv += (share * weights[j, i]) * self.handover_v[tri[i]]
        return dv

    def zero_grad(self) -> None:
        for fld in (self.query.verts, self.vel, self.impulse, self.frame_d, self.frame_n, self.frame_x, self.frame_w):
            fld.grad.fill(0)
        self.contact_mass.grad.fill(0)
        self.handover_v.grad.fill(0)

    def seed_reaction_grads(self, grads: dict[str, np.ndarray]) -> None:
        """dL/d(impulse) (V, 3) and dL/d(mass) (V,), after ``zero_grad`` and before the substeps' adjoints:
        the added mass's adjoint lands on the last substep's contact frames, which that substep's blend
        adjoint carries on to the particles and the sheet."""
        self.impulse.grad.from_numpy(np.asarray(grads["impulse"], dtype=self.real))
        g_mass = grads.get("mass")
        if g_mass is not None and self.engagement is not None and np.any(g_mass):
            self.contact_mass.grad.from_numpy(np.asarray(g_mass, dtype=self.real))
            K = self._substeps
            self._contact_mass.grad(K - 1, (K - 1) % self.slots, K)

    def state_grads(self, K: int) -> dict[str, np.ndarray]:
        """dL/dx, dL/dv, dL/d(handover) (V, 3) of the cloth states written for the step, after a vjp."""
        return {
            "x": self.query.verts.grad.to_numpy().astype(np.float64),
            "v": self.vel.grad.to_numpy().astype(np.float64),
            "handover": self.handover_v.grad.to_numpy().astype(np.float64),
        }

    @ti.kernel
    def _query_nodes(self):
        e = self.engine
        ti.loop_config(serialize=e.serial_grid_loops)
        for I in ti.grouped(ti.ndrange(*e.nodes)):
            f, _d2, _w, _r = self.query.nearest(ti.cast(I, float) * e.dx)
            self.node_face[I] = f
