"""Builds a scene's ``articulated:`` section: DART skeletons, their contact SDFs and mass properties.

Scene conventions carry over from kinematic rigid bodies: y is up, a link's shape is one
of our rigid shapes centred on the link's body origin (cylinders, capsules and glasses
along +y), rotations are rotation vectors (3D) or angles (2D) in radians. The shape is
both the MPM contact geometry (an SDF in the body frame) and the link's uniform mass
distribution: mass, centre of mass and inertia are integrated over the SDF's inside, so
a glass gets a glass's inertia, not a cylinder's. In 2D, DART still runs in 3D: free
links get a planar joint (x, y, angle about z), revolute joints turn about z, and masses
are per metre of depth like the MPM's. Skeletons with ``collide`` get DART collision shapes
(2D: extruded 1 m along z, ``_planar_shapes``); ``articulated.ground`` adds a static DART
floor, which the MPM does not see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cosim.couplers.sdf import (
    SDFGrid,
    function_sdf,
    placed_box_bounds,
    primitive_distance,
    primitive_extent,
    primitive_size,
    shape_sdf,
    shape_spec_sdf,
)
from cosim.engines import so3
from cosim.engines.rigid_build import GroundSpec, LinkSpec, ShapeSpec, SkeletonSpec
from cosim.errors import SceneError
from cosim.scene.shipped import resolve_asset
from cosim.scene.welded import merge_welded


@dataclass
class Articulated:
    """The built section: the engine, and per coupled body its index, name and SDF."""

    engine: object  # RigidEngine
    coupled: list[int]  # indices into engine.body_names
    names: list[str]  # "skeleton/link" of the coupled bodies
    grids: list[SDFGrid]
    n_segments: int  # actions in the sequence (one per ``hold`` macro steps)
    hold: int


def mass_properties(grid: SDFGrid, density: float | None, mass: float | None) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, centre of mass, 3x3 inertia about it) of the SDF's inside (d < 0), uniform density.

    Cells are weighted by their inside fraction clip(1/2 - d/h, 0, 1), so the volume of a box
    or sphere is right to ~0.1% at 10 cells across. 2D: mass per metre of depth, Izz the polar
    moment and Ixx = Iyy = Izz / 2 (a flat plate; the planar joint never uses them).
    """
    d, h = grid.dim, grid.spacing
    frac = np.clip(0.5 - grid.values / h, 0.0, 1.0)
    volume = float(frac.sum()) * h**d
    if volume <= 0:
        raise SceneError("a rigid link's shape has no inside at its SDF spacing; make it larger or refine sdf_spacing")
    m = mass if mass is not None else density * volume
    w = frac.reshape(-1) / frac.sum()
    x = grid.nodes().reshape(-1, d)
    com = w @ x
    r = x - com
    if d == 2:
        izz = m * float(w @ np.sum(r * r, axis=1))
        return m, np.array([*com, 0.0]), np.diag([izz / 2, izz / 2, izz])
    inertia = m * (np.eye(3) * float(w @ np.sum(r * r, axis=1)) - (r * w[:, None]).T @ r)
    return m, com, inertia


def _euler_deg(rotation, dim: int) -> tuple[float, float, float]:
    """Scene rotation (2D angle / 3D rotation vector) as the rigid specs' xyz Euler degrees."""
    if dim == 2:
        return (0.0, 0.0, math.degrees(float(rotation)))
    from scipy.spatial.transform import Rotation

    return tuple(Rotation.from_matrix(so3.scene_rotation(rotation, 3)).as_euler("xyz", degrees=True))


def _lift(v, dim: int, fill: float = 0.0):
    return None if v is None else tuple(list(v) + [fill] * (3 - len(v))) if dim == 2 else tuple(v)


DEPTH_2D = 1.0  # [m] how far a 2D link's collision shape extends along z (see _planar_shapes)


def _dart_shapes(shape, dim: int, offset, source_dir: Path) -> list[ShapeSpec]:
    """DART collision shapes of a scene shape in its link frame (``offset`` [m] moves them).

    3D: the primitive itself (y-axis shapes turned onto DART's z; a glass collides as its outer
    cylinder) or the mesh file. 2D: ``_planar_shapes``. A ring has none (validation refuses a
    colliding ring).
    """
    at = np.asarray(_lift(offset, dim) or (0.0, 0.0, 0.0), dtype=np.float64)
    if dim == 2:
        return [_moved(s, at) for s in _planar_shapes(shape)]
    if shape.type == "ring":
        return []
    if shape.type == "mesh":
        path = str((Path(source_dir) / shape.file).resolve())
        return [ShapeSpec("mesh", mesh=path, scale=(shape.scale,) * 3, position=tuple(at))]
    along_y = (-90.0, 0.0, 0.0)  # Rx(-90 deg) maps DART's z axis onto our y axis
    if shape.type == "box":
        return [ShapeSpec("box", size=tuple(shape.size), position=tuple(at))]
    if shape.type == "sphere":
        return [ShapeSpec("sphere", radius=shape.radius, position=tuple(at))]
    kind = "capsule" if shape.type == "capsule" else "cylinder"
    return [ShapeSpec(kind, radius=shape.radius, height=shape.height, position=tuple(at), rotation=along_y)]


def _planar_shapes(shape) -> list[ShapeSpec]:
    """A 2D shape extruded DEPTH_2D along z, centred on z = 0, as DART primitives.

    Every planar body lies in z = 0 (DART's xy-plane), so two extruded shapes overlap by the full
    depth along z and Bullet's contact normal is always the in-plane one (an in-plane penetration
    is millimetres, far below 1 m); the depth changes no force (DART's contacts are impulses, the
    planar joint drops their out-of-plane moments; depths of 1 mm, 5 cm and 1 m gave the same
    trajectories, measured) and matches the 2D convention of one metre of depth. Box and the 2D cylinder (a rectangle): a box; disc (sphere): a cylinder along z;
    capsule: a box and two end cylinders; glass: a bottom and two walls (a U, so things fit in it).
    """
    D = DEPTH_2D
    if shape.type == "box":
        return [ShapeSpec("box", size=(*shape.size, D))]
    if shape.type == "sphere":
        return [ShapeSpec("cylinder", radius=shape.radius, height=D)]
    r, h = shape.radius, shape.height
    if shape.type == "cylinder":
        return [ShapeSpec("box", size=(2 * r, h, D))]
    if shape.type == "capsule":
        ends = [ShapeSpec("cylinder", radius=r, height=D, position=(0.0, y, 0.0)) for y in (-h / 2, h / 2)]
        return [ShapeSpec("box", size=(2 * r, h, D)), *ends]
    if shape.type == "glass":
        t = shape.thickness
        bottom = ShapeSpec("box", size=(2 * r, t, D), position=(0.0, (t - h) / 2, 0.0))
        walls = [ShapeSpec("box", size=(t, h, D), position=(x, 0.0, 0.0)) for x in (t / 2 - r, r - t / 2)]
        return [bottom, *walls]
    return []  # a ring: refused by validation when it should collide


def _moved(shape: ShapeSpec, by: np.ndarray) -> ShapeSpec:
    return replace(shape, position=tuple(np.asarray(shape.position) + by))


_CENTRED = ("box", "sphere", "cylinder", "capsule", "ring")  # the centre of mass is the shape's centre


def _symmetric_com(shape, com: np.ndarray, centre) -> np.ndarray:
    """The integrated centre of mass with what symmetry fixes set exactly: the shape's centre for
    symmetric primitives, the axis (x, z) for a glass. The SDF grid is not centred on the shape, so
    integration puts a disc's centre of mass ~0.2 mm off its centre (at 4 cm radius, dx/2 spacing),
    enough to make a disc resting on a floor rock like an eccentric wheel (rolling ~10 cm)."""
    out = np.asarray(com, dtype=np.float64).copy()
    if shape.type in _CENTRED:
        out[:] = centre
    elif shape.type == "glass":
        out[[0, 2]] = np.asarray(centre, dtype=np.float64)[[0, 2]]
    return out


def _joint_values(value):
    """Scene q0/qd0 in DART's joint coordinates (2D free = planar: [x, y, angle])."""
    if value is None:
        return None
    return [float(value)] if isinstance(value, (int, float)) else [float(v) for v in value]


def _link_spec(link, dim: int, grid: SDFGrid, shapes: list[ShapeSpec]) -> LinkSpec:
    j = link.joint
    mass, com, inertia = mass_properties(grid, link.density, link.mass)
    com = _symmetric_com(link.shape, com, _lift(link.offset, dim) or (0.0, 0.0, 0.0))
    joint = "planar" if (dim == 2 and j.type == "free") else j.type
    if dim == 2 and j.type == "revolute":
        axis = (0.0, 0.0, 1.0)
    else:
        axis = _lift(j.axis, dim) or (0.0, 0.0, 1.0)
    return LinkSpec(
        name=link.name,
        shapes=shapes,
        mass=mass,
        com=tuple(com),
        inertia=inertia,
        joint=joint,
        parent=j.parent,
        origin_position=_lift(j.position, dim) or (0.0, 0.0, 0.0),
        origin_rotation=_euler_deg(j.rotation, dim),
        axis=axis,
        lower=j.lower,
        upper=j.upper,
        damping=j.damping,
        q0=_joint_values(j.q0),
        qd0=_joint_values(j.qd0),
    )


def _skeleton_spec(skel, dim: int, dx: float, source_dir: Path, key: str) -> tuple[SkeletonSpec, dict[str, SDFGrid]]:
    """The DART spec of one skeleton and the SDFs of its links (primitive skeletons)."""
    grids = {}
    links = []
    for i, link in enumerate(skel.links):
        spacing = link.sdf_spacing or 0.5 * dx
        grid = shape_sdf(link.shape, dim, spacing, 3 * dx, source_dir, f"{key}.links[{i}].shape")
        if link.offset is not None:
            grid.origin = grid.origin + np.asarray(link.offset, float)
        grids[link.name] = grid
        shapes = _dart_shapes(link.shape, dim, link.offset, source_dir) if skel.collide else []
        links.append(_link_spec(link, dim, grid, shapes))
    spec = SkeletonSpec(name=skel.name, links=links, controls=dict(skel.controls), collide=skel.collide)
    return spec, grids


def _base_transform(skel) -> np.ndarray | None:
    if skel.position is None and not np.any(skel.rotation):
        return None
    T = np.eye(4)
    T[:3, :3] = so3.scene_rotation(skel.rotation, 3)
    T[:3, 3] = skel.position or (0.0, 0.0, 0.0)
    return T


def placed_shape_sdf(placed, spacing: float, padding: float) -> SDFGrid:
    """The link-frame SDF of one of our primitive shapes placed by ``position`` / ``rotation``."""
    shape = placed.shape
    if shape.type in ("mesh", "ring"):
        raise SceneError(f"contact_shapes: a {shape.type} cannot be placed on a URDF link; use a primitive")
    R, t = so3.scene_rotation(placed.rotation, 3), np.asarray(placed.position, float)
    size = primitive_size(shape)
    lo, hi = placed_box_bounds(primitive_extent(shape.type, 3, **size), R, t)
    return function_sdf(lambda p: primitive_distance(shape.type, (p - t) @ R, **size), lo, hi, spacing, padding)


def _urdf_spec(skel, source_dir: Path, key: str) -> SkeletonSpec:
    return SkeletonSpec(
        name=skel.name,
        urdf=str(resolve_asset(skel.urdf, source_dir, f"{key}.urdf")),
        fixed_base=skel.fixed_base,
        base_transform=_base_transform(skel),
        package_dirs={
            k: str(resolve_asset(v, source_dir, f"{key}.package_dirs.{k}")) for k, v in skel.package_dirs.items()
        },
        initial_positions=dict(skel.initial_positions),
        collide=skel.collide,
        controls=dict(skel.controls),
    )


def build_articulated(scene, dx: float) -> Articulated:
    """DART engine (dt = the frame), coupled bodies and their SDFs for ``scene.articulated``."""
    from cosim.engines.rigid import RigidEngine

    spec = scene.articulated
    dim = scene.dim
    specs, link_grids = [], {}
    for i, skel in enumerate(spec.skeletons):
        if skel.urdf is not None:
            specs.append(_urdf_spec(skel, scene.source_dir, f"articulated.skeletons[{i}]"))
            continue
        s, grids = _skeleton_spec(skel, dim, dx, scene.source_dir, f"articulated.skeletons[{i}]")
        specs.append(s)
        link_grids.update({f"{skel.name}/{name}": g for name, g in grids.items()})
    gravity = _lift(scene.gravity, dim)
    ground = None
    if spec.ground is not None:  # y is up in scenes
        ground = GroundSpec(height=spec.ground.height, up=1, friction=spec.ground.friction)
    engine = RigidEngine(specs, scene.time.frame_dt, gravity=gravity, collision=spec.collision, ground=ground)
    coupled, names, grids = [], [], []
    for skel in spec.skeletons:
        for i, full in enumerate(engine.body_names):
            sk, link = full.split("/", 1)
            if sk != skel.name or not _is_coupled(skel, link):
                continue
            grid = link_grids.get(full)
            if grid is None and link in skel.contact_shapes:  # URDF link with our contact shape
                grid = placed_shape_sdf(skel.contact_shapes[link], 0.5 * dx, 3 * dx)
            if grid is None:  # URDF link: its collision shapes
                geometry = engine.link_geometry(full)
                if not geometry:
                    continue
                grid = shape_spec_sdf(geometry, 0.5 * dx, 3 * dx, key=f"{full} collision")
            coupled.append(i)
            names.append(full)
            grids.append(grid)
    coupled, names, grids = merge_welded(engine, coupled, names, grids, dim, 3 * dx)
    n_segments = math.ceil(scene.steps / spec.actions.hold)
    return Articulated(engine, coupled, names, grids, n_segments, spec.actions.hold)


def _is_coupled(skel, link: str) -> bool:
    if skel.urdf is None:
        return next(lk.couple for lk in skel.links if lk.name == link)
    if skel.couple == "all":
        return True
    return skel.couple != "none" and link in skel.couple


def link_shapes(scene, names: list[str]) -> list:
    """The scene shape of each coupled body "skeleton/link" (None for URDF links)."""
    shapes = {f"{skel.name}/{link.name}": link.shape for skel in scene.articulated.skeletons for link in skel.links}
    return [shapes.get(name) for name in names]
