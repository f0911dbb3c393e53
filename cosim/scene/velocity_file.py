"""A soft body's initial velocity read from a file: ``mpm.bodies[i].velocity: {file: PATH}``.

PATH (relative to the scene file) holds one of two things:

- **one row per particle**: an (n, dim) array [m/s] in a ``.npy``, a ``.csv`` (numbers separated
  by commas, ``#`` starts a comment) or an ``.npz`` (its array ``velocities``, or its only array),
  the rows in the order the body's particles are sampled: the order of ``x_<body>[0]`` in a run's
  ``trajectory.npz``. These particles start with C = 0 (a list of rows has no gradient).
- **a point cloud**: an ``.npz`` with ``positions`` (m, dim) [m] and ``velocities`` (m, dim) [m/s],
  interpolated linearly to the particles (barycentric over the Delaunay triangulation of the
  positions, as ``scipy.interpolate.LinearNDInterpolator`` does); a particle outside the cloud's
  convex hull takes the velocity of the nearest point. Linear rather than nearest-neighbour
  because it has a gradient: a particle inside the hull starts with C = the interpolant's
  gradient there (constant over each triangle or tetrahedron), one outside with C = 0.

Every problem is a ``SceneError`` naming the key, the file and the fix.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from cosim.errors import SceneError

SUFFIXES = (".npy", ".npz", ".csv")


def file_problems(path: Path, key: str) -> list[str]:
    """What is wrong with the velocity file at ``path`` before reading it (``key``: its scene key)."""
    if path.suffix.lower() not in SUFFIXES:
        return [f"{key}: {path} is not a .npy, .npz or .csv file; save the velocities in one of those"]
    if not path.is_file():
        return [f"{key}: file not found: {path} (a relative path starts from the scene file's folder)"]
    return []


def file_velocity(path: Path, pts: np.ndarray, key: str, body: str) -> tuple[np.ndarray, np.ndarray]:
    """Initial velocities v (n, dim) [m/s] and APIC affine velocities C (n, dim, dim) [1/s] of the
    particles at ``pts`` (n, dim) [m] of ``body``, from the file at ``path``; errors name ``key``."""
    arrays = read_arrays(path, key)
    n, dim = pts.shape
    velocities = _checked(arrays, "velocities", path, key, dim)
    if "positions" not in arrays:
        if len(velocities) != n:
            raise SceneError(
                f"{key}.file: {path} has {len(velocities)} rows of velocities but body '{body}' has {n} "
                f"particles; give one row per particle in the order they are sampled (that of x_{body}[0] in "
                "a run's trajectory.npz), or an .npz with positions and velocities to interpolate"
            )
        return velocities, np.zeros((n, dim, dim))
    positions = _checked(arrays, "positions", path, key, dim)
    if len(positions) != len(velocities):
        raise SceneError(
            f"{key}.file: {path} has {len(positions)} positions but {len(velocities)} velocities; "
            "give one velocity per point of the cloud"
        )
    return interpolate_cloud(positions, velocities, pts, f"{key}.file: {path}")


def read_arrays(path: Path, key: str) -> dict[str, np.ndarray]:
    """The file's ``velocities`` and, for a point cloud, ``positions`` (as stored, not yet checked)."""
    try:
        if path.suffix.lower() == ".csv":
            return {"velocities": np.loadtxt(path, delimiter=",", comments="#", ndmin=2)}
        data = np.load(path, allow_pickle=False)
        if isinstance(data, np.ndarray):
            return {"velocities": data}
        with data:
            return _npz_arrays(dict(data.items()), path, key)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):  # not numbers, or a pickle
        raise SceneError(
            f"{key}.file: cannot read {path} as numbers; save a .npy or .npz with numpy.save / numpy.savez, "
            "or a .csv with one row per particle and one column per axis, separated by commas"
        ) from None


def _npz_arrays(arrays: dict[str, np.ndarray], path: Path, key: str) -> dict[str, np.ndarray]:
    names = sorted(arrays)
    if "velocities" in arrays:
        return {k: arrays[k] for k in ("positions", "velocities") if k in arrays}
    if len(names) == 1 and names[0] != "positions":
        return {"velocities": arrays[names[0]]}
    raise SceneError(
        f"{key}.file: {path} holds the arrays {names}; give 'velocities' (one row per particle) or "
        "'positions' and 'velocities' (a point cloud to interpolate)"
    )


def _checked(arrays: dict[str, np.ndarray], name: str, path: Path, key: str, dim: int) -> np.ndarray:
    """``arrays[name]`` as float64 (rows, dim), every value finite."""
    try:
        values = np.asarray(arrays[name], dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{key}.file: '{name}' in {path} does not hold numbers") from None
    if values.ndim != 2 or values.shape[1] != dim or len(values) == 0:
        raise SceneError(
            f"{key}.file: '{name}' in {path} has shape {values.shape}; it must be (rows, {dim}): "
            f"one row per point, one column per axis of this {dim}D scene"
        )
    bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    if len(bad):
        raise SceneError(
            f"{key}.file: '{name}' in {path} is not finite in {len(bad)} rows (the first is row {bad[0]}); "
            "every value must be a finite number"
        )
    return values


def interpolate_cloud(
    positions: np.ndarray, velocities: np.ndarray, pts: np.ndarray, where: str
) -> tuple[np.ndarray, np.ndarray]:
    """v (n, dim) [m/s] and C = grad v (n, dim, dim) [1/s] at ``pts`` of the linear interpolant of
    ``velocities`` (m, dim) given at ``positions`` (m, dim) [m]; outside their convex hull (or in a
    flat simplex) the nearest point's velocity and C = 0. ``where`` prefixes errors."""
    from scipy.spatial import Delaunay, QhullError, cKDTree

    n, dim = pts.shape
    try:
        triangulation = Delaunay(positions)
    except (QhullError, ValueError):
        extent, flat = ("area", "line") if dim == 2 else ("volume", "plane")
        raise SceneError(
            f"{where}: the positions span no {extent} (fewer than {dim + 1} points, or all on one {flat}); "
            "give a cloud of points around the body"
        ) from None
    simplex = triangulation.find_simplex(pts)
    transform = triangulation.transform[np.maximum(simplex, 0)]
    inside = (simplex >= 0) & np.isfinite(transform).all(axis=(1, 2))
    v, C = np.empty((n, dim)), np.zeros((n, dim, dim))
    corners = velocities[triangulation.simplices[simplex[inside]]]  # (k, dim + 1, dim)
    v[inside], C[inside] = _barycentric(transform[inside], corners, pts[inside])
    if not inside.all():
        _, nearest = cKDTree(positions).query(pts[~inside])
        v[~inside] = velocities[nearest]
    return v, C


def _barycentric(transform: np.ndarray, corners: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Value and gradient at ``pts`` (k, dim) of the linear function taking ``corners`` (k, dim + 1, dim)
    at its simplex's vertices; ``transform`` (k, dim + 1, dim) is scipy's Delaunay.transform of each:
    barycentric coordinates b = T (x - r), the last one 1 - sum b."""
    dim = pts.shape[1]
    T, origin = transform[:, :dim, :], transform[:, dim, :]
    b = np.einsum("kij,kj->ki", T, pts - origin)
    b = np.concatenate([b, 1.0 - b.sum(axis=1, keepdims=True)], axis=1)
    grad_b = np.concatenate([T, -T.sum(axis=1, keepdims=True)], axis=1)  # d b_c / d x: (k, dim + 1, dim)
    return np.einsum("kc,kcd->kd", b, corners), np.einsum("kci,kcj->kij", corners, grad_b)
