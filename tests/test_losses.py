"""Loss terms: the Chamfer distance against brute force and central differences, targets from
shapes and saved rollouts, weighted sums, and running terms through the tape (float64)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene, scene_dict

from cosim.adjoint.gradcheck import check_gradients
from cosim.adjoint.objective import Objective
from cosim.errors import SceneError
from cosim.losses.chamfer import Chamfer
from cosim.scene.build import build_system


def brute_chamfer(x: np.ndarray, t: np.ndarray) -> float:
    d2 = ((x[:, None, :] - t[None, :, :]) ** 2).sum(axis=2)  # (N, M)
    return float(d2.min(axis=1).mean() + d2.min(axis=0).mean())


def test_chamfer_matches_brute_force_and_central_differences():
    """Value against the O(N M) definition; gradient against central differences (eps 1e-7, where
    no nearest neighbour changes: the value is a quadratic there) to 1e-7 relative."""
    rng = np.random.default_rng(0)
    x, t = rng.random((300, 3)), rng.random((200, 3)) * 0.8 + 0.1
    chamfer = Chamfer(t)
    value, grad = chamfer(x)
    assert value == pytest.approx(brute_chamfer(x, t), rel=1e-12)
    direction = rng.standard_normal(x.shape)
    eps = 1e-7
    fd = (chamfer(x + eps * direction)[0] - chamfer(x - eps * direction)[0]) / (2 * eps)
    assert (grad * direction).sum() == pytest.approx(fd, rel=1e-7)
    assert chamfer(t.copy())[0] == 0.0  # the target itself is at distance 0


def running_scene(**loss):
    return make_scene(
        steps=4,
        time={"frame_dt": 2e-3, "substeps": 3},
        mpm={
            "grid": {"cells": 32},
            "bodies": [
                {
                    "name": "block",
                    "material": {"type": "elastic", "E": 2e3, "nu": 0.3},
                    "shape": {"type": "box", "center": [0.5, 0.5], "size": [0.125, 0.125]},
                    "velocity": [0.4, -0.6],
                }
            ],
        },
        controls=[{"body": "block", "impulse": [1e-5, 2e-5]}],
        loss=loss,
    )


def test_running_and_weighted_terms_match_central_differences():
    """A running centre-of-mass term (summed over the 5 states of a 4-step rollout) plus a final
    Chamfer term to a box target: the value is the weighted sum of the terms, and the adjoint
    (each running gradient fed in at its step) matches central differences to 1e-5."""
    terms = [
        {"type": "com_target", "body": "block", "target": [0.55, 0.45], "running": True, "weight": 2.0},
        {
            "type": "chamfer",
            "body": "block",
            "points": {"shape": {"type": "box", "center": [0.52, 0.5], "size": [0.1, 0.15]}},
        },
    ]
    objective = Objective(build_system(running_scene(terms=terms), requires_grad=True))
    params = objective.initial_params()
    value, _ = objective.evaluate(params, False)
    values = dict(objective.loss.values)
    assert set(values) == {"com_target:block", "chamfer:block"}
    assert value == pytest.approx(2.0 * values["com_target:block"] + values["chamfer:block"], rel=1e-12)
    # the running term is a sum over the 5 states, not 5 x the final one (one body, equal masses)
    com = objective.system.state()["mpm"]["x"].mean(axis=0)
    final_term = float(((com - [0.55, 0.45]) ** 2).sum())
    assert abs(values["com_target:block"] - 5 * final_term) > 1e-3 * values["com_target:block"]
    results = check_gradients(objective.evaluate, params, ["v0", "impulse"], objective.natural_scales(), 2)
    worst = max(r.relative_error for r in results)
    assert worst < 1e-5, [(r.param, r.adjoint, r.finite_difference) for r in results]


def test_a_custom_loss_callable_gets_its_exact_gradient():
    """A user's loss (``Objective(system, loss=fn)``, fn(state) -> (value, dL/dstate)): the MPM's
    kinetic energy plus the spread of its x positions, neither a built-in term; its adjoint through
    the rollout matches central differences to 1e-5."""
    from cosim.losses import zeros_like

    def energy_and_spread(state):
        mpm = state["mpm"]
        x, v = mpm["x"], mpm["v"]
        spread = x[:, 0] - x[:, 0].mean()
        grad = zeros_like(state)
        grad["mpm"]["v"] = v.copy()  # d(sum v^2 / 2)/dv
        grad["mpm"]["x"][:, 0] = 2.0 * spread
        return float(0.5 * (v * v).sum() + (spread * spread).sum()), grad

    objective = Objective(build_system(running_scene(), requires_grad=True), loss=energy_and_spread)
    params = objective.initial_params()
    results = check_gradients(objective.evaluate, params, ["v0", "impulse"], objective.natural_scales(), 2)
    worst = max(r.relative_error for r in results)
    assert worst < 1e-5, [(r.param, r.adjoint, r.finite_difference) for r in results]


def test_chamfer_target_from_a_saved_rollout(tmp_path):
    """`cosim run --save-target` writes the final positions; a chamfer term on them is 0 for the
    same rollout and positive for another; a missing file is named with the fix."""
    import yaml

    from cosim.cli import main

    data = scene_dict(steps=3)

    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["run", str(path), "--out", str(tmp_path / "ref"), "--quiet", "--save-target", "--no-preview"]) == 0
    saved = np.load(tmp_path / "ref" / "target.npz")
    assert list(saved.keys()) == ["x_block"]
    loss = {"type": "chamfer", "body": "block", "points": {"rollout": str(tmp_path / "ref" / "target.npz")}}
    same = Objective(build_system(make_scene(steps=3, loss=loss)))
    assert same.evaluate(same.initial_params())[0] == pytest.approx(0.0, abs=1e-20)
    moved = make_scene(steps=3, loss=loss)
    moved.mpm.bodies[0].velocity = [0.5, 0.0]
    assert Objective(build_system(moved)).evaluate(Objective(build_system(moved)).initial_params())[0] > 1e-6
    missing = {"type": "chamfer", "body": "block", "points": {"rollout": str(tmp_path / "none.npz")}}
    with pytest.raises(SceneError, match="--save-target"):
        Objective(build_system(make_scene(steps=3, loss=missing)))


def test_a_chamfer_term_without_points_is_refused_by_name():
    terms = [{"type": "com_target", "body": "block", "target": [0.5, 0.5]}, {"type": "chamfer", "body": "block"}]
    with pytest.raises(SceneError, match=r"loss.terms\[1\].points: chamfer needs its target point set"):
        make_scene(loss={"terms": terms})
