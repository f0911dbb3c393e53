"""Exact signed distance fields of watertight triangle meshes, cached on disk.

Meshes (any format trimesh reads, watertight) are evaluated exactly by a
brute-force Taichi kernel: the distance to the closest point of every triangle,
the sign from the generalised winding number; the node normals are the unit
directions from the closest surface points. Distances in metres (the mesh's
units), negative inside; body frame = the mesh's own frame. Mesh fields are
cached on disk as ``.npz`` files keyed by a SHA-256 of the vertices, faces and
settings (loaded with ``allow_pickle=False``).
"""

import hashlib
import os
from pathlib import Path

import numpy as np
import taichi as ti

from cosim.couplers.sdf_grid import SDFGrid, grid_over
from cosim.engines.meshes import require_watertight
from cosim.errors import SceneError

SDF_VERSION = "2"  # bump when the computation changes: invalidates the cache


@ti.func
def _closest_on_triangle(p, a, b, c):
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection 5.1.5)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab.dot(ap), ac.dot(ap)
    result = a
    done = d1 <= 0 and d2 <= 0
    bp = p - b
    d3, d4 = ab.dot(bp), ac.dot(bp)
    if not done and d3 >= 0 and d4 <= d3:
        result, done = b, True
    vc = d1 * d4 - d3 * d2
    if not done and vc <= 0 and d1 >= 0 and d3 <= 0:
        result, done = a + d1 / (d1 - d3) * ab, True
    cp = p - c
    d5, d6 = ab.dot(cp), ac.dot(cp)
    if not done and d6 >= 0 and d5 <= d6:
        result, done = c, True
    vb = d5 * d2 - d1 * d6
    if not done and vb <= 0 and d2 >= 0 and d6 <= 0:
        result, done = a + d2 / (d2 - d6) * ac, True
    va = d3 * d6 - d5 * d4
    if not done and va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        result, done = b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b), True
    if not done:
        denom = 1.0 / (va + vb + vc)
        result = a + ab * (vb * denom) + ac * (vc * denom)
    return result


@ti.kernel
def _mesh_sdf_kernel(
    points: ti.types.ndarray(), tris: ti.types.ndarray(), out: ti.types.ndarray(), closest: ti.types.ndarray()
):
    for i in range(points.shape[0]):
        p = ti.Vector([points[i, 0], points[i, 1], points[i, 2]], dt=ti.f64)
        best = 1e30
        best_q = p
        winding = 0.0
        for t in range(tris.shape[0]):
            a = ti.Vector([tris[t, 0, 0], tris[t, 0, 1], tris[t, 0, 2]], dt=ti.f64)
            b = ti.Vector([tris[t, 1, 0], tris[t, 1, 1], tris[t, 1, 2]], dt=ti.f64)
            c = ti.Vector([tris[t, 2, 0], tris[t, 2, 1], tris[t, 2, 2]], dt=ti.f64)
            q = _closest_on_triangle(p, a, b, c)
            if (p - q).norm_sqr() < best:
                best, best_q = (p - q).norm_sqr(), q
            # solid angle of the triangle seen from p (Van Oosterom and Strackee)
            ra, rb, rc = a - p, b - p, c - p
            la, lb, lc = ra.norm(), rb.norm(), rc.norm()
            num = ra.dot(rb.cross(rc))
            den = la * lb * lc + ra.dot(rb) * lc + rb.dot(rc) * la + rc.dot(ra) * lb
            winding += 2.0 * ti.atan2(num, den)
        sign = -1.0 if winding / (4.0 * 3.141592653589793) > 0.5 else 1.0
        out[i] = sign * ti.sqrt(best)
        for k in ti.static(range(3)):
            closest[i, k] = best_q[k]


def cache_dir() -> Path:
    """Where mesh SDFs are cached: $COSIM_CACHE/sdf, default ~/.cache/cosim/sdf."""
    return Path(os.environ.get("COSIM_CACHE", Path.home() / ".cache" / "cosim")) / "sdf"


def mesh_key(vertices: np.ndarray, faces: np.ndarray, spacing: float, padding: float) -> str:
    """The cache key: SHA-256 of the vertices [m], faces, spacing, padding and ``SDF_VERSION``."""
    h = hashlib.sha256()
    for part in (np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64)):
        h.update(part.tobytes())
    h.update(f"{spacing!r}|{padding!r}|{SDF_VERSION}".encode())
    return h.hexdigest()


def mesh_sdf(mesh, spacing: float, padding: float, key: str = "mesh", use_cache: bool = True) -> SDFGrid:
    """Exact SDF of a watertight trimesh (body frame = the mesh's own frame).

    ``key`` names the mesh in error messages (the scene key or file).
    Needs Taichi initialised (any precision: the kernel computes in float64).
    """
    require_watertight(
        mesh,
        f"{key}: the mesh",
        "inside and outside are undefined for its signed distance",
        "close its holes (e.g. trimesh.repair.fill_holes) or use a primitive",
        SceneError,
    )
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    digest = mesh_key(vertices, faces, spacing, padding)
    path = cache_dir() / f"{digest}.npz"
    if use_cache and path.is_file():
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) == digest:
                return SDFGrid(data["origin"], float(data["spacing"]), data["values"], data["normals"])
    origin, counts = grid_over(vertices.min(axis=0), vertices.max(axis=0), spacing, padding)
    grid = SDFGrid(origin, spacing, np.zeros(counts))
    points = np.ascontiguousarray(grid.nodes().reshape(-1, 3))
    out, closest = np.zeros(len(points)), np.zeros_like(points)
    _mesh_sdf_kernel(points, np.ascontiguousarray(vertices[faces]), out, closest)
    grid.values = out.reshape(counts)
    grid.normals = _mesh_normals(grid, points, closest, out)
    if use_cache:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(
            tmp,
            key=np.asarray(digest),
            origin=grid.origin,
            spacing=np.asarray(spacing),
            values=grid.values,
            normals=grid.normals,
        )
        tmp.replace(path)
    return grid


def _mesh_normals(grid: SDFGrid, points: np.ndarray, closest: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Exact SDF gradient at the nodes: the unit direction from the closest surface point,
    flipped inside; central differences of the distances at nodes on the surface itself."""
    offset = points - closest
    length = np.linalg.norm(offset, axis=1, keepdims=True)
    exact = np.sign(dist)[:, None] * offset / np.maximum(length, 1e-300)
    fallback = np.stack(np.gradient(grid.values, grid.spacing), axis=-1).reshape(-1, 3)
    on_surface = length[:, 0] < 1e-9 * grid.spacing
    return np.where(on_surface[:, None], fallback, exact).reshape(*grid.values.shape, 3)
