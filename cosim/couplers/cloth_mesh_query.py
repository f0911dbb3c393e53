"""Nearest face of a triangle mesh to points: a uniform hash of face boxes and exact point-triangle distances.

The cloth is frozen during the MPM substeps of a macro step, so the hash is built
once per macro step on the host (NumPy: sorted cell keys and offsets) and uploaded;
the queries run in Taichi. Each face is registered in every cell its bounding box,
grown by the search band, overlaps; the cell size h is the largest grown box extent,
so a face touches at most 2 x 2 x 2 cells and the table holds at most 8 F entries
whatever the mesh does. A point then needs only its own cell: a face within the band
of the point has a grown box containing it. Cells are hashed into a power-of-two
table (collisions only add candidates). Faces farther than the band are not found:
the query answers "none" (-1), which is exact, not an approximation.

``closest_point_on_triangle`` is Ericson's region method (Real-Time Collision
Detection, 5.1.5): barycentrics from 3D dot products, valid for any triangle
orientation (no projection onto a coordinate plane), and differentiable within
each region (contact models call it with a fixed face inside differentiated kernels).
"""

import numpy as np
import taichi as ti

from cosim.engines import field_pool
from cosim.engines.arch import current_choices
from cosim.engines.data_oriented import data_oriented

PRIMES = (73856093, 19349663, 83492791)  # spatial-hash multipliers (Teschner et al. 2003)

# region codes of closest_point_on_triangle: 0 the face's interior, 1 + k corner k, 4 + k edge k
# (corner k -> corner k + 1)
INTERIOR, CORNER, EDGE = 0, 1, 4


@ti.func
def closest_point_on_triangle(x, a, b, c):
    """Closest point on triangle (a, b, c) to x [m], its barycentrics (u, v, w) (point = u a + v b + w c)
    and the region code (0 interior, 1..3 corner a/b/c, 4..6 edge ab/bc/ca)."""
    ab, ac = b - a, c - a
    d1, d2 = ab.dot(x - a), ac.dot(x - a)
    d3, d4 = ab.dot(x - b), ac.dot(x - b)
    d5, d6 = ab.dot(x - c), ac.dot(x - c)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    region = INTERIOR
    bary = ti.Vector([0.0, 0.0, 0.0])
    if d1 <= 0 and d2 <= 0:
        region = CORNER
        bary = ti.Vector([1.0, 0.0, 0.0])
    elif d3 >= 0 and d4 <= d3:
        region = CORNER + 1
        bary = ti.Vector([0.0, 1.0, 0.0])
    elif vc <= 0 and d1 >= 0 and d3 <= 0:
        t = d1 / (d1 - d3)
        region = EDGE
        bary = ti.Vector([1.0 - t, t, 0.0])
    elif d6 >= 0 and d5 <= d6:
        region = CORNER + 2
        bary = ti.Vector([0.0, 0.0, 1.0])
    elif vb <= 0 and d2 >= 0 and d6 <= 0:
        t = d2 / (d2 - d6)
        region = EDGE + 2
        bary = ti.Vector([1.0 - t, 0.0, t])
    elif va <= 0 and d4 - d3 >= 0 and d5 - d6 >= 0:
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        region = EDGE + 1
        bary = ti.Vector([0.0, 1.0 - t, t])
    else:
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        bary = ti.Vector([1.0 - v - w, v, w])
    return bary[0] * a + bary[1] * b + bary[2] * c, bary, region


def face_hash(verts: np.ndarray, faces: np.ndarray, band: float, table: int) -> tuple[float, np.ndarray, np.ndarray]:
    """(h, start, entries): cell size [m], offsets (table + 1) and face ids (<= 8 F) sorted by cell key."""
    tri = verts.take(faces, axis=0)
    lo, hi = tri.min(axis=1) - band, tri.max(axis=1) + band
    h = float((hi - lo).max()) * (1.0 + 1e-9)
    lo_c = np.floor(lo / h).astype(np.int64)
    span = np.floor(hi / h).astype(np.int64) - lo_c  # 0 or 1 per axis
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.int64)
    cells = lo_c[:, None, :] + corners[None]  # (F, 8, 3)
    valid = (corners[None] <= span[:, None, :]).all(axis=2)
    keys = cell_keys(cells[valid], table)
    ids = np.broadcast_to(np.arange(len(faces), dtype=np.int32)[:, None], valid.shape)[valid]
    order = np.argsort(keys, kind="stable")
    start = np.zeros(table + 1, dtype=np.int32)
    start[1:] = np.cumsum(np.bincount(keys, minlength=table))
    entries = np.full(8 * len(faces), -1, dtype=np.int32)
    entries[: len(ids)] = ids[order]
    return h, start, entries


def cell_keys(cells: np.ndarray, table: int) -> np.ndarray:
    """Hash of integer cells (n, 3) into [0, table) (table a power of two); the Taichi query computes the same."""
    c = cells.astype(np.int64)
    return ((c[:, 0] * PRIMES[0]) ^ (c[:, 1] * PRIMES[1]) ^ (c[:, 2] * PRIMES[2])) & (table - 1)


@data_oriented
class MeshQuery:
    """Vertices ``verts`` (V, 3) [m] (with adjoints when ``requires_grad``), ``faces`` (F, 3) and the face
    hash; ``nearest(x)`` gives the nearest face within ``band`` [m] of x, or -1."""

    def __init__(self, faces: np.ndarray, n_verts: int, band: float, requires_grad: bool = False):
        self.n_faces = F = len(faces)
        self.n_verts = n_verts
        self.band = float(band)
        self.table = 1 << int(np.ceil(np.log2(max(16, 16 * F))))
        self.faces_np = np.ascontiguousarray(faces, dtype=np.int32)
        self.verts = field_pool.vector(self, 3, float, shape=n_verts, needs_grad=requires_grad)
        self.faces = field_pool.vector(self, 3, ti.i32, shape=F)
        self.faces.from_numpy(self.faces_np)
        self.start = field_pool.scalar(self, ti.i32, shape=self.table + 1)
        self.entries = field_pool.scalar(self, ti.i32, shape=8 * F)
        self.inv_h = field_pool.scalar(self, float, shape=())
        self.real = np.float64 if self.verts.dtype == ti.f64 else np.float32
        # copies of this size run on one thread on a CPU (a thread-pool dispatch costs more), in parallel on a GPU
        self.serial_copies = current_choices().serial_nodes(self.table + 8 * F)

    def update(self, verts: np.ndarray) -> None:
        """New vertex positions (V, 3) [m]: rebuild the hash (host) and upload both in one launch."""
        verts = np.asarray(verts, dtype=np.float64)
        hashed, inv_h = self.packed_hash(verts)
        self._upload(verts.astype(self.real), hashed, inv_h)

    def packed_hash(self, verts: np.ndarray) -> tuple[np.ndarray, float]:
        """The face hash at positions ``verts`` (V, 3) [m] as one int32 array (``start`` (table + 1), then
        ``entries`` (8 F)) and 1 / h [1/m]: what ``load`` takes."""
        h, start, entries = face_hash(np.asarray(verts, dtype=np.float64), self.faces_np, self.band, self.table)
        return np.concatenate([start, entries]), 1.0 / h

    @ti.kernel
    def _upload(self, verts: ti.types.ndarray(), hashed: ti.types.ndarray(), inv_h: float):
        self.load(verts, hashed, inv_h)

    @ti.func
    def load(self, rows: ti.template(), hashed: ti.template(), inv_h):
        """Positions from the first V rows of ``rows`` (>= V, 3) [m] and the hash (``packed_hash``), at a kernel's
        top level (a caller uploads them with its own arrays in one launch)."""
        self.inv_h[None] = inv_h
        ti.loop_config(serialize=self.serial_copies)
        for v in range(self.n_verts):
            self.verts[v] = ti.Vector([rows[v, k] for k in ti.static(range(3))])
        ti.loop_config(serialize=self.serial_copies)
        for i in range(self.table + 1 + 8 * self.n_faces):
            if i <= self.table:
                self.start[i] = hashed[i]
            else:
                self.entries[i - self.table - 1] = hashed[i]

    @ti.func
    def corners(self, f):
        tri = self.faces[f]
        return self.verts[tri[0]], self.verts[tri[1]], self.verts[tri[2]]

    @ti.func
    def cell_key(self, x):
        c = ti.cast(ti.floor(x * self.inv_h[None]), ti.i64)
        return ti.cast(((c[0] * PRIMES[0]) ^ (c[1] * PRIMES[1]) ^ (c[2] * PRIMES[2])) & (self.table - 1), ti.i32)

    @ti.func
    def nearest(self, x):
        """(face, squared distance [m^2], barycentrics, region) of the nearest face within the band
        (ties: the lower face index), or face -1 when none is."""
        key = self.cell_key(x)
        best, best_d2, best_bary, best_region = -1, self.band * self.band, ti.Vector([0.0, 0.0, 0.0]), 0
        for j in range(self.start[key], self.start[key + 1]):
            f = self.entries[j]
            a, b, c = self.corners(f)
            point, bary, region = closest_point_on_triangle(x, a, b, c)
            d2 = (x - point).norm_sqr()
            if d2 < best_d2 or (d2 == best_d2 and best >= 0 and f < best):
                best, best_d2, best_bary, best_region = f, d2, bary, region
        return best, best_d2, best_bary, best_region

    @ti.func
    def nearest_brute(self, x):
        """As ``nearest``, over every face (the reference and the benchmark's baseline)."""
        best, best_d2, best_bary, best_region = -1, self.band * self.band, ti.Vector([0.0, 0.0, 0.0]), 0
        for f in range(self.n_faces):
            a, b, c = self.corners(f)
            point, bary, region = closest_point_on_triangle(x, a, b, c)
            d2 = (x - point).norm_sqr()
            if d2 < best_d2:
                best, best_d2, best_bary, best_region = f, d2, bary, region
        return best, best_d2, best_bary, best_region

    @ti.kernel
    def _query(
        self,
        brute: ti.template(),
        points: ti.types.ndarray(),
        face: ti.types.ndarray(),
        dist: ti.types.ndarray(),
        bary: ti.types.ndarray(),
    ):
        for i in range(points.shape[0]):
            x = ti.Vector([points[i, 0], points[i, 1], points[i, 2]])
            f, d2, w = -1, 0.0, ti.Vector([0.0, 0.0, 0.0])
            if ti.static(brute):
                f, d2, w, _r = self.nearest_brute(x)
            else:
                f, d2, w, _r = self.nearest(x)
            face[i], dist[i] = f, ti.sqrt(d2)
            for k in ti.static(range(3)):
                bary[i, k] = w[k]

    def query(self, points: np.ndarray, brute: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(face (n,), distance (n,) [m], barycentrics (n, 3)) of points (n, 3); face -1 beyond the band."""
        points = np.ascontiguousarray(points, dtype=self.real)
        n = len(points)
        face, dist, bary = np.empty(n, np.int32), np.empty(n, self.real), np.empty((n, 3), self.real)
        self._query(bool(brute), points, face, dist, bary)
        return face, dist.astype(np.float64), bary.astype(np.float64)
