"""Cloth contact planes from python-fcl against the closed-form signed distances of our primitives."""

from types import SimpleNamespace

import numpy as np
import pytest

from cosim.couplers.cloth_rigid import RigidObstacles
from cosim.couplers.sdf import primitive_distance
from cosim.engines import so3

SHAPES = {
    "box": (SimpleNamespace(type="box", size=[0.2, 0.1, 0.3]), 1e-12),
    "sphere": (SimpleNamespace(type="sphere", radius=0.1), 2e-4),  # fcl's GJK on round shapes: ~1e-4 m
    "cylinder": (SimpleNamespace(type="cylinder", radius=0.05, height=0.3), 2e-4),
    "capsule": (SimpleNamespace(type="capsule", radius=0.05, height=0.2), 2e-4),
}
RADIUS = 0.03


def _size(shape) -> dict:
    if shape.type == "box":
        return {"half": 0.5 * np.asarray(shape.size)}
    return {k: v for k, v in vars(shape).items() if k != "type"}


@pytest.mark.parametrize("kind", list(SHAPES))
def test_planes_match_primitive_distances_on_a_moved_body(kind):
    """Every point within RADIUS of the rotated, moved body gets a plane, and the plane's offset
    n . (x - p) is the signed distance (negative inside: the normal points out of the body)."""
    shape, tol = SHAPES[kind]
    obstacles = RigidObstacles([shape], ".", ["shape"])
    pos, R = np.array([0.5, 0.4, 0.6]), so3.exp(np.array([0.3, -0.5, 0.7]))
    points = pos + np.random.default_rng(0).uniform(-0.25, 0.25, (3000, 3))
    planes = obstacles.planes(points, [(pos, R)], RADIUS)
    exact = primitive_distance(kind, (points - pos) @ R, **_size(shape))
    assert set(planes.index) == set(np.flatnonzero(exact < RADIUS))
    offset = np.einsum("ij,ij->i", points[planes.index] - planes.point, planes.normal)
    np.testing.assert_allclose(offset, exact[planes.index], atol=tol)
    np.testing.assert_allclose(np.linalg.norm(planes.normal, axis=1), 1.0, atol=1e-12)


def test_glass_wall_is_a_sheet_with_planes_on_both_sides():
    """A glass is an fcl triangle mesh: points just inside and just outside its wall both get a plane
    whose normal points back to their own side, at their distance from the wall."""
    shape = SimpleNamespace(type="glass", radius=0.1, height=0.2, thickness=0.02)
    obstacles = RigidObstacles([shape], ".", ["glass"])
    heights = np.linspace(-0.05, 0.05, 5)
    outside = np.stack([np.full(5, 0.11), heights, np.zeros(5)], axis=1)  # 1 cm outside the outer wall
    inside = np.stack([np.full(5, 0.07), heights, np.zeros(5)], axis=1)  # 1 cm inside the cavity
    planes = obstacles.planes(np.concatenate([outside, inside]), [(np.zeros(3), np.eye(3))], RADIUS)
    assert sorted(planes.index) == list(range(10))
    order = np.argsort(planes.index)
    normal_x = planes.normal[order, 0]
    assert np.all(normal_x[:5] > 0.99) and np.all(normal_x[5:] < -0.99)
    offset = np.einsum("ij,ij->i", np.concatenate([outside, inside]) - planes.point[order], planes.normal[order])
    np.testing.assert_allclose(offset, 0.01, atol=3e-4)  # 64 sections: the polygon sits 1.2e-4 m inside the circle


def _towel(size=0.3, n=11, height=0.2, damping=0.0, bend=1e-3):
    from cosim.engines.cloth import ClothEngine, ClothMaterial
    from cosim.engines.cloth_mesh import rectangle

    mesh = rectangle((size, size), (n, n), (0.0, height, 0.0), "y")
    material = ClothMaterial(k_stretch=500.0, k_bend=bend, c_mass=damping)
    return ClothEngine(mesh, material, frame_dt=2e-3)


def _planes(towel, obstacles, pose, thickness: float) -> dict:
    """A step's inputs with the contact planes of the towel's current points against one body at ``pose``."""
    return {"boundaries": {"body": obstacles.planes(towel.contact.points(towel.x), [pose], thickness)}}


def test_towel_dropped_on_a_rod_drapes_over_it():
    """A soft towel falling onto a horizontal rod (a cylinder along z, python-fcl) ends up hanging on it
    (friction 0.5; without friction a draped towel slides off on the triangulation's asymmetry): the
    middle row rests on the rod's top at about the contact thickness r, both halves hang below the rod's
    axis, and the towel stays left-right balanced (friction holds it).

    The contact layer holds: a vertex gets a contact plane only when a step starts with it within r of
    the rod, so a vertex that starts a step farther out can enter the layer by at most the distance it
    moves in that step (the next step's plane pushes it out); one under a plane sits at most F / k inside
    it, F <= the towel's weight M g and k = kappa m / h^2 the penalty (``cloth_contact``), plus fcl's
    ~1e-4 m error on round shapes (``SHAPES``). So every step, every vertex is at least
    r - |dx| - M g h^2 / (kappa m_min) - 2e-4 from the rod's surface, whatever the CPU's round-off
    makes of the fall (a bound on the closest approach over the whole run was machine-dependent:
    the falling halves move up to ~3 mm a step), and never inside the rod."""
    rod = SimpleNamespace(type="cylinder", radius=0.02, height=0.6)
    pose = (np.zeros(3), so3.exp(np.array([np.pi / 2, 0.0, 0.0])))  # our y axis onto z
    obstacles = RigidObstacles([rod], ".", ["rod"])
    thickness = 0.005
    towel = _towel(size=0.2, n=9, height=0.03, damping=2.0, bend=1e-5)
    towel.attach_rigid_contact(thickness, friction=0.5)
    masses = towel.masses()
    load_gap = masses.sum() * 9.81 * towel.frame_dt**2 / (100.0 * masses.min())  # kappa = 100
    x_before = towel.state()["x"]
    deepest, closest = -np.inf, np.inf
    for _ in range(250):
        towel.step(_planes(towel, obstacles, pose, thickness))
        x = towel.state()["x"]
        surface = np.hypot(x[:, 0], x[:, 1]) - rod.radius
        moved = np.linalg.norm(x - x_before, axis=1)
        deepest = max(deepest, float((thickness - surface - moved).max()))
        closest = min(closest, float(surface.min()))
        x_before = x
    assert deepest < load_gap + 2e-4, deepest
    assert closest > 0.0
    middle = np.abs(x[:, 0]) < 0.01
    # the face-centroid contacts of the wrapped faces hold the middle vertices up to one thickness higher
    gap = x[middle, 1] - (rod.radius + thickness)
    assert np.all(gap > -0.2 * thickness) and np.all(gap < thickness)
    assert x[x[:, 0] < -0.04, 1].max() < 0.0 and x[x[:, 0] > 0.04, 1].max() < 0.0  # both halves hang
    assert abs(float(x[:, 0].mean())) < 0.005  # and stay balanced on the rod


def test_cloth_adjoint_with_active_floor_contact_matches_central_differences():
    """A towel pressed onto a box floor: the contact planes of a flat top face do not depend on where
    the towel was (p moves with x, n does not), so the step is a smooth function of its inputs and the
    adjoint, with the contact's Hessian, must match central differences (rel. 1e-6)."""
    floor = SimpleNamespace(type="box", size=[1.0, 0.1, 1.0])
    pose = (np.array([0.0, -0.05, 0.0]), np.eye(3))
    obstacles = RigidObstacles([floor], ".", ["floor"])
    towel = _towel(n=6, height=0.004)
    towel.attach_rigid_contact(0.005, friction=0.0)
    rng = np.random.default_rng(3)
    start = towel.state()
    start["v"] = rng.normal(0.0, 0.3, start["v"].shape) - [0.0, 1.0, 0.0]
    wx, wv = rng.normal(size=start["x"].shape), rng.normal(size=start["v"].shape)

    def loss(v0):
        towel.set_state({"x": start["x"], "v": v0})
        records = [towel.step(_planes(towel, obstacles, pose, 0.005))[1] for _ in range(2)]
        s = towel.state()
        return float(np.sum(wx * s["x"]) + np.sum(wv * s["v"])), records

    _, records = loss(start["v"])
    assert all(len(r.contacts.face) > 0 for r in records)
    grad = {"x": wx, "v": wv}
    for r in reversed(records):
        grad = towel.vjp(r, {"state": grad})["state"]
    d = rng.normal(size=start["v"].shape)
    eps = 1e-6
    fd = (loss(start["v"] + eps * d)[0] - loss(start["v"] - eps * d)[0]) / (2 * eps)
    adjoint = float(np.sum(grad["v"] * d))
    assert abs(adjoint - fd) <= 1e-6 * abs(fd)


@pytest.mark.parametrize(
    "width, friction, n, height, fall, tolerance",
    [(1.0, 0.5, 6, 0.006, 0.1, 1e-5), (0.15, 0.0, 8, 0.004, 0.3, 1e-7)],
    ids=["floor-friction", "box-edges"],
)
def test_cloth_adjoint_with_a_moving_tilted_box_matches_central_differences(
    width, friction, n, height, fall, tolerance
):
    """A towel pressed onto a tilted box, three steps: a wide floor with friction 0.5 (the step depends
    on its start through the lagged normal force and the slip), and a box narrower than the towel
    without friction (the towel meets its edges and corners, whose planes turn with the queried point:
    ``feature_jacobians``). The adjoint of x0, v0, the box's height and its tilt about the world z axis
    (through the returned plane adjoints and their Jacobians, and the reactions' adjoints of a loss on
    the reaction's force and torque) must match central differences: 1e-5 with friction (its Newton solves leave
    the differences themselves uncertain at a few 1e-6; without the start's path the x0, v0 adjoint is
    25 % off), 1e-7 without."""
    floor = SimpleNamespace(type="box", size=[width, 0.1, width])
    obstacles = RigidObstacles([floor], ".", ["floor"])
    towel = _towel(n=n, height=height)
    towel.attach_rigid_contact(0.005, friction=friction)
    rng = np.random.default_rng(5)
    start = towel.state()
    start["v"] += [0.02, -fall, 0.0]  # sliding into the box
    wx, wv, wr, wt = rng.normal(size=start["x"].shape), rng.normal(size=start["v"].shape), *rng.normal(size=(2, 3))

    def pose(height: float, tilt: float):
        return np.array([0.0, -0.05 + height, 0.0]), so3.exp(np.array([0.0, 0.0, tilt])) @ so3.exp([0.02, 0.0, 0.01])

    def loss(x0, v0, height=0.0, tilt=0.0):
        towel.set_state({"x": x0, "v": v0})
        total, records = 0.0, []
        for _ in range(3):
            out, record = towel.step(_planes(towel, obstacles, pose(height, tilt), 0.005))
            on_box = out["reactions"]["body"]
            total += float(
                wr @ on_box["force"].sum(axis=0) + wt @ np.cross(on_box["point"], on_box["force"]).sum(axis=0)
            )
            records.append(record)
        s = towel.state()
        return total + float(np.sum(wx * s["x"]) + np.sum(wv * s["v"])), records

    _, records = loss(start["x"], start["v"])
    assert all(len(r.contacts.face) >= 3 for r in records)
    o, R0 = pose(0.0, 0.0)
    off_faces = sum(int(np.sum(np.abs(r.contacts.normal @ R0).max(axis=1) < 1 - 1e-9)) for r in records)
    assert off_faces > 0 if width < 0.5 else off_faces == 0  # the narrow box's edges and corners are met
    grad, g_height, g_tilt = {"x": wx, "v": wv}, 0.0, 0.0
    spin = np.array([0.0, 0.0, 1.0])
    for r in reversed(records):
        c = r.contacts  # the loss's reaction terms: the force and its torque about the origin
        force = -towel.contact.forces(r.x_next, c)
        g_reactions = {"force": wr + np.cross(wt, c.point), "point": np.cross(force, wt)}
        out = towel.vjp(r, {"state": grad, "reactions": {"body": g_reactions}})
        grad, planes = out["state"], out["boundaries"]["body"]
        g_point, g_normal = planes["point"], planes["normal"]  # moving the box = moving the queries the other way
        g_query = np.einsum("cki,ck->ci", c.point_jacobian, g_point) + np.einsum(
            "cki,ck->ci", c.normal_jacobian, g_normal
        )
        g_height += float((g_point - g_query)[:, 1].sum())
        g_tilt += float(
            np.sum(g_point * np.cross(spin, c.point - o))
            + np.sum(g_normal * np.cross(spin, c.normal))
            - np.sum(g_query * np.cross(spin, c.start - o))
        )
    eps = 1e-6
    dx, dv = rng.normal(size=start["x"].shape) * 1e-1, rng.normal(size=start["v"].shape)
    checks = [
        (np.sum(grad["x"] * dx) + np.sum(grad["v"] * dv), lambda e: loss(start["x"] + e * dx, start["v"] + e * dv)[0]),
        (g_height, lambda e: loss(start["x"], start["v"], height=e)[0]),
        (g_tilt, lambda e: loss(start["x"], start["v"], tilt=e)[0]),
    ]
    for adjoint, f in checks:
        fd = (f(eps) - f(-eps)) / (2 * eps)
        assert abs(adjoint - fd) <= tolerance * abs(fd), (adjoint, fd)


def _moving_planes(towel, obstacles, pose, twist, thickness: float) -> dict:
    """``_planes`` for a body moving with ``twist`` (v, w): the surface velocity under each point and how it
    moves with the queried point, as ``ClothRigidCoupler`` gives them."""
    inputs = _planes(towel, obstacles, pose, thickness)
    planes = inputs["boundaries"]["body"]
    v, w = (np.asarray(a, dtype=np.float64) for a in twist)
    planes.velocity = v + np.cross(w, planes.point - pose[0])
    planes.velocity_jacobian = np.cross(w[None, :, None], planes.jacobians()[0], axis=1)
    return inputs


def test_friction_drags_a_towel_along_a_moving_floor_and_its_adjoint_matches():
    """A towel resting on a floor that slides at 0.2 m/s and spins about y (friction 0.5): friction acts on
    the slip relative to the floor, so within 40 frames the towel moves with it (mean x velocity within
    5 % of the floor's; before friction was relative to the floor it stayed behind, braked). The adjoint of
    x0, v0 and of the floor's velocity and spin (through the planes' velocity adjoints and their Jacobians)
    matches central differences over three frames to 1e-4: the towel sticks, and sticking friction's spring
    (2 mu lambda / eps, about 1e3 times the penalty) makes the differences noisy. Measured (direct and
    preconditioned-CG linear solves alike): x0 / v0 at step 1e-6 off by 1e-5..4e-5 (1e-5: 9e-4, truncation),
    the floor's velocity and spin at step 1e-5 off by 1e-5..3e-5 (1e-6: up to 1.4e-4, round-off), so each
    check takes its step. Without the surface velocity's dependence on the queried points the x0, v0 adjoint
    is 3 % off, without its adjoint the floor's velocity gets none."""
    floor = SimpleNamespace(type="box", size=[1.0, 0.1, 1.0])
    obstacles = RigidObstacles([floor], ".", ["floor"])
    towel = _towel(n=6, height=0.005)  # on the contact layer
    towel.attach_rigid_contact(0.005, friction=0.5)
    pose = (np.array([0.0, -0.05, 0.0]), np.eye(3))
    slide = np.array([0.2, 0.0, 0.0])
    start = towel.state()
    for _ in range(40):
        towel.step(_moving_planes(towel, obstacles, pose, (slide, np.zeros(3)), 0.005))
    assert abs(float(towel.state()["v"][:, 0].mean()) - 0.2) < 0.01

    rng = np.random.default_rng(7)
    start = towel.state()
    wx, wv = rng.normal(size=start["x"].shape), rng.normal(size=start["v"].shape)
    spin = np.array([0.0, 0.5, 0.0])

    def loss(x0, v0, v_b=slide, w_b=spin):
        towel.set_state({"x": x0, "v": v0})
        records = [towel.step(_moving_planes(towel, obstacles, pose, (v_b, w_b), 0.005))[1] for _ in range(3)]
        s = towel.state()
        return float(np.sum(wx * s["x"]) + np.sum(wv * s["v"])), records

    _, records = loss(start["x"], start["v"])
    assert all(len(r.contacts.face) > 30 for r in records), [len(r.contacts.face) for r in records]
    grad, g_slide, g_spin = {"x": wx, "v": wv}, np.zeros(3), np.zeros(3)
    for r in reversed(records):
        out = towel.vjp(r, {"state": grad})
        grad, g_velocity = out["state"], out["boundaries"]["body"]["velocity"]
        g_slide += g_velocity.sum(axis=0)
        g_spin += np.cross(r.contacts.point - pose[0], g_velocity).sum(axis=0)
    dx, dv, d_slide, d_spin = (
        rng.normal(size=start["x"].shape) * 1e-3,
        rng.normal(size=start["v"].shape),
        *rng.normal(size=(2, 3)),
    )
    checks = [
        (
            1e-6,
            np.sum(grad["x"] * dx) + np.sum(grad["v"] * dv),
            lambda e: loss(start["x"] + e * dx, start["v"] + e * dv)[0],
        ),
        (1e-5, g_slide @ d_slide, lambda e: loss(start["x"], start["v"], v_b=slide + e * d_slide)[0]),
        (1e-5, g_spin @ d_spin, lambda e: loss(start["x"], start["v"], w_b=spin + e * d_spin)[0]),
    ]
    for eps, adjoint, f in checks:
        fd = (f(eps) - f(-eps)) / (2 * eps)
        assert abs(adjoint - fd) <= 1e-4 * abs(fd), (eps, adjoint, fd)


def test_a_kinematic_tray_carries_a_towel_through_the_scene_coupler():
    """A towel lying on a kinematic tray (a box moving at 0.2 m/s along x) in a built scene: the cloth-rigid
    coupler hands the tray's planes and surface velocity to the towel, friction 0.5 carries it along (its
    mean x velocity within 5 % of the tray's after 60 frames, and it stays on the tray), the tray takes no
    reaction, and the whole-system energy budget accounts for the tray's work on the towel (the run is
    not stopped; the towel's kinetic energy comes from that work)."""
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    scene = parse_scene(
        {
            "name": "tray",
            "dim": 3,
            "precision": "float64",
            "steps": 60,
            "time": {"frame_dt": 2e-3, "substeps": 2},
            "mpm": {
                "grid": {"cells": 16},
                "bodies": [
                    {
                        "name": "crumb",
                        "material": {"type": "elastic", "E": 1e4, "nu": 0.3, "density": 500},
                        "shape": {"type": "box", "center": [0.7, 0.25, 0.7], "size": [0.1, 0.1, 0.1]},
                    }
                ],
            },
            "rigid": {
                "bodies": [
                    {
                        "name": "tray",
                        "shape": {"type": "box", "size": [0.5, 0.05, 0.5]},
                        "position": [0.35, 0.4, 0.5],
                        "motion": {"type": "constant", "velocity": [0.2, 0.0, 0.0]},
                    }
                ]
            },
            "cloth": [
                {
                    "name": "towel",
                    "mesh": {
                        "type": "rectangle",
                        "center": [0.35, 0.4564, 0.5],
                        "size": [0.2, 0.2],
                        "resolution": [6, 6],
                    },
                    "material": {"stretch": 300, "bend": 1e-3, "density": 0.3},
                }
            ],
            "contact": {"model": "forecast", "friction": 0.5},
        }
    )
    sim = build_system(scene)
    sim.rollout()
    towel = sim.engines["towel"].state()
    assert abs(float(towel["v"][:, 0].mean()) - 0.2) < 0.01
    assert np.all(np.abs(towel["x"][:, 1] - 0.4564) < 0.005)  # still on the tray, at its contact layer
    assert sim.conservation.work > 0.5 * 0.5 * sim.engines["towel"].masses().sum() * 0.2**2


@pytest.mark.parametrize(
    "friction, velocity", [(0.5, [0.05, -0.3, 0.0]), (0.2, [0.05, -0.3, 0.0]), (0.5, [0.3, -0.5, 0.0])]
)
def test_newton_converges_when_a_towel_slides_onto_a_tilted_floor_with_friction(friction, velocity):
    """A towel sliding onto a slightly tilted floor with friction: every point sticks or slips within a
    slip of eps = 2 um, where the friction potential switches from quadratic to linear. With the exact
    Hessian alone Newton flew past the sticking points and back (line-search steps of 1/512) and did not
    converge within 200 iterations in 16 of 18 such starts; with the friction's majorizing curvature in
    its fallback direction (``point_hessians(majorize=True)``) every step converges within 40."""
    floor = SimpleNamespace(type="box", size=[1.0, 0.1, 1.0])
    obstacles = RigidObstacles([floor], ".", ["floor"])
    towel = _towel(n=6, height=0.004)
    towel.attach_rigid_contact(0.005, friction=friction)
    state = towel.state()
    towel.set_state({"x": state["x"], "v": state["v"] + velocity})
    pose = (np.array([0.0, -0.05, 0.0]), so3.exp(np.array([0.0, 0.0, 0.01])))
    iterations = [towel.step(_planes(towel, obstacles, pose, 0.005))[1].iterations for _ in range(3)]
    assert max(iterations) <= 40, iterations
