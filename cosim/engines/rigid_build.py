"""Rigid-body specs and their construction as DART skeletons.

Frames and units (SI):
- a transform is given as ``position`` [m] plus ``rotation``: fixed-axis xyz Euler angles in DEGREES,
  R = Rz(c) @ Ry(b) @ Rx(a) for rotation = (a, b, c) (URDF's roll-pitch-yaw convention, in degrees);
- a shape's transform places it in its link's body frame; a joint's origin places the joint frame in the
  parent body frame (the world for a root link). At zero joint position the child body frame coincides with
  the joint frame, so every link's body frame is its joint frame.

The specs are plain dataclasses; the scene schema maps onto them. URDF skeletons keep DART's URDF loader
for the dynamics and parse the ``<collision>`` elements here (``urdf_geometry``) so the MPM coupler gets
the same shapes, with mesh files resolved to absolute paths.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import dartpy as dart
import numpy as np

from cosim.engines import so3
from cosim.engines.meshes import load_mesh, require_watertight
from cosim.engines.shapes import DART_SHAPE_KINDS, required_keys
from cosim.errors import InputError

SHAPE_KINDS = DART_SHAPE_KINDS
JOINT_TYPES = ("free", "planar", "revolute", "prismatic", "ball", "weld")
CONTROL_MODES = ("passive", "torque", "velocity", "wrench", "twist")


@dataclass
class ShapeSpec:
    """A collision/contact shape in its link's body frame.

    box: ``size`` = full extents (x, y, z); sphere: ``radius``; cylinder: ``radius`` and ``height`` along the
    local z axis; capsule: ``radius`` and ``height`` = length of the cylindrical part along z (total length
    height + 2 radius); mesh: ``mesh`` file path (a closed mesh if its mass is derived) scaled per axis by
    ``scale``. ``position``/``rotation`` (xyz Euler degrees) place the shape in the body frame.
    """

    kind: str
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    height: float | None = None
    mesh: str | None = None
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def transform(self) -> np.ndarray:
        """4x4 pose of the shape in the body frame."""
        return make_transform(self.position, self.rotation)


@dataclass
class LinkSpec:
    """A body plus the joint that attaches it to ``parent`` (None = world); the joint carries the link's name.

    Mass properties: ``mass`` or ``density`` [kg/m^3]; from ``density`` the mass, centre of mass and inertia
    are integrated over ``shapes`` (assumed not to overlap). With ``mass`` alone the shapes give the mass
    distribution. ``inertia`` (3 diagonal values or 3x3, about the COM, body axes) and ``com`` (body frame)
    override the derived values. ``axis`` is the revolute/prismatic axis in the joint frame; ``lower``/``upper``
    are position limits (enforced); ``damping`` is viscous joint damping [N m s/rad or N s/m], implicit in DART.
    ``q0``/``qd0``: initial joint positions/velocities (free: [rotation vector, translation] and
    [angular, linear] world velocity; ball: rotation vector; planar: [x, y, angle]).
    """

    name: str
    shapes: list[ShapeSpec] = field(default_factory=list)
    mass: float | None = None
    density: float | None = None
    inertia: list | None = None
    com: tuple[float, float, float] | None = None
    joint: str = "free"
    parent: str | None = None
    origin_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    origin_rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    lower: float | list[float] | None = None
    upper: float | list[float] | None = None
    damping: float = 0.0
    q0: float | list[float] | None = None
    qd0: float | list[float] | None = None


@dataclass
class SkeletonSpec:
    """An articulated rigid body: either ``links`` (primitives built here) or a ``urdf`` file.

    ``controls`` maps a joint name to its control mode; joints not listed get ``default_control``:
    - ``passive``: no action entries;
    - ``torque``: generalised forces on the joint's dofs (DART's coordinates);
    - ``velocity``: kinematic velocity target on the joint's dofs (DART VELOCITY actuator): the dofs follow
      the commanded velocity exactly, so forces and wrenches on those dofs do not move them;
    - ``wrench`` (free root joint only): 6-D [torque; force] in world coordinates about the body origin;
    - ``twist`` (free root joint only): 6-D [angular; linear] world velocity of the body origin, kinematic.
    URDF: ``fixed_base`` welds the root link to the world (else it floats), ``base_transform`` places the
    root in the world (e.g. a z-up robot in a y-up scene), ``package_dirs`` resolves
    ``package://name/`` URIs, ``initial_positions`` maps joint names to positions. ``collide``: take part in
    DART rigid-rigid collision.
    """

    name: str
    links: list[LinkSpec] = field(default_factory=list)
    urdf: str | None = None
    fixed_base: bool = True
    base_transform: np.ndarray | None = None  # 4x4 pose of a URDF's root link in the world (default identity)
    package_dirs: dict[str, str] = field(default_factory=dict)
    initial_positions: dict[str, float | list[float]] = field(default_factory=dict)
    collide: bool = True
    controls: dict[str, str] = field(default_factory=dict)
    default_control: str = "passive"


# ----------------------------------------------------------------------------------------------- transforms


def euler_xyz_deg(rotation) -> np.ndarray:
    """R = Rz @ Ry @ Rx from fixed-axis xyz Euler angles in degrees."""
    return so3.euler_xyz(np.radians(np.asarray(rotation, dtype=np.float64)))


def make_transform(position, rotation) -> np.ndarray:
    """4x4 homogeneous transform from a position and xyz Euler degrees."""
    T = np.eye(4)
    T[:3, :3] = euler_xyz_deg(rotation)
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def _isometry(T: np.ndarray) -> dart.math.Isometry3:
    iso = dart.math.Isometry3()
    iso.set_matrix(np.asarray(T, dtype=np.float64))
    return iso


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
    node.setRelativeTransform(_isometry(shape.transform()))
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
        joint.setTransformFromParentBodyNode(_isometry(make_transform(link.origin_position, link.origin_rotation)))
        return joint, body
    p = props()
    p.mName = link.name
    p.mT_ParentBodyToJoint = _isometry(make_transform(link.origin_position, link.origin_rotation))
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


def dof_vector(value, n: int, where: str) -> np.ndarray:
    """A scalar or list as an n-vector; InputError on a wrong length."""
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.size == 1 and n != 1:
        v = np.full(n, v[0])
    if v.size != n:
        raise InputError(f"{where}: expected {n} value(s) for this joint, got {v.size}")
    return v


# ---------------------------------------------------------------------------------------- URDF skeletons


def build_urdf_skeleton(spec: SkeletonSpec):
    """A DART skeleton from a URDF: floating or welded root, all finite joint limits enforced."""
    path = _urdf_path(spec)
    urdf_geometry(spec)  # checks every collision mesh resolves, with errors naming the file
    loader = dart.utils.DartLoader()
    for name, folder in spec.package_dirs.items():
        loader.addPackageDirectory(name, str(Path(folder).resolve()))
    options = loader.getOptions()
    root = dart.utils.DartLoaderRootJointType
    options.mDefaultRootJointType = root.FIXED if spec.fixed_base else root.FLOATING
    loader.setOptions(options)
    skel = loader.parseSkeleton(dart.common.Uri(f"file://{path}"))
    if skel is None:
        raise InputError(f"DART could not parse URDF {path}; check it with check_urdf and the package_dirs")
    skel.setName(spec.name)
    if spec.base_transform is not None:
        skel.getRootJoint().setTransformFromParentBodyNode(_isometry(spec.base_transform))
    for joint in skel.getJoints():
        limits = np.concatenate([joint.getPositionLowerLimits(), joint.getPositionUpperLimits()])
        if np.isfinite(limits).any():
            joint.setLimitEnforcement(True)
    joints = {j.getName(): j for j in skel.getJoints()}
    for name, value in spec.initial_positions.items():
        if name not in joints:
            raise InputError(
                f"skeleton '{spec.name}': initial_positions names unknown joint '{name}'; joints: {sorted(joints)}"
            )
        joint = joints[name]
        joint.setPositions(dof_vector(value, joint.getNumDofs(), f"skeleton '{spec.name}', joint '{name}'"))
    return skel


def _urdf_path(spec: SkeletonSpec) -> Path:
    path = Path(spec.urdf).resolve()
    if not path.is_file():
        raise InputError(f"skeleton '{spec.name}': URDF file not found: {spec.urdf}; fix the 'urdf' path")
    return path


def resolve_uri(filename: str, urdf_dir: Path, package_dirs: dict[str, str], where: str) -> str:
    """Absolute path of a URDF mesh reference (package://, file:// or relative to the URDF); must exist."""
    if filename.startswith("package://"):
        package, _, rest = filename[len("package://") :].partition("/")
        if package not in package_dirs:
            raise InputError(f"{where}: mesh '{filename}' uses package '{package}'; add it to package_dirs")
        path = Path(package_dirs[package]) / rest
    elif filename.startswith("file://"):
        path = Path(filename[len("file://") :])
    else:
        path = urdf_dir / filename
    path = path.resolve()
    if not path.is_file():
        raise InputError(f"{where}: mesh file not found: {path} (from '{filename}')")
    return str(path)


def urdf_geometry(spec: SkeletonSpec) -> dict[str, list[ShapeSpec]]:
    """Collision shapes of every URDF link (link frame), parsed with xml.etree; mesh paths made absolute."""
    path = _urdf_path(spec)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise InputError(f"URDF {path} is not valid XML: {exc}") from exc
    out: dict[str, list[ShapeSpec]] = {}
    for link in root.findall("link"):
        name = link.get("name")
        out[name] = [
            _urdf_shape(c, path.parent, spec.package_dirs, f"URDF {path.name}, link '{name}'")
            for c in link.findall("collision")
        ]
    return out


def _floats(text: str | None, default) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split()) if text else tuple(default)


def _urdf_shape(collision, urdf_dir: Path, package_dirs: dict[str, str], where: str) -> ShapeSpec:
    origin = collision.find("origin")
    xyz = _floats(origin.get("xyz") if origin is not None else None, (0, 0, 0))
    rpy = _floats(origin.get("rpy") if origin is not None else None, (0, 0, 0))
    pose = {"position": xyz, "rotation": tuple(math.degrees(a) for a in rpy)}
    geom = collision.find("geometry")
    g = next(iter(geom), None) if geom is not None else None
    if g is None:
        raise InputError(f"{where}: <collision> without a <geometry> child")
    if g.tag == "box":
        return ShapeSpec("box", size=_floats(g.get("size"), ()), **pose)
    if g.tag == "sphere":
        return ShapeSpec("sphere", radius=float(g.get("radius")), **pose)
    if g.tag in ("cylinder", "capsule"):
        return ShapeSpec(g.tag, radius=float(g.get("radius")), height=float(g.get("length")), **pose)
    if g.tag == "mesh":
        mesh = resolve_uri(g.get("filename", ""), urdf_dir, package_dirs, where)
        scale = _floats(g.get("scale"), (1, 1, 1))
        return ShapeSpec("mesh", mesh=mesh, scale=tuple(np.broadcast_to(scale, 3)), **pose)
    raise InputError(f"{where}: unsupported collision geometry <{g.tag}>; use box, sphere, cylinder or mesh")


def build_skeleton(spec: SkeletonSpec):
    """The DART skeleton of a spec (links or URDF, exactly one)."""
    if (spec.urdf is None) == (not spec.links):
        raise InputError(f"skeleton '{spec.name}': give exactly one of 'links' or 'urdf'")
    return build_urdf_skeleton(spec) if spec.urdf is not None else build_link_skeleton(spec)
