"""Unstable or invalid runs stop at the step where they go wrong, naming body and quantity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_scene, scene_dict

from cosim.errors import SceneError, SimulationError
from cosim.scene.build import build_system


def block(**material):
    b = scene_dict()["mpm"]["bodies"][0]
    b["material"] = {"type": "elastic", "E": 2e3, **material}
    return b


def test_fixed_substeps_below_the_elastic_bound_is_refused_naming_the_body():
    """E = 1e8 Pa gives c ~ 370 m/s; 2 substeps of 1 ms put c dt / dx >> 1."""
    bodies = [block(E=1e8) | {"name": "steel"}]
    scene = make_scene(time={"frame_dt": 2e-3, "substeps": 2}, mpm={"grid": {"cells": 32}, "bodies": bodies})
    with pytest.raises(SceneError, match=r"time.substeps: .*body 'steel'.*use at least \d+ substeps"):
        build_system(scene)


def test_auto_substeps_follow_the_cfl_bound():
    """Auto substeps: K = ceil(frame_dt (v + |g| frame_dt + c) / (cfl dx)) from the state before each
    step, v the largest velocity component and c = sqrt((lam + 2 mu) / rho) the P-wave speed (1.64 m/s
    here), so that (v + c) dt / dx <= cfl. The count is an integer, so any other rule shows."""
    bodies = [block() | {"velocity": [6.0, 0.0]}]
    scene = make_scene(
        time={"frame_dt": 4e-3, "substeps": "auto", "cfl": 0.3}, mpm={"grid": {"cells": 32}, "bodies": bodies}, steps=5
    )
    sim = build_system(scene)
    E, nu, rho, dx, frame_dt = 2e3, 0.3, 1000.0, 1 / 32, 4e-3
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    c = math.sqrt((lam + 2 * mu) / rho)
    infos = []
    for _ in range(5):
        v = float(np.abs(sim.mpm.state()["v"]).max()) + 9.81 * frame_dt
        infos.append(sim.step())
        assert infos[-1].substeps == math.ceil(frame_dt * (v + c) / (0.3 * dx))
    # 6 m/s over 4 ms is 0.77 cells; at CFL 0.3 that needs at least 3 substeps
    assert min(i.substeps for i in infos) >= 3


def test_fixed_substeps_cfl_violation_names_body_and_step():
    bodies = [
        block()
        | {
            "name": "bullet",
            "velocity": [30.0, 0.0],
            "shape": {"type": "box", "center": [0.3, 0.5], "size": [0.1, 0.1]},
        }
    ]
    scene = make_scene(time={"frame_dt": 4e-3, "substeps": 4}, mpm={"grid": {"cells": 32}, "bodies": bodies})
    sim = build_system(scene)
    with pytest.raises(SimulationError, match=r"step 0: CFL number .* in body 'bullet'"):
        sim.step()


def test_nan_is_caught_at_the_step_it_appears_with_body_and_quantity():
    bodies = [
        block() | {"name": "a"},
        block() | {"name": "b", "shape": {"type": "box", "center": [0.5, 0.2], "size": [0.1, 0.1]}},
    ]
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "bodies": bodies}))
    sim.step()
    state = sim.mpm.state()
    state["F"][sim.slices["b"].start + 3] = np.nan  # a corrupted deformation gradient in body b
    sim.mpm.set_state(state)
    with pytest.raises(SimulationError, match=r"step 1: body 'b': non-finite"):
        sim.step()


def test_forward_run_allocates_no_gradient_buffers():
    sim = build_system(make_scene(controls=[{"body": "block"}]))
    assert sim.mpm.n_slots == 2
    assert not sim.mpm.gradient_buffers_allocated()
    assert build_system(make_scene(controls=[{"body": "block"}]), requires_grad=True).mpm.gradient_buffers_allocated()


def test_state_round_trip_replays_bit_for_bit():
    """set_state(state()) then the same steps reproduce the same numbers exactly."""
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "bodies": [block() | {"velocity": [1.0, -1.0]}]}))
    s0 = sim.mpm.state()
    for _ in range(3):
        sim.step()
    a = sim.mpm.state()
    sim.mpm.set_state(s0)
    for _ in range(3):
        sim.step()
    b = sim.mpm.state()
    for key in a:
        assert np.array_equal(a[key], b[key]), key
