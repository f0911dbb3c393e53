"""Contact fidelity of the three models: elastic restitution against the MPM domain wall, a
contact surface where the geometry is, and losses continuous across the contact band.

The full matrix (every model, two impact speeds, 3D, the floating box's three density ratios,
two seconds of the welded tub) runs with ``-m fidelity``; the default run keeps the cheap cases."""

from __future__ import annotations

import functools

import numpy as np
import pytest
from conftest import ROOT

from cosim.scene import parse_scene
from cosim.scene.build import build_system

MODELS = ("grid", "particle", "forecast")
WALL_FACE = 0.25  # [m] x of the rigid wall's face the bodies are thrown at
GAP = 0.05  # [m] between a thrown body and the wall it is thrown at


def _bounce_scene(dim: int, cells: int, speed: float, model: str | None) -> dict:
    """An elastic disc / sphere (radius 0.1 m) thrown at ``speed`` along -x, without gravity, at a
    static rigid wall under ``model``, or (None) at the MPM domain's own slip wall."""
    dx = 1.0 / cells
    face = 3 * dx if model is None else WALL_FACE
    rest = [0.5] * (dim - 1)
    scene = {
        "name": "bounce",
        "dim": dim,
        "precision": "float64",
        "steps": int(2.6 * GAP / speed / 4e-3) + 20,
        "time": {"frame_dt": 4e-3, "substeps": "auto", "cfl": 0.3},
        "mpm": {
            "grid": {"cells": cells},
            "boundary": {"type": "slip", "thickness": 3},
            "gravity": [0.0] * dim,
            "bodies": [
                {
                    "name": "disc",
                    "material": {"type": "elastic", "E": 5e4, "nu": 0.3, "density": 1000},
                    "shape": {"type": "sphere", "center": [face + GAP + 0.1, *rest], "radius": 0.1},
                    "velocity": [-speed] + [0.0] * (dim - 1),
                }
            ],
        },
        "output": {"preview": "none"},
    }
    if model is not None:
        wall = {"name": "wall", "shape": {"type": "box", "size": [0.1] + [0.8] * (dim - 1)}}
        scene["rigid"] = {"bodies": [{**wall, "position": [WALL_FACE - 0.05, *rest]}]}
        scene["contact"] = {"model": model}
    return scene


@functools.cache
def restitution(dim: int, cells: int, speed: float, model: str | None) -> float:
    """Rebound speed / impact speed of the body's centre of mass."""
    data = _bounce_scene(dim, cells, speed, model)
    system = build_system(parse_scene(data, ROOT, origin="bounce"))
    mass = system.mpm.mass
    fastest = 0.0
    for _ in range(data["steps"]):
        system.step()
        fastest = max(fastest, float(np.average(system.state()["mpm"]["v"][:, 0], weights=mass)))
    return fastest / speed


def _check_restitution(dim: int, cells: int, speed: float, model: str) -> None:
    reference = restitution(dim, cells, speed, None)
    e = restitution(dim, cells, speed, model)
    # with the paper's blend the forecast model gave 0.27 against 0.94 (2D, 64 cells, 0.3 m/s)
    assert abs(e - reference) <= 0.1 * reference, (model, speed, e, reference)
    assert reference > 0.8, reference  # the reference itself bounces (measured 0.90-0.94)


# the default run (CI's 10 minutes) keeps the forecast model's scan and the union SDF; the rest -m fidelity
FORECAST_FIRST = [pytest.param(m, marks=[] if m == "forecast" else [pytest.mark.fidelity]) for m in MODELS]


@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
def test_an_elastic_disc_rebounds_from_a_rigid_wall_as_from_the_domain_wall(model):
    _check_restitution(2, 64, 1.0, model)


@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("dim, cells, speed", [(2, 64, 0.3), (3, 32, 0.3), (3, 32, 1.0)])
def test_restitution_at_another_speed_and_in_3d(model, dim, cells, speed):
    _check_restitution(dim, cells, speed, model)


def scan_loss(model: str, points: int = 50, material: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The final centre of mass's x [m] of a disc (elastic, or ``material``) thrown at a rigid wall at
    0.5 m/s, over 3 macro steps, as its start is shifted along x by theta: from 0.7 cells farther to
    0.7 cells closer than a front 0.8 cells from the wall's face, so its front particles cross every
    model's switch (the forecast's threshold, the grid's last constrained node) within the scan."""
    cells = 32
    dx = 1.0 / cells
    data = _bounce_scene(2, cells, 0.5, model)
    if material is not None:
        data["mpm"]["bodies"][0]["material"] = material
    data.update(steps=3, loss={"type": "com_target", "body": "disc", "target": [0.0, 0.5]})
    front = WALL_FACE + GAP  # the disc's front edge as scene data places it
    data["mpm"]["bodies"][0]["shape"]["center"][0] += (WALL_FACE + 0.8 * dx) - front
    system = build_system(parse_scene(data, ROOT, origin="scan"))
    from cosim.adjoint.objective import Objective

    objective = Objective(system)
    name = "mpm.x0" if "mpm.x0" in objective.parameters else "x0"
    x0 = objective.initial_params()[name]
    thetas = np.linspace(-0.7 * dx, 0.7 * dx, points)
    values = []
    for theta in thetas:
        shifted = x0.copy()
        shifted[:, 0] -= theta
        values.append(objective.evaluate({name: shifted})[0])
    return thetas, np.asarray(values)


def largest_jump(values: np.ndarray) -> float:
    """The largest departure of a first difference from the mean of its two neighbours, relative
    to the larger neighbour: about 0 for a smooth or kinked sampled function (a kink moves one
    difference by at most half the slope change), 1 or more where the function jumps."""
    d = np.diff(values)
    middle = np.abs(d[1:-1] - 0.5 * (d[:-2] + d[2:]))
    scale = np.maximum(np.abs(d[:-2]), np.abs(d[2:]))
    return float(np.max(middle / scale))


@pytest.mark.parametrize("model", FORECAST_FIRST)
def test_a_loss_through_contact_has_no_jump_across_the_band(model):
    _thetas, values = scan_loss(model)
    step = np.median(np.abs(np.diff(values)))
    with_jump = values + np.where(np.arange(len(values)) >= len(values) // 2, 0.2 * step, 0.0)
    assert largest_jump(with_jump) > 0.15  # the measure sees a jump of a fifth of one step's change
    assert largest_jump(values) < 0.05, largest_jump(values)


def test_a_liquid_loss_through_grid_contact_has_no_jump():
    """The grid model holds liquid by its own edge, read off the nodes' fills (``support: material``):
    the same scan with a water disc crosses where that reading, the splash switch and the band's
    shift take over, and finds no jump (measured 0.021: two kinks 4 points apart)."""
    water = {"type": "liquid", "E": 2e5, "nu": 0.3, "density": 1000, "viscosity": 1.0}
    _thetas, values = scan_loss("grid", material=water)
    assert largest_jump(values) < 0.05, largest_jump(values)


# ------------------------------------------------------------------ sealed composite bodies
TUB_FLOOR = 0.1875  # [m] the tub floor's top: on a grid line at 32, 64 and 128 cells/m
TUB_WALL_CELLS = 2  # the tub's wall thickness [cells]


def _tub_links(thickness: float) -> list[dict]:
    """A 0.5 m wide tub of three welded links: a floor plate (welded to the world, top at TUB_FLOOR)
    and two walls standing on it, 0.25 m high, ``thickness`` [m] thick."""
    t = thickness
    wall = {"type": "box", "size": [t, 0.25]}
    return [
        {
            "name": "floor",
            "shape": {"type": "box", "size": [0.5, t]},
            "density": 1000,
            "joint": {"type": "weld", "position": [0.5, TUB_FLOOR - t / 2]},
        },
        *(
            {
                "name": side,
                "shape": wall,
                "density": 1000,
                "joint": {"type": "weld", "parent": "floor", "position": [x, t / 2 + 0.125]},
            }
            for side, x in (("left", -0.25 + t / 2), ("right", 0.25 - t / 2))
        ),
    ]


def tub_scene(model: str, seconds: float, cells: int = 64) -> dict:
    """Water at rest (hydrostatic, 0.12 m deep) in the welded tub, 2D."""
    dx = 1.0 / cells
    t = TUB_WALL_CELLS * dx
    inner = (0.25 + t, 0.75 - t)
    water = {
        "name": "water",
        "material": {"type": "liquid", "E": 2e5, "nu": 0.3, "density": 1000, "viscosity": 1.0},
        "shape": {"type": "box", "center": [0.5, TUB_FLOOR + 0.06], "size": [inner[1] - inner[0], 0.12]},
        "hydrostatic": True,
    }
    return {
        "name": "tub",
        "dim": 2,
        "precision": "float64",  # the session's: another precision would re-initialise Taichi for later tests
        "steps": round(seconds / 4e-3),
        "time": {"frame_dt": 4e-3, "substeps": "auto"},
        "mpm": {"grid": {"cells": cells}, "boundary": {"type": "slip", "thickness": 3}, "bodies": [water]},
        "articulated": {"skeletons": [{"name": "tub", "links": _tub_links(t)}]},
        "contact": {"model": model},
        "output": {"preview": "none"},
    }


def tub_run(model: str, seconds: float) -> tuple[int, float]:
    """(particles that left the tub's cavity, mean vertical reaction on the tub over the last 0.2 s
    divided by the water's weight)."""
    from cosim.trajectory import step_reactions

    data = tub_scene(model, seconds)
    system = build_system(parse_scene(data, ROOT, origin="tub"))
    assert system.rigid.names == ["tub/floor+left+right"]  # one sealed contact body
    weight = float(system.mpm.mass.sum()) * 9.81
    dx = 1.0 / data["mpm"]["grid"]["cells"]
    forces = []
    for _ in range(data["steps"]):
        system.step()
        forces.append(step_reactions(system)[0, 4])  # [torque; force]: the y force
    x = system.state()["mpm"]["x"]
    inner_left, inner_right = 0.25 + TUB_WALL_CELLS * dx, 0.75 - TUB_WALL_CELLS * dx
    lost = (x[:, 0] < inner_left - dx) | (x[:, 0] > inner_right + dx) | (x[:, 1] < TUB_FLOOR - dx)
    last = round(0.2 / data["time"]["frame_dt"])
    return int(lost.sum()), -float(np.mean(forces[-last:])) / weight


@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
def test_water_at_rest_stays_in_a_tub_of_welded_links(model):
    lost, load = tub_run(model, 0.5)
    assert lost == 0
    assert abs(load - 1.0) < 0.02, load  # the tub carries the water's weight


@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
def test_water_stays_in_a_welded_tub_for_two_seconds(model):
    lost, load = tub_run(model, 2.0)
    assert lost == 0
    assert abs(load - 1.0) < 0.02, load


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    t = np.clip(((points - a) @ (b - a)) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * (b - a)), axis=1)


def test_the_sdf_of_welded_boxes_is_the_exact_sdf_of_their_union():
    """Three boxes forming a U (a tub's floor and two walls standing on it, 2 cells thick at 64
    cells/m): the union's SDF matches the U polygon's exact signed distance everywhere, seams
    included, where the minimum of the boxes' distances is off by up to half the wall thickness."""
    from cosim.couplers.sdf import primitive_sdf
    from cosim.couplers.sdf_union import Member, union_sdf

    t, spacing = 2 / 64, 0.5 / 64
    boxes = [((0.5, 0.1875 - t / 2), (0.5, t))] + [((x, 0.3125), (t, 0.25)) for x in (0.25 + t / 2, 0.75 - t / 2)]
    members = [
        Member(primitive_sdf("box", 2, spacing, 3 * spacing, half=np.array(size) / 2), np.eye(2), np.array(c))
        for c, size in boxes
    ]
    grid = union_sdf(members, spacing, 3 * spacing)
    nodes = grid.nodes().reshape(-1, 2)
    outline = np.array(
        [[0.25, 0.1875 - t], [0.75, 0.1875 - t], [0.75, 0.4375], [0.75 - t, 0.4375], [0.75 - t, 0.1875],
         [0.25 + t, 0.1875], [0.25 + t, 0.4375], [0.25, 0.4375]]
    )  # fmt: skip
    unsigned = np.min([_segment_distance(nodes, a, b) for a, b in zip(outline, np.roll(outline, -1, axis=0))], axis=0)
    inside = np.any([np.all(np.abs(nodes - c) <= np.array(s) / 2, axis=1) for c, s in boxes], axis=0)
    exact = np.where(inside, -unsigned, unsigned)
    near = unsigned < 3 * spacing  # where contact reads it (farther out, a box's grid only bounds it)
    error = np.abs(grid.values.ravel() - exact)[near]
    # at most 0.17 spacings (measured), at the inner corners where the open surface's samples stop
    assert error.max() < 0.2 * spacing, error.max() / spacing
    assert np.mean(error < 0.01 * spacing) > 0.98
    naive = np.min([m.sample(nodes)[0] for m in members], axis=0)
    assert np.abs(naive - exact)[near].max() > 0.4 * t  # what the seam looked like before
    # on the seam under the left wall, 1/3 of the wall's thickness from its inner face: the nearest
    # open surface is that face, so the normal points at the water, not along the seam
    d, n = grid.sample(np.array([[0.25 + 2 * t / 3, 0.1875]]))
    assert d[0] == pytest.approx(-t / 3, abs=0.05 * spacing)
    assert n[0] @ np.array([1.0, 0.0]) > 0.9, n  # measured 0.92 (node normals interpolated)
    _d, naive_normal = members[1].sample(np.array([[0.25 + 2 * t / 3, 0.1875]]))
    assert abs(naive_normal[0] @ np.array([1.0, 0.0])) < 0.1  # the wall alone: along the seam's normal


# ------------------------------------------------------------------ where the surface is
@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
def test_a_resting_block_sits_where_the_geometry_is(model):
    """An elastic block resting on a rigid support (64 cells/m): its centre of mass within 0.15
    cells of the closed form (measured: grid 0.003 cells, particle 0.03, forecast 0.005; the
    forecast model without the radius offset sat 0.245 cells deep)."""
    from cosim.bench.accuracy_coupled import RestingBlock
    from cosim.bench.accuracy_problem import Setting

    problem = RestingBlock()
    observation = problem.run(Setting(64, 0.3, "float64", model))  # the session's precision
    assert problem.error(observation, None) * problem.side * 64 < 0.15
    assert observation["inside"] == 0


@pytest.mark.fidelity
@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("ratio", [0.3, 0.5, 0.7])
def test_a_floating_box_sits_at_its_archimedes_draft(model, ratio):
    """A free DART box on water (64 cells/m, 2.5 s to settle): its draft within 0.15 cells of
    rho_box / rho_water times its height (measured: grid -0.04 to +0.07 cells, particle -0.04 to
    -0.09, forecast -0.08 to -0.15, i.e. up to 3.2% of the submerged fraction; the grid model held
    at node rows, ``support: nodes``, was -0.04 to -0.38 cells off depending on where the water
    level fell between rows: ``test_the_grid_model_holds_material_where_the_geometry_is``)."""
    from cosim.bench.accuracy_coupled import FloatingBox
    from cosim.bench.accuracy_problem import Setting

    problem = FloatingBox()
    problem.density, problem.duration = 1000.0 * ratio, 2.5
    observation = problem.run(Setting(64, 0.3, "float64", model))  # the session's precision
    draft_error = (observation["fraction"] - ratio) * problem.size[1]  # [m]
    assert abs(draft_error) * 64 < 0.15, draft_error * 64


def settled_water(support: str, shift: float, cells: int = 64) -> tuple[float, int]:
    """Water (0.125 m deep, wall to wall) dropped one cell onto a static plate whose top lies
    ``shift`` cells above a node row, settled for 0.4 s under the grid model: (its centre of mass
    above the plate's top less half its depth [cells], particle centres inside the plate)."""
    dx, depth = 1.0 / cells, 0.125
    top = 0.25 + shift * dx
    water = {
        "name": "water",
        "material": {"type": "liquid", "E": 2e5, "nu": 0.3, "density": 1000, "viscosity": 30.0},
        "shape": {"type": "box", "center": [0.5, top + dx + depth / 2], "size": [1 - 4 * dx, depth]},
    }
    plate = {"name": "plate", "shape": {"type": "box", "size": [1.0, 0.125]}, "position": [0.5, top - 0.0625]}
    data = {
        "name": "settle",
        "dim": 2,
        "precision": "float64",  # the session's
        "steps": 100,
        "time": {"frame_dt": 4e-3, "substeps": "auto"},
        "mpm": {"grid": {"cells": cells}, "boundary": {"type": "slip", "thickness": 2}, "bodies": [water]},
        "rigid": {"bodies": [plate]},
        "contact": {"model": "grid", "support": support},
        "output": {"preview": "none"},
    }
    system = build_system(parse_scene(data, ROOT, origin="settle"))
    for _ in range(data["steps"]):
        system.step()
    y = system.state()["mpm"]["x"][:, 1]
    return (float(y.mean()) - top - depth / 2) / dx, int(np.sum(y < top))


@pytest.mark.parametrize("shift", [0.0, 0.5])
def test_the_grid_model_holds_liquid_where_the_geometry_is(shift):
    """Held by its own edge (``support: material``) water settles on a plate within 0.15 cells of
    where the geometry puts it (measured -0.09, -0.12, -0.07, -0.02 at shifts 0, 1/4, 1/2, 3/4: its
    own weight compresses it by about 0.02) and only corner particles, at the domain's walls, end inside.
    Held at node rows (``support: nodes``, the paper's) it stops where the outermost held row's
    stencil first catches it: +0.71 and +0.89 cells high here."""
    offset, inside = settled_water("material", shift)
    assert abs(offset) < 0.15, offset
    assert inside <= 4, inside
    offset_nodes, _ = settled_water("nodes", shift)
    assert offset_nodes > 0.5, offset_nodes
