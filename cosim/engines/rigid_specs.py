"""Rigid-body specs: plain dataclasses describing shapes, links and skeletons, and their transforms.

Frames and units (SI):
- a transform is given as ``position`` [m] plus ``rotation``: fixed-axis xyz Euler angles in DEGREES,
  R = Rz(c) @ Ry(b) @ Rx(a) for rotation = (a, b, c) (URDF's roll-pitch-yaw convention, in degrees);
- a shape's transform places it in its link's body frame; a joint's origin places the joint frame in the
  parent body frame (the world for a root link). At zero joint position the child body frame coincides with
  the joint frame, so every link's body frame is its joint frame.

The scene schema maps onto these specs; ``rigid_build`` turns them into DART skeletons (``urdf`` for URDF
files). Shape kinds and their size keys come from ``cosim.engines.shapes``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import dartpy as dart
import numpy as np
from numpy.typing import ArrayLike

from cosim.engines import so3
from cosim.engines.shapes import DART_SHAPE_KINDS
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


@dataclass
class GroundSpec:
    """A static floor for the rigid bodies: the half-space below ``height`` [m] along axis ``up``
    (0 = x, 1 = y, 2 = z; scenes are y-up), as a DART box whose top face is that plane, ``half_extent`` [m]
    to each side along the two other axes and ``thickness`` [m] deep (so a body that lands fast cannot
    tunnel through it in one step). ``friction``: Coulomb coefficient of its surface; DART takes the
    smaller of the two coefficients in a contact (links keep DART's default 1.0). It collides with the
    skeletons that have ``collide`` (and only when the engine's ``collision`` is on)."""

    height: float = 0.0
    up: int = 2
    friction: float = 1.0
    half_extent: float = 100.0
    thickness: float = 1.0


# ----------------------------------------------------------------------------------------------- transforms


def euler_xyz_deg(rotation: ArrayLike) -> np.ndarray:
    """R = Rz @ Ry @ Rx from fixed-axis xyz Euler angles in degrees."""
    return so3.euler_xyz(np.radians(np.asarray(rotation, dtype=np.float64)))


def make_transform(position: ArrayLike, rotation: ArrayLike) -> np.ndarray:
    """4x4 homogeneous transform from a position and xyz Euler degrees."""
    T = np.eye(4)
    T[:3, :3] = euler_xyz_deg(rotation)
    T[:3, 3] = np.asarray(position, dtype=np.float64)
    return T


def isometry(T: np.ndarray) -> dart.math.Isometry3:
    """A 4x4 transform as DART's Isometry3."""
    iso = dart.math.Isometry3()
    iso.set_matrix(np.asarray(T, dtype=np.float64))
    return iso


# ------------------------------------------------------------------------------------------- joint values


def dof_vector(value: ArrayLike, n: int, where: str) -> np.ndarray:
    """A scalar or list as an n-vector; InputError on a wrong length."""
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.size == 1 and n != 1:
        v = np.full(n, v[0])
    if v.size != n:
        raise InputError(f"{where}: expected {n} value(s) for this joint, got {v.size}")
    return v
