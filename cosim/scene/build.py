"""A scene made runnable: builds the engines and couplers it needs into a ``CoupledSystem``.

Only what the scene uses is built: soft bodies only -> the MPM engine alone (no
boundaries, no contact hook, no DART, no cloth code); ``rigid:`` bodies -> a
kinematic engine and its coupler; ``articulated:`` skeletons -> the DART engine and
its coupler for the links the MPM sees; one contact model serves every boundary source.
The checks before the first step, and the host-side parts they build (SDFs, the DART engine,
cloth meshes and action plans), come from ``cosim.scene.start.check_start``, which ``cosim
validate`` runs too; this module adds the Taichi side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cosim.errors import SceneError
from cosim.scene.preflight import BodyStart, control_indices, hydrostatic_compression
from cosim.scene.schema import Scene
from cosim.scene.start import Start, check_start
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


def build_system(scene: Scene, requires_grad: bool = False, steps: int | None = None) -> CoupledSystem:
    """The coupled system of ``scene``; ``requires_grad`` builds gradient buffers and fixes K."""
    from cosim.runtime import ensure_taichi

    ensure_taichi(scene.arch, scene.precision, gradients=requires_grad)
    from cosim.engines.mpm import MPMConfig, MPMEngine

    steps = steps or scene.steps
    start = check_start(scene)  # every check before the first step, also `cosim validate`'s
    bodies, affine = build_bodies(scene, start.bodies)
    stepping = build_stepping(scene, bodies, requires_grad, steps, start.exchanges)
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
        scatter=None if scene.mpm.scatter == "auto" else scene.mpm.scatter,
        checkpoints=scene.gradient.checkpoints,
    )
    mpm = MPMEngine(cfg, bodies)
    mpm.set_state({**mpm.state(), "C": affine})  # a ParticleBody carries x, v and F; C enters by the contract
    controls = build_controls(scene, mpm.body_slices(), mpm.state()["x"])
    parts = build_manipulators(scene, mpm, stepping, start)
    rigid = start.rigid  # with rigid engines (a cloth alone needs no rigid view)
    if rigid is not None:
        rigid.sources = parts.rigid_sources
        for cloth_index, cloth in enumerate(parts.cloths):
            parts.couplers += cloth_rigid_couplers(scene, scene.cloth[cloth_index], cloth, rigid)
    domain = np.asarray(scene.cells) * scene.dx
    return CoupledSystem(
        mpm, parts.engines, parts.couplers, stepping, scene.gravity, domain, steps, controls, parts.plans, scene, rigid
    )


def build_stepping(scene: Scene, bodies: list, requires_grad: bool, steps: int, exchanges: int = 1) -> Stepping:
    """Substep settings per exchange, ``exchanges`` per frame (``start.exchanges_per_frame``; ``preflight``
    checked a fixed count per frame against the stability bound, each exchange takes its share); with
    ``requires_grad`` a fixed count for the whole horizon, refused above ``time.max_substeps``."""
    frame_dt, dx = scene.time.frame_dt / exchanges, scene.dx
    wave = max(_wave_speed(b, scene.dim) for b in bodies)
    fixed = math.ceil(scene.time.substeps / exchanges) if scene.time.substeps else 0
    horizon = scene.time.frame_dt * steps  # [s] the fall the gradient run's fixed count must allow for
    speed = max(np.abs(b.velocities).max() for b in bodies) + np.linalg.norm(scene.gravity) * horizon
    grad_substeps = fixed or max(1, math.ceil(frame_dt / (scene.time.cfl * dx / (speed + wave)) - 1e-9))
    if grad_substeps > scene.time.max_substeps and requires_grad:
        raise SceneError(
            f"time.substeps: gradients need a fixed substep count and the CFL bound asks for "
            f"{grad_substeps} > time.max_substeps = {scene.time.max_substeps}; shorten the horizon or frame_dt"
        )
    return Stepping(
        scene.time.frame_dt, scene.time.cfl, scene.time.max_substeps, fixed, grad_substeps, requires_grad, exchanges
    )


@dataclass
class Manipulators:
    """What the scene's rigid bodies add to the system, collected engine by engine."""

    engines: list = field(default_factory=list)
    couplers: list = field(default_factory=list)
    plans: dict = field(default_factory=dict)
    sources: list = field(default_factory=list)  # boundary sources, for the contact model
    rigid_sources: list = field(default_factory=list)  # the rigid ones (``RigidBoundaries``), in body order
    cloths: list = field(default_factory=list)  # cloth engines

    def couple(self, mpm, coupler, grids: list, dim: int, slots: int, grad: bool, added_mass: bool = False) -> None:
        """Attach ``coupler``'s boundary source (``grids``: one SDF per body; ``added_mass``: it reports the
        material that follows each body) to the MPM."""
        from cosim.couplers.boundary import RigidBoundaries

        source = RigidBoundaries(grids, dim, slots, requires_grad=grad, added_mass=added_mass)
        mpm.attach_boundary(coupler.source, source)
        self.couplers.append(coupler)
        self.sources.append(source)
        self.rigid_sources.append(source)


def build_manipulators(scene: Scene, mpm, stepping: Stepping, start: Start) -> Manipulators:
    """The engines, couplers and action plans of the scene's rigid bodies and cloths, from what
    ``check_start`` built: the kinematic ones (``rigid:``) first, then the cloths, then the DART
    skeletons (``articulated:``), each engine with its own boundary source where the MPM sees it,
    all under the scene's one contact model."""
    from cosim.couplers.contact import attach_contact

    out = Manipulators()
    slots = max(scene.time.max_substeps, stepping.grad_substeps)
    grad = stepping.requires_grad
    if start.kinematic is not None:
        out.engines.append(start.kinematic)
        out.couple(mpm, start.kinematic_coupler, start.kinematic_grids, scene.dim, slots, grad)
    for i, cloth in enumerate(start.cloths):  # before DART: a cloth's reaction on DART links enters the same step
        _add_cloth(scene, i, cloth, mpm, out, stepping.frame_dt / stepping.exchanges)
    if start.articulated is not None:
        engine = start.articulated.engine
        out.engines.append(engine)
        if start.dart_plan is not None:
            out.plans[engine.name] = start.dart_plan
        if start.dart_coupler is not None:
            coupler = start.dart_coupler
            out.couple(mpm, coupler, start.articulated.grids, scene.dim, slots, grad, coupler.added_mass)
    if out.sources:  # with nothing the MPM sees, no contact hook
        attach_contact(mpm, out.sources, scene.contact)
    return out


def _add_cloth(scene: Scene, index: int, cloth_start, mpm, out: Manipulators, step_length: float) -> None:
    """A cloth (``cloth[index]``) from its ``ClothStart``, stepping ``step_length`` [s] per exchange: its engine,
    action plan, boundary source (with penetration tracing unless ``contact.tracing`` is off) and coupler."""
    from cosim.couplers.cloth_boundary import ClothBoundary
    from cosim.couplers.mpm_cloth import MPMClothCoupler
    from cosim.scene.cloth import build_cloth

    engine, plan = build_cloth(scene, index, cloth_start, step_length)
    out.engines.append(engine)
    out.cloths.append(engine)
    if plan is not None:
        out.plans[engine.name] = plan
    source = ClothBoundary(mpm, engine.mesh.vertices, engine.mesh.faces, trace=scene.contact.tracing)
    coupler = MPMClothCoupler(engine, max_travel=source.max_step_travel())
    mpm.attach_boundary(coupler.source, source)
    out.couplers.append(coupler)
    out.sources.append(source)


def cloth_rigid_couplers(scene: Scene, spec, cloth, rigid) -> list:
    """The couplers that let a cloth collide with the rigid bodies the MPM sees that have a scene shape
    (python-fcl, ``cosim.couplers.cloth_rigid_coupler``): one for the kinematic bodies (prescribed: they
    take no reaction), one for the DART links (pushed back, differentiated)."""
    from cosim.couplers.cloth_rigid import RigidObstacles
    from cosim.couplers.cloth_rigid_coupler import ClothRigidCoupler

    bodies = [i for i, shape in enumerate(rigid.shapes) if shape is not None and shape.type != "ring"]
    if not bodies:
        return []
    thickness = spec.thickness or 0.5 * scene.dx
    cloth.attach_rigid_contact(thickness, scene.contact.friction)
    n_kinematic = len(rigid.kinematic.motions) if rigid.kinematic is not None else 0
    # (engine, the view's bodies it moves, their indices in that engine)
    kinematic = [i for i in bodies if i < n_kinematic]
    groups = [(rigid.kinematic, kinematic, kinematic)]
    if rigid.coupler is not None:
        dart = [i for i in bodies if i >= n_kinematic]
        groups.append((rigid.coupler.rigid, dart, [rigid.coupler.coupled[i - n_kinematic] for i in dart]))
    out = []
    for engine, members, indices in groups:
        if members:
            obstacles = RigidObstacles(
                [rigid.shapes[i] for i in members], scene.source_dir, [rigid.names[i] for i in members]
            )
            name = f"{cloth.name}-{engine.name}"
            out.append(ClothRigidCoupler(cloth, engine, indices, obstacles, thickness, name))
    return out


def _wave_speed(body, dim: int) -> float:
    from cosim.engines.moduli import wave_speed

    return wave_speed(body.E, body.nu, body.density, dim)
