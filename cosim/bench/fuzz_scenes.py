"""Random valid scenes for the fuzz benchmark (``cosim.bench.fuzz``), one per seed.

``random_scene(seed)`` draws a scene as the YAML loader would hand it over (plain dicts,
lists, floats), using only keys the schema accepts: 2D or 3D; 1-3 soft bodies (elastic,
plastic or liquid; E 1e2..1e6 Pa, density 2e2..5e3 kg/m^3, nu 0..0.49, drawn on log or
linear scales) as boxes, spheres and, in 3D, cylinders, some against the domain walls,
some only 1-2 cells thin, some moving at up to 3 m/s; sometimes kinematic rigid bodies
with every kind of motion, a DART skeleton of 1-3 primitive links with controls, a cloth
(3D), particle impulse controls; the contact model, the walls, gravity and the time
stepping drawn too. Grids are 16-32 cells and runs 2-6 frames, so a case costs seconds
(mostly kernel compiles). Bodies are placed apart from each other, or rigid bodies, links
and cloths a fraction of a cell beside a soft body (``fuzz_space``), so that most scenes
pass validation and contact happens within those frames; a refused scene is a finding only
when its message is unclear. The rigid side is drawn by ``fuzz_manipulators``.
"""

from __future__ import annotations

import numpy as np

from cosim.bench import fuzz_manipulators as manipulators
from cosim.bench.fuzz_space import Space, log_uniform, rounded

SOFT_MATERIALS = ("elastic", "plastic", "liquid")
CONTACT_MODELS = ("grid", "particle", "forecast")
MAX_PARTICLES = {2: 6000, 3: 12000}  # per body: keeps a case at seconds


def random_scene(seed: int, precision: str | None = None) -> dict:
    """A random scene (a dict as ``yaml.safe_load`` gives it) drawn from ``numpy.random.default_rng(seed)``;
    ``precision`` 'float32' or 'float64' fixes the precision (default: drawn, float32 three times in four)."""
    rng = np.random.default_rng(seed)
    dim = int(rng.choice([2, 3]))
    cells = [int(rng.integers(16, 33))] * dim if rng.random() < 0.8 else [int(c) for c in rng.integers(16, 33, dim)]
    dx = log_uniform(rng, 0.01, 0.06) if rng.random() < 0.25 else 1.0 / max(cells)
    wall = str(rng.choice(["slip", "sticky", "none"], p=[0.6, 0.3, 0.1]))
    thickness = int(rng.integers(2, 5))
    margin = (thickness if wall != "none" else 2) * dx
    domain = np.asarray(cells) * dx
    space = Space(rng, domain, margin, dx)
    grid: dict = {"cells": cells[0] if len(set(cells)) == 1 and rng.random() < 0.5 else cells}
    if dx != 1.0 / max(cells):
        grid["dx"] = rounded(dx, 6)
    mpm: dict = {"grid": grid, "boundary": {"type": wall, "thickness": thickness}, "bodies": []}
    draw = rng.random()
    if draw < 0.15:
        mpm["gravity"] = [0.0] * dim
    elif draw < 0.3:
        mpm["gravity"] = rounded(rng.normal(0.0, 8.0, dim))
    drawn_precision = str(rng.choice(["float32", "float64"], p=[0.75, 0.25]))  # drawn always: same stream
    steps = int(rng.integers(2, 7))
    frame_dt = log_uniform(rng, 1e-3, 8e-3)
    scene: dict = {
        "name": f"fuzz_{seed}",
        "description": f"cosim bench fuzz, seed {seed}",
        "dim": dim,
        "precision": precision or drawn_precision,
        "seed": int(seed),
        "steps": steps,
        "time": _time(rng, frame_dt),
        "mpm": mpm,
        "output": {"preview": "none"},
    }
    for i in range(int(rng.integers(1, 4))):
        body = _soft_body(rng, space, dim, dx, f"body{i}")
        if body is not None:
            mpm["bodies"].append(body)
    if not mpm["bodies"]:  # no room was found: one small block in the middle
        center = 0.5 * domain
        size = np.full(dim, 4 * dx)
        mpm["bodies"].append(
            {
                "name": "body0",
                "material": {"type": "elastic", "E": 1e4},
                "shape": {"type": "box", "center": rounded(center), "size": rounded(size)},
            }
        )
    if rng.random() < 0.3:
        rigid = [
            manipulators.rigid_body(rng, space, dim, dx, f"rigid{i}", frame_dt * steps)
            for i in range(int(rng.integers(1, 3)))
        ]
        rigid = [r for r in rigid if r is not None]
        if rigid:
            scene["rigid"] = {"bodies": rigid}
    if rng.random() < 0.3:
        skeleton = manipulators.skeleton(rng, space, dim, dx)
        if skeleton is not None:
            scene["articulated"] = skeleton
    if dim == 3 and rng.random() < 0.2:
        cloth = manipulators.cloth(rng, space, dx)
        if cloth is not None:
            scene["cloth"] = [cloth]
    scene["contact"] = _contact(rng, dx, "cloth" in scene)
    if rng.random() < 0.2:
        scene["controls"] = [_control(rng, mpm["bodies"], dim, dx)]
    return scene


def _time(rng: np.random.Generator, frame_dt: float) -> dict:
    """Frame [s], substeps (auto, or a fixed count that may be too few: a clear SceneError), CFL bound."""
    spec: dict = {"frame_dt": rounded(frame_dt, 7)}
    spec["substeps"] = int(rng.integers(1, 60)) if rng.random() < 0.15 else "auto"
    if rng.random() < 0.2:
        spec["cfl"] = rounded(rng.uniform(0.1, 0.8), 3)
    if rng.random() < 0.1:
        spec["max_substeps"] = int(rng.integers(20, 400))
    return spec


def _material(rng: np.random.Generator) -> dict:
    kind = str(rng.choice(SOFT_MATERIALS))
    nu = rng.uniform(0.0, 0.45) if rng.random() < 0.9 else rng.uniform(0.45, 0.49)
    m: dict = {"type": kind, "E": rounded(log_uniform(rng, 1e2, 1e6), 1), "nu": rounded(nu, 3)}
    m["density"] = rounded(log_uniform(rng, 2e2, 5e3), 1)
    if kind == "plastic":
        m["yield_stress"] = rounded(m["E"] * log_uniform(rng, 1e-3, 1e-1), 3)
    if kind == "liquid" and rng.random() < 0.5:
        m["viscosity"] = rounded(log_uniform(rng, 1e-3, 1.0), 5)
    return m


def _soft_body(rng: np.random.Generator, space: Space, dim: int, dx: float, name: str) -> dict | None:
    """One soft body: a material, a shape (some thin, some against a wall), a velocity, a spacing."""
    kinds = ["box", "sphere"] + (["cylinder"] if dim == 3 else [])
    kind = str(rng.choice(kinds))
    span = float(space.domain.min())
    spacing = dx * rng.uniform(0.35, 1.0) if rng.random() < 0.2 else 0.5 * dx
    for _ in range(6):  # shrink until the particle count is cheap
        shape, half = _soft_shape(rng, kind, dim, dx, span)
        volume = np.prod(2 * half)
        if volume / spacing**dim <= MAX_PARTICLES[dim]:
            break
        span *= 0.7
    if space.soft and rng.random() < 0.3:
        center = space.place_near(half, soft=True)
    else:
        center = space.place(half, wall=rng.random() < 0.3, soft=True)
    if center is None:
        return None
    shape["center"] = rounded(center, 6)
    body: dict = {"name": name, "material": _material(rng), "shape": shape}
    if rng.random() < 0.4:
        body["velocity"] = rounded(rng.uniform(-3.0, 3.0, dim), 3)
    if spacing != 0.5 * dx:
        body["spacing"] = rounded(spacing, 7)
    if rng.random() < 0.2:
        body["jitter"] = rounded(rng.uniform(0.0, 0.5), 3)
    if body["material"]["type"] == "liquid" and rng.random() < 0.3:
        body["hydrostatic"] = True
    return body


def _soft_shape(rng: np.random.Generator, kind: str, dim: int, dx: float, span: float) -> tuple[dict, np.ndarray]:
    """A soft shape without its centre, and its half extents [m]; thin ones are 0.6-2 cells across."""

    def length() -> float:
        return rng.uniform(0.6, 2.0) * dx if rng.random() < 0.15 else rng.uniform(3 * dx, max(3.5 * dx, 0.35 * span))

    if kind == "box":
        size = np.array([length() for _ in range(dim)])
        return {"type": "box", "size": rounded(size, 6)}, 0.5 * size
    if kind == "sphere":
        radius = 0.5 * length()
        return {"type": "sphere", "radius": rounded(radius, 6)}, np.full(dim, radius)
    radius, height = 0.5 * length(), length()
    axis = str(rng.choice(["x", "y", "z"]))
    half = np.full(dim, radius)
    half["xyz".index(axis)] = 0.5 * height
    return {"type": "cylinder", "radius": rounded(radius, 6), "height": rounded(height, 6), "axis": axis}, half


def _contact(rng: np.random.Generator, dx: float, cloth: bool) -> dict:
    model = str(rng.choice(CONTACT_MODELS))
    contact: dict = {"model": model}
    if rng.random() < 0.6:
        contact["friction"] = rounded(rng.uniform(0.0, 1.0), 3)
    if model == "grid" and rng.random() < 0.3:
        contact["band"] = rounded(dx * rng.uniform(0.25, 1.5), 6)
    if model == "particle" and rng.random() < 0.3:
        contact["stiffness"] = rounded(log_uniform(rng, 50.0, 5000.0), 1)
    if model == "forecast" and rng.random() < 0.3:
        contact["alpha"] = rounded(rng.uniform(0.1, 2.0), 3)
        contact["threshold"] = rounded(dx * rng.uniform(0.5, 2.0), 6)
        contact["smoothing"] = rounded(rng.uniform(0.5, 4.0) / dx, 3)
    if cloth and rng.random() < 0.2:
        contact["tracing"] = False
    return contact


def _control(rng: np.random.Generator, bodies: list[dict], dim: int, dx: float) -> dict:
    """Impulses [N s] per particle per frame on one body, about a particle's momentum at up to 1 m/s."""
    body = bodies[int(rng.integers(len(bodies)))]
    spacing = body.get("spacing", 0.5 * dx)
    particle_mass = body["material"]["density"] * spacing**dim
    control: dict = {"body": body["name"], "impulse": rounded(particle_mass * rng.uniform(-1.0, 1.0, dim), 12)}
    if rng.random() < 0.4:
        center = np.asarray(body["shape"]["center"])
        control["region"] = {"min": rounded(center - 1.0, 6), "max": rounded(center + 0.0 * dx, 6)}
    return control
