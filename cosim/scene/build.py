"""A scene made runnable: builds the engines and couplers it needs into a ``CoupledSystem``.

Only what the scene uses is built: soft bodies only -> the MPM engine alone (no
boundaries, no contact hook, no DART, no cloth code); ``rigid:`` bodies -> a
kinematic engine and its coupler; ``articulated:`` skeletons -> the DART engine and
its coupler for the links the MPM sees; one contact model serves every boundary source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cosim.engines import so3
from cosim.errors import SceneError
from cosim.scene.preflight import BodyStart, control_indices, hydrostatic_compression, preflight
from cosim.scene.schema import Scene
from cosim.system import Control, CoupledSystem, Stepping


def build_bodies(scene: Scene, starts: list[BodyStart]) -> tuple[list, np.ndarray]:
    """Every body of the scene as an ``mpm.ParticleBody`` from its start (``preflight``): particles,
    material and initial velocities; and every particle's initial APIC affine velocity C
    (N, dim, dim) [1/s], the bodies in order."""
    from cosim.engines.mpm import ParticleBody

    bodies = []
    for spec, start in zip(scene.mpm.bodies, starts):
        spacing = spec.spacing or 0.5 * scene.dx
        pts = start.positions
        m = spec.material
        deformation = hydrostatic_deformation(pts, spacing, m, scene.gravity) if spec.hydrostatic else None
        bodies.append(
            ParticleBody(
                name=spec.name,
                material=m.type,
                E=m.E,
                nu=m.nu,
                density=m.density,
                particle_volume=spacing**scene.dim,
                positions=pts,
                velocities=start.velocities,
                yield_stress=getattr(m, "yield_stress", math.inf),
                viscosity=getattr(m, "viscosity", 0.0),
                deformation=deformation,
            )
        )
    return bodies, np.concatenate([start.affine for start in starts])


def hydrostatic_deformation(pts: np.ndarray, spacing: float, material, gravity) -> np.ndarray:
    """F = J^(1/d) I with J = 1 - rho |g| depth / K: the liquid's own weight balanced.

    The pressure law sigma = K (J - 1) I makes the Cauchy pressure
    p = K (1 - J); depth is measured along gravity from the body's top
    (``preflight.hydrostatic_compression``; ``preflight`` refused J <= 0).
    """
    dim = pts.shape[1]
    J = hydrostatic_compression(pts, spacing, material, gravity)
    return J[:, None, None] ** (1.0 / dim) * np.eye(dim)[None]


def build_controls(scene: Scene, slices: dict[str, slice], x0: np.ndarray) -> list[Control]:
    """The impulse controls on particles of ``x0`` (all bodies' positions; ``preflight`` checked
    that each region selects some)."""
    controls = []
    for spec in scene.controls:
        sl = slices[spec.body]
        idx = sl.start + control_indices(spec, x0[sl])
        initial = np.zeros(scene.dim) if spec.impulse is None else np.asarray(spec.impulse, float)
        controls.append(Control(spec.body, idx, initial))
    return controls


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


def build_system(scene: Scene, requires_grad: bool = False, steps: int | None = None) -> CoupledSystem:
    """The coupled system of ``scene``; ``requires_grad`` builds gradient buffers and fixes K."""
    from cosim.runtime import ensure_taichi

    ensure_taichi(scene.arch, scene.precision, gradients=requires_grad)
    from cosim.engines.mpm import MPMConfig, MPMEngine

    steps = steps or scene.steps
    bodies, affine = build_bodies(scene, preflight(scene))
    stepping = build_stepping(scene, bodies, requires_grad, steps)
    cfg = MPMConfig(
        dim=scene.dim,
        cells=scene.cells,
        dx=scene.dx,
        gravity=scene.gravity,
        wall=scene.mpm.boundary.type,
        wall_cells=scene.mpm.boundary.thickness,
        requires_grad=requires_grad,
        grad_substeps=stepping.grad_substeps if requires_grad else 1,
        has_controls=bool(scene.controls),
    )
    mpm = MPMEngine(cfg, bodies)
    mpm.set_state({**mpm.state(), "C": affine})  # a ParticleBody carries x, v and F; C enters by the contract
    controls = build_controls(scene, mpm.body_slices(), mpm.state()["x"])
    parts = build_manipulators(scene, mpm, stepping)
    rigid = None
    if any(e not in parts.cloths for e in parts.engines):  # rigid engines (a cloth alone needs no rigid view)
        from cosim.couplers.rigid_view import RigidBodies

        rigid = RigidBodies(
            parts.names, parts.shapes, parts.grids, parts.kinematic, parts.dart_coupler, scene.dim, parts.rigid_sources
        )
        _check_start_outside_rigid(rigid, mpm.state()["x"], scene.dx)
        for cloth_index, cloth in enumerate(parts.cloths):
            _attach_cloth_rigid_contact(scene, scene.cloth[cloth_index], cloth, rigid)
    domain = np.asarray(scene.cells) * scene.dx
    return CoupledSystem(
        mpm, parts.engines, parts.couplers, stepping, scene.gravity, domain, steps, controls, parts.plans, scene, rigid
    )


def build_stepping(scene: Scene, bodies: list, requires_grad: bool, steps: int) -> Stepping:
    """Substep settings (``preflight`` checked a fixed count against the stability bound); with
    ``requires_grad`` a fixed count for the whole horizon, refused above ``time.max_substeps``."""
    frame_dt, dx = scene.time.frame_dt, scene.dx
    wave = max(_wave_speed(b, scene.dim) for b in bodies)
    fixed = scene.time.substeps
    speed = max(np.abs(b.velocities).max() for b in bodies) + np.linalg.norm(scene.gravity) * frame_dt * steps
    grad_substeps = fixed or max(1, math.ceil(frame_dt / (scene.time.cfl * dx / (speed + wave)) - 1e-9))
    if grad_substeps > scene.time.max_substeps and requires_grad:
        raise SceneError(
            f"time.substeps: gradients need a fixed substep count and the CFL bound asks for "
            f"{grad_substeps} > time.max_substeps = {scene.time.max_substeps}; shorten the horizon or frame_dt"
        )
    return Stepping(frame_dt, scene.time.cfl, scene.time.max_substeps, fixed or 0, grad_substeps, requires_grad)


@dataclass
class Manipulators:
    """What the scene's rigid bodies add to the system, collected engine by engine."""

    engines: list = field(default_factory=list)
    couplers: list = field(default_factory=list)
    plans: dict = field(default_factory=dict)
    sources: list = field(default_factory=list)  # boundary sources, for the contact model
    rigid_sources: list = field(default_factory=list)  # the rigid ones (``RigidBoundaries``), in body order
    names: list = field(default_factory=list)  # rigid bodies the MPM sees, in source order
    shapes: list = field(default_factory=list)
    grids: list = field(default_factory=list)
    kinematic: object = None
    dart_coupler: object = None
    cloths: list = field(default_factory=list)  # cloth engines

    def couple(self, mpm, coupler, grids: list, dim: int, slots: int, grad: bool) -> None:
        """Attach ``coupler``'s boundary source (``grids``: one SDF per body) to the MPM."""
        from cosim.couplers.boundary import RigidBoundaries

        source = RigidBoundaries(grids, dim, slots, requires_grad=grad)
        mpm.attach_boundary(coupler.source, source)
        self.couplers.append(coupler)
        self.sources.append(source)
        self.rigid_sources.append(source)
        self.grids += grids


def build_manipulators(scene: Scene, mpm, stepping: Stepping) -> Manipulators:
    """The engines, couplers and action plans of the scene's rigid bodies: the kinematic ones
    (``rigid:``) first, then the coupled links of DART skeletons (``articulated:``), each
    engine with its own boundary source, all under the scene's one contact model."""
    from cosim.couplers.contact import attach_contact

    out = Manipulators()
    slots = max(scene.time.max_substeps, stepping.grad_substeps)
    if scene.rigid is not None and scene.rigid.bodies:
        _add_kinematic(scene, mpm, out, slots, stepping.requires_grad)
    for i in range(len(scene.cloth)):  # before DART: a cloth's reaction on DART links enters the same step
        _add_cloth(scene, i, mpm, out)
    if scene.articulated is not None:
        _add_articulated(scene, mpm, out, slots, stepping.requires_grad)
    if out.sources:  # with nothing the MPM sees, no contact hook
        attach_contact(mpm, out.sources, scene.contact)
    return out


def _add_kinematic(scene: Scene, mpm, out: Manipulators, slots: int, grad: bool) -> None:
    """Prescribed motions (``rigid:``) as a kinematic engine and its coupler."""
    from cosim.couplers.mpm_kinematic import MPMKinematicCoupler
    from cosim.couplers.sdf import shape_sdf
    from cosim.engines.kinematic import KinematicEngine

    specs = scene.rigid.bodies
    grids = [
        shape_sdf(
            spec.shape,
            scene.dim,
            spec.sdf_spacing or 0.5 * scene.dx,
            3 * scene.dx,
            scene.source_dir,
            f"rigid.bodies[{i}].shape",
        )
        for i, spec in enumerate(specs)
    ]
    motions = [build_motion(spec, scene.dim) for spec in specs]
    out.kinematic = KinematicEngine(motions, [spec.name for spec in specs], scene.time.frame_dt)
    out.engines.append(out.kinematic)
    out.couple(mpm, MPMKinematicCoupler(out.kinematic), grids, scene.dim, slots, grad)
    out.names += [spec.name for spec in specs]
    out.shapes += [spec.shape for spec in specs]


def _add_articulated(scene: Scene, mpm, out: Manipulators, slots: int, grad: bool) -> None:
    """DART skeletons (``articulated:``): the engine, its action plan and, for the links the MPM
    sees, the coupler (a skeleton the MPM never sees needs none)."""
    from cosim.couplers.mpm_rigid import MPMRigidCoupler
    from cosim.scene.actions import action_plan
    from cosim.scene.articulated import build_articulated, link_shapes

    articulated = build_articulated(scene, scene.dx)
    engine = articulated.engine
    out.engines.append(engine)
    if engine.action_size:
        plan = action_plan(scene.articulated.actions, engine.action_size, articulated.n_segments, "articulated.actions")
        out.plans[engine.name] = plan
    if articulated.coupled:
        out.dart_coupler = MPMRigidCoupler(engine, articulated.coupled, scene.dim)
        out.couple(mpm, out.dart_coupler, articulated.grids, scene.dim, slots, grad)
        out.names += articulated.names
        out.shapes += link_shapes(scene, articulated.names)


def _add_cloth(scene: Scene, index: int, mpm, out: Manipulators) -> None:
    """A cloth (``cloth[index]``): its engine, action plan, boundary source (with penetration
    tracing unless ``contact.tracing`` is off) and coupler."""
    from cosim.couplers.cloth_boundary import ClothBoundary
    from cosim.couplers.mpm_cloth import MPMClothCoupler
    from cosim.scene.cloth import build_cloth

    engine, plan = build_cloth(scene, index)
    out.engines.append(engine)
    out.cloths.append(engine)
    if plan is not None:
        out.plans[engine.name] = plan
    source = ClothBoundary(mpm, engine.mesh.vertices, engine.mesh.faces, trace=scene.contact.tracing)
    coupler = MPMClothCoupler(engine, max_travel=source.max_step_travel())
    mpm.attach_boundary(coupler.source, source)
    out.couplers.append(coupler)
    out.sources.append(source)


def _attach_cloth_rigid_contact(scene: Scene, spec, cloth, rigid) -> None:
    """Let a cloth collide with the rigid bodies the MPM sees that have a scene shape (python-fcl
    planes, ``cosim.couplers.cloth_rigid``); DART links take the reaction, kinematic bodies none."""
    from cosim.couplers.cloth_rigid import RigidObstacles

    bodies = [i for i, shape in enumerate(rigid.shapes) if shape is not None and shape.type != "ring"]
    if not bodies:
        return
    obstacles = RigidObstacles([rigid.shapes[i] for i in bodies], scene.source_dir, [rigid.names[i] for i in bodies])
    thickness = spec.thickness or 0.5 * scene.dx
    n_kinematic = len(rigid.kinematic.motions) if rigid.kinematic is not None else 0

    def planes(points):
        poses = rigid.poses()
        return obstacles.planes(points, [poses[i] for i in bodies], thickness)

    route = None
    coupler = rigid.coupler
    if coupler is not None and any(i >= n_kinematic for i in bodies):

        def route(wrenches):
            poses = rigid.poses()
            w = wrenches(np.array([poses[i][0] for i in bodies]))
            full = np.zeros((len(coupler.rigid.body_names), 6))
            for row, i in enumerate(bodies):
                if i >= n_kinematic:
                    full[coupler.coupled[i - n_kinematic]] += w[row]
            return {coupler.engine: full}

    cloth.attach_rigid_contact(planes, thickness, route, scene.contact.friction)


def _check_start_outside_rigid(rigid, x: np.ndarray, dx: float) -> None:
    """Material starting inside a rigid body would be expelled at once with a huge reaction
    (a floating box started half under water was launched upwards: measured), so refuse it."""
    for body, count in rigid.particles_inside(x, depth=0.5 * dx).items():
        if count:
            raise SceneError(
                f"{count} particles start more than dx/2 inside rigid body '{body}'; move the body or the "
                "material so that they do not overlap at t = 0"
            )


def _wave_speed(body, dim: int) -> float:
    from cosim.engines.moduli import wave_speed

    return wave_speed(body.E, body.nu, body.density, dim)
