"""Particles from shapes: a regular lattice clipped to a primitive or a mesh.

Each particle stands for one lattice cell, so its volume is spacing^d and a
body's mass is density times its sampled volume. A seeded jitter (a fraction
of the spacing) breaks the lattice's symmetry reproducibly.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from cosim.engines.meshes import load_mesh, require_watertight
from cosim.errors import SceneError

# The most lattice points one shape may sample: ~2 GB of positions in float64 3D, and about
# 20 GB of MPM state (x, v, F, C, material per particle) were they all kept.
MAX_LATTICE_POINTS = 10**8


def lattice(lo: np.ndarray, hi: np.ndarray, spacing: float, key: str = "shape") -> np.ndarray:
    """Cell-centred lattice points covering the box [lo, hi]; refuses more than ``MAX_LATTICE_POINTS``
    (``key`` names the shape in the error)."""
    count = math.prod(max(0, math.ceil((b - a) / spacing)) for a, b in zip(lo, hi))
    if count > MAX_LATTICE_POINTS:
        raise SceneError(
            f"{key}: sampling this shape at spacing {spacing:g} m takes {count:.3g} lattice points, more than "
            f"{MAX_LATTICE_POINTS:.0e}; use a coarser grid (dx) or spacing, or a smaller shape"
        )
    axes = [np.arange(a + 0.5 * spacing, b, spacing) for a, b in zip(lo, hi)]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grids], axis=-1)


def inside_box(points: np.ndarray, center, size) -> np.ndarray:
    return np.all(np.abs(points - np.asarray(center)) <= 0.5 * np.asarray(size), axis=1)


def inside_sphere(points: np.ndarray, center, radius: float) -> np.ndarray:
    return np.linalg.norm(points - np.asarray(center), axis=1) <= radius


def inside_cylinder(points: np.ndarray, center, radius: float, height: float, axis: str) -> np.ndarray:
    k = "xyz".index(axis)
    rel = points - np.asarray(center)
    radial = np.delete(rel, k, axis=1)
    return (np.linalg.norm(radial, axis=1) <= radius) & (np.abs(rel[:, k]) <= 0.5 * height)


def load_volume_mesh(path: Path, scale, center, key: str):
    """Load a watertight mesh, scale it (scalar or per axis) and centre its bounding box at ``center`` [m]."""
    mesh = load_mesh(path, scale, key, SceneError)
    require_watertight(
        mesh,
        f"{key}: mesh {path}",
        "it has no inside to fill with particles",
        "close its holes (e.g. trimesh.repair.fill_holes, or remesh it) or use a primitive shape",
        SceneError,
    )
    mesh.apply_translation(np.asarray(center) - mesh.bounds.mean(axis=0))
    return mesh


def sample_shape(
    shape, dim: int, spacing: float, jitter: float, rng: np.random.Generator, key: str, source_dir: Path
) -> np.ndarray:
    """Particle positions (n, dim) filling ``shape`` (a validated scene shape)."""
    center = np.asarray(shape.center, dtype=np.float64)
    if shape.type == "box":
        half = 0.5 * np.asarray(shape.size)
        pts = lattice(center - half, center + half, spacing, key)
    elif shape.type == "sphere":
        pts = lattice(center - shape.radius, center + shape.radius, spacing, key)
        pts = pts[inside_sphere(pts, center, shape.radius)]
    elif shape.type == "cylinder":
        ext = np.full(dim, max(shape.radius, 0.5 * shape.height))
        pts = lattice(center - ext, center + ext, spacing, key)
        pts = pts[inside_cylinder(pts, center, shape.radius, shape.height, shape.axis)]
    elif shape.type == "mesh":
        mesh = load_volume_mesh((source_dir / shape.file).resolve(), shape.scale, center, key)
        pts = lattice(mesh.bounds[0], mesh.bounds[1], spacing, key)
        pts = pts[mesh.contains(pts)]
    else:  # the schema admits no other type
        raise SceneError(f"{key}.type: unknown shape '{shape.type}'")
    if len(pts) == 0:
        raise SceneError(
            f"{key}: the shape holds no particle at spacing {spacing:g} m; make it larger or the spacing finer"
        )
    if jitter > 0:
        pts = pts + rng.uniform(-0.5 * jitter * spacing, 0.5 * jitter * spacing, size=pts.shape)
    return pts
