"""A scene made runnable: builds the engines it needs and steps them safely.

``Simulation`` owns the macro-step loop: it picks the substep count from the
CFL bound (or checks a fixed one), applies the controls, and stops with a
``SimulationError`` naming the step, the body and the quantity as soon as a
step produces NaN/inf, violates the CFL bound or leaves the grid. Scenes with
only soft bodies build only the MPM engine (no DART, no cloth code).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.errors import SceneError, SimulationError
from cosim.scene.schema import Scene

RETRIES = 4  # auto substeps: how often a step is redone with twice the substeps


@dataclass
class Control:
    """Particles driven by impulses: ``indices`` into the engine's particles."""

    body: str
    indices: np.ndarray
    initial: np.ndarray  # (d,) [N s] per particle per macro step


def build_bodies(scene: Scene):
    """Sample every body of the scene into an ``mpm.ParticleBody``."""
    from cosim.engines.mpm import ParticleBody
    from cosim.sampling import sample_shape

    rng = np.random.default_rng(scene.seed)
    bodies = []
    for i, spec in enumerate(scene.mpm.bodies):
        spacing = spec.spacing or 0.5 * scene.dx
        key = f"mpm.bodies[{i}].shape"
        pts = sample_shape(spec.shape, scene.dim, spacing, spec.jitter, rng, key, scene.source_dir)
        domain = np.asarray(scene.cells) * scene.dx
        margin = (scene.mpm.boundary.thickness if scene.mpm.boundary.type != "none" else 2) * scene.dx
        outside = np.any((pts < margin) | (pts > domain - margin), axis=1)
        if outside.any():
            raise SceneError(
                f"mpm.bodies[{i}] ('{spec.name}'): {int(outside.sum())} particles lie outside the usable grid "
                f"[{margin:g}, {domain.tolist()} - {margin:g}] m (walls/margin of the domain); move or shrink the shape"
            )
        vel = np.zeros_like(pts) + (np.asarray(spec.velocity) if spec.velocity is not None else 0.0)
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
                velocities=vel,
                yield_stress=getattr(m, "yield_stress", math.inf),
                viscosity=getattr(m, "viscosity", 0.0),
                deformation=deformation,
            )
        )
    return bodies


def hydrostatic_deformation(pts: np.ndarray, spacing: float, material, gravity) -> np.ndarray:
    """F = J^(1/d) I with J = 1 - rho |g| depth / K: the liquid's own weight balanced.

    The pressure law sigma = K (J - 1) I makes the Cauchy pressure
    p = K (1 - J); depth is measured along gravity from the body's top.
    """
    from cosim.engines.materials import lame_parameters

    dim = pts.shape[1]
    g = np.asarray(gravity, dtype=np.float64)
    g_norm = np.linalg.norm(g)
    if g_norm == 0:
        return np.broadcast_to(np.eye(dim), (len(pts), dim, dim)).copy()
    up = -g / g_norm
    height = pts @ up
    depth = height.max() + 0.5 * spacing - height
    mu, lam = lame_parameters(material.E, material.nu, dim)
    J = 1.0 - material.density * g_norm * depth / (lam + 2.0 * mu / dim)
    return J[:, None, None] ** (1.0 / dim) * np.eye(dim)[None]


def build_controls(scene: Scene, slices: dict[str, slice], x0: np.ndarray) -> list[Control]:
    controls = []
    for i, spec in enumerate(scene.controls):
        sl = slices[spec.body]
        idx = np.arange(sl.start, sl.stop)
        if spec.region is not None:
            pts = x0[idx]
            keep = np.all((pts >= spec.region.min) & (pts <= spec.region.max), axis=1)
            idx = idx[keep]
        if len(idx) == 0:
            raise SceneError(f"controls[{i}].region: selects no particle of body '{spec.body}'")
        initial = np.zeros(scene.dim) if spec.impulse is None else np.asarray(spec.impulse, float)
        controls.append(Control(spec.body, idx, initial))
    return controls


def rotation_matrix(value, dim: int) -> np.ndarray:
    """A scene rotation (2D angle, 3D rotation vector) as a matrix."""
    from cosim.engines.kinematic import rotation_about

    if dim == 2:
        return rotation_about(float(value), 1.0, 2)
    vec = np.zeros(3) if isinstance(value, (int, float)) else np.asarray(value, dtype=np.float64)
    return rotation_about(vec, 1.0, 3)


def build_motion(spec, dim: int):
    """A kinematic.Motion from a validated rigid-body spec."""
    from cosim.engines.kinematic import Motion, Segment

    p0 = np.asarray(spec.position, dtype=np.float64)
    R0 = rotation_matrix(spec.rotation, dim)
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


class Simulation:
    """The MPM scene runner. ``requires_grad`` builds gradient buffers and fixes K."""

    def __init__(self, scene: Scene, requires_grad: bool = False, steps: int | None = None):
        from cosim.runtime import ensure_taichi

        self.scene = scene
        self.steps = steps or scene.steps
        self.requires_grad = requires_grad
        ensure_taichi(scene.arch, scene.precision)
        from cosim.engines.mpm import MPMConfig, MPMEngine

        bodies = build_bodies(scene)
        self.frame_dt = scene.time.frame_dt
        self.dx = scene.dx
        wave = max(_wave_speed(b, scene.dim) for b in bodies)
        self.wave_speed = wave
        fixed = scene.time.substeps
        if fixed:
            dt = self.frame_dt / fixed
            if dt * wave / self.dx > 1.0:
                worst = max(bodies, key=lambda b: _wave_speed(b, scene.dim))
                need = math.ceil(self.frame_dt * wave / (scene.time.cfl * self.dx))
                raise SceneError(
                    f"time.substeps: {fixed} substeps give dt = {dt:.3g} s, above the explicit stability bound "
                    f"dx / c = {self.dx / wave:.3g} s of body '{worst.name}' (elastic wave speed c = {wave:.3g} m/s "
                    f"from its E); use at least {need} substeps, or 'auto'"
                )
        self.grad_substeps = fixed or self._auto_substeps(
            max(np.abs(b.velocities).max() for b in bodies) + np.linalg.norm(scene.gravity) * self.frame_dt * self.steps
        )
        if self.grad_substeps > scene.time.max_substeps and requires_grad:
            raise SceneError(
                f"time.substeps: gradients need a fixed substep count and the CFL bound asks for "
                f"{self.grad_substeps} > time.max_substeps = {scene.time.max_substeps}; shorten the horizon or frame_dt"
            )
        cfg = MPMConfig(
            dim=scene.dim,
            cells=scene.cells,
            dx=self.dx,
            gravity=scene.gravity,
            wall=scene.mpm.boundary.type,
            wall_cells=scene.mpm.boundary.thickness,
            requires_grad=requires_grad,
            grad_substeps=self.grad_substeps if requires_grad else 1,
            has_controls=bool(scene.controls),
        )
        self.mpm = MPMEngine(cfg, bodies)
        self.slices = self.mpm.body_slices()
        self.controls = build_controls(scene, self.slices, self.mpm.state()["x"])
        self.step_index = 0
        self.max_cfl = 0.0
        # called as before_step(t0, dt, K) before each MPM step without DART: moving boundaries set their states
        self.before_step = None
        self.rigid = None
        self.articulated = None  # DART skeletons (cosim.articulated.Articulated)
        self.coupler = None  # MPM <-> DART (cosim.couplers.mpm_rigid)
        self.last_coupled = None  # the coupled record of the last step
        if scene.rigid is not None or scene.articulated is not None:
            self._build_rigid()

    def _build_rigid(self) -> None:
        """Rigid bodies as SDF boundaries under the scene's contact model: the kinematic ones
        (``rigid:``) first, then the coupled links of DART skeletons (``articulated:``)."""
        from cosim.couplers.contact import RigidBoundaries
        from cosim.couplers.sdf import shape_sdf

        scene = self.scene
        names, shapes, grids, motions = [], [], [], []
        for i, spec in enumerate(scene.rigid.bodies if scene.rigid else []):
            spacing = spec.sdf_spacing or 0.5 * self.dx
            grids.append(
                shape_sdf(spec.shape, scene.dim, spacing, 3 * self.dx, scene.source_dir, f"rigid.bodies[{i}].shape")
            )
            motions.append(build_motion(spec, scene.dim))
            names.append(spec.name)
            shapes.append(spec.shape)
        articulated = None
        if scene.articulated is not None:
            from cosim.articulated import build_articulated, link_shapes

            articulated = build_articulated(scene, self.dx)
            names += articulated.names
            shapes += link_shapes(scene, articulated.names)
            grids += articulated.grids
        slots = max(scene.time.max_substeps, self.grad_substeps)
        boundaries = RigidBoundaries(grids, scene.dim, slots, requires_grad=self.requires_grad) if grids else None
        if boundaries is not None:  # with nothing the MPM sees, no contact hook
            self._attach_contact(boundaries)
        coupler = None
        if articulated is not None:
            from cosim.articulated import action_sequence
            from cosim.couplers.mpm_rigid import MPMRigidCoupler

            coupler = MPMRigidCoupler(articulated.engine, boundaries, articulated.coupled, len(motions), scene.dim)
            self.articulated = articulated
            self.coupler = coupler
            self.rigid_state0 = articulated.engine.state()
            self.rigid_actions = action_sequence(scene, articulated.engine.action_size, articulated.n_segments)
        self.rigid = RigidScene(names, shapes, grids, motions, boundaries, coupler, scene.dim)
        if boundaries is not None:
            self.before_step = self.set_boundaries
        self._check_start_outside_rigid()

    def _check_start_outside_rigid(self) -> None:
        """Material starting inside a rigid body would be expelled at once with a huge reaction
        (a floating box started half under water was launched upwards: measured), so refuse it."""
        deep = self.rigid.particles_inside(self.mpm.state()["x"], 0.0, depth=0.5 * self.dx)
        for body, count in deep.items():
            if count:
                raise SceneError(
                    f"{count} particles start more than dx/2 inside rigid body '{body}'; move the body or the "
                    "material so that they do not overlap at t = 0"
                )

    def _attach_contact(self, boundaries) -> None:
        """The scene's contact model between the MPM and ``boundaries``."""
        from cosim.couplers.contact import ForecastContact, GridContact, ParticlePenalty

        c = self.scene.contact
        if c.model == "grid":
            GridContact(self.mpm, boundaries, c.friction, c.band)
        elif c.model == "forecast":
            ForecastContact(self.mpm, boundaries, c.friction, c.alpha, c.threshold, c.smoothing)
        else:
            ParticlePenalty(self.mpm, boundaries, c.stiffness, c.friction)

    def set_boundaries(self, t0: float, dt: float, K: int, bodies=None) -> None:
        """Per-substep states of every rigid boundary for the step starting at t0: kinematic bodies
        from their motions, DART links from ``bodies`` (default: the rigid engine's current state)."""
        from cosim.couplers.contact import kinematic_states

        parts = []
        if self.rigid.motions:
            parts.append(kinematic_states(self.rigid.motions, t0, dt, K))
        if self.coupler is not None:
            bodies = self.coupler.current_bodies() if bodies is None else bodies
            parts.append(self.coupler.boundary_arrays(bodies, dt, K))
        arrays = [np.concatenate([p[i] for p in parts], axis=1) for i in range(4)]
        self.rigid.boundaries.set_states(*arrays)

    def step_vjp(self, record, grad: dict[str, np.ndarray]) -> dict:
        """Vector-Jacobian product of one recorded macro step (the tape's ``step_vjp``).

        MPM only: restore the step's boundaries and run the MPM vjp. Coupled (the paper's
        backward equations): DART's vjp gives dL/ds_D^n (own dynamics), dL/da^n and dL/dF^n;
        dL/dF^n seeds the reaction adjoints, so the MPM vjp returns dL/ds_M^n along both
        paths and the boundary adjoints, which the coupler takes back to dL/ds_D^n.
        """
        from cosim.engines.mpm import STATE_KEYS

        mpm_grad = {k: grad[k] for k in STATE_KEYS}
        if self.coupler is None:
            if self.before_step is not None:
                self.before_step(record.time, record.dt, record.substeps)
            return self.mpm.vjp(record.as_dict(), mpm_grad)
        c = record.coupled
        g_dynamics, g_action, g_wrenches = self.articulated.engine.vjp(c.rigid, grad["rigid"])
        arms = self.coupler.seed_reaction_grads(c, g_wrenches)
        if self.rigid.boundaries is not None:
            self.set_boundaries(record.time, record.dt, record.substeps, c.bodies)
        out = self.mpm.vjp(record.as_dict(), mpm_grad)
        out["state"]["rigid"] = g_dynamics + self.coupler.boundary_vjp(c, arms)
        out["action"] = g_action
        return out

    def action(self, n: int, actions: np.ndarray | None = None) -> np.ndarray | None:
        """The rigid action of macro step n from a sequence (default: the scene's), held ``hold`` steps."""
        if self.articulated is None:
            return None
        seq = self.rigid_actions if actions is None else actions
        return seq[self.action_segment(n, len(seq))]

    def action_segment(self, n: int, segments: int) -> int:
        """Which of ``segments`` held actions macro step n uses (the last one after the sequence)."""
        return min(n // self.articulated.hold, segments - 1)

    # ------------------------------------------------------------ time stepping
    def _auto_substeps(self, speed: float) -> int:
        """Substeps so that (|v| + c) dt / dx <= cfl, c the fastest elastic wave."""
        bound = self.scene.time.cfl * self.dx / (speed + self.wave_speed)
        return max(1, math.ceil(self.frame_dt / bound - 1e-9))

    def default_actions(self) -> list[np.ndarray]:
        """The scene's initial action sequence: one (n_ctrl, d) array per control."""
        return [np.broadcast_to(c.initial, (self.steps, len(c.indices), self.scene.dim)).copy() for c in self.controls]

    def impulse_field(self, actions: list[np.ndarray] | None, n: int) -> np.ndarray | None:
        """Per-particle impulses (N, d) of macro step ``n`` from the control actions."""
        if not self.controls:
            return None
        full = np.zeros((self.mpm.n_particles, self.scene.dim))
        for c, a in zip(self.controls, actions or self.default_actions()):
            full[c.indices] += a[n]
        return full

    def step(self, impulse: np.ndarray | None = None, action: np.ndarray | None = None):
        """One macro step with checks (MPM, then DART with the averaged reactions when the
        scene has skeletons); returns the MPM's StepInfo. ``action``: the rigid action
        (default: the scene's sequence)."""
        state = self.mpm.state()
        bodies = self.coupler.current_bodies() if self.coupler is not None else None
        speed = float(np.abs(state["v"]).max()) + np.linalg.norm(self.scene.gravity) * self.frame_dt
        fixed = self.scene.time.substeps or (self.grad_substeps if self.requires_grad else 0)
        K = fixed or self._auto_substeps(speed)
        for attempt in range(RETRIES + 1):
            if K > self.scene.time.max_substeps:
                raise SimulationError(
                    f"step {self.step_index}: the CFL bound needs {K} substeps, more than time.max_substeps = "
                    f"{self.scene.time.max_substeps} (max speed {speed:.3g} m/s): the simulation is blowing up or "
                    "frame_dt is too long"
                )
            if self.coupler is not None and self.rigid.boundaries is not None:
                self.set_boundaries(self.step_index * self.frame_dt, self.frame_dt / K, K, bodies)
            elif self.before_step is not None:
                self.before_step(self.step_index * self.frame_dt, self.frame_dt / K, K)
            info = self.mpm.step(self.frame_dt / K, K, impulse)
            after = self.mpm.state()
            self._check_finite(after)
            cfl, body = self._cfl(after, self.frame_dt / K)
            if cfl <= self.scene.time.cfl:
                break
            if fixed or attempt == RETRIES:
                if self.scene.time.substeps:
                    fix = "raise time.substeps or set it to 'auto'"
                elif fixed:
                    fix = f"gradient runs fix the substeps at the start ({K} here); set time.substeps higher"
                else:
                    fix = "the motion is too violent for time.max_substeps"
                raise SimulationError(
                    f"step {self.step_index}: CFL number {cfl:.3f} > {self.scene.time.cfl} in body '{body}' "
                    f"(max |v| dt / dx with dt = {self.frame_dt / K:.3g} s); {fix}"
                )
            self.mpm.set_state(state)
            K *= 2
        self._check_domain(after)
        if self.coupler is not None:
            act = self.action(self.step_index) if action is None else action
            self.last_coupled = self.coupler.finish_step(bodies, act, self.frame_dt / K, K)
        self.max_cfl = max(self.max_cfl, cfl)
        self.step_index += 1
        return info

    # ------------------------------------------------------------ checks
    def _per_body(self, values: np.ndarray):
        for name, sl in self.slices.items():
            yield name, values[sl]

    def _check_finite(self, state: dict[str, np.ndarray]) -> None:
        names = {"x": "position", "v": "velocity", "F": "deformation gradient", "C": "affine velocity"}
        for key in ("v", "x", "F", "C"):
            for body, vals in self._per_body(state[key]):
                bad = ~np.isfinite(vals.reshape(len(vals), -1)).all(axis=1)
                if bad.any():
                    raise SimulationError(
                        f"step {self.step_index}: body '{body}': non-finite {names[key]} ({key}) in "
                        f"{int(bad.sum())} particles; the step is unstable: lower time.frame_dt, use more substeps "
                        "or a smaller time.cfl, or check the material's E"
                    )

    def _cfl(self, state: dict[str, np.ndarray], dt: float) -> tuple[float, str]:
        worst, name = 0.0, ""
        for body, vals in self._per_body(state["v"]):
            c = float(np.abs(vals).max()) * dt / self.dx
            if c > worst:
                worst, name = c, body
        return worst, name

    def _check_domain(self, state: dict[str, np.ndarray]) -> None:
        domain = np.asarray(self.scene.cells) * self.dx
        for body, vals in self._per_body(state["x"]):
            out = np.any((vals < self.dx) | (vals > domain - self.dx), axis=1)
            if out.any():
                raise SimulationError(
                    f"step {self.step_index}: body '{body}': {int(out.sum())} particles left the grid domain "
                    f"[0, {domain.tolist()}] m; enable walls (mpm.boundary.type) or enlarge mpm.grid"
                )


@dataclass
class RigidScene:
    """The scene's rigid bodies: names, SDF grids, motions and their MPM boundary."""

    names: list[str]
    shapes: list  # scene RigidShape specs (None: a URDF link)
    grids: list
    motions: list  # of the kinematic bodies, which come first
    boundaries: object
    coupler: object = None  # DART links after them (cosim.couplers.mpm_rigid)
    dim: int = 3

    def poses(self, t: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """(position, rotation) of every body: kinematic ones at time t, DART links now."""
        out = [m.pose(t) for m in self.motions]
        if self.coupler is not None:
            b = self.coupler.current_bodies()
            d = self.dim
            out += [(p[:d].copy(), R[:d, :d].copy()) for p, R in zip(b.pos, b.R)]
        return out

    def particles_inside(self, x: np.ndarray, t: float, depth: float = 0.0) -> dict[str, int]:
        """How many particles sit inside each body (signed distance < -depth) at time t."""
        out = {}
        for name, grid, (p, R) in zip(self.names, self.grids, self.poses(t)):
            d, _ = grid.sample((x - p) @ R)  # world to body frame: R^T (x - p)
            out[name] = int(np.sum(d < -depth))
        return out

    def particles_held(self, x: np.ndarray, t: float) -> dict[str, int]:
        """How many particles each container body (glass, ring) holds in its cavity at time t
        (not counting those inside its wall, which ``particles_inside`` counts)."""
        from cosim.couplers.sdf import in_cavity, is_container

        out = {}
        for name, shape, grid, (p, R) in zip(self.names, self.shapes, self.grids, self.poses(t)):
            if shape is not None and is_container(shape):
                local = (x - p) @ R
                out[name] = int(np.sum(in_cavity(shape, local) & (grid.sample(local)[0] >= 0)))
        return out


def _wave_speed(body, dim: int) -> float:
    from cosim.engines.materials import wave_speed

    return wave_speed(body.E, body.nu, body.density, dim)
