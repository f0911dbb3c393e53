"""The start-of-run checks of the soft bodies, in NumPy (no Taichi, no DART).

``cosim.scene.start.check_start`` runs them first (then the cloths', rigid bodies' and skeletons'),
for ``cosim validate`` and ``build_system`` alike: the grid fits in memory, every body samples
into the grid, its initial velocity (expressions or a file) is finite and fits its particles,
control regions select particles, a fixed substep count is below the explicit stability bound
and an automatic one within ``time.max_substeps``, a liquid started hydrostatic is stiff enough
to carry its own weight, and a loss's target points can be read.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from cosim.engines.moduli import lame_parameters, viscous_time_step, wave_speed
from cosim.errors import SceneError
from cosim.scene.particles import body_positions
from cosim.scene.schema import Scene, VelocityFile
from cosim.scene.velocity_field import GRADIENT_STEP, velocity_field, velocity_gradient
from cosim.scene.velocity_file import file_velocity

# Share of the machine's memory the forward run's grid may take (the particles, tape and
# the rest of the process need the remainder).
GRID_MEMORY_SHARE = 0.5


@dataclass
class BodyStart:
    """A body's particles at the start: positions (n, dim) [m] (``body_positions``), velocities
    (n, dim) [m/s] and APIC affine velocities C (n, dim, dim) [1/s] (``body_velocity``)."""

    positions: np.ndarray
    velocities: np.ndarray
    affine: np.ndarray


def preflight(scene: Scene) -> list[BodyStart]:
    """Run the soft bodies' start checks; return every body's start, which ``build_system`` builds from
    (so a velocity file is read, and a point cloud triangulated, once)."""
    check_grid_memory(scene)
    positions = body_positions(scene)
    check_control_regions(scene, positions)
    bodies = [BodyStart(pts, *body_velocity(scene, i, pts)) for i, pts in enumerate(positions)]
    check_substeps(scene, [b.velocities for b in bodies])
    check_hydrostatic(scene, positions)
    check_loss_targets(scene)
    return bodies


def machine_memory() -> int:
    """Physical memory [bytes] of this machine."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_grid_memory(scene: Scene) -> None:
    """The grid's nodes (velocity and mass per node, in the scene's precision) fit in memory."""
    nodes = math.prod(c + 1 for c in scene.cells)
    need = nodes * (scene.dim + 1) * (8 if scene.precision == "float64" else 4)
    have = machine_memory()
    if need > GRID_MEMORY_SHARE * have:
        raise SceneError(
            f"mpm.grid.cells: {scene.cells} is {nodes:.3g} grid nodes, {need / 2**30:.3g} GiB for the grid "
            f"alone, more than half this machine's {have / 2**30:.3g} GiB; use fewer cells (a larger dx)"
        )


def control_indices(spec, positions: np.ndarray) -> np.ndarray:
    """Indices into ``positions`` (one body's particles) a ``ControlSpec`` acts on: all, or those
    in its region at the start."""
    if spec.region is None:
        return np.arange(len(positions))
    lo, hi = np.asarray(spec.region.min), np.asarray(spec.region.max)
    return np.flatnonzero(np.all((positions >= lo) & (positions <= hi), axis=1))


def check_control_regions(scene: Scene, bodies: list[np.ndarray]) -> None:
    by_name = {spec.name: pts for spec, pts in zip(scene.mpm.bodies, bodies)}
    for i, ctl in enumerate(scene.controls):
        if len(control_indices(ctl, by_name[ctl.body])) == 0:
            raise SceneError(
                f"controls[{i}].region: selects no particle of body '{ctl.body}'; "
                "move the box over the body (min and max in metres)"
            )


def first_frame_substeps(scene: Scene, velocities: list[np.ndarray]) -> int:
    """The substeps of the first frame: the fixed count, else the CFL and viscous bounds' (``_needs``)."""
    return scene.time.substeps or max(1, math.ceil(max(n[0] for n in _needs(scene, velocities)) - 1e-9))


def _needs(scene: Scene, velocities: list[np.ndarray]) -> list[tuple]:
    """Per body: (substeps the first frame needs, its index, wave speed c [m/s], initial speed [m/s], viscous
    bound [s]), from the CFL bound over c, the initial speed and one frame of gravity, and the viscous bound."""
    frame_dt, dx, time = scene.time.frame_dt, scene.dx, scene.time
    fall = float(np.linalg.norm(scene.gravity)) * frame_dt
    out = []
    for i, spec in enumerate(scene.mpm.bodies):
        m = spec.material
        c = wave_speed(m.E, m.nu, m.density, scene.dim)
        v = float(np.linalg.norm(velocities[i], axis=1).max()) if len(velocities[i]) else 0.0
        viscous = viscous_time_step(m.density, getattr(m, "viscosity", 0.0), dx, scene.dim)
        out.append((max(frame_dt * (c + v + fall) / (time.cfl * dx), frame_dt / viscous), i, c, v, viscous))
    return out


def check_substeps(scene: Scene, velocities: list[np.ndarray]) -> None:
    """A fixed count keeps dt below dx / c and the viscous bound rho dx^2 / (2 d eta); an automatic
    count for the first frame (initial speeds, one frame of gravity) stays within ``time.max_substeps``."""
    frame_dt, dx, time = scene.time.frame_dt, scene.dx, scene.time
    worst = None  # (substeps needed, body index, wave speed, initial speed, viscous bound)
    for need, i, c, v, viscous in _needs(scene, velocities):
        spec = scene.mpm.bodies[i]
        m = spec.material
        dt = frame_dt / time.substeps if time.substeps else 0.0
        if dt * c > dx:
            raise SceneError(
                f"time.substeps: {time.substeps} substeps give dt = {dt:.3g} s, above the "
                f"explicit stability bound dx / c = {dx / c:.3g} s of body '{spec.name}' (elastic wave speed "
                f"c = {c:.3g} m/s from its E); use at least {math.ceil(need)} substeps, or 'auto'"
            )
        if dt > viscous:
            raise SceneError(
                f"time.substeps: {time.substeps} substeps give dt = {dt:.3g} s, above the explicit viscous "
                f"bound rho dx^2 / (2 d eta) = {viscous:.3g} s of body '{spec.name}' (mpm.bodies[{i}].material."
                f"viscosity = {m.viscosity:g} Pa s); use at least {math.ceil(need)} substeps, or 'auto'"
            )
        if worst is None or need > worst[0]:
            worst = (need, i, c, v, viscous)
    need, i, c, v, viscous = worst
    if not time.substeps and need > time.max_substeps:
        if frame_dt / viscous >= need:
            key, what = f"mpm.bodies[{i}].material.viscosity", "lower the viscosity"
        elif c >= v:
            key, what = f"mpm.bodies[{i}].material.E", "lower E"
        else:
            key, what = f"mpm.bodies[{i}].velocity", "slow it"
        raise SceneError(
            f"{key}: body '{scene.mpm.bodies[i].name}' needs {need:.3g} substeps per frame for the CFL and "
            f"viscous bounds (wave speed {c:.3g} m/s, initial speed {v:.3g} m/s, viscous dt bound {viscous:.3g} s), "
            f"more than time.max_substeps = {time.max_substeps}; {what}, shorten time.frame_dt or raise "
            "time.max_substeps"
        )


def body_velocity(scene: Scene, i: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Initial velocities v (n, dim) [m/s] and APIC affine velocities C = grad v (n, dim, dim) [1/s]
    of body i's particles at ``pts`` [m]: from its expressions (C by differences with a step of
    ``GRADIENT_STEP`` times the domain's size) or its file (``cosim.scene.velocity_file``).
    Refused where an expression or its gradient is not finite."""
    spec, key = scene.mpm.bodies[i], f"mpm.bodies[{i}].velocity"
    if isinstance(spec.velocity, VelocityFile):
        return file_velocity(spec.velocity.path(scene.source_dir), pts, key, spec.name)
    v = _finite(velocity_field(spec.velocity, pts), "not finite", key, spec.name)
    step = GRADIENT_STEP * max(scene.cells) * scene.dx
    C = velocity_gradient(spec.velocity, pts, step)
    return v, _finite(C, "its gradient (the particles' initial APIC C) is not finite", key, spec.name)


def _finite(values: np.ndarray, what: str, key: str, body: str) -> np.ndarray:
    """``values`` (one row or matrix per particle), refused naming ``key`` if any is not finite."""
    bad = int((~np.isfinite(values.reshape(len(values), -1))).any(axis=1).sum())
    if bad:
        raise SceneError(
            f"{key}: {what} at {bad} particles of body '{body}'; keep the expressions finite over the body"
        )
    return values


def hydrostatic_compression(pts: np.ndarray, spacing: float, material, gravity) -> np.ndarray:
    """J = 1 - rho |g| depth / K per particle: the volume ratio at which a liquid's pressure law
    p = K (1 - J) carries the weight above it (K = lambda + 2 mu / d [Pa]; depth [m] along gravity
    from the body's top, half a spacing above its highest particle). Ones without gravity."""
    dim = pts.shape[1]
    g = np.asarray(gravity, dtype=np.float64)
    g_norm = float(np.linalg.norm(g))
    if g_norm == 0:
        return np.ones(len(pts))
    height = pts @ (-g / g_norm)
    depth = height.max() + 0.5 * spacing - height
    mu, lam = lame_parameters(material.E, material.nu, dim)
    return 1.0 - material.density * g_norm * depth / (lam + 2.0 * mu / dim)


def check_hydrostatic(scene: Scene, bodies: list[np.ndarray]) -> None:
    """A liquid started hydrostatic has J > 0 everywhere: softer, its bottom would need a negative volume."""
    for i, (spec, pts) in enumerate(zip(scene.mpm.bodies, bodies)):
        if not spec.hydrostatic:
            continue
        J = hydrostatic_compression(pts, spec.spacing or 0.5 * scene.dx, spec.material, scene.gravity)
        if J.min() <= 0:
            E_zero = spec.material.E * (1.0 - J.min())  # K scales with E: the E of J = 0 at the bottom
            raise SceneError(
                f"mpm.bodies[{i}].hydrostatic: liquid '{spec.name}' is too soft to carry its own weight at rest: "
                f"its bottom would need the volume ratio J = 1 - rho |g| depth / K = {J.min():.3g} <= 0 "
                f"(K from material.E and nu); raise material.E above {E_zero:.3g} Pa (10 times that keeps "
                "the compression under 10%), lower the density, or remove hydrostatic"
            )


def check_loss_targets(scene: Scene) -> None:
    """Each Chamfer term's target points can be read and have the scene's dimension."""
    from cosim.losses.chamfer import target_points

    terms = scene.loss.all_terms()
    for i, term in enumerate(terms):
        if term.type == "chamfer" and term.points is not None:
            key = "loss" if not scene.loss.terms else f"loss.terms[{i}]"
            target_points(term.points, term.body, scene.dim, scene.dx, scene.seed, scene.source_dir, f"{key}.points")
