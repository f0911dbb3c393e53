"""Rigid-body specs built as DART skeletons: mass properties, DART shapes, skeletons from links.

The specs (``ShapeSpec``, ``LinkSpec``, ``SkeletonSpec``) and their frames and units are in
``rigid_specs``; URDF skeletons in ``urdf``. Both stay importable from here. Units are SI: masses [kg],
densities [kg/m^3], inertias [kg m^2] about the centre of mass in body axes.
"""

from __future__ import annotations

import math
from pathlib import Path

import dartpy as dart
import numpy as np

from cosim.engines.meshes import load_mesh, require_watertight
from cosim.engines.rigid_specs import (
    CONTROL_MODES,
    JOINT_TYPES,
    SHAPE_KINDS,
    GroundSpec,
    LinkSpec,
    ShapeSpec,
    SkeletonSpec,
    dof_vector,
    euler_xyz_deg,
    isometry,
    make_transform,
)
from cosim.engines.shapes import required_keys
from cosim.engines.urdf import build_urdf_skeleton, resolve_uri, urdf_geometry
from cosim.errors import InputError

__all__ = [
    "CONTROL_MODES",
    "JOINT_TYPES",
    "SHAPE_KINDS",
    "GroundSpec",
    "LinkSpec",
    "ShapeSpec",
    "SkeletonSpec",
    "attach_shape",
    "build_ground",
    "build_link_skeleton",
    "build_skeleton",
    "build_urdf_skeleton",
    "check_shape",
    "dart_shape",
    "dof_vector",
    "euler_xyz_deg",
    "link_mass_properties",
    "load_mesh",
    "make_transform",
    "resolve_uri",
    "shape_mass_properties",
    "urdf_geometry",
]


# ---------------------------------------------------------------------------------------- mass properties


def shape_mass_properties(shape: ShapeSpec, density: float) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, COM in the body frame, inertia about the COM in body axes) of a uniform shape."""
    volume, com, inertia_unit = _unit_density_properties(shape)
    T = shape.transform()
    R = T[:3, :3]
    return density * volume, T[:3, :3] @ com + T[:3, 3], density * (R @ inertia_unit @ R.T)


def _unit_density_properties(shape: ShapeSpec) -> tuple[float, np.ndarray, np.ndarray]:
    """Volume, COM and inertia (density 1) in the shape's own frame, closed form except for meshes."""
    k = shape.kind
    if k == "mesh":
        mesh = load_mesh(shape.mesh, shape.scale)
        require_watertight(
            mesh,
            f"mesh {shape.mesh}",
            "its volume and inertia are undefined",
            "repair/close the mesh or give the link's mass and inertia explicitly",
        )
        return float(mesh.volume), np.asarray(mesh.center_mass), np.asarray(mesh.moment_inertia)
    if k == "box":
        a, b, c = shape.size
        m = a * b * c
        return m, np.zeros(3), m / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])
    r = shape.radius
    if k == "sphere":
        m = 4.0 / 3.0 * math.pi * r**3
        return m, np.zeros(3), 0.4 * m * r * r * np.eye(3)
    h = shape.height
    mc = math.pi * r * r * h
    if k == "cylinder":
        ixx = mc * (3 * r * r + h * h) / 12.0
        return mc, np.zeros(3), np.diag([ixx, ixx, 0.5 * mc * r * r])
    ms = 4.0 / 3.0 * math.pi * r**3  # capsule: cylinder + two hemispheres
    ixx = mc * (h * h / 12.0 + r * r / 4.0) + ms * (0.4 * r * r + h * h / 4.0 + 3.0 * h * r / 8.0)
    izz = 0.5 * mc * r * r + 0.4 * ms * r * r
    return mc + ms, np.zeros(3), np.diag([ixx, ixx, izz])


def link_mass_properties(link: LinkSpec) -> tuple[float, np.ndarray, np.ndarray]:
    """(mass, COM, inertia about the COM) of a link: explicit values win, the rest is integrated over shapes.

    With both ``mass`` and ``inertia`` given the shapes are not integrated (so open meshes are fine) and the
    COM is ``com`` or the body origin.
    """
    if link.mass is None and link.density is None:
        raise InputError(f"link '{link.name}': give 'mass' or 'density'")
    if link.mass is not None and link.mass <= 0:
        raise InputError(f"link '{link.name}': mass must be > 0, got {link.mass}")
    com = None if link.com is None else np.asarray(link.com, dtype=np.float64)
    if link.mass is not None and link.inertia is not None:
        return float(link.mass), np.zeros(3) if com is None else com, _inertia_matrix(link)
    if not link.shapes:
        raise InputError(f"link '{link.name}' has no shapes: give 'mass' and 'inertia' explicitly")
    parts = [shape_mass_properties(s, 1.0 if link.mass is not None else link.density) for s in link.shapes]
    mass = sum(p[0] for p in parts)
    shape_com = sum(p[0] * p[1] for p in parts) / mass
    inertia = np.zeros((3, 3))
    for m, c, I in parts:
        d = c - shape_com
        inertia += I + m * (d @ d * np.eye(3) - np.outer(d, d))
    if link.mass is not None:
        inertia *= link.mass / mass
        mass = link.mass
    if link.inertia is not None:
        inertia = _inertia_matrix(link)
    return float(mass), shape_com if com is None else com, inertia


def _inertia_matrix(link: LinkSpec) -> np.ndarray:
    I = np.asarray(link.inertia, dtype=np.float64)
    if I.shape == (3,):
        return np.diag(I)
    if I.shape != (3, 3):
        raise InputError(f"link '{link.name}': inertia must be 3 diagonal values or a 3x3 matrix, got shape {I.shape}")
    return I


# ------------------------------------------------------------------------------------------- DART shapes


def dart_shape(shape: ShapeSpec):
    """The DART shape for a spec; meshes go through DART's URDF loader (MeshShape has no Python constructor)."""
    k = shape.kind
    if k == "box":
        return dart.dynamics.BoxShape(np.asarray(shape.size, dtype=np.float64))
    if k == "sphere":
        return dart.dynamics.SphereShape(float(shape.radius))
    if k == "cylinder":
        return dart.dynamics.CylinderShape(float(shape.radius), float(shape.height))
    if k == "capsule":
        return dart.dynamics.CapsuleShape(float(shape.radius), float(shape.height))
    return _mesh_shape(shape)


def _mesh_shape(shape: ShapeSpec):
    path = Path(shape.mesh).resolve()
    load_mesh(str(path))  # clear error for a missing/unreadable file
    scale = " ".join(str(float(v)) for v in np.broadcast_to(shape.scale, 3))
    xml = (
        '<robot name="m"><link name="l"><collision><geometry>'
        f'<mesh filename="{path}" scale="{scale}"/></geometry></collision></link></robot>'
    )
    skel = dart.utils.DartLoader().parseSkeletonString(xml, dart.common.Uri(f"file://{path.parent}/"))
    if skel is None:
        raise InputError(f"DART could not load mesh {path}; export it as OBJ/STL")
    return skel.getBodyNode(0).getShapeNode(0).getShape()


def check_shape(shape: ShapeSpec, where: str) -> None:
    """InputError naming the field if a shape spec is incomplete."""
    if shape.kind not in SHAPE_KINDS:
        raise InputError(f"{where}: unknown shape kind '{shape.kind}'; use one of {', '.join(SHAPE_KINDS)}")
    for key in required_keys(shape.kind, mesh_key="mesh"):
        if getattr(shape, key) is None:
            raise InputError(f"{where}: a {shape.kind} shape needs '{key}'")
    if shape.kind == "mesh" and not Path(shape.mesh).is_file():
        raise InputError(f"{where}: mesh file not found: {shape.mesh}")


def attach_shape(body, shape: ShapeSpec) -> None:
    """Add a shape node with visual, collision and dynamics aspects (the last avoids DART's contact warnings)."""
    node = body.createShapeNode(dart_shape(shape))
    node.setRelativeTransform(isometry(shape.transform()))
    node.createVisualAspect()
    node.createCollisionAspect()
    node.createDynamicsAspect()


# ---------------------------------------------------------------------------------------- link skeletons


def build_link_skeleton(spec: SkeletonSpec):
    """A DART skeleton from primitive links (parents must precede children)."""
    skel = dart.dynamics.Skeleton(spec.name)
    bodies: dict[str, object] = {}
    for link in spec.links:
        where = f"skeleton '{spec.name}', link '{link.name}'"
        if link.joint not in JOINT_TYPES:
            raise InputError(f"{where}: unknown joint type '{link.joint}'; use one of {', '.join(JOINT_TYPES)}")
        if link.name in bodies:
            raise InputError(f"{where}: duplicate link name")
        if link.parent is not None and link.parent not in bodies:
            raise InputError(f"{where}: parent '{link.parent}' is not a link listed before it")
        for i, s in enumerate(link.shapes):
            check_shape(s, f"{where}, shape {i}")
        joint, body = _create_pair(skel, bodies.get(link.parent), link)
        _configure(joint, body, link, where)
        bodies[link.name] = body
    return skel


def _create_pair(skel, parent, link: LinkSpec):
    """createXJointAndBodyNodePair with the joint origin and, for 1-dof joints, the axis."""
    d = dart.dynamics
    kind = link.joint
    props = {
        "free": d.FreeJointProperties,
        "planar": d.PlanarJointProperties,
        "revolute": d.RevoluteJointProperties,
        "prismatic": d.PrismaticJointProperties,
        "ball": d.BallJointProperties,
        "weld": None,
    }[kind]
    create = getattr(skel, f"create{kind.capitalize()}JointAndBodyNodePair")
    if props is None:
        joint, body = create(parent)
        joint.setTransformFromParentBodyNode(isometry(make_transform(link.origin_position, link.origin_rotation)))
        return joint, body
    p = props()
    p.mName = link.name
    p.mT_ParentBodyToJoint = isometry(make_transform(link.origin_position, link.origin_rotation))
    if kind in ("revolute", "prismatic"):
        axis = np.asarray(link.axis, dtype=np.float64)
        if axis.shape != (3,) or np.linalg.norm(axis) == 0:
            raise InputError(f"link '{link.name}': axis must be a non-zero 3-vector, got {link.axis}")
        p.mAxis = axis / np.linalg.norm(axis)
    return create(parent, p)


def _configure(joint, body, link: LinkSpec, where: str) -> None:
    """Name, mass properties, shapes, damping, limits and initial state of one link."""
    joint.setName(link.name)
    body.setName(link.name)
    if link.joint == "planar":
        joint.setXYPlane()
    mass, com, inertia = link_mass_properties(link)
    body.setInertia(dart.dynamics.Inertia(mass, com, inertia))
    for s in link.shapes:
        attach_shape(body, s)
    n = joint.getNumDofs()
    for i in range(n):
        joint.setDampingCoefficient(i, float(link.damping))
    _set_limits(joint, link, n, where)
    for value, setter in ((link.q0, joint.setPositions), (link.qd0, joint.setVelocities)):
        if value is not None:
            setter(dof_vector(value, n, where))


def _set_limits(joint, link: LinkSpec, n: int, where: str) -> None:
    if link.lower is None and link.upper is None:
        return
    lo = dof_vector(-np.inf if link.lower is None else link.lower, n, f"{where}: lower")
    hi = dof_vector(np.inf if link.upper is None else link.upper, n, f"{where}: upper")
    if np.any(lo > hi):
        raise InputError(f"{where}: lower limit {lo} exceeds upper limit {hi}")
    joint.setPositionLowerLimits(lo)
    joint.setPositionUpperLimits(hi)
    joint.setLimitEnforcement(True)


# ---------------------------------------------------------------------------------------- either kind


def build_skeleton(spec: SkeletonSpec):
    """The DART skeleton of a spec (links or URDF, exactly one)."""
    if (spec.urdf is None) == (not spec.links):
        raise InputError(f"skeleton '{spec.name}': give exactly one of 'links' or 'urdf'")
    return build_urdf_skeleton(spec) if spec.urdf is not None else build_link_skeleton(spec)


def build_ground(spec: GroundSpec, name: str = "cosim_ground"):
    """The immobile skeleton of a ``GroundSpec``: one welded box whose top face is the floor plane."""
    if spec.up not in (0, 1, 2):
        raise InputError(f"ground: 'up' must be an axis index 0, 1 or 2, got {spec.up}")
    if spec.friction < 0 or spec.half_extent <= 0 or spec.thickness <= 0:
        raise InputError("ground: friction must be >= 0, half_extent and thickness > 0")
    size = [2.0 * spec.half_extent] * 3
    size[spec.up] = spec.thickness
    centre = [0.0, 0.0, 0.0]
    centre[spec.up] = spec.height - 0.5 * spec.thickness
    box = ShapeSpec("box", size=tuple(size))
    link = LinkSpec("ground", [box], mass=1.0, joint="weld", origin_position=tuple(centre))
    skel = build_link_skeleton(SkeletonSpec(name, links=[link]))
    skel.setMobile(False)
    for node in skel.getBodyNode(0).getShapeNodes():
        node.getDynamicsAspect().setFrictionCoeff(float(spec.friction))
    return skel
