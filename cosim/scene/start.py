"""Every check `cosim run` makes before its first step, and the host-side parts they build.

``check_start(scene)`` runs, in this order: ``preflight`` (grid memory, particles, velocities,
control regions, substeps, hydrostatic liquids, loss targets; NumPy); each cloth's mesh, vertex
selections and action plan (``cloth_start``); the kinematic bodies' SDFs (a shape with no node
inside at its SDF spacing is refused) and motions; the DART engine of ``articulated:`` (its joints,
limits, masses, URDF files and meshes) with its coupled links' SDFs and action plan; that no
material starts inside a rigid body; and that the loss's joint targets read joints the skeletons
have. ``cosim validate`` calls it (after ``check_machine``), and ``build_system`` builds the Taichi
side (MPM, boundary sources, contact model, cloth engines) on what it returns, so `run` and
`validate` refuse a scene at the same check with the same message. It imports dartpy only for an
``articulated:`` section, and Taichi only for a mesh SDF not cached yet (``cosim.couplers.sdf_mesh``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cosim.engines import so3
from cosim.engines.contract import declares
from cosim.errors import InputError, SceneError
from cosim.scene.preflight import BodyStart, first_frame_substeps, preflight
from cosim.scene.schema import Scene


@dataclass
class Start:
    """The checked start of a scene: every body's particles (``preflight``), each cloth's
    ``ClothStart``, the kinematic engine and its coupler, the ``Articulated`` section with its coupler
    and action plan, and the view of the rigid bodies the MPM sees (no boundary sources yet)."""

    bodies: list[BodyStart]
    cloths: list = field(default_factory=list)
    kinematic: object = None  # KinematicEngine
    kinematic_coupler: object = None  # MPMKinematicCoupler
    kinematic_grids: list = field(default_factory=list)
    articulated: object = None  # cosim.scene.articulated.Articulated
    dart_coupler: object = None  # MPMRigidCoupler, when the MPM sees a link
    dart_plan: object = None  # ActionPlan, when a joint is controlled
    rigid: object = None  # cosim.couplers.rigid_view.RigidBodies, with kinematic bodies or DART
    exchanges: int = 1  # exchanges per macro step (``exchanges_per_frame``); every engine steps frame_dt / this

    @property
    def particles(self) -> int:
        return sum(len(b.positions) for b in self.bodies)


def check_machine(scene: Scene) -> None:
    """What `run` checks of this machine before the scene (``cosim.runtime``): ``COSIM_CPU_THREADS``,
    and for a GPU arch that Taichi finds the GPU (which starts Taichi there)."""
    from cosim.runtime import ensure_taichi, init_options

    init_options(scene.arch)
    if scene.arch != "cpu":
        ensure_taichi(scene.arch, scene.precision)


def check_start(scene: Scene) -> Start:
    """Run the start-of-run checks (module docstring) and return what they built."""
    start = Start(preflight(scene))
    if scene.cloth:  # only cloth scenes load the cloth modules
        from cosim.scene.cloth import cloth_start

        start.cloths = [cloth_start(scene, i) for i in range(len(scene.cloth))]
    if scene.rigid is not None and scene.rigid.bodies:
        _kinematic(scene, start)
    if scene.articulated is not None:
        _articulated(scene, start)
    start.exchanges = exchanges_per_frame(scene, start)
    step_length = scene.time.frame_dt / start.exchanges
    if start.kinematic is not None:
        start.kinematic.frame_dt = step_length
    if start.articulated is not None:
        start.articulated.engine.set_time_step(step_length)
    if start.kinematic is not None or start.articulated is not None:
        _rigid_view(scene, start)
        check_start_outside_rigid(scene, start)
    check_loss_joints(scene, start.articulated.engine if start.articulated is not None else None)
    return start


def exchanges_per_frame(scene: Scene, start: Start) -> int:
    """How many exchanges a macro step makes: 1, or where a light body is coupled with added mass (a cloth, a
    DART body with free dofs), enough that none takes more MPM substeps than its coupler is measured to rest
    stably at (``exchange_substeps``; beyond, the body frozen over the substeps jitters on the material). From
    the first frame's substeps (``preflight.first_frame_substeps``): a fixed count, or the CFL bound's.
    ``time.exchanges`` set (not 0, "auto") overrides it."""
    if scene.time.exchanges:
        return scene.time.exchanges
    limits = []
    if scene.cloth:
        from cosim.couplers.mpm_cloth import MPMClothCoupler

        limits.append(MPMClothCoupler.exchange_substeps)
    if start.dart_coupler is not None and declares(start.dart_coupler, "exchange_limit"):
        limits.append(start.dart_coupler.exchange_substeps)
    if not limits:
        return 1
    K = first_frame_substeps(scene, [b.velocities for b in start.bodies])
    return max(1, math.ceil(K / min(limits)))


def _kinematic(scene: Scene, start: Start) -> None:
    """Prescribed motions (``rigid:``): each body's SDF, its motion, the engine and its coupler."""
    from cosim.couplers.mpm_kinematic import MPMKinematicCoupler
    from cosim.couplers.sdf import shape_sdf
    from cosim.engines.kinematic import KinematicEngine

    specs = scene.rigid.bodies
    key = "rigid.bodies[{}].shape"
    spacing = [spec.sdf_spacing or 0.5 * scene.dx for spec in specs]
    start.kinematic_grids = [
        shape_sdf(spec.shape, scene.dim, h, 3 * scene.dx, scene.source_dir, key.format(i))
        for i, (spec, h) in enumerate(zip(specs, spacing))
    ]
    motions = [build_motion(spec, scene.dim) for spec in specs]
    start.kinematic = KinematicEngine(motions, [spec.name for spec in specs], scene.time.frame_dt)
    start.kinematic_coupler = MPMKinematicCoupler(start.kinematic)


def build_motion(spec, dim: int):
    """A kinematic.Motion from a validated rigid-body spec."""
    from cosim.engines.kinematic import Motion, Segment

    p0 = np.asarray(spec.position, dtype=np.float64)
    R0 = so3.scene_rotation(spec.rotation, dim)
    m = spec.motion

    def omega(value):
        return (
            float(value) if dim == 2 else (np.zeros(3) if isinstance(value, (int, float)) else np.asarray(value, float))
        )

    if m.type == "static":
        return Motion("constant", p0, R0, [Segment(math.inf, np.zeros(dim), omega(0.0))])
    if m.type == "constant":
        return Motion("constant", p0, R0, [Segment(math.inf, np.asarray(m.velocity, float), omega(m.angular_velocity))])
    if m.type == "piecewise":
        segs = [Segment(g.duration, np.asarray(g.velocity, float), omega(g.angular_velocity)) for g in m.segments]
        return Motion("piecewise", p0, R0, segs, repeat=m.repeat)
    if m.type == "shake":
        return Motion("shake", p0, R0, amplitude=np.asarray(m.amplitude, float), frequency=m.frequency, phase=m.phase)
    return Motion("waypoints", p0, R0, times=np.asarray(m.times, float), positions=np.asarray(m.positions, float))


def _articulated(scene: Scene, start: Start) -> None:
    """DART skeletons (``articulated:``): the engine, its action plan and, for the links the MPM sees,
    the coupler."""
    from cosim.couplers.mpm_rigid import MPMRigidCoupler
    from cosim.scene.actions import action_plan
    from cosim.scene.articulated import build_articulated

    try:
        articulated = build_articulated(scene, scene.dx)
    except InputError as exc:  # DART's build names the skeleton, link or joint; this names the section
        raise SceneError(f"articulated: {exc}") from None
    engine = articulated.engine
    start.articulated = articulated
    if engine.action_size:
        start.dart_plan = action_plan(
            scene.articulated.actions, engine.action_size, articulated.n_segments, "articulated.actions"
        )
    if articulated.coupled:
        inertial = any(engine.has_free_dofs(i) for i in articulated.coupled)  # else nothing to add mass to
        start.dart_coupler = MPMRigidCoupler(engine, articulated.coupled, scene.dim, added_mass=inertial)


def _rigid_view(scene: Scene, start: Start) -> None:
    """The rigid bodies the MPM sees, kinematic ones first, then the coupled DART links."""
    from cosim.couplers.rigid_view import RigidBodies

    names, shapes, grids = [], [], []
    if start.kinematic is not None:
        names += [spec.name for spec in scene.rigid.bodies]
        shapes += [spec.shape for spec in scene.rigid.bodies]
        grids += start.kinematic_grids
    if start.dart_coupler is not None:
        from cosim.scene.articulated import link_shapes

        names += start.articulated.names
        shapes += link_shapes(scene, start.articulated.names)
        grids += start.articulated.grids
    start.rigid = RigidBodies(names, shapes, grids, start.kinematic, start.dart_coupler, scene.dim)


def rigid_key(scene: Scene, body: str) -> str:
    """The scene key of a rigid body of ``RigidBodies.names``: ``rigid.bodies[i]`` or the skeleton's."""
    kinematic = [spec.name for spec in scene.rigid.bodies] if scene.rigid is not None else []
    if body in kinematic:
        return f"rigid.bodies[{kinematic.index(body)}]"
    skeletons = [s.name for s in scene.articulated.skeletons]
    return f"articulated.skeletons[{skeletons.index(body.split('/', 1)[0])}]"


def check_start_outside_rigid(scene: Scene, start: Start) -> None:
    """Material starting inside a rigid body would be expelled at once with a huge reaction
    (a floating box started half under water was launched upwards: measured), so refuse it:
    particles more than dx/2 inside a body at t = 0, per soft body and rigid body."""
    depth = 0.5 * scene.dx
    for spec, body in zip(scene.mpm.bodies, start.bodies):
        for rigid, count in start.rigid.particles_inside(body.positions, depth=depth).items():
            if count:
                raise SceneError(
                    f"{rigid_key(scene, rigid)}: {count} particles of body '{spec.name}' start more than dx/2 "
                    f"inside rigid body '{rigid}'; move the body or the material so that they do not overlap at t = 0"
                )


def check_loss_joints(scene: Scene, engine) -> None:
    """Each joint_target term names a skeleton and joint the DART ``engine`` has, and its components
    and target fit the joint (``cosim.losses.terms.joint_dofs``, which the loss is built with)."""
    from cosim.losses.terms import joint_dofs

    terms = scene.loss.all_terms()
    for i, term in enumerate(terms):
        if term.type == "joint_target":
            joint_dofs(term, engine, "loss" if not scene.loss.terms else f"loss.terms[{i}]")
