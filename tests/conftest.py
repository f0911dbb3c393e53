"""Shared fixtures. Taichi runs once per process, here in float64 on the CPU:
gradient tests need float64, and sharing one configuration lets every test in
the session reuse compiled kernels."""

from __future__ import annotations

import copy
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
# The files with the longest tests (minutes of kernel compiles on a cold cache), longest first: xdist's
# loadfile hands files to the two workers in collection order, and a long file started last leaves the
# other worker idle; short files at the end even the two out.
LONGEST_FIRST = (
    "test_scene_gradients",
    "test_cli",
    "test_coupling",
    "test_sweep",
    "test_cloth_scenes",
    "test_cloth_contact",
    "test_fuzz",
    "test_contact",
    "test_tasks",
    "test_cloth_gradients",
    "test_system",
    "test_gradients",
    "test_stress",
    "test_mpm_physics",
    "test_optimize",
    "test_losses",
    "test_cloth_rigid",
    "test_tasks_manipulation",
    "test_tasks_cloth",
)


def pytest_collection_modifyitems(items: list) -> None:
    """Collection order with the files of ``LONGEST_FIRST`` ahead of the rest (stable within a file)."""

    def rank(item) -> int:
        stem = Path(str(item.fspath)).stem
        return LONGEST_FIRST.index(stem) if stem in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)


@pytest.fixture(scope="session", autouse=True)
def taichi_float64():
    from cosim.runtime import ensure_taichi

    ensure_taichi("cpu", "float64")


@pytest.fixture(autouse=True)
def keeps_the_sessions_taichi():
    """Fails a test that leaves Taichi re-initialised in another precision or arch: every later test
    of its worker would run in it (a float32 scene built in-process once made SDF and cloth tests
    of the same worker fail)."""
    yield
    from cosim.runtime import current

    assert current() in (None, ("cpu", "float64")), f"Taichi left at {current()}: run such a case in a subprocess"


def scene_dict(**overrides) -> dict:
    """A small valid 2D scene as Python data; ``overrides`` replace top-level keys."""
    base = {
        "name": "tiny",
        "dim": 2,
        "precision": "float64",
        "steps": 5,
        "time": {"frame_dt": 2e-3, "substeps": "auto"},
        "mpm": {
            "grid": {"cells": 32},
            "bodies": [
                {
                    "name": "block",
                    "material": {"type": "elastic", "E": 2e3, "nu": 0.3, "density": 1000},
                    "shape": {"type": "box", "center": [0.5, 0.5], "size": [0.25, 0.25]},
                }
            ],
        },
    }
    base = copy.deepcopy(base)
    base.update(copy.deepcopy(overrides))
    return base


def make_scene(**overrides):
    from cosim.scene import parse_scene

    return parse_scene(scene_dict(**overrides), ROOT)


def pushed_block_scene(model: str):
    """``make_scene``'s block pushed up by a kinematic plate through contact ``model``, a zero impulse control
    on the block and a loss on its positions: 3 steps whose loss and gradients go through contact."""
    return make_scene(
        steps=3,
        rigid={
            "bodies": [
                {
                    "name": "plate",
                    "shape": {"type": "box", "size": [0.3, 0.04]},
                    "position": [0.5, 0.36],
                    "motion": {"type": "constant", "velocity": [0.0, 0.5]},
                }
            ]
        },
        controls=[{"body": "block", "impulse": [0.0, 0.0]}],
        contact={"model": model, "friction": 0.2},
        loss={"type": "weighted_positions", "body": "block"},
    )


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """Run `cosim ...` in a fresh process (its own Taichi start-up)."""
    return subprocess.run(
        [sys.executable, "-m", "cosim.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd or ROOT,
        timeout=900,
        check=False,
    )


def shipped_scenes(exclude: tuple[str, ...] = ()) -> list:
    """Every scene under scenes/ but ``exclude`` (names), as pytest params; those that need the
    optional pybullet wheel (paths "pybullet_data:...") are skipped where it is not installed."""
    import importlib.util

    have_pybullet = importlib.util.find_spec("pybullet_data") is not None
    params = []
    for path in sorted(p for p in SCENES.glob("*.yaml") if p.stem not in exclude):
        needs = "pybullet_data:" in path.read_text()
        skip = [pytest.mark.skip(reason='needs the optional pybullet wheel: pip install -e ".[panda]"')]
        params.append(pytest.param(path, id=path.stem, marks=skip if needs and not have_pybullet else []))
    return params


def check_task_improves(task: str, steps: int, ratio: float, out: Path) -> None:
    """`cosim optimize` on the shipped task ``task`` (its plain initial guess) for 3 iterations of a
    ``steps``-step rollout: every iteration lowers the loss, the third below ``ratio`` times the first,
    and the run writes its trajectory and loss curve (no preview: ``--no-preview``). In this process
    (float64, like every optimisation), which saves each task a Taichi and DART start-up."""
    import csv
    from itertools import pairwise

    from cosim.cli import main

    args = [str(SCENES / f"{task}.yaml"), "--steps", str(steps), "--iters", "3", "--out", str(out)]
    assert main(["optimize", *args, "--quiet", "--no-preview"]) == 0
    assert (out / "trajectory.npz").is_file() and (out / "loss.png").is_file()
    assert not (out / "preview.gif").exists()
    losses = [float(r["loss"]) for r in csv.DictReader((out / "optimization.csv").open())]
    assert len(losses) == 3
    assert all(b < a for a, b in pairwise(losses)), losses
    assert losses[-1] < ratio * losses[0], losses
