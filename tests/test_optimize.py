"""Gradient descent through the simulation actually steers it."""

from __future__ import annotations

import yaml
from conftest import make_scene, run_cli, scene_dict

from cosim.adjoint.objective import Objective
from cosim.adjoint.optimize import adam
from cosim.scene.build import build_system


def steering_scene(**extra):
    """A block pushed by impulses on all its particles; the loss wants its centre of mass 3 cm to the right."""
    return dict(
        steps=6,
        time={"frame_dt": 4e-3, "substeps": 4},
        controls=[{"body": "block", "impulse": [0.0, 0.0]}],
        loss={"type": "com_target", "body": "block", "target": [0.53, 0.5]},
        mpm={**scene_dict()["mpm"], "gravity": [0.0, 0.0]},
        **extra,
    )


def test_adam_on_impulses_reaches_the_target():
    """Without gravity the centre of mass moves by (total impulse / mass) x time: reachable, so the
    loss (3 cm)^2 = 9e-4 m^2 must fall by more than 100x in 25 iterations."""
    obj = Objective(build_system(make_scene(**steering_scene()), requires_grad=True))
    params = obj.initial_params()
    result = adam(obj.evaluate, params, ["impulse"], obj.natural_scales(), iterations=25, learning_rate=0.3)
    assert result.losses[0] > 8e-4
    assert result.best_loss < result.losses[0] / 100


def test_cli_optimize_writes_its_outputs(tmp_path):
    path = tmp_path / "steer.yaml"
    path.write_text(
        yaml.safe_dump(
            scene_dict(**steering_scene(optimize={"params": ["impulse"], "iterations": 3, "learning_rate": 0.3}))
        )
    )
    res = run_cli("optimize", str(path), "--out", str(tmp_path / "o"))
    assert res.returncode == 0, res.stderr
    assert "loss" in res.stdout
    for name in ("params.npz", "optimization.json", "trajectory.npz", "preview.gif"):
        assert (tmp_path / "o" / name).is_file(), name
