"""Rigid-body signed distance fields on a compact body-frame grid.

Distances are in metres, negative inside the body. A field is sampled at the
nodes of a regular grid covering the body's bounding box plus ``padding``
(node spacing ``spacing``), then looked up anywhere by multilinear
interpolation. The normal is the SDF's gradient: the exact gradient at the
nodes (closed form for primitives, the direction to the closest surface point
for meshes), interpolated the same way and normalised, so it turns smoothly
around edges and corners instead of jumping between face normals (finite
differences of the node distances were 3-4x less accurate one cell from a box
edge: 14 against 4 degrees, measured).

Primitives are evaluated in closed form. Meshes (any format trimesh reads,
watertight) are evaluated exactly by a brute-force Taichi kernel: the distance
to the closest point of every triangle, the sign from the generalised winding
number. Mesh fields are cached on disk as ``.npz`` files keyed by a SHA-256 of
the vertices, faces and settings (loaded with ``allow_pickle=False``).

Body frame: the primitive's centre is the origin; cylinders, capsules and
glasses stand along +y (a glass's opening faces +y).
"""

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import taichi as ti

from cosim.engines.meshes import load_mesh, require_watertight
from cosim.engines.shapes import CONTAINER_KINDS, PRIMITIVE_SIZES
from cosim.errors import SceneError

SDF_VERSION = "2"  # bump when the computation changes: invalidates the cache


@dataclass
class SDFGrid:
    """Signed distances ``values`` at nodes origin + spacing * index (body frame)."""

    origin: np.ndarray  # (d,) [m]
    spacing: float  # [m]
    values: np.ndarray  # (n_0, ..., n_{d-1}) [m], negative inside
    normals: np.ndarray | None = None  # (*values.shape, d) exact gradient at the nodes, if known

    def gradients(self) -> np.ndarray:
        """SDF gradient at the nodes, (*shape, d): the exact one when known, else central
        differences (one-sided at the border)."""
        if self.normals is not None:
            return self.normals
        return np.stack(np.gradient(self.values, self.spacing), axis=-1)

    @property
    def dim(self) -> int:
        return self.values.ndim

    def nodes(self) -> np.ndarray:
        """Body-frame node positions, shape (*values.shape, d)."""
        axes = [self.origin[k] + self.spacing * np.arange(n) for k, n in enumerate(self.values.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance and unit normal at body-frame ``points`` (n, d) (host-side twin of ``SDFField``)."""
        d = self.dim
        shape = np.asarray(self.values.shape)
        upper = self.origin + self.spacing * (shape - 1)
        clamped = np.clip(points, self.origin, upper)
        outside = np.linalg.norm(points - clamped, axis=1)
        rel = (clamped - self.origin) / self.spacing
        base = np.clip(np.floor(rel).astype(int), 0, shape - 2)
        frac = rel - base
        node_grad = self.gradients()
        dist = np.zeros(len(points))
        grad = np.zeros((len(points), d))
        for corner in np.ndindex(*([2] * d)):
            c = np.asarray(corner)
            index = tuple((base + c).T)
            weight = np.prod(np.where(c, frac, 1.0 - frac), axis=1)
            dist += weight * self.values[index]
            grad += weight[:, None] * node_grad[index]
        normal = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
        return dist + outside, normal


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


def _grid_over(lo: np.ndarray, hi: np.ndarray, spacing: float, padding: float) -> tuple[np.ndarray, tuple]:
    origin = lo - padding
    counts = np.ceil((hi + padding - origin) / spacing).astype(int) + 1
    return origin, tuple(int(c) for c in counts)


def function_sdf(distance, lo: np.ndarray, hi: np.ndarray, spacing: float, padding: float) -> SDFGrid:
    """A closed-form SDF ``distance(points (..., d))`` sampled over the box [lo, hi] plus padding."""
    origin, counts = _grid_over(np.asarray(lo, float), np.asarray(hi, float), spacing, padding)
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


# ---------------------------------------------------------------- meshes
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
    origin, counts = _grid_over(vertices.min(axis=0), vertices.max(axis=0), spacing, padding)
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


def shape_sdf(shape, dim: int, spacing: float, padding: float, source_dir: Path, key: str) -> SDFGrid:
    """The SDF of a validated scene ``RigidShape`` (primitive or mesh file)."""
    if shape.type == "mesh":
        path = (Path(source_dir) / shape.file).resolve()
        mesh = load_mesh(path, shape.scale, f"{key}.file", SceneError)
        return mesh_sdf(mesh, spacing, padding, key=f"{key}.file ({path.name})")
    return primitive_sdf(shape.type, dim, spacing, padding, **primitive_size(shape))


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


# ---------------------------------------------------------------- Taichi lookup
@ti.data_oriented
class SDFField:
    """An ``SDFGrid`` uploaded to Taichi (distances and node gradients), looked up in kernels."""

    def __init__(self, grid: SDFGrid):
        self.dim = grid.dim
        self.shape = tuple(grid.values.shape)
        self.origin = ti.Vector([float(o) for o in grid.origin])
        self.spacing = float(grid.spacing)
        self.values = ti.field(float, shape=self.shape)
        self.grads = ti.Vector.field(self.dim, float, shape=self.shape)
        real = np.float64 if self.values.dtype == ti.f64 else np.float32
        self.values.from_numpy(grid.values.astype(real))
        self.grads.from_numpy(grid.gradients().astype(real))

    @ti.func
    def _cell(self, p):
        """The interpolation cell of body-frame point p: (base node, fraction, distance outside the grid)."""
        upper = self.origin + self.spacing * (ti.Vector(self.shape) - 1)
        clamped = ti.min(ti.max(p, self.origin), upper)
        out2 = (p - clamped).norm_sqr()
        outside = out2 / ti.sqrt(ti.max(out2, 1e-30))  # |p - clamped|, with a finite adjoint at 0
        rel = (clamped - self.origin) / self.spacing
        base = ti.min(ti.max(ti.cast(ti.floor(rel), ti.i32), 0), ti.Vector(self.shape) - 2)
        return base, rel - ti.cast(base, float), outside

    @ti.func
    def _weight(self, frac, corner):
        weight = 1.0
        for k in ti.static(range(self.dim)):
            weight *= frac[k] if corner[k] else 1.0 - frac[k]
        return weight

    @ti.func
    def distance(self, p):
        """Signed distance [m] at body-frame point p (cheaper than ``distance_normal``)."""
        base, frac, outside = self._cell(p)
        dist = 0.0
        for corner in ti.static(ti.grouped(ti.ndrange(*([2] * self.dim)))):
            dist += self._weight(frac, corner) * self.values[base + corner]
        return dist + outside

    @ti.func
    def distance_normal(self, p):
        """Signed distance [m] and unit outward normal at body-frame point p."""
        base, frac, outside = self._cell(p)
        dist = 0.0
        grad = ti.Vector.zero(float, self.dim)
        for corner in ti.static(ti.grouped(ti.ndrange(*([2] * self.dim)))):
            weight = self._weight(frac, corner)
            dist += weight * self.values[base + corner]
            grad += weight * self.grads[base + corner]
        # sqrt(|g|^2 + tiny): the normalisation keeps a finite adjoint where the
        # interpolated gradient vanishes (a box's centre, medial axes)
        return dist + outside, grad / ti.sqrt(grad.norm_sqr() + 1e-24)
