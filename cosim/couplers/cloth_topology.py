"""Topology of a cloth's triangle mesh for penetration tracing (host, NumPy; once per mesh).

The mesh may be open and non-orientable (a Möbius strip), so there is no global
"outside". What tracing needs is local: which faces lie near a face, and whether
each of them winds the same way as that face when carried along the sheet.

- Edge adjacency: face f's edge k runs from corner k to corner k+1; ``edge_face[f, k]``
  is the face across it (-1 on the open boundary) and ``edge_flag[f, k]`` is +1 when
  that face traverses the shared edge in the opposite direction (windings agree),
  -1 when in the same direction (windings disagree).
- Neighbourhoods: every face within a geodesic radius R of f, nearest first, with an
  orientation flag per entry: the product of the edge flags along the shortest path
  over edge-adjacent faces. Geodesic distance is measured along centroid-to-centroid
  paths, which overestimate the surface distance by at most twice the largest
  centroid-to-corner distance r, so faces with path length <= R + 2 r are kept (a
  superset of the faces within R). On a Möbius strip the flags are consistent within
  one neighbourhood as long as R is well below the strip's length.
- Vertex stars: the faces around each corner's vertex, flagged relative to the face
  (for the vertex pseudo-normal), and whether the vertex lies on the open boundary.

Lengths are metres, measured on the vertices given (the rest shape).
"""

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra


@dataclass
class ClothTopology:
    """Index arrays (int32) of one mesh; -1 pads every ragged list."""

    faces: np.ndarray  # (F, 3)
    edge_face: np.ndarray  # (F, 3) face across edge k (corner k -> k+1), -1 on the boundary
    edge_flag: np.ndarray  # (F, 3) +1 windings agree across edge k, -1 they disagree, 0 boundary
    star: np.ndarray  # (F, 3, S) faces around corner k's vertex (f itself included)
    star_flag: np.ndarray  # (F, 3, S) their winding relative to f
    vertex_boundary: np.ndarray  # (F, 3) 1 when corner k's vertex is on an open boundary
    neighbours: np.ndarray  # (F, M) faces within the radius, nearest first (f itself first)
    neighbour_flag: np.ndarray  # (F, M) their winding relative to f
    radius: float  # [m] geodesic radius of the neighbourhoods

    @property
    def max_neighbours(self) -> int:
        return self.neighbours.shape[1]


def edge_adjacency(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(edge_face, edge_flag), both (F, 3); raises on an edge shared by more than two faces."""
    F = len(faces)
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)  # half-edge f*3+k: corner k -> corner k+1
    key = np.minimum(a, b).astype(np.int64) * (int(faces.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    counts = np.diff(np.r_[starts, len(key)])
    if counts.max(initial=0) > 2:
        h = order[starts[np.argmax(counts)]]
        raise ValueError(
            f"cloth mesh: edge ({a[h]}, {b[h]}) is shared by {counts.max()} faces; tracing needs a manifold sheet"
        )
    edge_face = np.full(3 * F, -1, dtype=np.int32)
    edge_flag = np.zeros(3 * F, dtype=np.int32)
    pairs = starts[counts == 2]
    h0, h1 = order[pairs], order[pairs + 1]
    edge_face[h0], edge_face[h1] = h1 // 3, h0 // 3
    flag = np.where(a[h0] == a[h1], -1, 1)  # same direction: windings disagree
    edge_flag[h0] = edge_flag[h1] = flag
    return edge_face.reshape(F, 3), edge_flag.reshape(F, 3)


def vertex_stars(faces: np.ndarray, edge_face: np.ndarray, edge_flag: np.ndarray):
    """(star, star_flag, vertex_boundary): faces around each corner, flagged relative to the face,
    found by walking edge-adjacent faces that share the vertex (a breadth-first search)."""
    F = len(faces)
    stars: list[list[tuple[int, int]]] = []
    for f in range(F):
        for k in range(3):
            v = faces[f, k]
            seen, queue = {f: 1}, [f]
            while queue:
                g = queue.pop()
                for e in range(3):  # edges of g that contain v
                    if v not in (faces[g, e], faces[g, (e + 1) % 3]):
                        continue
                    h = edge_face[g, e]
                    if h >= 0 and h not in seen:
                        seen[h] = seen[g] * edge_flag[g, e]
                        queue.append(h)
            stars.append(list(seen.items()))
    S = max(len(s) for s in stars)
    star = np.full((F * 3, S), -1, dtype=np.int32)
    star_flag = np.zeros((F * 3, S), dtype=np.int32)
    for i, s in enumerate(stars):
        star[i, : len(s)] = [g for g, _ in s]
        star_flag[i, : len(s)] = [fl for _, fl in s]
    on_boundary = np.zeros(int(faces.max()) + 1, dtype=bool)
    open_f, open_k = np.nonzero(edge_face < 0)
    on_boundary[faces[open_f, open_k]] = True
    on_boundary[faces[open_f, (open_k + 1) % 3]] = True
    return star.reshape(F, 3, S), star_flag.reshape(F, 3, S), on_boundary[faces].astype(np.int32)


def neighbourhoods(
    verts: np.ndarray, faces: np.ndarray, edge_face: np.ndarray, edge_flag: np.ndarray, radius: float, limit: int
) -> tuple[np.ndarray, np.ndarray]:
    """(neighbours, flags) (F, M): faces within geodesic ``radius`` [m] of each face (see the module
    docstring), nearest first, -1 padded; raises when a face has more than ``limit`` of them."""
    F = len(faces)
    centroids = verts[faces].mean(axis=1)
    r_max = float(np.linalg.norm(verts[faces] - centroids[:, None], axis=2).max())
    f_idx, k_idx = np.nonzero(edge_face >= 0)
    g_idx = edge_face[f_idx, k_idx]
    weight = np.linalg.norm(centroids[f_idx] - centroids[g_idx], axis=1) + 1e-300  # > 0: kept by csr
    graph = csr_matrix((weight, (f_idx, g_idx)), shape=(F, F))
    reach = radius + 2.0 * r_max
    rows_out, flags_out = [], []
    chunk = max(1, min(F, 2_000_000 // max(F, 1)))
    for lo in range(0, F, chunk):
        rows = np.arange(lo, min(F, lo + chunk))
        dist, pred = dijkstra(graph, directed=True, indices=rows, limit=reach, return_predecessors=True)
        r, g = np.nonzero(np.isfinite(dist))  # the reached (row, face) pairs, row-major
        d, parent = dist[r, g], pred[r, g]
        slot = np.full(dist.shape, -1, dtype=np.int64)
        slot[r, g] = np.arange(len(r))
        # orientation: product of the edge flags along the shortest path, by pointer jumping
        up = np.where(parent >= 0, slot[r, np.maximum(parent, 0)], -1)
        acc = np.where(parent >= 0, (edge_flag[g] * (edge_face[g] == parent[:, None])).sum(axis=1), 1)
        while (up >= 0).any():
            valid = up >= 0
            safe = np.where(valid, up, 0)
            acc = np.where(valid, acc * acc[safe], acc)
            up = np.where(valid, up[safe], -1)
        order = np.lexsort((d, r))  # per row, nearest first
        bounds = np.searchsorted(r[order], np.arange(len(rows) + 1))
        for i in range(len(rows)):
            pick = order[bounds[i] : bounds[i + 1]]
            rows_out.append(g[pick])
            flags_out.append(acc[pick])
    M = max(len(x) for x in rows_out)
    if M > limit:
        raise ValueError(
            f"cloth tracing: a face has {M} faces within the search radius {radius:.3g} m (limit {limit}); "
            "the radius is far larger than the mesh's faces: lower it or raise max_neighbours"
        )
    neighbours = np.full((F, M), -1, dtype=np.int32)
    flags = np.zeros((F, M), dtype=np.int32)
    for f, (nb, fl) in enumerate(zip(rows_out, flags_out)):
        neighbours[f, : len(nb)], flags[f, : len(nb)] = nb, fl
    return neighbours, flags


def build_topology(verts: np.ndarray, faces: np.ndarray, radius: float, limit: int = 4096) -> ClothTopology:
    """Everything tracing needs about the mesh ``faces`` (F, 3) with rest vertices ``verts`` (V, 3) [m]."""
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    verts = np.asarray(verts, dtype=np.float64)
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"cloth mesh: faces must be (F, 3) triangles, got shape {faces.shape}")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise ValueError(f"cloth mesh: face indices must lie in [0, {len(verts)}), got {faces.min()}..{faces.max()}")
    edge_face, edge_flag = edge_adjacency(faces)
    star, star_flag, vertex_boundary = vertex_stars(faces, edge_face, edge_flag)
    neighbours, flags = neighbourhoods(verts, faces, edge_face, edge_flag, float(radius), limit)
    return ClothTopology(
        faces, edge_face, edge_flag, star, star_flag, vertex_boundary, neighbours, flags, float(radius)
    )
