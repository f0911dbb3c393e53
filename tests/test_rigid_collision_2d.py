"""DART rigid-rigid collision in 2D scenes (shapes extruded along z) and the scene's static ground
(``articulated.ground``), against closed forms: resting heights, stack heights, momentum through an
inelastic collision, Coulomb deceleration; and the refusals (bad keys, gradients through contact).

Tolerances come from DART's contact model: a contact is an impulse that stops the approach, and a
penetration is undone at no more than 1 mm/s, so a body that lands at speed v first sinks up to
v dt (about 2.5 mm for a 2 cm drop at dt = 4 ms) and then rises to the surface; after that
(measured: within 2 s) it sits within 0.2 mm of it. We allow 1 mm of height at every step of the
last second. At rest, the vertical velocity is zero but for DART's jolts: with friction, planar
bodies resting on two corners now and then get a one-step velocity jolt (measured up to 1.7 cm/s
in these cases, a few in 10 s; up to 6 cm/s in stacks on a frictionless ground; the static friction between the corners is indeterminate and DART's LCP solver
picks an internal squeeze, released when one corner's contact drops out at zero depth; 3D bodies
did not show it). So "at rest" is: a mean vertical velocity below 0.1 mm/s over the last second
(neither sinking nor rising), at least 97% of its steps below 1 mm/s, and no step above 3 cm/s.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from cosim.errors import InputError, SceneError, SimulationError
from cosim.scene.articulated import build_articulated

DT = 4e-3  # [s] the frame, DART's step
G = 9.81
FLOOR = 0.1  # [m] the ground's height
HEIGHT_TOL = 1e-3  # [m]
SPEED_TOL = 1e-3  # [m/s] the penetration recovery speed: a body still sinking or rising exceeds it
JOLT = 3e-2  # [m/s] DART's one-step jolts at rest (see above)


def body(name, x, y, shape=None, angle=0.0, vx=0.0, controls=None) -> dict:
    """A colliding skeleton of one free (2D: planar) link, a 0.1 m box unless ``shape`` is given."""
    skel = {
        "name": name,
        "collide": True,
        "links": [
            {
                "name": name,
                "shape": shape or {"type": "box", "size": [0.1, 0.1]},
                "density": 1000.0,
                "joint": {"type": "free", "q0": [x, y, angle], "qd0": [vx, 0.0, 0.0]},
            }
        ],
    }
    if controls:
        skel["controls"] = controls
    return skel


def scene(skeletons, friction=1.0, **extra):
    section = {"skeletons": skeletons, "collision": True, "ground": {"height": FLOOR, "friction": friction}}
    return make_scene(time={"frame_dt": DT}, articulated=section | extra.pop("articulated", {}), **extra)


def simulate(skeletons, seconds: float, friction: float = 1.0) -> tuple[object, np.ndarray]:
    """The engine after ``seconds`` and the (steps, 2 * dofs) states it went through (2D free = [x, y, angle])."""
    s = scene(skeletons, friction)
    engine = build_articulated(s, s.dx).engine
    states = np.array([engine.advance().next_state for _ in range(round(seconds / DT))])
    return engine, states


def assert_rests_at(states: np.ndarray, k: int, dofs: int, height: float) -> None:
    """Body k (2D free: [x, y, angle]) rests with its origin at ``height`` over the last second."""
    last = states[-round(1.0 / DT) :]
    y, vy = last[:, 3 * k + 1], last[:, dofs + 3 * k + 1]
    assert np.abs(y - height).max() < HEIGHT_TOL, (np.abs(y - height).max(), height)
    assert abs(vy.mean()) < 0.1 * SPEED_TOL
    assert np.mean(np.abs(vy) < SPEED_TOL) > 0.97
    assert np.abs(vy).max() < JOLT


# ------------------------------------------------------------------------------------------------ at rest


@pytest.mark.parametrize(
    "shape,angle,half_height",
    [
        ({"type": "box", "size": [0.1, 0.06]}, 0.0, 0.03),
        ({"type": "sphere", "radius": 0.04}, 0.0, 0.04),  # a disc: a cylinder along z
        ({"type": "cylinder", "radius": 0.04, "height": 0.1}, 0.0, 0.05),  # a rectangle in 2D
        ({"type": "capsule", "radius": 0.03, "height": 0.1}, np.pi / 2, 0.03),  # lying on its side
        ({"type": "glass", "radius": 0.05, "height": 0.08, "thickness": 0.01}, 0.0, 0.04),
    ],
    ids=["box", "disc", "cylinder", "capsule", "glass"],
)
def test_a_dropped_body_comes_to_rest_on_the_ground(shape, angle, half_height):
    """Dropped from 2 cm above the ground: after 3 s its lowest point is at the ground height and it
    no longer moves vertically (without collision shapes it would have fallen 44 m); it neither slid
    nor rolled: x within 1 mm, angle within 0.01 rad (a disc whose centre of mass sat 0.2 mm off its
    centre rolled 10 cm like an eccentric wheel)."""
    engine, states = simulate([body("b", 0.2, FLOOR + half_height + 0.02, shape, angle)], 3.0)
    assert_rests_at(states, 0, engine.dofs, FLOOR + half_height)
    assert np.abs(states[:, 0] - 0.2).max() < HEIGHT_TOL
    assert np.abs(states[:, 2] - angle).max() < 0.01


def test_a_box_dropped_on_another_rests_on_top():
    """Two 0.1 m boxes, the upper one 2 cm off-centre and dropped from 8 cm above the lower one:
    the stack's heights are 0.05 and 0.15 above the ground; neither box slides off or tips."""
    engine, states = simulate([body("low", 0.2, FLOOR + 0.06), body("top", 0.22, FLOOR + 0.23)], 4.0)
    assert_rests_at(states, 0, engine.dofs, FLOOR + 0.05)
    assert_rests_at(states, 1, engine.dofs, FLOOR + 0.15)
    final = states[-1]
    assert abs(final[3] - 0.22) < 2e-3 and abs(final[5]) < 0.01  # the top box's x [m] and angle [rad]


def test_a_box_in_a_glass_rests_on_its_inner_bottom():
    """The 2D glass collides as a U (bottom and walls), not as its outer rectangle: a small box
    dropped 2 cm into it rests on the bottom, a wall thickness above the ground."""
    glass = {"type": "glass", "radius": 0.08, "height": 0.1, "thickness": 0.01}
    cube = {"type": "box", "size": [0.04, 0.04]}
    engine, states = simulate([body("glass", 0.3, FLOOR + 0.05, glass), body("cube", 0.3, FLOOR + 0.05, cube)], 3.0)
    assert_rests_at(states, 1, engine.dofs, FLOOR + 0.01 + 0.02)


# ---------------------------------------------------------------------------------------------- sliding


def test_a_box_sliding_into_another_shares_its_momentum():
    """Frictionless ground: a 10 kg box at 1 m/s hits an equal box at rest. DART's contacts have no
    restitution, so the collision is perfectly inelastic: both move on at 0.5 m/s; the total
    x-momentum stays 10 kg m/s (to 0.1%) before, through and after the collision."""
    engine, states = simulate([body("a", 0.1, FLOOR + 0.05, vx=1.0), body("b", 0.3, FLOOR + 0.05)], 0.5, 0.0)
    n = engine.dofs
    mass = 1000.0 * 0.1 * 0.1  # [kg] per metre of depth
    momentum = mass * (states[:, n + 0] + states[:, n + 3])
    assert np.abs(momentum - mass * 1.0).max() < 1e-3 * mass
    assert states[-1, n + 3] == pytest.approx(0.5, rel=0.01)
    assert states[-1, n + 0] == pytest.approx(0.5, rel=0.01)
    assert states[-1, 3] - states[-1, 0] == pytest.approx(0.1, abs=HEIGHT_TOL)  # touching, not overlapping


def test_ground_friction_decelerates_a_sliding_box_at_mu_g():
    """Coulomb: a box sliding on the ground with friction 0.5 slows at 0.5 g (to 1%) and stops."""
    _, states = simulate([body("a", 0.1, FLOOR + 0.05, vx=1.0)], 0.4, friction=0.5)
    vx = states[:, 3]
    sliding = (vx > 0.2) & (vx < 0.8)
    rate = -np.polyfit(DT * np.flatnonzero(sliding), vx[sliding], 1)[0]
    assert rate == pytest.approx(0.5 * G, rel=0.01)
    assert abs(vx[-1]) < 1e-5  # stopped (what is left is the contact solver's jitter)


# ------------------------------------------------------------------------------------------------ 3D too


def test_a_3d_mesh_link_rests_on_the_ground(tmp_path):
    """3D: the ground and a mesh link (now a DART mesh shape, before it did not collide): a 0.1 m cube
    from an OBJ file dropped from 2 cm rests with its bottom on the ground."""
    import trimesh

    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "cube.obj")
    cube = body("cube", 0, 0, {"type": "mesh", "file": str(tmp_path / "cube.obj")})
    cube["links"][0]["joint"] = {"type": "free", "position": [0.3, FLOOR + 0.07, 0.5]}
    mpm = {"grid": {"cells": 16}, "bodies": [_blob([0.6, 0.6, 0.6])]}
    s = scene([cube], dim=3, mpm=mpm)
    engine = build_articulated(s, s.dx).engine
    states = np.array([engine.advance().next_state for _ in range(round(3.0 / DT))])
    last = states[-round(1.0 / DT) :]
    y = FLOOR + 0.07 + last[:, 4]  # free 3D: q = [rotation vector, translation from the joint position]
    assert np.abs(y - (FLOOR + 0.05)).max() < HEIGHT_TOL
    assert np.abs(last[:, engine.dofs + 4]).max() < SPEED_TOL


def _blob(center) -> dict:
    return {
        "name": "blob",
        "material": {"type": "elastic", "E": 2e3, "nu": 0.3, "density": 1000},
        "shape": {"type": "box", "center": center, "size": [0.1] * len(center)},
    }


# ------------------------------------------------------------------------------------------- refusals


@pytest.mark.parametrize(
    "change,message",
    [
        (
            lambda a: a["skeletons"][0]["links"][0].update(shape={"type": "ring", "radius": 0.05, "thickness": 0.01}),
            r"articulated\.skeletons\[0\]\.links\[0\]\.shape\.type: a ring has no DART collision shape",
        ),
        (lambda a: a.update(collision=False), r"articulated\.ground: .* set articulated\.collision: true"),
        (lambda a: a["skeletons"][0].update(collide=False), r"articulated\.ground: no skeleton collides"),
        (lambda a: a["ground"].update(friction=-1), r"articulated\.ground\.friction"),
    ],
    ids=["ring", "no_collision", "nothing_collides", "negative_friction"],
)
def test_bad_collision_keys_are_named(change, message):
    section = {"skeletons": [body("b", 0.2, 0.2)], "collision": True, "ground": {"height": FLOOR}}
    change(section)
    with pytest.raises(SceneError, match=message):
        make_scene(articulated=section)


def test_the_engine_refuses_a_ground_without_collision():
    from cosim.engines.rigid import RigidEngine
    from cosim.engines.rigid_build import GroundSpec

    with pytest.raises(InputError, match="a rigid ground needs collision on"):
        RigidEngine([], DT, collision=False, ground=GroundSpec())


def test_gradients_through_a_2d_rigid_contact_are_refused_and_the_mpm_ignores_the_ground():
    """A torque-driven box resting on the ground: DART's contact impulses are not differentiated, so
    the gradient check stops at the first step, naming the contact, instead of returning a gradient
    without them. The MPM sees the box, not the ground (its material keeps its own walls)."""
    from cosim.adjoint.gradcheck import check_gradients
    from cosim.adjoint.objective import Objective
    from cosim.scene.build import build_system

    box = body("box", 0.2, FLOOR + 0.05, controls={"box": "torque"})
    s = scene(
        [box],
        steps=3,
        mpm={"grid": {"cells": 32}, "bodies": [_blob([0.6, 0.6])]},
        articulated={"actions": {"initial": [0.0, 1.0, 0.0]}},
        loss={"type": "joint_target", "skeleton": "box", "joint": "box", "target": [0.2, 0.2, 0.0]},
        gradient={"params": ["action"]},
    )
    sim = build_system(s, requires_grad=True)
    (coupler,) = sim.couplers
    assert coupler.rigid.body_names == ["box/box"] and coupler.coupled == [0]  # the ground is no body
    obj = Objective(sim)
    with pytest.raises(
        SimulationError, match=r"a joint limit or a rigid contact acted on 'box/box.*rigid collisions off"
    ):
        check_gradients(obj.evaluate, obj.initial_params(), ["action"], obj.natural_scales(), 1)
