"""The rigid side of a random scene (``cosim.bench.fuzz_scenes``): kinematic bodies with every kind of
motion, a DART skeleton of primitive links with joint controls, and a cloth (3D). Sizes in metres."""

from __future__ import annotations

import math

import numpy as np

from cosim.bench.fuzz_space import Space, log_uniform, rounded

RIGID_KINDS_2D = ("box", "sphere", "capsule", "glass", "ring", "cylinder")
RIGID_KINDS_3D = ("box", "sphere", "capsule", "glass", "cylinder")
MOTIONS = ("static", "constant", "piecewise", "shake", "waypoints")


def rigid_shape(rng: np.random.Generator, dim: int, dx: float, span: float) -> tuple[dict, np.ndarray]:
    """A rigid shape (body frame: cylinders, capsules, glasses along y) and its half extents [m] unrotated."""
    kind = str(rng.choice(RIGID_KINDS_2D if dim == 2 else RIGID_KINDS_3D))
    size = rng.uniform(2 * dx, max(2.5 * dx, 0.25 * span))
    if kind == "box":
        extents = rng.uniform(dx, max(1.5 * dx, 0.3 * span), dim)
        return {"type": "box", "size": rounded(extents, 6)}, 0.5 * extents
    radius = 0.5 * size
    if kind == "sphere":
        return {"type": "sphere", "radius": rounded(radius, 6)}, np.full(dim, radius)
    if kind == "ring":
        thickness = rng.uniform(0.5, 2.0) * dx
        shape = {"type": "ring", "radius": rounded(radius, 6), "thickness": rounded(thickness, 6)}
        return shape, np.full(dim, radius + 0.5 * thickness)
    height = rng.uniform(2 * dx, max(2.5 * dx, 0.3 * span))
    shape = {"type": kind, "radius": rounded(radius, 6), "height": rounded(height, 6)}
    if kind == "glass":
        shape["thickness"] = rounded(rng.uniform(0.2, 0.8) * min(radius, height), 6)
    half = np.full(dim, radius)
    half[1] = 0.5 * height + (radius if kind == "capsule" else 0.0)
    return shape, half


def rotation(rng: np.random.Generator, dim: int, scale: float = 1.0):
    if dim == 2:
        return rounded(rng.uniform(-math.pi, math.pi) * scale, 4)
    return rounded(rng.normal(0.0, 1.0, 3) * scale, 4)


def rigid_body(rng: np.random.Generator, space: Space, dim: int, dx: float, name: str, horizon: float) -> dict | None:
    """A kinematic rigid body with one of the motions (``horizon`` [s]: the run's length)."""
    shape, half = rigid_shape(rng, dim, dx, float(space.domain.min()))
    rotated = rng.random() < 0.4
    if rotated:  # a ball around it
        half = np.full(dim, float(np.linalg.norm(half)))
    near = rng.random() < 0.7
    center = space.place_near(half) if near else space.place(half)
    if center is None:
        return None
    body: dict = {"name": name, "shape": shape, "position": rounded(center, 6)}
    if rotated:
        body["rotation"] = rotation(rng, dim)
    approach = near and space.target is not None and rng.random() < 0.5
    kind = "constant" if approach else str(rng.choice(MOTIONS))
    speed = rng.uniform(0.0, 1.0)
    motion: dict = {"type": kind}
    if approach:  # towards the soft body beside it, to meet it within the run
        direction = space.target - center
        motion["velocity"] = rounded(rng.uniform(0.2, 2.0) * direction / np.linalg.norm(direction), 4)
    elif kind == "constant":
        motion["velocity"] = rounded(rng.uniform(-speed, speed, dim), 4)
        if rng.random() < 0.5:
            motion["angular_velocity"] = rotation(rng, dim, 0.5)
    elif kind == "piecewise":
        motion["segments"] = [
            {
                "duration": rounded(horizon * rng.uniform(0.1, 1.0), 6),
                "velocity": rounded(rng.uniform(-speed, speed, dim)),
            }
            for _ in range(int(rng.integers(1, 4)))
        ]
        motion["repeat"] = bool(rng.random() < 0.5)
    elif kind == "shake":
        motion["amplitude"] = rounded(rng.uniform(-0.05, 0.05, dim), 4)
        motion["frequency"] = rounded(rng.uniform(0.5, 10.0), 3)
        motion["phase"] = rounded(rng.uniform(0.0, 2 * math.pi), 3)
    elif kind == "waypoints":
        n = int(rng.integers(2, 4))
        times = np.cumsum(np.concatenate([[0.0], rng.uniform(0.2, 1.0, n - 1) * horizon]))
        positions = [list(center)] + [list(center + rng.uniform(-0.05, 0.05, dim)) for _ in range(n - 1)]
        motion["times"] = rounded(times, 6)
        motion["positions"] = rounded(positions, 6)
    body["motion"] = motion
    if rng.random() < 0.15:
        body["sdf_spacing"] = rounded(dx * rng.uniform(0.3, 1.0), 6)
    return body


# joint type -> coordinates (2D, 3D); 2D free is DART's planar joint
_DOFS = {"free": (3, 6), "revolute": (1, 1), "prismatic": (1, 1), "ball": (None, 3), "weld": (0, 0)}


def skeleton(rng: np.random.Generator, space: Space, dim: int, dx: float) -> dict | None:
    """An ``articulated:`` section: one skeleton of 1-3 primitive links in a chain along +x, with controls."""
    n = int(rng.integers(1, 4))
    shapes = [rigid_shape(rng, dim, dx, 0.6 * float(space.domain.min())) for _ in range(n)]
    gaps = [shapes[k - 1][1][0] + shapes[k][1][0] + 0.5 * dx for k in range(1, n)]  # link origins along x
    half = np.max([h for _, h in shapes], axis=0)
    length = shapes[0][1][0] + sum(gaps) + shapes[-1][1][0]
    half[0] = 0.5 * length
    center = space.place_near(half) if rng.random() < 0.7 else space.place(half)
    if center is None:
        return None
    root = center.copy()
    root[0] += shapes[0][1][0] - 0.5 * length
    links, controls, action = [], {}, []
    for k, (shape, _) in enumerate(shapes):
        types = ["free", "revolute", "prismatic", "weld"] + (["ball"] if dim == 3 and k else [])
        kind = str(rng.choice(types))
        joint: dict = {"type": kind}
        if k == 0:
            joint["position"] = rounded(root, 6)
        else:
            joint["parent"] = f"link{k - 1}"
            offset = np.zeros(dim)
            offset[0] = gaps[k - 1]
            joint["position"] = rounded(offset, 6)
        if kind in ("revolute", "prismatic") and (dim == 3 or rng.random() < 0.3):
            axis = np.eye(dim)[int(rng.integers(dim))] if rng.random() < 0.6 else rng.normal(0.0, 1.0, dim)
            joint["axis"] = rounded(axis, 4)
        if kind in ("revolute", "prismatic") and rng.random() < 0.3:
            lower = -rng.uniform(0.01, 1.0)
            joint["lower"], joint["upper"] = rounded(lower, 4), rounded(rng.uniform(0.01, 1.0), 4)
        if rng.random() < 0.4:
            joint["damping"] = rounded(log_uniform(rng, 1e-3, 1.0), 5)
        dofs = _DOFS[kind][dim - 2]
        if dofs and rng.random() < 0.3:
            joint["qd0"] = rounded(rng.uniform(-0.5, 0.5, dofs), 4) if dofs > 1 else rounded(rng.uniform(-0.5, 0.5), 4)
        link: dict = {"name": f"link{k}", "shape": shape, "joint": joint}
        if rng.random() < 0.7:
            link["density"] = rounded(log_uniform(rng, 50.0, 3000.0), 2)
        else:
            link["mass"] = rounded(log_uniform(rng, 0.01, 2.0), 4)
        if rng.random() < 0.1:
            link["couple"] = False
        links.append(link)
        if dofs and rng.random() < 0.5:
            free_root = kind == "free" and k == 0 and dim == 3
            mode = str(rng.choice(["torque", "velocity", "wrench", "twist"] if free_root else ["torque", "velocity"]))
            controls[link["name"]] = mode
            size = 6 if mode in ("wrench", "twist") else dofs
            magnitude = 0.5 if mode in ("velocity", "twist") else 0.05
            action += list(rng.uniform(-magnitude, magnitude, size))
    skeleton: dict = {"name": "skeleton", "links": links}
    if controls:
        skeleton["controls"] = controls
    section: dict = {"skeletons": [skeleton]}
    if dim == 3 and rng.random() < 0.3:
        skeleton["collide"] = True
        section["collision"] = bool(rng.random() < 0.5)
    if action:
        actions: dict = {"hold": int(rng.integers(1, 4)), "initial": rounded(action, 5)}
        if rng.random() < 0.3:
            actions["sequence"] = [rounded(0.5 * np.asarray(action), 5)]
        section["actions"] = actions
    return section


def cloth(rng: np.random.Generator, space: Space, dx: float) -> dict | None:
    """A rectangle or disc cloth lying across x, y or z, sometimes pinned, sometimes driven."""
    normal = str(rng.choice(["y", "x", "z"], p=[0.6, 0.2, 0.2]))
    k = "xyz".index(normal)
    across = [(k + 1) % 3, (k + 2) % 3]  # the rectangle's size is along these, in cyclic order (cloth_mesh)
    span = float(space.domain.min())
    if rng.random() < 0.6:
        size = rng.uniform(0.2 * span, 0.6 * span, 2)
        mesh: dict = {
            "type": "rectangle",
            "size": rounded(size, 5),
            "resolution": [int(r) for r in rng.integers(3, 11, 2)],
        }
        half = np.zeros(3)
        half[across] = 0.5 * size
    else:
        radius = rng.uniform(0.1 * span, 0.3 * span)
        mesh = {"type": "disc", "radius": rounded(radius, 5), "rings": int(rng.integers(1, 5))}
        half = np.full(3, radius)
    half[k] = dx
    center = space.place_near(half) if rng.random() < 0.6 else space.place(half)
    if center is None:
        return None
    mesh["center"] = rounded(center, 6)
    mesh["normal"] = normal
    cloth: dict = {"name": "sheet", "mesh": mesh}
    cloth["material"] = {
        "stretch": rounded(log_uniform(rng, 1e2, 1e4), 2),
        "bend": rounded(log_uniform(rng, 1e-3, 1e-1), 5),
        "density": rounded(log_uniform(rng, 0.05, 1.0), 4),
        "damping": rounded(rng.uniform(0.0, 2.0), 3),
    }
    corners = [center.copy() for _ in range(2)]
    corners[0][across] -= half[across]
    corners[1][across] += half[across]
    if rng.random() < 0.6:
        cloth["fixed"] = {"points": [rounded(c, 6) for c in corners]}
    if rng.random() < 0.3:
        cloth["controls"] = [{"name": "grip", "vertices": {"points": [rounded(center, 6)]}}]
        cloth["actions"] = {"initial": rounded(rng.uniform(-0.2, 0.2, 3), 4)}
    return cloth
