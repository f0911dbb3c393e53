"""Exact signed distance fields of watertight triangle meshes, cached on disk.

Meshes (any format trimesh reads, watertight) are evaluated exactly by a
brute-force Taichi kernel (``sdf_mesh_kernel``, imported only on a cache miss): the distance to the closest point of every triangle,
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

from cosim.couplers.sdf_grid import SDFGrid, grid_over
from cosim.engines.meshes import require_watertight
from cosim.errors import SceneError

SDF_VERSION = "2"  # bump when the computation changes: invalidates the cache


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

    ``key`` names the mesh in error messages (the scene key or file). The kernel runs in the
    Taichi already started (any precision: it computes in float64), or, when none is (``cosim
    validate``), in one started on the CPU in float64; a cached field needs no Taichi.
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
    from cosim.couplers.sdf_mesh_kernel import mesh_sdf_kernel
    from cosim.runtime import current, ensure_taichi

    if current() is None:
        ensure_taichi("cpu", "float64")
    mesh_sdf_kernel(points, np.ascontiguousarray(vertices[faces]), out, closest)
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
