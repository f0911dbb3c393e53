"""Penetration tracing: which side of a cloth each MPM particle belongs on (SoftMAC, with the fixes below).

A sheet has no inside, so a particle's signed distance needs a remembered state:
per particle a reference face, its side of that face (+1 / -1 in the face's own
winding) and ``inside`` (1 = it is on the wrong side, it crossed the sheet). Each
time particles move (before every MPM substep, the particles of the previous one
having moved) or the mesh moves (the first trace of a macro step: particles as they
ended the last step, the new mesh), a particle within the band finds its nearest face
f'. If f' is the reference face or in its neighbourhood (``cloth_topology``), its side
of f' is compared with the stored side carried to f' by the neighbourhood's
orientation flag; a change flips ``inside``. If f' is not in the neighbourhood the
crossing could not be seen: the run stops (``ClothTracingError``).

Fixes over SoftMAC's tracing:
- the side is taken against the closest-point normal (the face normal in the face's
  interior, the pseudo-normal of the faces around an edge or vertex, each oriented
  like the face through the BFS flags), not against a neighbour's plane;
- a side change seen at the open boundary (closest point on a free edge or its
  vertices) is a particle going around the sheet's edge, not through it: the side
  is updated, ``inside`` is kept;
- a particle that moved at least the band since its last observation while near the
  mesh stops the run: that is the bound under which no crossing goes unseen.

Leaving the band resets the state (face -1, inside 0), as SoftMAC does: outside the
band there is nothing to trace against, and a state kept there would be compared
with a face arbitrarily far away on return. Since a particle moves less than the
band between observations, and the mesh moves less than the band per macro step
(both are the integrator's bound, ``max_step_travel``), a particle entering the band
has not crossed: it is legal where it is.

The per-substep result (face, side, inside) is kept in (slots, N) fields that the
differentiated contact kernels of that substep read (and their adjoints read the
same); these kernels are never differentiated.

Blend candidates: with the face, each traced particle keeps up to ``CANDIDATES`` faces of
its neighbourhood whose distance is within ``cutoff`` of the nearest (the face first,
then the others in hash order, a nearer one replacing the farthest once all places are
taken; a face whose closest point is a vertex already listed as a closest point is left
out: it adds nothing), with each one's winding relative to the face. ``ClothBoundary``
blends their closest points so that a particle's contact frame does not jump when its
nearest face changes (see there).
"""

import numpy as np
import taichi as ti

from cosim.couplers.cloth_mesh_query import CORNER, EDGE, MeshQuery, closest_point_on_triangle
from cosim.couplers.cloth_topology import ClothTopology
from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented
from cosim.errors import SimulationError

TRACKING_KEYS = ("face", "side", "inside")
# the ``errors`` entries: particles lost (a jump out of the neighbourhood) and the lowest of them, particles that moved
# the band or more between traces and the lowest of them, the first substep where each happened
ERRORS = ("lost", "lost_p", "fast", "fast_p", "lost_s", "fast_s")
CANDIDATES = 4  # faces blended per particle (ClothBoundary)


class ClothTracingError(SimulationError):
    """Tracing lost a particle: it crossed or may have crossed the sheet unseen."""


@data_oriented
class PenetrationTracer:
    """Tracing state of ``engine``'s particles against the mesh of ``query`` (see the module docstring)."""

    def __init__(self, engine, query: MeshQuery, topology: ClothTopology, slots: int, enabled: bool = True):
        self.engine = engine
        self.query = query
        self.enabled = field_pool.scalar(self, ti.i32, shape=())  # 0: every particle stays legal (comparisons only)
        self.enabled[None] = int(enabled)
        self.slots = slots
        F, N = query.n_faces, engine.capacity
        S, M = topology.star.shape[2], topology.max_neighbours
        self.S, self.M = S, M
        self.edge_face = _int_field(self, (F, 3), topology.edge_face)
        self.edge_flag = _int_field(self, (F, 3), topology.edge_flag)
        self.vertex_boundary = _int_field(self, (F, 3), topology.vertex_boundary)
        self.star = _int_field(self, (F, 3, S), topology.star)
        self.star_flag = _int_field(self, (F, 3, S), topology.star_flag)
        self.neighbours = _int_field(self, (F, M), topology.neighbours)
        self.neighbour_flag = _int_field(self, (F, M), topology.neighbour_flag)
        # closest-point normals of the current mesh (for sides only: never differentiated)
        self.face_normal = field_pool.vector(self, 3, float, shape=F)
        self.corner_angle = field_pool.scalar(self, float, shape=(F, 3))
        self.edge_normal = field_pool.vector(self, 3, float, shape=(F, 3))
        self.vertex_normal = field_pool.vector(self, 3, float, shape=(F, 3))
        # the state (between observations) and its per-substep copies
        self.face = field_pool.scalar(self, ti.i32, shape=N)
        self.side = field_pool.scalar(self, ti.i32, shape=N)
        self.inside = field_pool.scalar(self, ti.i32, shape=N)
        self.last_x = field_pool.vector(self, 3, float, shape=N)
        self.face_s = field_pool.scalar(self, ti.i32, shape=(slots, N))
        self.side_s = field_pool.scalar(self, ti.i32, shape=(slots, N))
        self.inside_s = field_pool.scalar(self, ti.i32, shape=(slots, N))
        self.cutoff = 0.0  # [m] blend candidates lie within it of the nearest distance (set by the owner)
        self.candidate_s = field_pool.scalar(self, ti.i32, shape=(slots, N, CANDIDATES))  # face ids, -1 unused
        self.candidate_flag_s = field_pool.scalar(
            self, ti.i32, shape=(slots, N, CANDIDATES)
        )  # winding relative to face_s
        self.overflow = field_pool.scalar(
            self, ti.i32, shape=()
        )  # candidates beyond CANDIDATES met so far (diagnostics)
        self.box = field_pool.vector(self, 3, float, shape=2)  # the mesh's bounding box grown by the band
        # what the traces of the macro step so far met (``ERRORS``), read with the step's results (``check``)
        self.errors = field_pool.scalar(self, ti.i32, shape=len(ERRORS))
        self.real = query.real

    # ------------------------------------------------------------ host
    def packed_tracking(self, tracking: dict | None) -> np.ndarray:
        """``tracking`` {face, side, inside} (N,) int as one (N, 3) int32 array (``tracking_pass``); None: fresh
        (no particle near the sheet)."""
        packed = np.zeros((self.engine.n_particles, len(TRACKING_KEYS)), dtype=np.int32)
        if tracking is None:
            packed[:, 0] = -1  # no face
        else:
            for i, key in enumerate(TRACKING_KEYS):
                packed[:, i] = tracking[key]
        return packed

    @staticmethod
    def unpacked_tracking(packed: np.ndarray) -> dict[str, np.ndarray]:
        """{face, side, inside} (N,) of a packed (N * 3,) or (N, 3) tracking state."""
        packed = packed.reshape(-1, len(TRACKING_KEYS))
        return {key: packed[:, i].copy() for i, key in enumerate(TRACKING_KEYS)}

    def set_state(self, tracking: dict | None) -> None:
        """Start from ``tracking`` {face, side, inside} (N,) int, or fresh (no particle near the sheet)."""
        self._tracking_io(self.packed_tracking(tracking).reshape(-1), True)

    def state(self) -> dict[str, np.ndarray]:
        packed = np.empty(self.engine.n_particles * len(TRACKING_KEYS), dtype=np.int32)
        self._tracking_io(packed, False)
        return self.unpacked_tracking(packed)

    @ti.kernel
    def _tracking_io(self, packed: ti.types.ndarray(), write: ti.template()):
        self.tracking_pass(packed, 0, write)

    @ti.func
    def tracking_pass(self, packed: ti.template(), offset, write: ti.template()):
        """The tracking state to (``write``) or from ``packed`` (flat int32, from ``offset``: face, side, inside of
        each particle in turn): the host's copy goes in and out with other arrays in one launch each way."""
        ti.loop_config(serialize=self.engine.serial_particle_loops)
        for p in range(self.engine.count[None]):
            i = offset + 3 * p
            if ti.static(write):
                self.face[p], self.side[p], self.inside[p] = packed[i], packed[i + 1], packed[i + 2]
            else:
                packed[i], packed[i + 1], packed[i + 2] = self.face[p], self.side[p], self.inside[p]

    @ti.func
    def load(self, rows: ti.template(), box_row, packed: ti.template(), offset):
        """A macro step's start, at a kernel's top level after the mesh's positions (``MeshQuery.load``): the
        mesh's box grown by the band from ``rows[box_row]`` and ``rows[box_row + 1]`` (lower and upper corner
        [m]), the tracking state from ``packed`` at ``offset`` (``tracking_pass``), the mesh's normals."""
        for i in ti.static(range(2)):
            self.box[i] = ti.Vector([rows[box_row + i, k] for k in ti.static(range(3))])
        self.tracking_pass(packed, offset, True)
        self._face_normals()
        self._pseudo_normals()

    def trace(self, src: int, s: int, first: bool, record: bool) -> None:
        """Trace the particles in slot ``src`` at substep s (s = K: the end of a macro step of K); ``first``: the
        first observation of a macro step (only the mesh moved; starts the step's ``errors``); ``record``: keep
        the result for substep s. What went wrong is kept for ``check`` at the end of the macro step: no read
        back between substeps (on a GPU a wait for the device)."""
        self._trace(src, s, s % self.slots, int(first), int(record))

    def check(self, errors: np.ndarray | None = None, end: int | None = None) -> None:
        """Raise ``ClothTracingError`` if a trace of the macro step so far lost a particle: ``errors`` the
        ``errors`` field as read with the step's results (read here when None), ``end`` the step's substeps K
        (a trace at K is the end of the step)."""
        found = dict(zip(ERRORS, (int(v) for v in (self.errors.to_numpy() if errors is None else errors))))

        def where(s: int) -> str:
            return "the end of the macro step" if s == end else f"substep {s}"

        if found["fast"]:
            raise ClothTracingError(
                f"cloth tracing: particle {found['fast_p']} (and {found['fast'] - 1} more) moved at least the tracing "
                f"band {self.query.band:.3g} m near the cloth before {where(found['fast_s'])}; a crossing could go "
                "unseen: use smaller substeps (|v| dt < band, see max_step_travel) or a larger band"
            )
        if found["lost"]:
            p = found["lost_p"]
            x = self.engine.x.to_numpy()[self.engine.slot, p]
            raise ClothTracingError(
                f"cloth tracing: particle {p} (and {found['lost'] - 1} more; now at {np.round(x, 4).tolist()}) was "
                f"nearest to a face outside the neighbourhood of its last face {self.face[p]} at "
                f"{where(found['lost_s'])}: it moved across the sheet farther than tracing can follow; use smaller "
                f"substeps or a larger search radius (now {self.neighbour_radius:.3g} m)"
            )

    neighbour_radius = 0.0  # [m] set by the owner, for messages

    # ------------------------------------------------------------ normals of the current mesh
    @ti.func
    def _face_normals(self):
        for f in range(self.query.n_faces):
            a, b, c = self.query.corners(f)
            n = (b - a).cross(c - a)
            self.face_normal[f] = n / ti.sqrt(n.norm_sqr() + 1e-300)
            corners = [a, b, c]
            for k in ti.static(range(3)):
                u, w = corners[(k + 1) % 3] - corners[k], corners[(k + 2) % 3] - corners[k]
                self.corner_angle[f, k] = ti.atan2(u.cross(w).norm(), u.dot(w))

    @ti.func
    def _pseudo_normals(self):
        for f, k in ti.ndrange(self.query.n_faces, 3):
            n = self.face_normal[f]
            g = self.edge_face[f, k]
            if g >= 0:
                n += self.edge_flag[f, k] * self.face_normal[g]
            self.edge_normal[f, k] = n
            v = self.query.faces[f][k]
            m = ti.Vector.zero(float, 3)
            for j in range(self.S):
                h = self.star[f, k, j]
                if h >= 0:
                    tri = self.query.faces[h]
                    corner = 0
                    for i in ti.static(range(3)):
                        if tri[i] == v:
                            corner = i
                    m += self.star_flag[f, k, j] * self.corner_angle[h, corner] * self.face_normal[h]
            self.vertex_normal[f, k] = m

    # ------------------------------------------------------------ what a side is
    @ti.func
    def side_of(self, f, region, diff):
        """+1 / -1: the side of face f (in f's winding) of a point at diff = x - closest point, against
        the closest-point normal of ``region``; 0 when the point is on it."""
        n = self.face_normal[f]
        if region >= EDGE:
            n = self.edge_normal[f, region - EDGE]
        elif region >= CORNER:
            n = self.vertex_normal[f, region - CORNER]
        h = n.dot(diff)
        out = 0
        if h > 0:
            out = 1
        elif h < 0:
            out = -1
        return out

    @ti.func
    def on_open_boundary(self, f, region):
        """1 when the closest point is on a free edge of the sheet or one of its vertices."""
        out = 0
        if region >= EDGE:
            out = ti.cast(self.edge_face[f, region - EDGE] < 0, ti.i32)
        elif region >= CORNER:
            out = self.vertex_boundary[f, region - CORNER]
        return out

    @ti.func
    def relative_flag(self, ref, f):
        """Winding of face f relative to face ref (+1 / -1), 0 when f is outside ref's neighbourhood."""
        out = 0
        for j in range(self.M):
            g = self.neighbours[ref, j]
            if g == f:
                out = self.neighbour_flag[ref, j]
                break
            if g < 0:
                break
        return out

    # ------------------------------------------------------------ the update
    @ti.kernel
    def _trace(self, src: ti.i32, s: ti.i32, slot: ti.i32, first: ti.i32, record: ti.i32):
        e = self.engine
        band = self.query.band
        if first:  # no error yet in this macro step (counts 0, first particles and substeps past the last)
            for i in ti.static(range(2)):
                self.errors[2 * i], self.errors[2 * i + 1], self.errors[4 + i] = 0, e.count[None], 1 << 30
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            x = e.x[src, p]
            if not first:
                x0 = self.last_x[p]
                near = 1
                for i in ti.static(range(3)):
                    if ti.max(x[i], x0[i]) < self.box[0][i] or ti.min(x[i], x0[i]) > self.box[1][i]:
                        near = 0
                if near and (x - x0).norm_sqr() >= band * band:
                    ti.atomic_add(self.errors[2], 1)
                    ti.atomic_min(self.errors[3], p)
                    ti.atomic_min(self.errors[5], s)
            self.last_x[p] = x
            f, d2, bary, region = self.query.nearest(x)
            ref, side, inside = self.face[p], 0, 0
            face = f
            if f >= 0:
                a, b, c = self.query.corners(f)
                side = self.side_of(f, region, x - (bary[0] * a + bary[1] * b + bary[2] * c))
                if ref < 0:  # entering the band: legal where it is
                    if side == 0:
                        side = 1
                else:
                    flag = self.relative_flag(ref, f)
                    if flag == 0:  # a jump tracing cannot follow: keep the state, report
                        ti.atomic_add(self.errors[0], 1)
                        ti.atomic_min(self.errors[1], p)
                        ti.atomic_min(self.errors[4], s)
                        face, side, inside = ref, self.side[p], self.inside[p]
                    else:
                        before = flag * self.side[p]
                        inside = self.inside[p]
                        if side == 0:
                            side = before
                        elif side != before and not self.on_open_boundary(f, region):
                            inside = self.enabled[None] * (1 - inside)
            self.face[p], self.side[p], self.inside[p] = face, side, inside
            if record:
                self.face_s[slot, p], self.side_s[slot, p], self.inside_s[slot, p] = face, side, inside
                self._candidates(slot, p, x, face, d2)

    @ti.func
    def _candidates(self, slot, p, x, face, d2_min):
        """Record the blend candidates of particle p at x (see the module docstring)."""
        ids = ti.Vector([-1] * CANDIDATES)
        dist = ti.Vector([0.0] * CANDIDATES)
        flags = ti.Vector([0] * CANDIDATES)
        corner = ti.Vector([-1] * CANDIDATES)  # the vertex that is the closest point, or -1
        if face >= 0:
            limit = ti.sqrt(d2_min) + self.cutoff
            count = 0
            key = self.query.cell_key(x)
            for j in range(self.query.start[key], self.query.start[key + 1] + 1):
                g = face  # the face itself first, then the hash cell's entries
                if j > self.query.start[key]:
                    g = self.query.entries[j - 1]
                if j == self.query.start[key] or g != face:
                    a, b, c = self.query.corners(g)
                    point, _w, region = closest_point_on_triangle(x, a, b, c)
                    d = ti.sqrt((x - point).norm_sqr())
                    vertex = -1
                    if region >= CORNER and region < EDGE:
                        vertex = self.query.faces[g][region - CORNER]
                    flag = 1
                    if g != face:
                        flag = self.relative_flag(face, g)
                    listed = 0
                    if vertex >= 0:
                        for k in ti.static(range(CANDIDATES)):
                            if corner[k] == vertex:
                                listed = 1
                    if d <= limit and flag != 0 and not listed:
                        slot_k = -1  # where it goes: the next free place, or the farthest if nearer
                        if count < CANDIDATES:
                            slot_k = count
                            count += 1
                        else:
                            ti.atomic_add(self.overflow[None], 1)
                            far, far_d = -1, d
                            for k in ti.static(range(1, CANDIDATES)):
                                if dist[k] > far_d:
                                    far, far_d = k, dist[k]
                            slot_k = far
                        for k in ti.static(range(CANDIDATES)):
                            if k == slot_k:
                                ids[k], dist[k], flags[k], corner[k] = g, d, flag, vertex
        for k in ti.static(range(CANDIDATES)):
            self.candidate_s[slot, p, k] = ids[k]
            self.candidate_flag_s[slot, p, k] = flags[k]


def _int_field(owner, shape: tuple, values: np.ndarray):
    fld = field_pool.scalar(owner, ti.i32, shape=shape)
    fld.from_numpy(np.ascontiguousarray(values, dtype=np.int32))
    return fld
