"""Stress: stiff materials, fast impacts on thin walls, bodies on the domain's margin, one-cell-thin
bodies. Each runs stably (checked by its physics) or stops with a message naming the cause and the fix."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from cosim.errors import SceneError, SimulationError
from cosim.scene.build import build_system


def elastic(name: str, center, size, E: float = 2e3, velocity=(0.0, 0.0)) -> dict:
    return {
        "name": name,
        "material": {"type": "elastic", "E": E, "nu": 0.3, "density": 1000},
        "shape": {"type": "box", "center": list(center), "size": list(size)},
        "velocity": list(velocity),
    }


def test_stiff_material_runs_stably_with_automatic_substeps():
    """E = 1e7 Pa (wave speed 116 m/s): the automatic count takes the substeps the wave needs and the
    falling block's energy does not grow (the runner's budget: at most round-off above the start)."""
    scene = make_scene(steps=15, mpm={"grid": {"cells": 32}, "bodies": [elastic("steel", [0.5, 0.5], [0.2, 0.2], 1e7)]})
    sim = build_system(scene)
    sim.rollout()
    c = np.sqrt(1e7 * 0.7 / (1.3 * 0.4 * 1000))
    assert sim.last.substeps >= np.ceil(scene.time.frame_dt * c / (scene.time.cfl * scene.dx))
    assert sim.conservation.excess < 1e-6


def impact(model: str, wall_thickness: float):
    """A block at 20 m/s towards a static wall, no gravity, 64 cells (dx = 1/64 m)."""
    return make_scene(
        steps=30,
        time={"frame_dt": 1e-3, "substeps": "auto"},
        mpm={
            "grid": {"cells": 64},
            "gravity": [0.0, 0.0],
            "bodies": [elastic("block", [0.3, 0.5], [0.1, 0.1], 1e5, velocity=(20.0, 0.0))],
        },
        rigid={
            "bodies": [
                {"name": "wall", "shape": {"type": "box", "size": [wall_thickness, 0.5]}, "position": [0.6, 0.5]}
            ]
        },
        contact={"model": model, "friction": 0.0},
    )


def test_a_20_m_per_s_impact_on_a_one_cell_wall_is_stopped_by_forecast_contact():
    """The forecast model stops the block at the wall: no particle beyond it, x-momentum gone
    or reversed (from 20 m/s)."""
    sim = build_system(impact("forecast", 1 / 64))
    sim.rollout()
    x, v = sim.mpm.state()["x"], sim.mpm.state()["v"]
    assert x[:, 0].max() < 0.6 + 0.5 / 64
    assert v[:, 0].mean() < 1.0
    assert sim.passed_through == {}


@pytest.mark.parametrize("model", ["grid", "particle"])
def test_particles_going_through_a_wall_stop_the_run_naming_bodies_and_fix(model):
    """The grid and particle models cannot stop 20 m/s at a one-cell wall (measured: 39 particles
    through in one step under grid; the block passes whole under particle): the run stops at the step
    it happens instead of going on with a silently wrong result."""
    sim = build_system(impact(model, 1 / 64))
    with pytest.raises(SimulationError, match=r"particles of body 'block' went through rigid body 'wall'.*forecast"):
        sim.rollout()


def test_a_wall_thinner_than_its_sdf_is_refused_naming_the_key():
    with pytest.raises(SceneError, match=r"rigid.bodies\[0\].shape: no SDF node lies inside"):
        build_system(impact("grid", 1 / 128))


@pytest.mark.parametrize("thickness", [1 / 32, 1 / 64], ids=["one cell", "half a cell"])
def test_thin_plate_on_the_floor_margin_stays_whole(thickness):
    """A plate one cell (or half a cell: one particle row) thin, resting on the floor's margin, next to a
    block touching the left wall: they stay in the domain, the energy only decreases, the plate stays
    in one piece (its particles' x-extent keeps its length)."""
    margin = 3 / 32
    scene = make_scene(
        steps=30,
        mpm={
            "grid": {"cells": 32},
            "bodies": [
                elastic("plate", [0.6, margin + thickness / 2 + 1e-3], [0.5, thickness]),
                elastic("block", [margin + 0.1 + 1e-3, 0.5], [0.2, 0.2]),
            ],
        },
    )
    sim = build_system(scene)
    x0 = sim.mpm.state()["x"][sim.slices["plate"]]
    sim.rollout()
    x = sim.mpm.state()["x"][sim.slices["plate"]]
    assert sim.conservation.excess <= 1e-9
    assert np.ptp(x[:, 0]) == pytest.approx(np.ptp(x0[:, 0]), rel=0.02)
    assert x[:, 1].min() > margin - 0.5 / 32


def test_a_watertight_mesh_with_sliver_faces_samples_and_collides(tmp_path):
    """An icosphere with one edge collapsed to 1e-7 of its length (two sliver faces, still watertight):
    as a soft body it samples its volume (within 5%); as a rigid body it stops a block thrown at it."""
    import trimesh
    from conftest import scene_dict

    from cosim.scene import parse_scene

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.08)
    v = ball.vertices.copy()
    a, b = ball.edges_unique[0]
    v[b] = v[a] + 1e-7 * (v[b] - v[a])
    sliver = trimesh.Trimesh(v, ball.faces, process=False)
    assert sliver.is_watertight
    sliver.export(tmp_path / "ball.obj")
    data = scene_dict(dim=3, steps=10)
    body = data["mpm"]["bodies"][0]
    body["shape"] = {"type": "mesh", "file": "ball.obj", "center": [0.5, 0.5, 0.5]}
    soft = build_system(parse_scene(data, tmp_path))
    volume = len(soft.mpm.state()["x"]) * (0.5 * soft.dx) ** 3
    assert volume == pytest.approx(sliver.volume, rel=0.05)
    body["shape"] = {"type": "box", "center": [0.5, 0.3, 0.5], "size": [0.2, 0.2, 0.2]}
    body["velocity"] = [0.0, 2.0, 0.0]
    data["rigid"] = {
        "bodies": [{"name": "ball", "shape": {"type": "mesh", "file": "ball.obj"}, "position": [0.5, 0.55, 0.5]}]
    }
    data["steps"] = 40  # free flight would lift the block's top from 0.40 to 0.53 m, past the ball's bottom at 0.47
    sim = build_system(parse_scene(data, tmp_path))
    sim.rollout()
    state = sim.mpm.state()
    free_flight = 2.0 - 9.81 * 40 * data["time"]["frame_dt"]
    assert state["v"][:, 1].mean() < free_flight - 0.1  # the ball pushed back (measured: 0.18 m/s below)
    assert sim.rigid.particles_inside(state["x"], depth=0.5 * sim.dx) == {"ball": 0}
    assert sim.passed_through == {}


def viscous_drop(eta: float, substeps="auto"):
    """A liquid block of viscosity ``eta`` [Pa s] falling in a 32-cell box: its explicit viscous bound
    rho dx^2 / (4 eta) is 2.4e-4 s at eta = 1000, 7x below the wave's CFL step at cfl 0.9."""
    liquid = {
        "name": "honey",
        "material": {"type": "liquid", "E": 2e5, "nu": 0.3, "density": 1000, "viscosity": eta},
        "shape": {"type": "box", "center": [0.5, 0.3], "size": [0.3, 0.2]},
    }
    return make_scene(
        steps=20,
        time={"frame_dt": 4e-3, "substeps": substeps, "cfl": 0.9},
        mpm={"grid": {"cells": 32}, "bodies": [liquid]},
    )


def test_a_very_viscous_liquid_takes_the_substeps_of_its_viscous_bound():
    """eta = 1000 Pa s: the automatic count keeps dt under rho dx^2 / (2 d eta) and the run keeps its
    energy budget (at the CFL step alone it went non-finite in its first frame)."""
    scene = viscous_drop(1000.0)
    sim = build_system(scene)
    sim.rollout()
    assert scene.time.frame_dt / sim.last.substeps <= 1000 * scene.dx**2 / (4 * 1000.0)
    assert sim.conservation.excess < 1e-6


def test_fixed_substeps_above_the_viscous_bound_are_refused_naming_the_viscosity():
    with pytest.raises(SceneError, match=r"time\.substeps: 4 substeps .*viscous bound .*material\.viscosity = 1000"):
        build_system(viscous_drop(1000.0, substeps=4))
