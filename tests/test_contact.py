"""The grid contact model against rigid SDF bodies: third law, friction, no penetration, adjoint."""

import re
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import make_scene

from cosim.couplers.boundary import RigidBoundaries
from cosim.couplers.contact import ForecastContact, GridContact, ParticlePenalty
from cosim.couplers.mpm_kinematic import MPMKinematicCoupler
from cosim.couplers.sdf import primitive_distance, primitive_sdf
from cosim.engines.kinematic import KinematicEngine, constant
from cosim.guards import measure_only
from cosim.scene.build import build_system
from cosim.system import CoupledSystem

DX = 1 / 32


def disc(name, center, radius, velocity, E=3e3):
    return {
        "name": name,
        "material": {"type": "elastic", "E": E, "nu": 0.3},
        "shape": {"type": "sphere", "center": center, "radius": radius},
        "velocity": velocity,
    }


MODELS = ["grid", "particle", "forecast"]


def build(
    bodies,
    boxes,
    motions,
    friction=0.0,
    gravity=(0.0, 0.0),
    walls="none",
    grad=False,
    substeps="auto",
    steps=40,
    model="grid",
):
    """A 2D MPM scene with static or moving rigid boxes (half extents ``boxes``) under a contact model
    (particle model: stiffness 100, i.e. 3.1e4 / s^2 at dx = 1/32)."""
    scene = make_scene(
        steps=steps,
        time={"frame_dt": 4e-3, "substeps": substeps},
        mpm={"grid": {"cells": 32}, "boundary": {"type": walls}, "gravity": list(gravity), "bodies": bodies},
    )
    mpm_only = build_system(scene, requires_grad=grad)
    mpm = mpm_only.mpm
    rb = RigidBoundaries(
        [primitive_sdf("box", 2, DX / 2, 3 * DX, half=h) for h in boxes],
        2,
        max(scene.time.max_substeps, mpm_only.grad_substeps),
        requires_grad=grad,
    )
    kinematic = KinematicEngine(motions, [f"box{i}" for i in range(len(boxes))], scene.time.frame_dt)
    coupler = MPMKinematicCoupler(kinematic)
    mpm.attach_boundary(coupler.source, rb)
    if model == "grid":
        GridContact(mpm, [rb], friction)
    elif model == "forecast":
        ForecastContact(mpm, [rb], friction)
    else:
        ParticlePenalty(mpm, [rb], 100.0, friction)
    sim = CoupledSystem(mpm, [kinematic], [coupler], mpm_only.stepping, scene.gravity, mpm_only.domain, mpm_only.steps)
    return sim, rb


def static(center):
    return constant(center, np.eye(2), [0.0, 0.0], 0.0)


@pytest.mark.parametrize("model", MODELS)
def test_newtons_third_law_holds_to_round_off(model):
    """Impulse on the particles + impulse on the body = 0 in every substep (no gravity, no walls),
    so the particles' momentum change equals minus the summed body impulses, to round-off."""
    half = np.array([0.06, 0.2])
    sim, _rb = build([disc("ball", [0.35, 0.5], 0.08, [2.0, 0.3])], [half], [static([0.6, 0.5])], model=model)
    m = sim.mpm.mass[:, None]
    p0 = (m * sim.mpm.state()["v"]).sum(axis=0)
    body_impulse, angular = np.zeros(2), 0.0
    for _ in range(40):
        reactions = sim.step().outputs["reactions"]["kinematic"]
        body_impulse += reactions["impulse"].sum(axis=(0, 1))
        angular += reactions["angular_impulse"].sum()
    p1 = (m * sim.mpm.state()["v"]).sum(axis=0)
    assert np.linalg.norm(body_impulse) > 0.3 * np.linalg.norm(p0)  # a real collision
    assert np.abs((p1 - p0) + body_impulse).max() < 1e-12 * np.abs(p0).max()
    assert p1[0] < 0.5 * p0[0]  # the ball was stopped or bounced back


def slide(friction, model):
    """A block sliding at 1 m/s on a static rigid slab under gravity; its speed after 0.12 s."""
    floor_half = np.array([0.4, 0.05])
    block = {
        "name": "block",
        "material": {"type": "elastic", "E": 2e4, "nu": 0.3},
        "shape": {"type": "box", "center": [0.35, 0.3 + 0.05], "size": [0.12, 0.1]},
        "velocity": [1.0, 0.0],
    }
    sim, _ = build(
        [block], [floor_half], [static([0.5, 0.25])], friction=friction, gravity=(0.0, -9.81), walls="slip", model=model
    )
    for _ in range(30):
        sim.step()
    return sim.mpm.state()["v"][:, 0].mean()


@pytest.mark.parametrize("model", MODELS)
def test_friction_slows_sliding(model):
    """Coulomb: mu = 0 keeps the block sliding (~1 m/s); mu = 0.5 takes about mu g t = 0.6 m/s off."""
    free, rough = slide(0.0, model), slide(0.5, model)
    assert free > 0.9
    assert free - rough > 0.3


@pytest.mark.parametrize("model", ["grid", "forecast"])
def test_thrown_particles_never_end_inside_a_thick_wall(model):
    """A disc thrown at 4 m/s (0.5 cells per substep at CFL) into a thick static wall stays out of it."""
    half = np.array([0.1, 0.3])
    center = np.array([0.7, 0.5])
    sim, _ = build([disc("ball", [0.35, 0.5], 0.06, [4.0, 0.0])], [half], [static(center)], model=model)
    for _ in range(40):
        sim.step()
        d = primitive_distance("box", sim.mpm.state()["x"] - center, half=half)
        assert d.min() >= 0.0


@pytest.fixture(scope="module", params=MODELS)
def pushed(request):
    """A box moving right at v_body pushes an elastic disc (float64, fixed substeps, gradients on)."""
    half = np.array([0.05, 0.12])
    ball = disc("ball", [0.5, 0.5], 0.07, [-0.5, 0.1])
    # the box's face off the particles' dyadic lattice: at x = 0.36 one particle sits exactly at its
    # contact switch (gap = 0, offset = its radius) in one substep, a kink central differences straddle
    sim, rb = build([ball], [half], [static([0.3607, 0.5])], grad=True, substeps=4, steps=4, model=request.param)
    return sim, rb, half


def rollout(sim, rb, v_body, v0, grad):
    """Loss sum_p w_p . x_p(T); with grad, dL/dv_body (through the body states) and dL/dv0."""
    x0 = sim.mpm.bodies[0].positions
    w = np.random.default_rng(0).standard_normal(x0.shape) / len(x0)
    n = len(x0)
    state0 = {"x": x0, "v": v0, "C": np.zeros((n, 2, 2)), "F": np.broadcast_to(np.eye(2), (n, 2, 2)).copy()}
    sim.engines["kinematic"].motions = [constant([0.3607, 0.5], np.eye(2), v_body, 0.0)]
    sim.set_state({"mpm": state0, "kinematic": {"steps": np.zeros(1)}})
    records = [sim.step() for _ in range(sim.steps)]
    loss = float((w * sim.mpm.state()["x"]).sum())
    if not grad:
        return loss, None, None
    g = {key: np.zeros_like(val) for key, val in state0.items()} | {"x": w}
    d_vbody = np.zeros(2)
    for rec in reversed(records):  # the MPM's own vjp: boundary adjoints are one of its results
        out = sim.mpm.vjp(rec.mpm, {"state": g})
        g, gs = out["state"], out["boundaries"]["kinematic"]
        times = rec.time + rec.dt * np.arange(rec.substeps)
        d_vbody += (times[:, None] * gs["pos"][:, 0]).sum(axis=0) + gs["vel"][:, 0].sum(axis=0)
    return loss, d_vbody, g["v"]


def test_adjoint_through_grid_contact_matches_finite_differences(pushed):
    """dL/d(body velocity) and dL/d(initial particle velocities) through 16 substeps with contact,
    against central differences (float64): relative error below 1e-5."""
    sim, rb, _ = pushed
    v_body = np.array([1.5, 0.2])
    v0 = np.tile([-0.5, 0.1], (sim.mpm.n_particles, 1))
    rollout(sim, rb, v_body, v0, grad=False)
    assert np.abs(rb.reactions(4)["impulse"]).max() > 1e-4  # the last step is in contact
    _loss, g_body, g_v0 = rollout(sim, rb, v_body, v0, grad=True)
    eps = 1e-6
    for d in (np.array([1.0, 0.0]), np.array([0.3, -1.0])):
        fd = (rollout(sim, rb, v_body + eps * d, v0, False)[0] - rollout(sim, rb, v_body - eps * d, v0, False)[0]) / (
            2 * eps
        )
        assert abs(fd) > 1e-6
        assert abs(fd - g_body @ d) < 1e-5 * abs(fd)
    d = np.random.default_rng(1).standard_normal(v0.shape)
    fd = (rollout(sim, rb, v_body, v0 + eps * d, False)[0] - rollout(sim, rb, v_body, v0 - eps * d, False)[0]) / (
        2 * eps
    )
    assert abs(fd - np.sum(g_v0 * d)) < 1e-5 * abs(fd)


def test_scene_with_a_shaken_container_drives_the_liquid(tmp_path):
    """From YAML: the ring container follows its piecewise motion and drags the water with it."""
    from conftest import SCENES

    from cosim.scene import load_scene
    from cosim.trajectory import Recorder

    scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 60})
    sim = build_system(scene)
    rec = Recorder(sim)
    rec(0)
    for n in range(60):  # 0.12 s of moving left at 0.3 m/s
        sim.step()
        if n + 1 in (30, 60):
            rec(n + 1)
    p, _ = sim.rigid.poses()[0]
    assert np.allclose(p, [0.5 - 0.3 * 0.12, 0.5])
    v = sim.mpm.state()["v"]
    assert v[:, 0].mean() < -0.05  # pushed along by the wall
    rec.write(tmp_path, preview=False)
    traj = np.load(tmp_path / "trajectory.npz")
    assert list(traj["rigid_names"]) == ["container"]
    assert np.allclose(traj["rigid_pos"][:, 0, 0], [0.5, 0.5 - 0.3 * 0.06, 0.5 - 0.3 * 0.12])


@pytest.mark.parametrize("model", MODELS)
def test_objective_gradients_through_a_moving_container_scene(model):
    """The scene-level Objective restores each step's boundary before its recompute: dL/dv0
    and dL/dE through 4 macro steps of a shaken ring container match central differences. The water
    starts 0.6 cells inside the ring's wall (moved clear of it, the finite differences of one model or
    another crossed a contact kink: 1.4e-5 and 3.4e-5); the forecast model's push-out gives it 46% of its
    energy from nowhere in step 0, which the energy guard would stop: measured here, not enforced."""
    from cosim.adjoint.gradcheck import check_gradients
    from cosim.adjoint.objective import Objective

    data = make_scene(
        steps=4,
        time={"frame_dt": 3e-3, "substeps": 3},
        mpm={"grid": {"cells": 32}, "bodies": [disc("water", [0.5, 0.42], 0.12, [0.3, -1.0], E=2e3)]},
        rigid={
            "bodies": [
                {
                    "name": "ring",
                    "shape": {"type": "ring", "radius": 0.2, "thickness": 0.04},
                    "position": [0.5, 0.5],
                    "motion": {"type": "constant", "velocity": [-0.8, 0.0]},
                }
            ]
        },
        contact={"model": model, "friction": 0.2, "stiffness": 100.0},
    )
    obj = Objective(build_system(data, requires_grad=True))
    measure_only(obj.system)
    results = check_gradients(obj.evaluate, obj.initial_params(), ["v0", "E"], obj.natural_scales(), directions=1)
    impulse = obj.system.last.outputs["reactions"]["kinematic"]["impulse"]
    assert np.abs(impulse).max() > 0  # the last step touched the wall
    for r in results:
        assert r.relative_error < 1e-5, r


def test_particles_inside_counts_against_the_moved_and_rotated_body():
    """The run's penetration report: points inside a rotated, moved box per its analytic SDF."""
    import math

    from cosim.couplers.rigid_view import RigidBodies
    from cosim.engines.kinematic import constant as const_motion

    half = np.array([0.1, 0.05])
    grid = primitive_sdf("box", 2, DX / 4, 2 * DX, half=half)
    motion = const_motion([0.5, 0.5], np.eye(2), [0.1, 0.0], math.pi / 2)
    kinematic = KinematicEngine([motion], ["lid"], frame_dt=0.25)
    scene = RigidBodies(["lid"], [SimpleNamespace(type="box", size=2 * half)], [grid], kinematic, dim=2)
    kinematic.step({})
    kinematic.step({})
    t = 0.5  # rotated by 45 degrees, moved 5 cm right
    p, R = motion.pose(t)
    pts = np.random.default_rng(3).uniform(0.3, 0.7, size=(4000, 2))
    exact = primitive_distance("box", (pts - p) @ R, half=half) < -0.5 * DX  # clearly inside
    outside = primitive_distance("box", (pts - p) @ R, half=half) > 0.5 * DX
    count = scene.particles_inside(pts)["lid"]
    assert exact.sum() > 200
    assert exact.sum() <= count <= len(pts) - outside.sum()
    assert scene.particles_held(pts) == {}  # a box holds nothing


def test_particles_held_by_a_moved_glass_are_those_in_its_cup():
    """A glass lying on its side (axis along world -x) 0.2 m right of the origin: points in the
    cup, in the wall and beyond the rim."""
    from cosim.couplers.rigid_view import RigidBodies
    from cosim.engines.kinematic import constant as const_motion

    shape = SimpleNamespace(type="glass", radius=0.05, height=0.1, thickness=0.01)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # body +y -> world -x
    motion = const_motion([0.2, 0.0, 0.0], R, [0.0, 0.0, 0.0], 0.0)
    grid = primitive_sdf("glass", 3, 0.005, 0.02, radius=0.05, height=0.1, thickness=0.01)
    scene = RigidBodies(["glass"], [shape], [grid], KinematicEngine([motion], ["glass"], frame_dt=0.1), dim=3)
    pts = np.array(
        [
            [0.2, 0.0, 0.0],  # the cup's middle
            [0.16, 0.035, 0.0],  # in the cup near the wall and the rim
            [0.2, 0.045, 0.0],  # in the side wall (counted as inside the wall, not held)
            [0.245, 0.0, 0.0],  # in the bottom
            [0.14, 0.0, 0.0],  # beyond the rim
        ]
    )
    assert scene.particles_held(pts) == {"glass": 2}


def test_bench_metrics_count_penetration_and_fast_separation_only():
    """The contact benchmark's metrics on hand-placed particles: a ring of inner radius 0.2,
    wall 0.02, moving at (0.3, 0); rebound counts only particles near the wall that leave it
    faster than the threshold relative to the wall."""
    from cosim.bench.contact import penetration_counts, rebound_count

    center, inner, wall = np.array([0.5, 0.5]), 0.2, 0.02
    radii = np.array([0.1, 0.19, 0.205, 0.215, 0.25, 0.3])
    x = center + radii[:, None] * np.array([1.0, 0.0])
    assert penetration_counts(x, center, inner, wall) == (2, 2)
    v_wall = np.array([0.3, 0.0])
    # inward speeds (relative to the wall) of particles at radius 0.195 on the +x side
    rel_inward = np.array([2.0, 1.4, 0.5, -1.0])
    x = np.tile(center + [0.195, 0.0], (4, 1))
    v = v_wall - rel_inward[:, None] * np.array([1.0, 0.0])
    assert rebound_count(x, v, center, v_wall, inner, band=0.01, speed=1.5) == 1
    assert rebound_count(x, v, center, v_wall, inner, band=0.01, speed=1.0) == 2
    # the same velocities far from the wall are not contact rebounds
    assert rebound_count(x - [0.1, 0.0], v, center, v_wall, inner, band=0.01, speed=1.0) == 0
    # a wall moving along with the particle: no separation at all
    assert rebound_count(x, v, center, v, inner, band=0.01, speed=0.1) == 0


@pytest.mark.parametrize("choices", ["cpu", "gpu"])
def test_the_contact_profile_splits_a_frame_into_kernels_launches_and_host_arrays(choices, tmp_path):
    """`cosim bench contact --profile --quick` (its own process: Taichi starts with the profiler): a frame of the
    grid run launches its fused substep once per substep and hands the device the few host arrays a coupled
    frame takes (``test_host_traffic``), and its kernels' time fits in the frame's wall time. With a GPU's
    loops (``COSIM_ARCH_CHOICES=gpu``) the fused substep runs no serial task: every loop's bounds are known
    when it compiles (a serial task computing them would be a launch of its own on a GPU)."""
    import csv
    import os
    import subprocess
    import sys

    env = {**os.environ, "COSIM_ARCH_CHOICES": "gpu"} if choices == "gpu" else None
    args = ["bench", "contact", "--profile", "--quick", "--out", str(tmp_path)]
    done = subprocess.run(
        [sys.executable, "-m", "cosim.cli", *args], capture_output=True, text=True, env=env, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    report = (tmp_path / "contact_profile.md").read_text()
    substeps = float(report.split("substeps a frame")[0].rsplit(", ", 1)[1])
    wall, in_kernels = (float(v) for v in re.findall(r"([\d.]+) ms", report.split("- wall: ")[1].split("\n")[0]))
    arrays = float(re.search(r"([\d.]+) host arrays", report).group(1))
    rows = {r["kernel"]: r for r in csv.DictReader((tmp_path / "contact_profile.csv").open())}
    assert 4 < substeps < 8  # the scene's CFL substeps (about 6)
    substep = rows["_substep_fused"]
    assert float(substep["launches_per_frame"]) == pytest.approx(substeps)
    assert arrays <= 5
    assert 0 < in_kernels < wall
    if choices == "gpu":  # the clear, P2G, grid update, liquid scatter, the hook's two passes, G2P
        assert float(substep["serial_per_launch"]) == 0 and float(substep["tasks_per_launch"]) == 7
