"""The YAML scene format: a validated, typed description of one simulation.

One pydantic model per section; each validates its own keys (types, ranges,
unknown keys). What spans several keys is checked in ``cosim.scene.checks``,
and ``cosim.scene.loader`` runs both. The reference of every key is
``docs/scene-format.md``; ``cosim.scene.build`` builds the engines.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Discriminator, Field, PlainValidator, Tag

from cosim.engines.shapes import RIGID_SHAPE_KINDS
from cosim.scene.schema_base import (  # noqa: F401  (re-exported: the scene's vocabulary)
    BoxShape,
    CylinderShape,
    MeshShape,
    Positive,
    Shape,
    SphereShape,
    Strict,
    Vec,
)
from cosim.scene.schema_objective import GradientSpec, LossSpec, OptimizeSpec
from cosim.scene.velocity_field import velocity_component


# ---------------------------------------------------------------- time, grid
def _auto_or_int(value: Any) -> Any:
    if value == "auto" or value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError("must be 'auto' or a positive integer")  # noqa: TRY004 (pydantic reports only ValueError)
    if value < 1:
        raise ValueError("must be 'auto' or a positive integer")
    return value


class TimeSpec(Strict):
    frame_dt: Positive = 4e-3  # [s] one macro step: what `steps` counts and frames show
    substeps: Annotated[int, BeforeValidator(_auto_or_int)] = 0  # 0 = auto (CFL)
    cfl: Annotated[float, Field(gt=0, le=1)] = 0.3
    max_substeps: Annotated[int, Field(ge=1, le=100000)] = 2000
    # exchanges per macro step; 0 = auto: one, or where a light body is coupled with added mass, as many as keep
    # each within the substeps its coupler rests a body at (``start.exchanges_per_frame``)
    exchanges: Annotated[int, BeforeValidator(_auto_or_int), Field(ge=0, le=1000)] = 0


def _int_or_list(value: Any) -> Any:
    if isinstance(value, int) and not isinstance(value, bool):
        return [value]
    if not isinstance(value, list):
        raise ValueError(f"must be an integer or a list of integers (got {value!r})")  # noqa: TRY004 (as above)
    return value


class GridSpec(Strict):
    cells: Annotated[list[Annotated[int, Field(ge=8, le=4096)]], BeforeValidator(_int_or_list)]
    dx: Positive | None = None  # [m]; default 1 / max(cells): a unit-sized domain


class BoundarySpec(Strict):
    type: Literal["slip", "sticky", "none"] = "slip"
    thickness: Annotated[int, Field(ge=2, le=16)] = 3  # [cells]


# ---------------------------------------------------------------- materials
class _MaterialBase(Strict):
    E: Positive  # Young's modulus [Pa] (liquids: stiffness of the pressure law)
    nu: Annotated[float, Field(ge=0, lt=0.5)] = 0.3
    density: Positive = 1000.0  # [kg/m^3]


class ElasticMaterial(_MaterialBase):
    type: Literal["elastic"]


class PlasticMaterial(_MaterialBase):
    type: Literal["plastic"]
    yield_stress: Positive  # [Pa], von Mises


class LiquidMaterial(_MaterialBase):
    type: Literal["liquid"]
    viscosity: Annotated[float, Field(ge=0)] = 0.0  # [Pa s]; water is 1e-3


Material = Annotated[ElasticMaterial | PlasticMaterial | LiquidMaterial, Field(discriminator="type")]


class VelocityFile(Strict):
    """An initial velocity read from a file (cosim.scene.velocity_file): one row per particle, or a
    point cloud of positions and velocities interpolated to the particles."""

    file: str  # .npy, .npz or .csv, relative to the scene file

    def path(self, source_dir: Path) -> Path:
        """The file's absolute path, for a scene read from ``source_dir``."""
        return (source_dir / self.file).resolve()


def _velocity_form(value: Any) -> str:
    return "file" if isinstance(value, (dict, VelocityFile)) else "components"


# [m/s] per component a number or an expression in x, y, z (cosim.scene.velocity_field), or {file: PATH}
Velocity = Annotated[
    Annotated[list[Annotated[Any, PlainValidator(velocity_component)]], Tag("components")]
    | Annotated[VelocityFile, Tag("file")],
    Discriminator(_velocity_form),
]


class BodySpec(Strict):
    name: str
    material: Material
    shape: Shape
    velocity: Velocity | None = None  # default at rest
    spacing: Positive | None = None  # [m] particle lattice spacing, default dx / 2
    jitter: Annotated[float, Field(ge=0, le=0.5)] = 0.0  # fraction of spacing
    hydrostatic: bool = False  # liquids: start compressed by their own weight (at rest)


class MPMSpec(Strict):
    grid: GridSpec
    boundary: BoundarySpec = BoundarySpec()
    gravity: Vec | None = None  # [m/s^2], default -9.81 along y
    bodies: Annotated[list[BodySpec], Field(min_length=1)]
    # how P2G and the G2P adjoint add to the grid (cosim.engines.arch.SCATTERS): auto picks by the arch and
    # CPU threads; serial and coloured sum in an order the particles fix (bit-reproducible on any thread
    # count), atomic in the threads' order (reproducible to round-off)
    scatter: Literal["auto", "serial", "coloured", "atomic"] = "auto"


# ---------------------------------------------------------------- controls
class RegionSpec(Strict):
    min: Vec
    max: Vec


class ControlSpec(Strict):
    """An impulse on selected particles, applied in P2G (the soft-gripper action)."""

    body: str
    region: RegionSpec | None = None  # particles of the body inside this box (initially)
    impulse: Vec | None = None  # [N s] per particle per macro step, the initial action


# ---------------------------------------------------------------- rigid bodies, contact
class RigidShape(Strict):
    """A rigid body's shape in its own frame (centred at the body origin; y is the axis of
    cylinders, capsules and glasses, a glass opens towards +y). ``mesh``: a watertight file."""

    type: Literal[RIGID_SHAPE_KINDS]  # cosim.engines.shapes: one vocabulary for scenes, SDFs and DART
    size: list[Positive] | None = None  # box: full extents
    radius: Positive | None = None
    height: Positive | None = None
    thickness: Positive | None = None  # glass and ring walls
    file: str | None = None
    scale: Positive = 1.0


class MotionSegment(Strict):
    duration: Positive
    velocity: Vec
    angular_velocity: float | Vec = 0.0


class MotionSpec(Strict):
    """Prescribed motion (see cosim.engines.kinematic): static, constant, piecewise, shake, waypoints."""

    type: Literal["static", "constant", "piecewise", "shake", "waypoints"] = "static"
    velocity: Vec | None = None  # constant [m/s]
    angular_velocity: float | Vec = 0.0  # constant [rad/s], world frame (a number in 2D)
    segments: list[MotionSegment] = []  # piecewise
    repeat: bool = False  # piecewise: cycle the segments
    amplitude: Vec | None = None  # shake [m]
    frequency: Positive | None = None  # shake [Hz]
    phase: float = 0.0  # shake [rad]
    times: list[float] = []  # waypoints [s], starting at 0
    positions: list[Vec] = []  # waypoints [m], the first one the body's position


class RigidBodySpec(Strict):
    name: str
    shape: RigidShape
    position: Vec  # [m] body origin in the world
    rotation: float | Vec = 0.0  # 2D: angle [rad]; 3D: rotation vector [rad]
    motion: MotionSpec = MotionSpec()
    sdf_spacing: Positive | None = None  # [m] default dx / 2


class RigidSpec(Strict):
    bodies: Annotated[list[RigidBodySpec], Field(min_length=1)]


class JointSceneSpec(Strict):
    """How a link hangs on its parent (``parent`` None: the world). The joint frame is placed
    by ``position`` [m] and ``rotation`` (2D angle / 3D rotation vector [rad]) in the parent's
    body frame; the link's body frame is the joint frame at q = 0."""

    type: Literal["free", "revolute", "prismatic", "ball", "weld"] = "free"  # 2D: free = planar (x, y, angle)
    parent: str | None = None
    position: Vec | None = None
    rotation: float | Vec = 0.0
    axis: Vec | None = None  # revolute / prismatic, joint frame (2D revolute: always z)
    lower: float | None = None  # limits, enforced [rad or m]
    upper: float | None = None
    damping: Annotated[float, Field(ge=0)] = 0.0  # [N m s/rad or N s/m]
    q0: float | Vec | None = None  # initial joint position(s) (free 3D: [rotation vector, translation])
    qd0: float | Vec | None = None  # initial joint velocity(ies) (free 3D: [angular, linear], world)


class LinkSceneSpec(Strict):
    """A rigid link: its shape is the MPM contact geometry and (uniform) mass distribution."""

    name: str
    shape: RigidShape
    density: Positive | None = None  # [kg/m^3] (2D: per metre of depth, like the MPM)
    mass: Positive | None = None  # [kg] instead of density
    offset: Vec | None = None  # [m] the shape's centre in the link frame (e.g. a door's middle off its hinge)
    joint: JointSceneSpec = JointSceneSpec()
    couple: bool = True  # the MPM sees it (False: costs nothing in the MPM)
    sdf_spacing: Positive | None = None  # [m] default dx / 2


class PlacedShape(Strict):
    """One of our rigid shapes placed in a link frame (e.g. a hollow bottle for a URDF's solid one)."""

    shape: RigidShape
    position: Vec = [0.0, 0.0, 0.0]  # [m] the shape's centre in the link frame
    rotation: Vec = [0.0, 0.0, 0.0]  # rotation vector [rad] from the shape's frame to the link frame


class SkeletonSceneSpec(Strict):
    """An articulated rigid body from ``links`` (primitives) or a ``urdf`` file (3D)."""

    name: str
    links: list[LinkSceneSpec] = []
    urdf: str | None = None
    fixed_base: bool = True  # urdf: weld the root link to the world
    position: Vec | None = None  # urdf: the root link's origin in the world [m]
    rotation: float | Vec = (
        0.0  # urdf: the root's rotation (rotation vector [rad]; a z-up URDF in a y-up scene: [-1.5708, 0, 0])
    )
    contact_shapes: dict[str, PlacedShape] = {}  # urdf: link -> our shape as its MPM contact geometry
    package_dirs: dict[str, str] = {}  # urdf: package://name/ -> folder (relative to the scene)
    initial_positions: dict[str, float | Vec] = {}  # urdf: joint name -> position
    couple: Literal["all", "none"] | list[str] = "all"  # urdf: links the MPM sees
    collide: bool = False  # DART rigid-rigid collision (2D: shapes extruded 1 m along z), with articulated.collision
    controls: dict[str, Literal["torque", "velocity", "wrench", "twist"]] = {}  # joint name -> mode


class ActionSpec(Strict):
    """The rigid action sequence: one action per ``hold`` macro steps (the paper's tasks hold
    each action several steps). An action concatenates every controlled joint's block in the
    skeletons' order (torque/velocity: one entry per dof; wrench/twist: 6, [angular; linear])."""

    hold: Annotated[int, Field(ge=1)] = 1
    initial: Vec | None = None  # the action of every segment not in ``sequence`` (default zeros)
    sequence: list[Vec] = []  # actions of the first segments
    # per-entry [lower, upper] limits: `cosim optimize` projects the actions onto them after each step
    bounds: Annotated[list[Vec], Field(min_length=2, max_length=2)] | None = None
    # an entry's natural size (one number, or one per entry) in its units: optimiser and finite-difference
    # steps are fractions of it (default: the largest |entry| of the initial actions)
    scale: Positive | list[Positive] | None = None


class GroundSceneSpec(Strict):
    """A static floor for the DART bodies only (the MPM keeps its own walls): everything below
    ``height`` along y (scenes are y-up). Skeletons with ``collide: true`` rest on it."""

    height: float = 0.0  # [m] the floor's top
    friction: Annotated[float, Field(ge=0)] = 1.0  # Coulomb coefficient (DART takes the smaller of a pair's)


class ArticulatedSpec(Strict):
    """Articulated rigid bodies simulated by DART and coupled two-way with the MPM."""

    skeletons: Annotated[list[SkeletonSceneSpec], Field(min_length=1)]
    actions: ActionSpec = ActionSpec()
    collision: bool = False  # DART rigid-rigid collision for skeletons with collide: true
    ground: GroundSceneSpec | None = None  # a static DART floor (needs collision: true)


class ClothMeshSpec(Strict):
    """The cloth's triangle mesh [m]: a rectangle grid or a disc lying flat across ``normal``, or a
    mesh file (any format trimesh reads; open, possibly non-orientable)."""

    type: Literal["rectangle", "disc", "file"]
    center: Vec  # [m] the sheet's centre (file: where the file's origin goes)
    normal: Literal["x", "y", "z"] = "y"  # rectangle, disc: the axis the flat sheet faces
    size: list[Positive] | None = None  # rectangle: [width, depth] [m] along the two other axes in order
    resolution: list[Annotated[int, Field(ge=2, le=1000)]] | None = None  # rectangle: vertices per side
    radius: Positive | None = None  # disc [m]
    rings: Annotated[int, Field(ge=1, le=200)] | None = None  # disc: concentric rings of vertices
    file: str | None = None
    scale: Positive = 1.0


class ClothMaterialSpec(Strict):
    """Membrane and bending stiffness, areal density and damping of a cloth."""

    stretch: Positive = 1000.0  # [N/m] membrane (corotated) stiffness, SoftMAC's k_stiff_stretching
    bend: Annotated[float, Field(ge=0)] = 0.03  # [N m] bending stiffness, SoftMAC's k_stiff_bending
    density: Positive = 0.2  # [kg/m^2] areal density
    damping: Annotated[float, Field(ge=0)] = 0.0  # [1/s] mass-proportional damping


class VertexSelectSpec(Strict):
    """Cloth vertices by their rest positions: the vertex nearest to each point, and every vertex in a box."""

    points: list[Vec] = []  # [m]
    region: RegionSpec | None = None


class ClothControlSpec(Strict):
    """Vertices moved together by the action: three velocity entries [m/s] per control."""

    name: str
    vertices: VertexSelectSpec


class ReachSpec(Strict):
    """Where a cloth's controls may go: each control's centroid stays within ``radius`` of the line
    through ``center`` along ``axis`` (e.g. a tortilla's rim points within the tortilla's radius of
    its fold line). `cosim optimize` projects the actions onto it after each step."""

    center: Vec  # [m] a point of the line
    axis: Vec  # its direction
    radius: Positive  # [m]


class ClothActionSpec(ActionSpec):
    """A cloth's action sequence: (controls x 3) velocities [m/s] per action, held ``hold`` steps."""

    reach: ReachSpec | None = None


class ClothSpec(Strict):
    """A cloth simulated by our implicit cloth engine and coupled two-way with the MPM (3D)."""

    name: str = "cloth"
    mesh: ClothMeshSpec
    material: ClothMaterialSpec = ClothMaterialSpec()
    fixed: VertexSelectSpec | None = None  # pinned vertices
    controls: list[ClothControlSpec] = []
    actions: ClothActionSpec = ClothActionSpec()
    thickness: Positive | None = None  # [m] contact distance to rigid bodies, default dx / 2
    tolerance: Positive = 1e-9  # Newton: residual force relative to the cloth's weight
    max_iterations: Annotated[int, Field(ge=1, le=1000)] = 200


class ContactSpec(Strict):
    """How MPM material meets rigid bodies (see cosim.couplers.contact)."""

    model: Literal["grid", "particle", "forecast"] = "grid"
    friction: Annotated[float, Field(ge=0)] = 0.0  # Coulomb coefficient
    # grid model: where liquid is held, "material" (by its own edge, read off the nodes' liquid volume fractions:
    # the surface where the geometry is) or "nodes" (the paper's: at the node rows within ``band``); solids: the band
    support: Literal["material", "nodes"] = "material"
    # [m] grid model: nodes closer than this hold solids (with support "nodes", all material) off, beyond it the
    # constraint fades in; default dx / 2 (smaller bands let walls thinner than about 3 cells leak)
    band: Annotated[float, Field(ge=0)] | None = None
    stiffness: Positive = 600.0  # particle model: push one cell deep, in units of g (see ParticlePenalty)
    # forecast: gradient step (mass-normalised); default 0.8 in 2D and with a cloth, else 0.3 in 3D (more
    # spreads each particle's correction over its neighbours: 3D elastic restitution 0.79 at 0.8, 0.83 at 0.3)
    alpha: Annotated[float, Field(gt=0, le=2)] | None = None
    threshold: Positive | None = None  # [m] forecast: contact distance d_hat, default dx
    smoothing: Positive | None = None  # [1/m] forecast with blend: beta of s = min(exp(-beta d), 1), default 2 / dx
    # forecast: which particles get the paper's BC_p blended over the band (a dashpot that brakes them
    # before they touch: liquids meet walls without rebound, but an elastic disc's restitution fell from
    # 0.94 to 0.27); the others keep any approach that does not reach the surface within the substep
    blend: Literal["liquids", "all", "none"] = "liquids"
    # [m] particle and forecast: how far from a surface particle centres are held; default each
    # particle's radius (half its spacing), so the material meets the surface where the geometry is
    offset: Annotated[float, Field(ge=0)] | None = None
    tracing: bool = True  # cloth: penetration tracing (off: a particle's legal side is where it is now)


# Differentiable parameters by name: one name selects it in every engine that has it (``action``:
# DART's and every cloth's; ``x0``: the particles' and each cloth's vertices). Cloth material:
# k_stretch, k_bend, c_mass (damping), density.
class OutputSpec(Strict):
    every: Annotated[int, Field(ge=1)] = 1  # save a frame every N macro steps
    preview: Literal["gif", "mp4", "none"] = "gif"
    fps: Annotated[int, Field(ge=1, le=120)] = 30
    resolution: Annotated[int, Field(ge=64, le=2048)] = 640  # preview pixels (longest side)
    velocities: bool = False  # also save particle (and cloth vertex) velocities per frame


class Scene(Strict):
    name: str = "scene"
    description: str = ""
    dim: Literal[2, 3]
    precision: Literal["float32", "float64"] = "float32"
    # grid refinement, time.cfl and precision in one word, applied before validation (cosim.scene.accuracy)
    accuracy: Literal["coarse", "default", "fine"] | None = None
    arch: Literal["cpu", "cuda"] = "cpu"
    seed: int = 0
    steps: Annotated[int, Field(ge=1)] = 100
    time: TimeSpec = TimeSpec()
    mpm: MPMSpec
    rigid: RigidSpec | None = None
    articulated: ArticulatedSpec | None = None
    cloth: list[ClothSpec] = []
    contact: ContactSpec = ContactSpec()
    controls: list[ControlSpec] = []
    loss: LossSpec = LossSpec()
    gradient: GradientSpec = GradientSpec()
    optimize: OptimizeSpec = OptimizeSpec()
    output: OutputSpec = OutputSpec()

    # Set by the loader, not by the YAML file.
    source_dir: Path = Field(default=Path("."), exclude=True)

    @property
    def dx(self) -> float:
        """[m] the grid spacing: ``mpm.grid.dx``, default 1 / max(cells)."""
        return self.mpm.grid.dx or 1.0 / max(self.cells)

    @property
    def cells(self) -> tuple[int, ...]:
        """Grid cells per axis (one number in the file means the same on every axis)."""
        c = self.mpm.grid.cells
        return tuple(c * self.dim if len(c) == 1 else c)

    @property
    def gravity(self) -> tuple[float, ...]:
        """[m/s^2] ``mpm.gravity``, default -9.81 along y."""
        g = self.mpm.gravity
        if g is None:
            return (0.0, -9.81) + (0.0,) * (self.dim - 2)
        return tuple(g)
