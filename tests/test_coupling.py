"""Two-way MPM-DART coupling: momentum and angular momentum exchange, hydrostatics, buoyancy,
and adjoint gradients across the coupling against central differences (float64)."""

import numpy as np
import pytest
from conftest import ROOT, make_scene, scene_dict

from cosim.adjoint.gradcheck import check_gradients
from cosim.adjoint.objective import Objective
from cosim.adjoint.tape import Tape
from cosim.errors import SceneError
from cosim.scene.build import build_system

MODELS = ["grid", "particle", "forecast"]


def elastic(name, center, size, velocity, E=2e4, density=500.0):
    return {
        "name": name,
        "material": {"type": "elastic", "E": E, "nu": 0.3, "density": density},
        "shape": {"type": "box", "center": center, "size": size},
        "velocity": velocity,
    }


def coupled_scene(bodies, skeletons, model, cells=48, steps=60, gravity=(0.0, 0.0), walls="none", **extra):
    return make_scene(
        steps=steps,
        time={"frame_dt": 2e-3, "substeps": extra.pop("substeps", "auto"), "exchanges": extra.pop("exchanges", "auto")},
        mpm={"grid": {"cells": cells}, "boundary": {"type": walls}, "gravity": list(gravity), "bodies": bodies},
        articulated={"skeletons": skeletons, **extra.pop("articulated", {})},
        contact={"model": model, **extra.pop("contact", {})},
        **extra,
    )


def free_box(name, position, size, density, **joint):
    return {
        "name": name,
        "links": [
            {
                "name": name,
                "shape": {"type": "box", "size": size},
                "density": density,
                "joint": {"type": "free", "position": position, **joint},
            }
        ],
    }


@pytest.mark.parametrize("model", MODELS)
def test_momentum_is_exchanged_with_a_free_box(model):
    """Gravity off: an elastic ball thrown at a free box; box + particles keep their linear
    momentum within 1% through the collision, and the box takes a real share of it."""
    ball = elastic("ball", [0.3, 0.5], None, [2.0, 0.0])
    ball["shape"] = {"type": "sphere", "center": [0.3, 0.5], "radius": 0.08}
    scene = coupled_scene(
        [ball],
        [free_box("box", [0.55, 0.5], [0.15, 0.15], 400.0)],
        model,
    )
    sim = build_system(scene)
    box = sim.engines["dart"].skeletons[0]

    def momenta():
        v = sim.mpm.state()["v"]
        return (sim.mpm.mass[:, None] * v).sum(axis=0), box.getMass() * box.getCOMLinearVelocity()[:2]

    soft0, rigid0 = momenta()
    total0 = soft0 + rigid0
    for _ in range(sim.steps):
        sim.step()
    soft, rigid = momenta()
    assert np.linalg.norm(soft + rigid - total0) <= 0.01 * np.linalg.norm(total0)
    assert rigid[0] > 0.3 * total0[0]  # the box was pushed


@pytest.mark.parametrize("model", MODELS)
def test_liquid_at_rest_in_a_welded_cup_weighs_on_it(model):
    """Hydrostatics: water at rest in a cup held by a weld joint; the reaction force on the cup,
    averaged over the second half of 0.6 s, equals the water's weight within 5%."""
    scene = make_scene(
        steps=150,
        time={"frame_dt": 4e-3, "substeps": "auto"},
        mpm={
            "grid": {"cells": 32},
            "bodies": [
                {
                    "name": "water",
                    "material": {"type": "liquid", "E": 2e4, "nu": 0.3, "viscosity": 1.0},
                    "shape": {"type": "box", "center": [0.5, 0.4], "size": [0.24, 0.16]},
                    "hydrostatic": True,
                }
            ],
        },
        articulated={
            "skeletons": [
                {
                    "name": "cup",
                    "links": [
                        {
                            "name": "cup",
                            "shape": {"type": "glass", "radius": 0.15, "height": 0.3, "thickness": 0.03},
                            "density": 1000,
                            "joint": {"type": "weld", "position": [0.5, 0.44]},
                        }
                    ],
                }
            ]
        },
        contact={"model": model},
    )
    sim = build_system(scene)
    weight = sim.mpm.mass.sum() * 9.81
    forces = []
    for n in range(sim.steps):
        sim.step()
        forces.append(sim.last.engines["dart"].wrenches[0, 3:5])
    mean = np.mean(forces[sim.steps // 2 :], axis=0)
    assert abs(-mean[1] - weight) <= 0.05 * weight, (mean, weight)
    assert abs(mean[0]) <= 0.02 * weight  # no net sideways push


@pytest.mark.fidelity
def test_a_light_box_floats_with_the_submerged_fraction_of_its_density_ratio():
    """Archimedes (forecast contact): a free box of density 500 dropped on water of density 1000
    settles half submerged; box height and water surface averaged over the last 0.8 s (the
    surface: median over columns away from the box of the top particle + dx/4). In the fidelity
    set (``-m fidelity``) beside its matrix of models and density ratios: too long for the default
    run."""
    cells, steps = 64, 400
    dx = 1 / cells
    floor, width = 3 * dx, 1 - 6 * dx
    scene = make_scene(
        steps=steps,
        time={"frame_dt": 4e-3, "substeps": "auto"},
        mpm={
            "grid": {"cells": cells},
            "bodies": [
                {
                    "name": "water",
                    "material": {"type": "liquid", "E": 2e5, "nu": 0.3, "viscosity": 3.0},
                    "shape": {"type": "box", "center": [0.5, floor + 0.11], "size": [width, 0.22]},
                    "hydrostatic": True,
                }
            ],
        },
        articulated={"skeletons": [free_box("box", [0.5, floor + 0.28], [0.24, 0.12], 500.0)]},
        contact={"model": "forecast"},
    )
    sim = build_system(scene)
    engine = sim.engines["dart"]
    heights, surfaces = [], []
    for n in range(steps):
        sim.step()
        if n >= steps // 2:
            heights.append(engine.body_states()["position"][0, 1])
            x = sim.mpm.state()["x"]
            far = x[np.abs(x[:, 0] - 0.5) > 0.2]
            columns = np.floor(far[:, 0] / dx).astype(int)
            surfaces.append(np.median([far[columns == c, 1].max() for c in np.unique(columns)]) + dx / 4)
    submerged = (np.mean(surfaces) - (np.mean(heights) - 0.06)) / 0.12
    assert abs(submerged - 0.5) <= 0.05, submerged  # 10% of the density ratio 0.5


@pytest.mark.parametrize("model", ["grid", "forecast"])
def test_a_hinged_door_turns_by_the_angular_impulse_it_receives(model):
    """Gravity off: a block thrown at a door hanging from a hinge below the hinge turns it the
    positive way (counter-clockwise); the angle equals the one integrated from the reaction
    torques handed to DART with the door's inertia plus the added mass of the material that
    follows it (the forecast model's; ``cosim.engines.rigid_added_mass``), and the door's angular
    momentum about the hinge equals the one the block lost (within 2%: the block's APIC spin is
    not counted; the material handed the door's velocity change is part of the block)."""
    from cosim.engines.rigid_added_mass import body_jacobians, generalised

    hinge = np.array([0.65, 0.75])
    door = {
        "name": "door",
        "links": [
            {
                "name": "panel",
                "shape": {"type": "box", "size": [0.05, 0.4]},
                "offset": [0.0, -0.2],
                "density": 300,
                "joint": {"type": "revolute", "position": hinge.tolist()},
            }
        ],
    }
    scene = coupled_scene([elastic("block", [0.45, 0.52], [0.12, 0.12], [2.0, 0.0], E=5e4)], [door], model, steps=80)
    sim = build_system(scene)
    engine = sim.engines["dart"]
    inertia = engine.skeletons[0].getMassMatrix()[0, 0]

    def block_spin():
        s = sim.mpm.state()
        r, v = s["x"] - hinge, s["v"]
        return float(np.sum(sim.mpm.mass * (r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0])))

    spin0 = block_spin()
    omega = angle = 0.0
    for _ in range(sim.steps):
        sim.step()
        for exchange in sim.last.exchanges:  # each of the macro step's exchanges steps DART by exchange_dt
            record = exchange.engines["dart"]
            added = 0.0
            if record.added is not None:  # J^T A J at the exchange's start
                now = engine.flat_state()
                engine.set_flat_state(record.state)
                added = generalised(engine, record.added, body_jacobians(engine, record.added))[0][0, 0]
                engine.set_flat_state(now)
            omega += record.wrenches[0, 2] * sim.exchange_dt / (inertia + added)
            angle += sim.exchange_dt * omega  # semi-implicit Euler, as DART
    q, qd = engine.state()["q"][0], engine.state()["qd"][0]
    assert q > 0.2  # turned, the right way
    assert q == pytest.approx(angle, rel=1e-9) and qd == pytest.approx(omega, rel=1e-9)
    assert inertia * qd == pytest.approx(spin0 - block_spin(), rel=0.02)


def gradient_scene(model, loss, substeps: int = 4):
    """A soft block pushed by impulses and a light free box pushed by DART generalised forces
    (x, y, angle) toward each other: 10 macro steps with contact in most of them; ``substeps`` per frame
    (above 4 the box's coupler makes each frame several exchanges)."""
    box = free_box("box", [0.615, 0.52], [0.15, 0.15], 100.0, qd0=[-1.0, 0.0, 0.0])
    box["controls"] = {"box": "torque"}
    return coupled_scene(
        [elastic("ball", [0.45, 0.5], [0.14, 0.14], [0.5, 0.1], E=2e3)],
        [box],
        model,
        cells=32,
        steps=10,
        substeps=substeps,
        articulated={"actions": {"hold": 2, "initial": [-20.0, 5.0, 0.5]}},
        controls=[{"body": "ball", "impulse": [0.0, 0.0]}],
        contact={"friction": 0.2},
        loss=loss,
    )


@pytest.mark.parametrize("model", MODELS)
def test_gradients_from_rigid_actions_to_particles(model):
    """rigid -> MPM: a loss on the block's particle positions w.r.t. the box's force/torque
    actions (and the particles' initial velocities), adjoint vs central differences, 1e-5."""
    scene = gradient_scene(model, {"type": "weighted_positions", "body": "ball"})
    obj = Objective(build_system(scene, requires_grad=True))
    results = check_gradients(obj.evaluate, obj.initial_params(), ["action", "v0"], obj.natural_scales(), 2)
    impulse = obj.system.last.outputs["reactions"]["dart"]["impulse"]
    assert np.abs(impulse).max() > 0  # in contact at the last step
    for r in results:
        assert abs(r.adjoint) > 0 and r.relative_error < 1e-5, r


@pytest.mark.parametrize("model", MODELS)
def test_gradients_from_particle_impulses_to_a_joint(model):
    """MPM -> rigid: a loss on the box's joint coordinates w.r.t. the control impulses on the
    soft block (the soft-gripper case) and the box's actions, adjoint vs central differences."""
    loss = {"type": "joint_target", "skeleton": "box", "joint": "box", "target": [0.1, 0.0, 0.0]}
    obj = Objective(build_system(gradient_scene(model, loss), requires_grad=True))
    results = check_gradients(obj.evaluate, obj.initial_params(), ["impulse", "action"], obj.natural_scales(), 2)
    for r in results:
        assert abs(r.adjoint) > 0 and r.relative_error < 1e-5, r


@pytest.mark.parametrize("exchanges", [1, 3])
def test_each_exchange_steps_dart_by_its_share_of_the_frame(exchanges):
    """time.exchanges = M: DART steps M times per macro step with dt = frame / M. A free box falling clear of
    the material gains g T in a macro step of T, and drops g h^2 M (M + 1) / 2 (semi-implicit Euler, h = T / M):
    g T^2 with one exchange, 2/3 g T^2 with three."""
    ball = elastic("ball", [0.3, 0.3], [0.1, 0.1], [0.0, 0.0])
    scene = coupled_scene(
        [ball],
        [free_box("box", [0.7, 0.7], [0.1, 0.1], 100.0)],
        "forecast",
        steps=1,
        gravity=(0.0, -9.81),
        exchanges=exchanges,
    )
    sim = build_system(scene)
    assert sim.exchanges == exchanges and sim.engines["dart"].dt == pytest.approx(2e-3 / exchanges, rel=1e-12)
    y0 = sim.engines["dart"].body_states()["position"][0, 1]
    sim.step()
    b = sim.engines["dart"].body_states()
    T, h = 2e-3, 2e-3 / exchanges
    assert b["linear_velocity"][0, 1] == pytest.approx(-9.81 * T, rel=1e-9)
    assert b["position"][0, 1] - y0 == pytest.approx(-9.81 * h * h * exchanges * (exchanges + 1) / 2, rel=1e-9)


@pytest.mark.parametrize("substeps, exchanges, per_exchange", [(6, 2, 3), (16, 4, 4)])
def test_gradients_through_several_exchanges_per_frame(substeps, exchanges, per_exchange):
    """More substeps per frame than the light box's coupler rests a body at (4 per exchange): each macro step
    is several exchanges, each engine steps their share of the frame, the impulses are shared; a loss on the
    box's joint w.r.t. the impulses, the box's actions and the block's initial velocities, adjoint vs central
    differences, 1e-5. (At 8 substeps, two exchanges of 4, a contact switch lies so near the trajectory that
    differences along one action direction converge to the adjoint only as the step shrinks: 7e-2 off at a
    relative step of 1e-4, 2e-3 at 1e-5, 6e-6 at 1e-7.)"""
    loss = {"type": "joint_target", "skeleton": "box", "joint": "box", "target": [0.1, 0.0, 0.0]}
    obj = Objective(build_system(gradient_scene("forecast", loss, substeps=substeps), requires_grad=True))
    assert obj.system.exchanges == exchanges and obj.system.grad_substeps == per_exchange
    names = ["impulse", "action", "v0"]
    results = check_gradients(obj.evaluate, obj.initial_params(), names, obj.natural_scales(), 2)
    for r in results:
        assert abs(r.adjoint) > 0 and r.relative_error < 1e-5, r


@pytest.mark.parametrize("substeps, exchanges", [(4, 1), (8, 2)])
def test_keeping_every_kth_checkpoint_gives_the_same_gradients(substeps, exchanges):
    """The tape keeps the MPM state of every 4th of 7 coupled steps (forecast contact) and the backward
    pass replays the MPM from them with the recorded boundaries: the gradients equal those of keeping
    every step's state to round-off, and the tape holds 2 MPM states instead of 7 (per exchange, with
    several per frame)."""
    loss = {"type": "joint_target", "skeleton": "box", "joint": "box", "target": [0.1, 0.0, 0.0]}
    scene = gradient_scene("forecast", loss, substeps=substeps)
    obj = Objective(build_system(scene, requires_grad=True, steps=7))
    assert obj.system.exchanges == exchanges
    params = obj.initial_params()
    value_every, grads_every = obj.evaluate(params, grad=True)
    held_every = sum(r.checkpoint is not None for r in obj.tape.records)  # per macro step
    obj.tape = Tape(checkpoint_every=4)
    value, grads = obj.evaluate(params, grad=True)
    assert value == value_every
    for key in ("impulse", "action", "v0", "x0"):
        scale = np.abs(grads_every[key]).max()
        assert scale > 0 and np.abs(grads[key] - grads_every[key]).max() <= 1e-12 * scale, key
    held = sum(sub.checkpoint is not None for r in obj.tape.records for sub in r.exchanges)
    assert (held_every, held) == (7, 2 * exchanges)


def test_an_uncoupled_link_costs_nothing_in_the_mpm():
    """couple: false keeps a link out of the MPM: no boundaries, no contact hook, and the soft
    block passes through where the box is."""
    skel = free_box("box", [0.55, 0.5], [0.15, 0.15], 400.0)
    skel["links"][0]["couple"] = False
    scene = coupled_scene([elastic("ball", [0.3, 0.5], [0.1, 0.1], [2.0, 0.0])], [skel], "grid")
    sim = build_system(scene)
    assert sim.mpm.boundaries == {} and sim.mpm.grid_hooks == [] and sim.couplers == []
    for _ in range(sim.steps):
        sim.step()
    assert sim.mpm.state()["x"][:, 0].mean() > 0.5  # went through


@pytest.mark.parametrize(
    "change,message",
    [
        (lambda s: s["links"][0].update(mass=3.0), "give density"),
        (lambda s: s["links"][0]["joint"].update(parent="nowhere"), "not a link listed before"),
        (lambda s: s.update(controls={"box": "wrench"}), "needs a 3D free joint"),
        (lambda s: s.update(controls={"lid": "torque"}), "no such joint"),
        (lambda s: s["links"][0]["joint"].update(q0=[0.0]), "has 3 coordinates"),
        (lambda s: s.update(urdf="missing.urdf"), "either links"),
    ],
)
def test_bad_articulated_sections_name_the_key_and_the_fix(change, message):
    skel = free_box("box", [0.55, 0.5], [0.15, 0.15], 400.0)
    change(skel)
    with pytest.raises(SceneError, match=message):
        coupled_scene([elastic("ball", [0.3, 0.5], [0.1, 0.1], [0.0, 0.0])], [skel], "grid")


def test_material_starting_inside_a_rigid_link_is_refused():
    scene = coupled_scene(
        [elastic("ball", [0.5, 0.5], [0.1, 0.1], [0.0, 0.0])],
        [free_box("box", [0.5, 0.5], [0.15, 0.15], 400.0)],
        "grid",
    )
    with pytest.raises(SceneError, match="start more than dx/2 inside rigid body 'box/box'"):
        build_system(scene)


def urdf_scene(**skeleton):
    base = {
        "name": "panda",
        "urdf": "scenes/assets/panda_like/panda_like.urdf",
        "position": [-0.25, 0.0, 0.33],
        "rotation": [-np.pi / 2, 0.0, 0.0],
        "couple": ["bottle"],
        "contact_shapes": {
            "bottle": {
                "shape": {"type": "glass", "radius": 0.035, "height": 0.2, "thickness": 0.006},
                "rotation": [np.pi / 2, 0.0, 0.0],
            }
        },
    }
    return make_scene(
        dim=3,
        mpm={"grid": {"cells": 16}, "bodies": [elastic("b", [0.5, 0.5, 0.5], [0.1, 0.1, 0.1], [0, 0, 0])]},
        articulated={"skeletons": [base | skeleton]},
    )


def test_a_urdf_arm_is_placed_in_the_y_up_world_with_a_hollow_bottle():
    """The Panda-like URDF: the base transform turns its z-up onto the scene's y-up (joint 2 sits
    0.333 m above the base), only the listed link is coupled, and the bottle's contact geometry
    is the placed glass: hollow along the bottle link's +z, walls negative."""
    from cosim.scene.articulated import build_articulated

    built = build_articulated(urdf_scene(), dx=1 / 96)
    engine = built.engine
    states = engine.body_states()
    link2 = states["position"][engine.body_index("panda_link2")]
    assert np.allclose(link2, [-0.25, 0.333, 0.33], atol=1e-9)
    assert built.names == ["panda/bottle"]
    grid = built.grids[0]
    cavity, wall, above = np.array([[0.0, 0.0, 0.05]]), np.array([[0.032, 0.0, 0.0]]), np.array([[0.0, 0.0, 0.15]])
    assert grid.sample(cavity)[0][0] > 0.02 and grid.sample(wall)[0][0] < 0 and grid.sample(above)[0][0] > 0


def test_a_typo_in_a_urdf_link_name_is_an_error():
    """Caught when the scene is read, naming the key and the links the URDF has."""
    with pytest.raises(SceneError, match=r"couple\.botle: the URDF has no link 'botle'; it has \[.*'bottle'\]"):
        urdf_scene(couple=["botle"])


def test_the_real_panda_scene_names_its_optional_extra_when_missing(monkeypatch):
    """Without the pybullet wheel, pour_franka_meshes stops at validation with the install line."""
    import sys

    from cosim.scene import load_scene

    monkeypatch.setitem(sys.modules, "pybullet_data", None)  # import fails as if not installed
    with pytest.raises(SceneError, match=r'pip install -e "\.\[panda\]"'):
        load_scene(ROOT / "scenes/pour_franka_meshes.yaml")


def test_the_real_panda_carries_the_bottle_where_our_arm_does():
    """Where the pybullet wheel is installed: the real Panda at our arm's joint angles puts its
    hand, hence the bottle placed on it, where our Panda-like URDF puts its bottle (1 mm)."""
    pytest.importorskip("pybullet_data")
    from cosim.scene import load_scene
    from cosim.scene.articulated import build_articulated

    real = build_articulated(load_scene(ROOT / "scenes/pour_franka_meshes.yaml"), dx=1 / 96)
    ours = build_articulated(load_scene(ROOT / "scenes/pour_franka.yaml"), dx=1 / 96)
    hand = real.engine.body_states()
    bottle = ours.engine.body_states()
    i, j = real.engine.body_index("panda_hand"), ours.engine.body_index("bottle")
    offset = hand["rotation"][i] @ np.array([0.0, 0.0, 0.1034])  # the bottle's centre on the real hand
    assert np.allclose(hand["position"][i] + offset, bottle["position"][j], atol=1e-3)


def test_coupler_pieces_match_central_differences():
    """The coupler's own adjoints: substep motion of the boundaries (p + k dt v, exp(k dt w) R)
    and the frame-averaged wrench (torque moved to the frame's origin), against differences."""
    from scipy.spatial.transform import Rotation

    from cosim.couplers.mpm_rigid import (
        BodyStates,
        average_wrench,
        average_wrench_vjp,
        substep_states,
        substep_states_vjp,
    )

    rng = np.random.default_rng(0)
    m, K, dt, eps = 2, 5, 1e-2, 1e-6
    b = BodyStates(
        rng.normal(size=(m, 3)),
        Rotation.random(m, random_state=1).as_matrix(),
        rng.normal(size=(m, 3)),
        3 * rng.normal(size=(m, 3)),
    )
    G = BodyStates(*(rng.normal(size=(K, m) + shape) for shape in ((3,), (3, 3), (3,), (3,))))
    keys = ("pos", "R", "v", "w")

    def probe(states):
        s = substep_states(states, dt, K)
        return sum(np.sum(getattr(G, k) * getattr(s, k)) for k in keys)

    adjoint = substep_states_vjp(G, b, dt)
    for key in keys:
        for idx in np.ndindex(getattr(b, key).shape):
            plus, minus = (BodyStates(*(getattr(b, k).copy() for k in keys)) for _ in range(2))
            getattr(plus, key)[idx] += eps
            getattr(minus, key)[idx] -= eps
            fd = (probe(plus) - probe(minus)) / (2 * eps)
            assert abs(getattr(adjoint, key)[idx] - fd) < 1e-7 * max(1.0, abs(fd)), (key, idx)

    J, L, pk, p = (rng.normal(size=s) for s in ((K, m, 3), (K, m, 3), (K, m, 3), (m, 3)))
    gW = rng.normal(size=(m, 6))
    grads = dict(zip(("J", "L", "pk", "p"), average_wrench_vjp(gW, J, pk, p, 0.3)))
    args = {"J": J, "L": L, "pk": pk, "p": p}
    for name, value in args.items():
        for idx in np.ndindex(value.shape):
            hi, lo = value.copy(), value.copy()
            hi[idx] += eps
            lo[idx] -= eps

            def f(x, name=name):
                a = {**args, name: x}
                return np.sum(gW * average_wrench(a["J"], a["L"], a["pk"], a["p"], 0.3))

            fd = (f(hi) - f(lo)) / (2 * eps)
            assert abs(grads[name][idx] - fd) < 1e-7 * max(1.0, abs(fd)), (name, idx)


def test_optimised_actions_stay_within_their_bounds():
    """A joint-velocity target (+5 m/s for the free box, needing ~700 N) far beyond the x-force bound
    of 30 N: Adam drives every segment's x-force to the bound and no entry leaves [lower, upper];
    a scene whose initial actions lie outside the bounds is refused by key."""
    from cosim.adjoint.optimize import PARAM_BOUNDS, minimise
    from cosim.errors import SceneError

    box = free_box("box", [0.615, 0.52], [0.15, 0.15], 100.0)
    box["controls"] = {"box": "torque"}
    actions = {"hold": 2, "initial": [-20.0, 5.0, 0.5], "bounds": [[-30.0, -10.0, -1.0], [30.0, 10.0, 1.0]]}
    loss = {"type": "joint_target", "skeleton": "box", "joint": "box", "target": [5.0, 0.0, 0.0], "velocity": True}

    def scene(actions):
        ball = elastic("ball", [0.3, 0.5], [0.1, 0.1], [0.0, 0.0], E=2e3)
        return coupled_scene(
            [ball], [box], "grid", cells=32, steps=6, substeps=2, articulated={"actions": actions}, loss=loss
        )

    obj = Objective(build_system(scene(actions), requires_grad=True))
    bounds = {**PARAM_BOUNDS, **obj.bounds()}
    result = minimise(obj.evaluate, obj.initial_params(), ["action"], obj.natural_scales(), 8, 0.5, bounds=bounds)
    final = result.params["action"]
    assert np.all(final >= [-30.0, -10.0, -1.0]) and np.all(final <= [30.0, 10.0, 1.0])
    assert np.all(final[:, 0] > 29.0)  # pressed against the bound (the unbounded optimum is ~700 N)
    assert result.best_loss < result.losses[0]
    outside = dict(actions, initial=[-40.0, 5.0, 0.5])
    with pytest.raises(SceneError, match="articulated.actions: the initial actions lie outside bounds"):
        build_system(scene(outside))


def test_run_contact_override_works_on_a_scene_with_only_articulated_bodies(tmp_path, capsys):
    """`cosim run --contact` on a scene whose rigid bodies are all DART links switches their model (the
    metrics say which ran); on a scene with nothing to meet the MPM it is refused, exit 2, naming it."""
    import json

    import yaml

    from cosim.cli import main

    skeleton = free_box("box", [0.7, 0.5], [0.1, 0.1], 400.0)
    data = scene_dict(
        steps=2,
        articulated={"skeletons": [skeleton]},
        contact={"model": "grid"},
        mpm={**scene_dict()["mpm"], "gravity": [0.0, 0.0]},
    )
    path = tmp_path / "dart_only.yaml"
    path.write_text(yaml.safe_dump(data))
    args = ["run", str(path), "--contact", "particle", "--out", str(tmp_path / "o"), "--quiet", "--no-preview"]
    assert main(args) == 0
    assert json.loads((tmp_path / "o" / "metrics.json").read_text())["contact_model"] == "particle"
    plain = tmp_path / "plain.yaml"
    plain.write_text(yaml.safe_dump(scene_dict()))
    assert main(["run", str(plain), "--contact", "forecast", "--out", str(tmp_path / "p"), "--quiet"]) == 2
    assert "--contact forecast: nothing meets the MPM" in capsys.readouterr().err
