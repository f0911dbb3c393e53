"""The command line, end to end, in fresh processes (each with its own Taichi)."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import yaml
from conftest import ROOT, run_cli, scene_dict, shipped_scenes
from scene_behaviour import BEHAVIOUR

from cosim.scene import load_scene

# Scenes whose rollout the suite already runs through the CLI elsewhere (each compile costs a minute):
# the six optimisation tasks in tests/test_tasks*.py (`cosim optimize` writes the same trajectory and
# preview) and towel_squash, checked by numbers in test_cloth_scenes.py; cloth_catch, the default
# scene, by test_default_scene_preview_shows_the_body_moving (the same output checks, and its preview).
COVERED_ELSEWHERE = (
    "cloth_catch",
    "make_taco",
    "push_towel",
    "towel_squash",
    "squeeze_plasticine",
    "pour_franka",
    "pour_water",
    "pull_door",
)


@pytest.mark.parametrize("path", shipped_scenes(exclude=COVERED_ELSEWHERE))
def test_every_shipped_scene_runs_and_writes_its_outputs(path, tmp_path):
    """Each scene runs (4 steps, or as long as ``scene_behaviour`` needs to check what it is for)."""
    steps, behaviour = BEHAVIOUR.get(path.stem, (4, None))
    steps = steps or yaml.safe_load(path.read_text())["steps"]
    preview = () if behaviour is None else ("--no-preview",)  # a long run's preview costs seconds of rendering
    res = run_cli("run", str(path), "--steps", str(steps), "--out", str(tmp_path), "--quiet", *preview)
    assert res.returncode == 0, res.stderr
    traj, metrics, scene = check_run_outputs(path, steps, tmp_path)
    if behaviour is None:
        assert (tmp_path / "preview.gif").stat().st_size > 1000
    else:
        assert not (tmp_path / "preview.gif").exists()
        behaviour(traj, metrics, scene)


def check_run_outputs(path, steps: int, out) -> tuple:
    """What every `cosim run` of the scene at ``path`` for ``steps`` steps must have written into ``out``:
    a finite trajectory of the right length, the metrics, and at least the substeps the elastic wave
    asks for; an undriven scene's energy does not grow. Returns (trajectory, metrics, scene)."""
    traj = np.load(out / "trajectory.npz")
    names = [str(n) for n in traj["body_names"]]
    assert len(traj["time"]) >= 2 and np.isclose(
        traj["time"][-1], steps * yaml.safe_load(path.read_text())["time"]["frame_dt"]
    )
    for name in names:
        x = traj[f"x_{name}"]
        assert x.shape[0] == len(traj["time"]) and np.isfinite(x).all()
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("wall_time_s", "steps", "substeps_total", "particles", "max_cfl", "energy_final", "hardware"):
        assert key in metrics
    assert metrics["steps"] == steps
    # Explicit stability: every step takes at least the substeps the elastic wave asks for,
    # c frame_dt / K <= cfl dx (speeds only add to it; measured: equal in 9 of the 10 scenes run here).
    scene = load_scene(path)
    c = max(p_wave_speed(b.material.E, b.material.nu, b.material.density) for b in scene.mpm.bodies)
    need = math.ceil(scene.time.frame_dt * c / (scene.time.cfl * scene.dx) - 1e-9)
    substeps = metrics["substeps_per_step"]
    assert substeps["min"] >= need, (substeps, need)
    assert steps * substeps["min"] <= metrics["substeps_total"] <= steps * substeps["max"]
    driven = scene.rigid or scene.articulated or any(ctl.impulse and any(ctl.impulse) for ctl in scene.controls)
    if not driven:
        # nothing drives the material: MPM only dissipates (measured: -7e-5 to -2e-4 of the total in 4 steps)
        assert metrics["energy_final"]["total"] <= metrics["energy_initial"]["total"]
    return traj, metrics, scene


def p_wave_speed(E: float, nu: float, density: float) -> float:
    """sqrt((lam + 2 mu) / rho) = sqrt(E (1 - nu) / ((1 + nu) (1 - 2 nu) rho)) [m/s]."""
    return math.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu) * density))


def test_default_scene_preview_shows_the_body_moving(tmp_path):
    """`cosim run` with no scene picks the default; the GIF's frames show the body's colour and change."""
    import imageio.v2 as imageio

    res = run_cli("run", "--steps", "40", "--out", str(tmp_path), "--quiet")
    assert res.returncode == 0, res.stderr
    assert "cloth_catch" in res.stdout
    check_run_outputs(ROOT / "scenes" / "cloth_catch.yaml", 40, tmp_path)
    frames = imageio.mimread(tmp_path / "preview.gif")
    first, last = (np.asarray(f)[..., :3].astype(int) for f in (frames[0], frames[-1]))
    # body 0's colour (31, 119, 180), lit and depth-shaded: blue well above red and green
    blue = lambda img: (img[..., 2] > img[..., 0] + 60) & (img[..., 2] > img[..., 1] + 20)
    assert blue(first).sum() > 200
    rows_first = np.nonzero(blue(first).any(axis=1))[0]
    rows_last = np.nonzero(blue(last).any(axis=1))[0]
    assert rows_last.mean() > rows_first.mean() + 5  # it fell: lower in the picture


def cli_in_fresh_process(args: list[str], forbidden: str) -> subprocess.CompletedProcess:
    """Run the CLI with ``args`` in a fresh interpreter and fail if a module matching ``forbidden``
    (a Python expression in ``m``, a module name) was imported."""
    code = (
        "import sys\n"
        "from cosim.cli import main\n"
        f"assert main({args!r}) == 0\n"
        f"bad = [m for m in sys.modules if {forbidden}]\n"
        "assert not bad, bad\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=600, check=False
    )
    assert res.returncode == 0, res.stderr
    return res


def test_run_without_rigid_bodies_imports_neither_dartpy_nor_cloth(tmp_path):
    """A 2D scene without rigid bodies also leaves the 3D renderer unloaded: VTK is imported only for 3D previews."""
    cli_in_fresh_process(
        ["run", "elastic_bounce_2d", "--steps", "2", "--out", str(tmp_path), "--quiet"],
        "m.startswith('dartpy') or 'cloth' in m or m.split('.')[0] in ('pyvista', 'vtk', 'vtkmodules')",
    )


@pytest.mark.parametrize(
    "scene, forbidden",
    [("shake_container_2d", ("taichi", "dartpy")), ("pour_water", ("taichi",)), ("pour_franka", ("taichi",))],
)
def test_validate_imports_no_taichi_and_dartpy_only_for_skeletons(scene, forbidden):
    """Validating makes every check `run` makes before its first step (``cosim.scene.start``) without
    Taichi: kinematic rigid bodies (shake_container_2d) need neither engine; DART links built from
    primitives (pour_water) and a URDF arm (pour_franka) need DART, which builds the skeletons."""
    res = cli_in_fresh_process(["validate", scene], f"m.split('.')[0] in {forbidden!r}")
    assert f"{scene}: valid" in res.stdout


def write_scene(tmp_path, **overrides):
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(scene_dict(**overrides)))
    return path


def test_gradcheck_passes_and_can_fail(tmp_path, capsys, monkeypatch):
    path = write_scene(
        tmp_path,
        steps=2,
        time={"frame_dt": 2e-3, "substeps": 3},
        controls=[{"body": "block", "impulse": [0.0, 1e-3]}],
        gradient={"params": ["v0", "impulse", "E"], "directions": 1},
    )
    ok = run_cli("gradcheck", str(path))
    assert ok.returncode == 0, ok.stderr
    worst = float(ok.stdout.split("max relative error:")[1].split()[0])
    assert worst < 1e-5
    from cosim.adjoint.objective import Objective
    from cosim.cli import main

    evaluate = Objective.evaluate

    def twice(self, params, grad=False):  # an adjoint off by a factor 2
        value, grads = evaluate(self, params, grad)
        return value, grads and {k: 2 * g for k, g in grads.items()}

    monkeypatch.setattr(Objective, "evaluate", twice)
    assert main(["gradcheck", str(path)]) == 4  # in this process (float64 too)
    assert "disagree" in capsys.readouterr().err


def test_validate_reports_size(tmp_path):
    res = run_cli("validate", str(write_scene(tmp_path)))
    assert res.returncode == 0 and "valid (2D, 1 bodies" in res.stdout


def test_unstable_run_exits_3_with_message(tmp_path, capsys):
    from cosim.cli import main

    data = scene_dict(time={"frame_dt": 4e-3, "substeps": 4})
    data["mpm"]["bodies"][0]["velocity"] = [30.0, 0.0]
    path = tmp_path / "fast.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["run", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 3  # in this process (float64)
    err = capsys.readouterr().err
    assert "CFL number" in err and "Traceback" not in err


def test_render_rerenders_a_trajectory_and_rejects_a_missing_one(tmp_path):
    res = run_cli("run", "elastic_bounce_2d", "--steps", "3", "--out", str(tmp_path), "--quiet")
    assert res.returncode == 0, res.stderr
    ok = run_cli("render", "elastic_bounce_2d", str(tmp_path / "trajectory.npz"), str(tmp_path / "again.gif"))
    assert ok.returncode == 0 and (tmp_path / "again.gif").stat().st_size > 1000
    bad = run_cli("render", "elastic_bounce_2d", str(tmp_path / "nope.npz"), str(tmp_path / "x.gif"))
    assert bad.returncode == 2 and "trajectory file not found" in bad.stderr and "Traceback" not in bad.stderr


def test_run_contact_override_reports_particles_inside_rigid_bodies(tmp_path):
    args = ("shake_container_2d", "--contact", "forecast", "--steps", "3", "--out", str(tmp_path), "--quiet")
    res = run_cli("run", *args, "--no-preview")
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "trajectory.npz").is_file() and not (tmp_path / "preview.gif").exists()
    assert "contact model forecast: particles inside rigid bodies at the end: container:" in res.stdout
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["contact_model"] == "forecast"
    # 3 frames of 2 ms move the water less than a cell: it all stays in the container's cavity, none in
    # its wall or spilled (measured: 1485 of 1485 held); the three counts partition the particles
    inside, held = metrics["particles_inside_rigid"]["container"], metrics["particles_held"]["container"]
    assert inside + held + metrics["particles_elsewhere"] == metrics["particles"]
    assert held == metrics["particles"] and inside == 0
    bad = run_cli("run", "elastic_bounce_2d", "--contact", "grid", "--steps", "2", "--out", str(tmp_path / "b"))
    assert bad.returncode == 2 and "nothing meets the MPM" in bad.stderr


def test_kernel_optimisation_choice_reaches_child_processes():
    """`cosim bench` turns Taichi's advanced optimisation on and runs each configuration in a child
    process, which must compile the same way (before, the children silently compiled without it)."""
    from cosim import runtime

    before = runtime._optimize
    probe = [sys.executable, "-c", "from cosim import runtime; print(runtime._optimize)"]
    try:
        for enabled in (True, False):
            runtime.optimize_kernels(enabled)
            res = subprocess.run(probe, capture_output=True, text=True, check=True)
            assert res.stdout.strip() == str(enabled)
    finally:
        runtime.optimize_kernels(before)


def test_a_rerun_is_bitwise_identical(tmp_path):
    """Two processes running the shaken container (liquid against a moving rigid ring) write the same
    trajectory to the last bit: P2G scatters serially on the CPU, so no atomic sum changes order."""
    arrays = []
    for run in ("a", "b"):
        out = tmp_path / run
        res = run_cli("run", "shake_container_2d", "--steps", "30", "--no-preview", "--quiet", "--out", str(out))
        assert res.returncode == 0, res.stderr
        arrays.append(np.load(out / "trajectory.npz"))
    first, second = arrays
    assert set(first.files) == set(second.files) and "x_water" in first.files
    for key in first.files:
        if key.startswith("reaction_"):  # summed over particles by atomic adds, in any order; frame 0 is NaN
            assert np.allclose(first[key], second[key], rtol=1e-6, atol=0, equal_nan=True), key
        else:
            assert np.array_equal(first[key], second[key]), key


def test_saved_velocities_follow_free_fall(tmp_path):
    """`output.velocities: true` adds v_<body> to trajectory.npz: a block thrown sideways in free fall
    keeps its mean horizontal velocity and gains -g t vertically, exactly (gravity is applied on the
    grid; MPM moves a uniformly moving body without stress); without the key no velocities are saved."""
    from cosim.cli import main

    data = scene_dict(steps=5, output={"velocities": True, "preview": "none"})
    data["mpm"]["bodies"][0]["velocity"] = [0.3, 0.0]
    path = tmp_path / "throw.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["run", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 0  # in this process (float64)
    traj = np.load(tmp_path / "o" / "trajectory.npz")
    v = traj["v_block"].astype(np.float64).mean(axis=1)
    assert v.shape == (6, 2)
    np.testing.assert_allclose(v[:, 0], 0.3, atol=1e-6)
    np.testing.assert_allclose(v[:, 1], -9.81 * traj["time"], atol=1e-6)
    assert main(["run", str(path), "--set", "output.velocities=false", "--out", str(tmp_path / "p"), "--quiet"]) == 0
    assert not any(k.startswith("v_") for k in np.load(tmp_path / "p" / "trajectory.npz"))
