"""Rigid-body signed distance fields of primitives and scene shapes, on a compact body-frame grid.

Distances are in metres, negative inside the body. Primitives are evaluated in
closed form and sampled on a grid (``sdf_grid.SDFGrid``) over their bounding box
plus ``padding``; mesh files go to ``sdf_mesh.mesh_sdf``. The grid and its
interpolated lookup live in ``sdf_grid``, its Taichi twin ``SDFField`` in ``sdf_field``;
both are importable from here too (``SDFField`` on first use: building grids imports no Taichi). Shape kinds and their size keys come from
``cosim.engines.shapes``.

Body frame: the primitive's centre is the origin; cylinders, capsules and
glasses stand along +y (a glass's opening faces +y).
"""

from pathlib import Path

import numpy as np

from cosim.couplers.sdf_grid import SDFGrid, grid_over
from cosim.couplers.sdf_mesh import mesh_sdf
from cosim.engines.meshes import load_mesh
from cosim.engines.shapes import CONTAINER_KINDS, PRIMITIVE_SIZES
from cosim.errors import SceneError

__all__ = [
    "SDFGrid",
    "function_sdf",
    "in_cavity",
    "is_container",
    "mesh_sdf",
    "placed_box_bounds",
    "primitive_distance",
    "primitive_extent",
    "primitive_sdf",
    "primitive_size",
    "shape_sdf",
    "shape_spec_sdf",
    "surface_points",
]


def __getattr__(name: str):
    """``SDFField`` imported when first asked for (it imports Taichi; grids need only NumPy)."""
    if name == "SDFField":
        from cosim.couplers.sdf_field import SDFField

        return SDFField
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


# ---------------------------------------------------------------- primitives
def _box(p: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = np.abs(p) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _radial(p: np.ndarray) -> np.ndarray:
    """Distance from the y axis (3D) or |x| (2D)."""
    return np.linalg.norm(np.delete(p, 1, axis=-1), axis=-1)


def _cylinder(p: np.ndarray, radius: float, half_height: float) -> np.ndarray:
    q = np.stack([_radial(p), p[..., 1]], axis=-1)
    return _box(q, np.array([radius, half_height]))


def primitive_distance(kind: str, p: np.ndarray, **size) -> np.ndarray:
    """Closed-form signed distance of a primitive centred at the origin.

    box: ``half`` (d,); sphere: ``radius``; cylinder: ``radius``, ``height``;
    capsule: ``radius``, ``height`` (of the straight part); glass: ``radius``,
    ``height``, ``thickness`` (an open-topped cup, wall and bottom that thick);
    ring (2D): ``radius`` (of the wall's middle), ``thickness``.
    """
    if kind == "box":
        return _box(p, np.asarray(size["half"], dtype=np.float64))
    if kind == "sphere":
        return np.linalg.norm(p, axis=-1) - size["radius"]
    if kind == "cylinder":
        return _cylinder(p, size["radius"], 0.5 * size["height"])
    if kind == "capsule":
        axis_point = np.zeros_like(p)
        axis_point[..., 1] = np.clip(p[..., 1], -0.5 * size["height"], 0.5 * size["height"])
        return np.linalg.norm(p - axis_point, axis=-1) - size["radius"]
    if kind == "glass":
        r, h, t = size["radius"], size["height"], size["thickness"]
        outer = _cylinder(p, r, 0.5 * h)
        cavity = p.copy()
        cavity[..., 1] -= 0.5 * t + 0.5  # the cavity starts t above the bottom and runs past the rim
        inner = _cylinder(cavity, r - t, 0.5 * (h - t) + 0.5)
        return np.maximum(outer, -inner)
    if kind == "ring":
        return np.abs(np.linalg.norm(p, axis=-1) - size["radius"]) - 0.5 * size["thickness"]
    raise ValueError(f"unknown primitive '{kind}'")


def primitive_extent(kind: str, dim: int, **size) -> np.ndarray:
    """Half extent (d,) of the primitive's bounding box."""
    if kind == "box":
        return np.asarray(size["half"], dtype=np.float64)
    r = size["radius"] + (0.5 * size["thickness"] if kind == "ring" else 0.0)
    ext = np.full(dim, r)
    if kind in ("cylinder", "glass"):
        ext[1] = 0.5 * size["height"]
    elif kind == "capsule":
        ext[1] = 0.5 * size["height"] + r
    return ext


def function_sdf(distance, lo: np.ndarray, hi: np.ndarray, spacing: float, padding: float) -> SDFGrid:
    """A closed-form SDF ``distance(points (..., d))`` sampled over the box [lo, hi] plus padding."""
    origin, counts = grid_over(np.asarray(lo, float), np.asarray(hi, float), spacing, padding)
    grid = SDFGrid(origin, spacing, np.zeros(counts))
    nodes = grid.nodes()
    grid.values = distance(nodes)
    # the closed form's gradient by central differences far below the spacing (exact away
    # from kinks; on a medial axis it averages the two sides, which the lookup normalises)
    eps = 1e-6 * spacing
    grid.normals = np.stack(
        [(distance(nodes + eps * e) - distance(nodes - eps * e)) / (2 * eps) for e in np.eye(len(lo))], axis=-1
    )
    return grid


def primitive_sdf(kind: str, dim: int, spacing: float, padding: float, **size) -> SDFGrid:
    """A primitive's SDF sampled on its padded bounding box."""
    ext = primitive_extent(kind, dim, **size)
    return function_sdf(lambda p: primitive_distance(kind, p, **size), -ext, ext, spacing, padding)


# DART's shape conventions (cosim.engines.rigid_build.ShapeSpec): cylinders and capsules along z
_Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, y, z) -> (x, z, -y)


def _spec_distance(spec, p: np.ndarray) -> np.ndarray:
    """Signed distance of a rigid-engine ShapeSpec at points in its own frame."""
    size = _size_keywords(spec.kind, spec)
    if spec.kind in ("box", "sphere"):
        return primitive_distance(spec.kind, p, **size)
    return primitive_distance(spec.kind, p @ _Z_TO_Y.T, **size)


def _spec_half_extent(spec) -> np.ndarray:
    """Half extent (3,) of a ShapeSpec's bounding box in its own frame (DART's axis is z)."""
    ext = primitive_extent(spec.kind, 3, **_size_keywords(spec.kind, spec))
    return ext if spec.kind in ("box", "sphere") else np.abs(_Z_TO_Y.T @ ext)


def shape_spec_sdf(geometry: list, spacing: float, padding: float, key: str) -> SDFGrid:
    """The body-frame SDF of a link's shapes [(ShapeSpec, 4x4 pose in the body frame)] (URDF
    collision geometry): one mesh, or the union (minimum) of primitives."""
    meshes = [(g, T) for g, T in geometry if g.kind == "mesh"]
    if meshes:
        if len(geometry) > 1:
            raise SceneError(f"{key}: a link with a mesh must have no other collision shapes (got {len(geometry)})")
        spec, T = meshes[0]
        mesh = load_mesh(spec.mesh, spec.scale, key, SceneError)
        mesh.apply_transform(T)
        return mesh_sdf(mesh, spacing, padding, key=f"{key} ({Path(spec.mesh).name})")
    bounds = [placed_box_bounds(_spec_half_extent(g), T[:3, :3], T[:3, 3]) for g, T in geometry]

    def union(p: np.ndarray) -> np.ndarray:
        return np.min([_spec_distance(g, (p - T[:3, 3]) @ T[:3, :3]) for g, T in geometry], axis=0)

    lo, hi = np.min([b[0] for b in bounds], axis=0), np.max([b[1] for b in bounds], axis=0)
    return function_sdf(union, lo, hi, spacing, padding)


def placed_box_bounds(half: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) of a box of half extents ``half`` rotated by R and moved by t."""
    corners = (np.array(list(np.ndindex(2, 2, 2))) * 2.0 - 1.0) * half
    placed = corners @ R.T + t
    return placed.min(axis=0), placed.max(axis=0)


def shape_sdf(shape, dim: int, spacing: float, padding: float, source_dir: Path, key: str) -> SDFGrid:
    """The SDF of a validated scene ``RigidShape`` (primitive or mesh file); refuses a shape with no
    inside at ``spacing`` [m] (thinner than an SDF cell), which the contact models cannot see through."""
    if shape.type == "mesh":
        path = (Path(source_dir) / shape.file).resolve()
        mesh = load_mesh(path, shape.scale, f"{key}.file", SceneError)
        grid = mesh_sdf(mesh, spacing, padding, key=f"{key}.file ({path.name})")
    else:
        grid = primitive_sdf(shape.type, dim, spacing, padding, **primitive_size(shape))
    if grid.values.min() >= 0.0:
        raise SceneError(
            f"{key}: no SDF node lies inside the shape at the SDF spacing {spacing:.3g} m (its thinnest part "
            f"is thinner than that): the particles would not see it; make it thicker or set sdf_spacing finer"
        )
    return grid


def primitive_size(shape) -> dict:
    """The size keywords of ``primitive_distance`` from a scene ``RigidShape``."""
    return _size_keywords(shape.type, shape)


def _size_keywords(kind: str, shape) -> dict:
    """``primitive_distance``'s keywords from any object with the kind's size attributes
    (``shapes.PRIMITIVE_SIZES``): a box's full ``size`` becomes the ``half`` extents [m]."""
    if kind == "box":
        return {"half": 0.5 * np.asarray(shape.size, dtype=np.float64)}
    return {k: getattr(shape, k) for k in PRIMITIVE_SIZES[kind] if getattr(shape, k) is not None}


def is_container(shape) -> bool:
    """Whether a scene ``RigidShape`` has a cavity that holds material (a glass, a ring)."""
    return shape.type in CONTAINER_KINDS


def in_cavity(shape, p: np.ndarray) -> np.ndarray:
    """Which body-frame points (n, d) are held by a container shape: inside a glass's cup
    (below the rim, above the bottom, within the inner wall) or a ring's inner disc."""
    size = primitive_size(shape)
    if shape.type == "ring":
        return np.linalg.norm(p, axis=-1) < size["radius"] - 0.5 * size["thickness"]
    if shape.type == "glass":
        r, h, t = size["radius"], size["height"], size["thickness"]
        return (_radial(p) < r - t) & (p[..., 1] > -0.5 * h + t) & (p[..., 1] <= 0.5 * h)
    raise ValueError(f"a {shape.type} is not a container")


def surface_points(grid: SDFGrid) -> np.ndarray:
    """Body-frame nodes within half a spacing of the surface (for drawing the body)."""
    nodes = grid.nodes().reshape(-1, grid.dim)
    return nodes[np.abs(grid.values.ravel()) <= 0.5 * grid.spacing]
