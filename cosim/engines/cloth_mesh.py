"""Cloth meshes: triangle meshes with the topology and rest geometry the cloth energies need.

A ``ClothMesh`` holds the rest positions (V, 3) [m] and faces (F, 3) as given (no reorientation),
and derives once: unique edges, hinges (interior edges with their two opposite vertices), rest
areas [m^2], the rest 2x2 inverse metric of each face (``Dm_inv``: maps the face's edge vectors in
its own flat 2-D rest frame to the deformation gradient, F = [x1 - x0, x2 - x0] Dm_inv, 3x2) and
the boundary vertices.

Hinge ordering (well defined on non-orientable meshes such as a Moebius strip): a hinge is
``(a, b, c, d)`` with (a, b) the shared edge with a < b, c the opposite vertex of the edge's first
face (lowest face index) and d that of the second. The dihedral angle is computed from this
ordering alone (``cloth_energy.hinge_angle``: normals (b - a) x (c - a) and (d - a) x (b - a)),
never from the faces' windings, so it is the same whether the two faces agree in winding or not;
swapping c and d flips the sign of both the angle and its rest value, which leaves the energy
(theta - theta0)^2 unchanged.

Builders: ``rectangle``, ``disc``, ``from_file`` (trimesh, ``process=False``). Problems in the
input (zero-area faces, edges shared by more than two faces, unreadable files) raise ValueError
naming the source and the problem.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

SLIVER_RATIO = 1e-3  # a face whose smallest height is below this share of its longest edge is refused
AREA_EPS = 1e-14  # [m^2] faces at or below this rest area are degenerate (rejected)
AXES = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class ClothMesh:
    """Rest geometry and topology of a triangle mesh (see the module docstring)."""

    vertices: np.ndarray  # (V, 3) [m] rest positions
    faces: np.ndarray  # (F, 3) vertex indices, windings as given
    edges: np.ndarray  # (E, 2) unique edges, a < b
    hinges: np.ndarray  # (H, 4) (a, b, c, d): edge a < b, opposite vertices c (first face), d (second)
    hinge_faces: np.ndarray  # (H, 2) the two faces of each hinge
    rest_area: np.ndarray  # (F,) [m^2]
    Dm_inv: np.ndarray  # (F, 2, 2) [1/m] inverse of the face's edge vectors in its flat rest frame
    boundary: np.ndarray  # (B,) sorted indices of vertices on a boundary edge
    source: str = "mesh"

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def vertex_areas(self) -> np.ndarray:
        """(V,) [m^2] one third of the rest area of every face around each vertex (lumped mass / density)."""
        return np.bincount(self.faces.ravel(), np.repeat(self.rest_area / 3.0, 3), minlength=self.n_vertices)


def build(vertices, faces, source: str = "mesh") -> ClothMesh:
    """A ``ClothMesh`` from rest positions (V, 3) [m] and faces (F, 3); ValueError on bad input."""
    x = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if x.ndim != 2 or x.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"{source}: need vertices (V, 3) and faces (F, 3), got {x.shape} and {f.shape}")
    if f.min() < 0 or f.max() >= len(x):
        raise ValueError(f"{source}: face indices must lie in [0, {len(x)}), got [{f.min()}, {f.max()}]")
    area, Dm_inv = _rest_frames(x, f, source)
    edges, hinges, hinge_faces, boundary = _topology(f, source)
    return ClothMesh(x, f, edges, hinges, hinge_faces, area, Dm_inv, boundary, source)


def _rest_frames(x: np.ndarray, f: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Rest areas and 2x2 inverse metrics: each face's edges e1, e2 in an orthonormal frame of its plane."""
    e1 = x[f[:, 1]] - x[f[:, 0]]
    e2 = x[f[:, 2]] - x[f[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    bad = np.flatnonzero(area <= AREA_EPS)
    if len(bad):
        raise ValueError(
            f"{source}: {len(bad)} degenerate (zero-area) faces, first face {bad[0]} with vertices {f[bad[0]].tolist()}; "
            "remove them or merge their vertices"
        )
    longest = np.max(np.linalg.norm([e1, e2, e2 - e1], axis=2), axis=0)
    flatness = 2.0 * area / longest**2  # smallest height over longest edge
    thin = np.flatnonzero(flatness < SLIVER_RATIO)
    if len(thin):
        k = thin[np.argmin(flatness[thin])]
        raise ValueError(
            f"{source}: {len(thin)} sliver faces (height under {SLIVER_RATIO:g} of the longest edge), the worst face "
            f"{k} with vertices {f[k].tolist()} at {flatness[k]:.2g}: their stiffness grows as 1 / height^2 and the "
            "implicit solve cannot converge; remesh it (near-equilateral triangles) or merge the close vertices"
        )
    l1 = np.linalg.norm(e1, axis=1)
    t = e1 / l1[:, None]
    along = np.einsum("ij,ij->i", e2, t)
    Dm = np.zeros((len(f), 2, 2))
    Dm[:, 0, 0] = l1
    Dm[:, 0, 1] = along
    Dm[:, 1, 1] = 2.0 * area / l1  # height of e2 over e1 (> 0)
    return area, np.linalg.inv(Dm)


def _topology(f: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unique edges, hinges (see the module docstring), hinge faces and boundary vertices."""
    half = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])  # edge k of face i at row k F + i
    opposite = np.concatenate([f[:, 2], f[:, 0], f[:, 1]])
    face_of = np.tile(np.arange(len(f)), 3)
    key = np.sort(half, axis=1)
    order = np.lexsort((face_of, key[:, 1], key[:, 0]))
    key, opposite, face_of = key[order], opposite[order], face_of[order]
    edges, start, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    if count.max() > 2:
        e = int(np.argmax(count))
        raise ValueError(
            f"{source}: non-manifold edge {edges[e].tolist()} is shared by {count[e]} faces "
            f"(faces {face_of[start[e] : start[e] + count[e]].tolist()}); a cloth edge may border at most 2 faces"
        )
    inner = start[count == 2]
    hinges = np.column_stack([key[inner], opposite[inner], opposite[inner + 1]])
    hinge_faces = np.column_stack([face_of[inner], face_of[inner + 1]])
    boundary = np.unique(edges[count == 1])
    return edges, hinges, hinge_faces, boundary


# --------------------------------------------------------------------------------------------- builders


def rectangle(size=(1.0, 1.0), resolution=(10, 10), center=(0.0, 0.0, 0.0), normal: str = "y") -> ClothMesh:
    """A flat w x h [m] rectangle with nx x ny vertices (nx, ny >= 2), centred at ``center`` [m].

    ``normal``: the axis the sheet faces ("x", "y" or "z"); the sheet spans the other two axes in
    cyclic order (normal y: width along z, height along x; normal z: width along x, height along y).
    Vertex (i, j) (i along the width) has index j * nx + i; each cell is split along one diagonal.
    """
    (w, h), (nx, ny) = size, resolution
    if nx < 2 or ny < 2 or w <= 0 or h <= 0:
        raise ValueError(f"rectangle: need size > 0 and resolution >= (2, 2), got size {size}, resolution {resolution}")
    if normal not in AXES:
        raise ValueError(f"rectangle: normal must be one of {sorted(AXES)}, got {normal!r}")
    n = AXES[normal]
    u, v = (n + 1) % 3, (n + 2) % 3
    s, t = np.meshgrid(np.linspace(-w / 2, w / 2, nx), np.linspace(-h / 2, h / 2, ny))
    x = np.zeros((nx * ny, 3))
    x[:, u], x[:, v] = s.ravel(), t.ravel()
    x += np.asarray(center, dtype=np.float64)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    faces = np.concatenate([np.column_stack([a, a + 1, a + nx + 1]), np.column_stack([a, a + nx + 1, a + nx])])
    return build(x, faces, f"rectangle {w}x{h} m, {nx}x{ny} vertices")


def disc(radius: float = 1.0, rings: int = 8, center=(0.0, 0.0, 0.0), normal: str = "y") -> ClothMesh:
    """A flat disc of ``radius`` [m]: a centre vertex and ``rings`` rings, ring k holding 6 k vertices
    (1 + 3 rings (rings + 1) vertices, 6 rings^2 faces, near-equilateral triangles); the outer ring
    lies on the circle, so the area is that of the inscribed 6-rings-gon."""
    if rings < 1 or radius <= 0:
        raise ValueError(f"disc: need radius > 0 and rings >= 1, got radius {radius}, rings {rings}")
    if normal not in AXES:
        raise ValueError(f"disc: normal must be one of {sorted(AXES)}, got {normal!r}")
    pts, faces = [np.zeros(2)], []
    first = [0]  # index of the first vertex of each ring
    for k in range(1, rings + 1):
        first.append(len(pts))
        ang = 2 * np.pi * np.arange(6 * k) / (6 * k)
        pts.extend(radius * k / rings * np.column_stack([np.cos(ang), np.sin(ang)]))
    for k in range(1, rings + 1):
        outer, inner = first[k], first[k - 1]
        n_out, n_in = 6 * k, max(6 * (k - 1), 1)
        for s in range(6):  # six sectors: k outer edges and k - 1 inner edges each
            for q in range(k):
                o = s * k + q
                i0 = (s * (k - 1) + q) % n_in
                faces.append([inner + i0, outer + o, outer + (o + 1) % n_out])
                if q < k - 1:
                    faces.append([inner + i0, outer + (o + 1) % n_out, inner + (i0 + 1) % n_in])
    n = AXES[normal]
    x = np.zeros((len(pts), 3))
    x[:, [(n + 1) % 3, (n + 2) % 3]] = np.asarray(pts)
    return build(x + np.asarray(center, dtype=np.float64), np.asarray(faces), f"disc r={radius} m, {rings} rings")


def from_file(path) -> ClothMesh:
    """A mesh file (.obj, .ply, .stl, ... as trimesh reads them), faces kept exactly as given
    (``process=False``: no merging, no reorientation, so non-orientable meshes load as they are)."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"cloth mesh file '{path}' does not exist")
    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"cloth mesh file '{path}' could not be read as a triangle mesh: {exc}") from exc
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))))
    if faces.ndim != 2 or len(faces) == 0:
        raise ValueError(f"cloth mesh file '{path}' holds no triangles")
    return build(np.asarray(mesh.vertices), faces, f"cloth mesh file '{path}'")
