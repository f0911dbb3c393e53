"""Gradient descent through the simulation actually steers it."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import yaml
from conftest import make_scene, scene_dict

from cosim.adjoint.objective import Objective
from cosim.adjoint.optimize import adam, minimise
from cosim.adjoint.tape import Tape
from cosim.errors import SimulationError
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


def test_cli_optimize_writes_its_outputs(tmp_path, capsys):
    path = tmp_path / "steer.yaml"
    path.write_text(
        yaml.safe_dump(
            scene_dict(**steering_scene(optimize={"params": ["impulse"], "iterations": 3, "learning_rate": 0.3}))
        )
    )
    from cosim.cli import main

    assert main(["optimize", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 0  # in this process (float64)
    assert "loss" in capsys.readouterr().out
    for name in ("params.npz", "optimization.json", "trajectory.npz", "preview.gif", "loss.png", "checkpoint.npz"):
        assert (tmp_path / "o" / name).is_file(), name
    rows = list(csv.DictReader((tmp_path / "o" / "optimization.csv").open()))
    assert [int(r["iteration"]) for r in rows] == [0, 1, 2]
    assert set(rows[0]) == {"iteration", "loss", "com_target:block", "grad:impulse", "seconds"}
    losses = [float(r["loss"]) for r in rows]
    assert losses[-1] < losses[0]  # Adam at lr 0.3 steers towards the target from the first step
    assert float(rows[0]["com_target:block"]) == pytest.approx(losses[0], rel=1e-12)  # the only term, weight 1


@pytest.fixture(scope="module")
def steering():
    return Objective(build_system(make_scene(**steering_scene()), requires_grad=True))


def test_an_interrupted_run_resumes_to_the_uninterrupted_result(steering, tmp_path):
    """4 Adam iterations straight, against 2 then (after an interruption) 2 more from the checkpoint:
    the same parameters, losses and history (float64; 1e-10 for the order of atomic adds)."""
    obj = steering
    args = (obj.evaluate, obj.initial_params(), ["impulse"], obj.natural_scales(), 4, 0.3)
    straight = minimise(*args, checkpoint=tmp_path / "a.npz")

    def interrupt(row, _history):
        if row["iteration"] == 1:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        minimise(*args, checkpoint=tmp_path / "b.npz", on_iteration=interrupt)
    resumed = minimise(*args, checkpoint=tmp_path / "b.npz", resume=True)
    assert [r["iteration"] for r in resumed.history] == [0, 1, 2, 3]
    np.testing.assert_allclose(resumed.losses, straight.losses, rtol=1e-10)
    np.testing.assert_allclose(resumed.params["impulse"], straight.params["impulse"], rtol=1e-10, atol=1e-20)


def test_sgd_with_momentum_lowers_the_loss(steering):
    """SGD's learning rate carries the loss's units (step = lr scale^2 g): 1e6 / m^2 here, where the
    loss is 9e-4 m^2 and the impulse's scale 0.024 N s; the loss falls 100x within 6 iterations."""
    result = minimise(
        steering.evaluate, steering.initial_params(), ["impulse"], steering.natural_scales(), 6, 1e6, "sgd"
    )
    assert result.best_loss < 0.01 * result.losses[0], result.losses


def test_a_non_finite_adjoint_names_its_step_engine_and_quantity():
    """The backward pass stops at the last macro step whose vjp returned NaN, naming it."""

    class Step:  # the record protocol the tape needs: a checkpoint it may keep or release
        def __init__(self, n: int):
            self.n, self.checkpoint = n, "state"

        def keep_checkpoint(self, state) -> None:
            self.checkpoint = state

    def vjp(record, grad):
        value = np.nan if record.n == 2 else 1.0
        return {"state": {"mpm": {"x": np.full(3, value)}}, "action": {}, "material": {}, "impulse": None}

    tape = Tape()
    for n in range(4):
        tape.push(Step(n))
    with pytest.raises(SimulationError, match=r"dL/d\(mpm.x\) is not finite at macro step 2"):
        tape.backward(vjp, {"mpm": {"x": np.zeros(3)}})


def test_lbfgs_reaches_the_bounded_optimum(steering):
    """L-BFGS-B (scipy) on the adjoint gradient, parameters in units of their scale, with the impulse
    bounded to +-2 scales (2 x 0.1 m_p x 1 m/s: +0.2 m/s per particle per step): the target 3 cm
    away is out of reach, and the bounded optimum pushes every x impulse against the bound. The
    centre of mass then moves 0.2 m/s x (5.5 + 4.5 + ... + 0.5) x 4 ms ~ 1.5 cm (no gravity, no
    walls), leaving (1.5 cm)^2 = 2.25e-4 m^2; every evaluation is logged once."""
    scales = steering.natural_scales()
    limit = 2.0 * scales["impulse"]
    seen = []
    result = minimise(
        steering.evaluate,
        steering.initial_params(),
        ["impulse"],
        scales,
        8,
        1.0,
        "lbfgs",
        bounds={"impulse": (-limit, limit)},
        on_iteration=lambda row, _h: seen.append(row["loss"]),
    )
    assert seen == result.losses  # one row per evaluation
    impulse = result.params["impulse"]
    assert np.all(np.abs(impulse) <= limit * (1 + 1e-12))
    assert np.allclose(impulse[..., 0], limit, rtol=1e-9)
    assert result.best_loss == pytest.approx(2.25e-4, rel=1e-6)


def _walled_quadratic(wall: float = 2.5):
    """loss (x - 3)^2 whose rollout fails (SimulationError) beyond x = ``wall``; logs every x evaluated."""
    seen: list[float] = []

    def evaluate(params, grad):
        x = float(params["x"][0])
        seen.append(x)
        if x > wall:
            raise SimulationError(f"x = {x} left the domain")
        return (x - 3.0) ** 2, ({"x": np.array([2.0 * (x - 3.0)])} if grad else None)

    return evaluate, seen


def test_a_step_whose_rollout_fails_is_taken_again_at_half_its_length(tmp_path):
    """Adam at lr 1 from x = 0 steps by about 1 per iteration towards 3, past the wall at 2.5: each step
    whose rollout fails is retried at half its length from the point before it until one passes, and the
    row says how often. Every accepted point is x_prev + (first try - x_prev) / 2^halvings, none lies
    beyond the wall, and the loss falls. The same run interrupted after iteration 2 and resumed from its
    checkpoint halves the same steps and ends equal."""
    evaluate, seen = _walled_quadratic()
    args = (evaluate, {"x": np.array([0.0])}, ["x"], {"x": 1.0}, 5, 1.0)
    straight = minimise(*args, checkpoint=tmp_path / "a.npz")
    halvings = [r.get("step_halvings", 0) for r in straight.history]
    assert sum(halvings) >= 2, halvings
    accepted = [x for x in seen if x <= 2.5]
    assert len(accepted) == len(straight.losses)  # one evaluation per iteration, one final
    np.testing.assert_allclose(straight.losses, [(x - 3.0) ** 2 for x in accepted], rtol=1e-12)
    tries = iter(seen)
    previous = next(tries)
    for h in halvings[1:]:
        first = next(tries)
        for _ in range(h):
            next(tries)
        if h:
            assert first > 2.5
            accepted_x = previous + (first - previous) / 2**h
            assert accepted_x <= 2.5
            previous = accepted_x
        else:
            previous = first
    assert straight.best_loss < 0.05 * straight.losses[0]

    def interrupt(row, _history):
        if row["iteration"] == 2:
            raise KeyboardInterrupt

    evaluate, _ = _walled_quadratic()
    args = (evaluate, {"x": np.array([0.0])}, ["x"], {"x": 1.0}, 5, 1.0)
    with pytest.raises(KeyboardInterrupt):
        minimise(*args, checkpoint=tmp_path / "b.npz", on_iteration=interrupt)
    resumed = minimise(*args, checkpoint=tmp_path / "b.npz", resume=True)
    assert [r.get("step_halvings", 0) for r in resumed.history] == halvings
    np.testing.assert_allclose(resumed.losses, straight.losses, rtol=1e-12)


def test_a_rollout_that_fails_before_any_step_is_reported_with_its_iteration():
    evaluate, _ = _walled_quadratic(wall=-1.0)
    with pytest.raises(SimulationError, match=r"iteration 0: the rollout failed: x = 0.0 left the domain"):
        minimise(evaluate, {"x": np.array([0.0])}, ["x"], {"x": 1.0}, 3, 1.0)


def test_a_step_no_halving_saves_stops_the_run_with_the_best_parameters():
    """Every rollout after the second fails: iteration 2's step and its 6 halvings all fail, so the run
    stops there, keeps the best of the two iterations done and says why."""
    calls = []

    def evaluate(params, grad):
        calls.append(float(params["x"][0]))
        if len(calls) > 2:
            raise SimulationError("the water went through the bottle")
        x = calls[-1]
        return (x - 3.0) ** 2, ({"x": np.array([2.0 * (x - 3.0)])} if grad else None)

    result = minimise(evaluate, {"x": np.array([0.0])}, ["x"], {"x": 1.0}, 5, 1.0)
    assert len(calls) == 2 + 1 + 6
    assert [r["iteration"] for r in result.history] == [0, 1]
    assert "iteration 2" in result.stopped and "halved 6 times" in result.stopped
    assert "went through the bottle" in result.stopped
    assert result.best_loss == min(result.losses) == (calls[1] - 3.0) ** 2
    assert result.params["x"][0] == calls[1]
