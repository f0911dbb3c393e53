"""The generic coupled system: several engines and boundary sources at once, per-body reactions,
chained contact hooks, and gradients through all of it against central differences (float64)."""

import math

import numpy as np
import pytest
from conftest import make_scene

from cosim.adjoint.gradcheck import check_gradients
from cosim.adjoint.objective import Objective
from cosim.scene.build import build_system

DX = 1 / 48


def thin_blob(width, velocity):
    return {
        "name": "blob",
        "material": {"type": "elastic", "E": 5e3, "nu": 0.3, "density": 500.0},
        "shape": {"type": "box", "center": [0.5, 0.5], "size": [width, 0.2]},
        "velocity": velocity,
    }


def static_box(name, x):
    return {
        "name": name,
        "shape": {"type": "box", "size": [0.12, 0.3]},
        "position": [x, 0.5],
        "motion": {"type": "static"},
    }


def two_box_scene(model, steps, **contact):
    """A blob one cell wide thrown at 1 m/s (+x) between two static boxes 0.3 cells away on each
    side; the box it hits is listed first, the one it leaves last."""
    gap = 0.3 * DX + 0.06 + 0.5 * DX
    return make_scene(
        steps=steps,
        time={"frame_dt": 2e-3},
        mpm={
            "grid": {"cells": 48},
            "boundary": {"type": "none"},
            "gravity": [0.0, 0.0],
            "bodies": [thin_blob(DX, [1.0, 0.0])],
        },
        rigid={"bodies": [static_box("hit", 0.5 + gap), static_box("left", 0.5 - gap)]},
        contact={"model": model, **contact},
    )


def test_forecast_gives_each_body_the_reaction_of_its_own_contact():
    """Every particle is within the contact threshold (2 cells) of both boxes. The blob moves
    away from the left box, whose BC_p leaves the velocities unchanged, so the momentum the blob
    loses is taken by the box it hits: that box's impulse equals the blob's momentum change
    (within 2%; what the left box feels is the little the blob bounces back onto it, 1% here).
    Before the fix the whole residual went to the last body listed: the hit box got 0 and the
    left box 2.06 N s (measured)."""
    sim = build_system(two_box_scene("forecast", 8, threshold=2 * DX))
    p0 = (sim.mpm.mass[:, None] * sim.mpm.state()["v"]).sum(axis=0)
    impulse = np.zeros((2, 2))
    for _ in range(sim.steps):
        impulse += sim.step().outputs["reactions"]["kinematic"]["impulse"].sum(axis=0)
    lost = p0 - (sim.mpm.mass[:, None] * sim.mpm.state()["v"]).sum(axis=0)
    hit, left = impulse
    assert lost[0] > 0.5 * p0[0]  # a real collision
    assert abs(hit[0] - lost[0]) <= 0.02 * lost[0], (hit, lost)
    assert np.linalg.norm(left) <= 0.02 * lost[0], left
    assert np.abs(impulse.sum(axis=0) - lost).max() < 1e-12 * p0[0]  # third law, to round-off


def test_contact_hooks_chain_like_one_model_over_both_sources():
    """The engine takes several grid hooks: a grid model per box, chained (the second reads the
    first's velocities), gives bit for bit the rollout of one grid model over both sources."""
    from cosim.couplers.contact import GridContact

    finals = []
    for split in (False, True):
        scene = two_box_scene("grid", 6)
        sim = _split_grid_contact(scene, GridContact) if split else build_system(scene)
        for _ in range(sim.steps):
            sim.step()
        finals.append(sim.mpm.state()["x"])
    assert np.abs(finals[0] - finals[0][0]).max() > 0  # it moved
    assert np.array_equal(finals[0], finals[1])


def _split_grid_contact(scene, GridContact):
    """The scene's system with its boxes as two boundary sources, each under its own grid hook."""
    from cosim.couplers.boundary import RigidBoundaries
    from cosim.couplers.mpm_kinematic import MPMKinematicCoupler
    from cosim.couplers.sdf import shape_sdf
    from cosim.engines.kinematic import KinematicEngine
    from cosim.scene.start import build_motion
    from cosim.system import CoupledSystem

    rigid = scene.rigid
    scene.rigid = None
    base = build_system(scene)
    engines, couplers = [], []
    for spec in rigid.bodies:
        kinematic = KinematicEngine([build_motion(spec, 2)], [spec.name], scene.time.frame_dt)
        kinematic.name = f"kinematic_{spec.name}"
        coupler = MPMKinematicCoupler(kinematic, name=kinematic.name)
        grid = shape_sdf(spec.shape, 2, 0.5 * DX, 3 * DX, scene.source_dir, spec.name)
        source = RigidBoundaries([grid], 2, scene.time.max_substeps)
        base.mpm.attach_boundary(coupler.source, source)
        GridContact(base.mpm, [source], scene.contact.friction, scene.contact.band)
        engines.append(kinematic)
        couplers.append(coupler)
    return CoupledSystem(base.mpm, engines, couplers, base.stepping, scene.gravity, base.domain, base.steps)


def n_engine_scene():
    """A soft block driven by impulses, squeezed by two DART skeletons (free boxes under torque
    control, one from each side) and pushed up by a kinematic plate: two engines, three
    manipulators, two boundary sources, forecast contact; 10 macro steps of 4 substeps."""

    def box(name, x, vx):
        return {
            "name": name,
            "links": [
                {
                    "name": name,
                    "shape": {"type": "box", "size": [0.12, 0.12]},
                    "density": 100.0,
                    "joint": {"type": "free", "position": [x, 0.5], "qd0": [vx, 0.0, 0.0]},
                }
            ],
            "controls": {name: "torque"},
        }

    return make_scene(
        steps=10,
        time={"frame_dt": 2e-3, "substeps": 4},
        mpm={
            "grid": {"cells": 32},
            "boundary": {"type": "none"},
            "gravity": [0.0, 0.0],
            "bodies": [
                {
                    "name": "ball",
                    "material": {"type": "elastic", "E": 2e3, "nu": 0.3, "density": 500.0},
                    "shape": {"type": "box", "center": [0.5, 0.5], "size": [0.14, 0.14]},
                    "velocity": [0.1, 0.2],
                }
            ],
        },
        articulated={
            "skeletons": [box("right", 0.64, -1.0), box("left", 0.36, 1.0)],
            "actions": {"hold": 2, "initial": [-5.0, 2.0, 0.3, 5.0, -1.0, 0.2]},
        },
        rigid={
            "bodies": [
                {
                    "name": "plate",
                    "shape": {"type": "box", "size": [0.3, 0.06]},
                    "position": [0.5, 0.395],
                    "motion": {"type": "constant", "velocity": [0.0, 0.5]},
                }
            ]
        },
        controls=[{"body": "ball", "impulse": [0.0, 0.0]}],
        contact={"model": "forecast", "friction": 0.2},
        loss={"type": "weighted_positions", "body": "ball"},
        precision="float64",
    )


def test_gradients_through_two_skeletons_and_a_kinematic_body_match_central_differences():
    """N engines: the loss on the soft block w.r.t. both skeletons' actions and the particles'
    impulses, adjoint against central differences along a random direction each, relative 1e-5; every
    manipulator touches the block, and each skeleton's action block gets its own gradient."""
    obj = Objective(build_system(n_engine_scene(), requires_grad=True))
    assert list(obj.system.engines) == ["kinematic", "dart"]
    params = obj.initial_params()
    _value, grads = obj.evaluate(params, grad=True)
    reactions = obj.system.last.outputs["reactions"]
    touched = [np.abs(reactions[s]["impulse"]).sum(axis=(0, 2)) for s in ("kinematic", "dart")]
    assert np.all(np.concatenate(touched) > 0), touched  # plate, right box, left box all in contact
    per_skeleton = np.abs(grads["action"]).reshape(len(params["action"]), 2, 3).sum(axis=(0, 2))
    assert np.all(per_skeleton > 1e-6 * np.abs(grads["action"]).max()), per_skeleton
    results = check_gradients(obj.evaluate, params, ["action", "impulse"], obj.natural_scales(), directions=1)
    for r in results:
        assert abs(r.finite_difference) > 0 and r.relative_error < 1e-5, r


def test_engines_and_couplers_keep_the_contract_and_refuse_what_they_cannot_honour():
    """The adapters a scene builds satisfy the contract's protocols; a gradient asked of an engine
    built without one, a missing boundary and an action for a prescribed motion are refused by name."""
    from cosim.engines.contract import Coupler, Engine

    sim = build_system(two_box_scene("grid", 2))
    assert all(isinstance(e, Engine) for e in [sim.mpm, *sim.engines.values()])
    assert all(isinstance(c, Coupler) for c in sim.couplers)
    record = sim.step()
    with pytest.raises(NotImplementedError, match=r"MPMEngine\.vjp"):
        sim.mpm.vjp(record.mpm, {"state": sim.mpm.state()})
    with pytest.raises(ValueError, match=r"no boundary states for sources \['kinematic'\]"):
        sim.mpm.step({"dt": 1e-3, "substeps": 1})
    with pytest.raises(ValueError, match="kinematic bodies take no action"):
        sim.engines["kinematic"].step({"action": np.ones(2)})


def test_the_substep_count_keeps_a_fast_boundary_under_a_cell_per_substep():
    """A resting block and a 0.12 m wide box spinning at 40 rad/s about its origin (its SDF box's
    corners at about 0.19 m move at about 7.6 m/s), far from the block: the particles alone would need
    one substep per frame, the boundary needs its surface to move at most cfl cells per substep."""
    box = {
        **static_box("spinner", 0.2),
        "motion": {"type": "constant", "velocity": [0.0, 0.0], "angular_velocity": 40.0},
    }
    scene = make_scene(
        steps=2,
        time={"frame_dt": 2e-3},
        mpm={"grid": {"cells": 48}, "gravity": [0.0, 0.0], "bodies": [thin_blob(DX, [0.0, 0.0])]},
        rigid={"bodies": [box]},
    )
    sim = build_system(scene)
    reach = sim.rigid.reach[0]
    assert 0.15 < reach < 0.25  # half-diagonal of the box plus the SDF's padding
    sim.step()
    needed = math.ceil(sim.frame_dt * 40.0 * reach / (sim.stepping.cfl * sim.dx) - 1e-9)
    assert sim.last.substeps >= needed >= 3
