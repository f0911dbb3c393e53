"""Action parametrisations for optimisers: per-entry scales and the reach projection of cloth controls."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SCENES

from cosim.adjoint.optimize import minimise
from cosim.errors import SceneError
from cosim.scene import load_scene
from cosim.scene.actions import ReachProjection, action_scale
from cosim.scene.schema import ActionSpec

CENTER, AXIS, RADIUS, DURATION = np.array([0.5, 0.2, 0.5]), np.array([0.0, 0.0, 1.0]), 0.3, 0.04


def _positions(project: ReachProjection, sequence: np.ndarray) -> np.ndarray:
    """(segments, groups, 3): each group's position at the end of each segment [m]."""
    steps = DURATION * np.asarray(sequence).reshape(len(sequence), -1, 3)
    return project.start[None] + np.cumsum(steps, axis=0)


def test_reach_projection_cuts_only_what_leaves_reach():
    """A rim point at 0.3 m from the line: pushed outwards, it stays on the circle (the radial part of
    the velocity is removed, the rest kept: the projection of the end point onto the disc); an arc of
    radius 0.25 m about the line is within reach and passes unchanged; the map is idempotent and
    every projected position is within reach."""
    project = ReachProjection(np.array([[0.8, 0.2, 0.5]]), DURATION, CENTER, AXIS, RADIUS)
    out = project(np.array([[1.0, 0.0, 0.5]]))
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.5]], atol=1e-12)  # z (along the line) is free
    angles = np.radians(np.arange(0, 81, 10))
    arc = np.stack([0.5 + 0.25 * np.cos(angles), 0.2 + 0.25 * np.sin(angles), np.full_like(angles, 0.5)], 1)
    inside = ReachProjection(arc[:1], DURATION, CENTER, AXIS, RADIUS)
    sequence = np.diff(arc, axis=0) / DURATION
    np.testing.assert_array_equal(inside(sequence), sequence)
    wild = np.random.default_rng(0).normal(scale=5.0, size=(12, 3))
    once = project(wild)
    np.testing.assert_allclose(project(once), once, atol=1e-12)
    distance = np.linalg.norm(project.radial(_positions(project, once).reshape(-1, 3)), axis=1)
    assert distance.max() <= RADIUS * (1 + 1e-12)
    assert np.linalg.norm(project.radial(_positions(project, wild).reshape(-1, 3)), axis=1).max() > 2 * RADIUS


def test_adam_with_a_reach_constraint_ends_on_the_circle_nearest_its_target():
    """Minimising the squared distance of a point's final position to a target 0.5 m from the line,
    under reach 0.3: the optimum is the circle's point towards the target, 0.2 m short of it; Adam
    with the projection gets there (and stays within reach at every iteration)."""
    project = ReachProjection(np.array([[0.8, 0.2, 0.5]]), DURATION, CENTER, AXIS, RADIUS)
    target = CENTER + 0.5 * np.array([0.0, 1.0, 0.0])
    seen = []

    def evaluate(params, grad):
        sequence = params["action"]
        end = _positions(project, sequence)[-1, 0]
        seen.append(np.linalg.norm(project.radial(_positions(project, sequence).reshape(-1, 3)), axis=1).max())
        r = end - target
        g = np.broadcast_to(2.0 * DURATION * r, sequence.shape).copy()
        return float(r @ r), ({"action": g} if grad else None)

    params = {"action": np.zeros((4, 3))}
    result = minimise(evaluate, params, ["action"], {"action": 1.0}, 300, 0.05, projections={"action": project})
    assert max(seen) <= RADIUS * (1 + 1e-9)
    np.testing.assert_allclose(result.best_loss, 0.2**2, rtol=1e-3)


def test_action_scale_per_entry_and_errors():
    """One number fills every entry; a list must have one per entry, else the error names the key."""
    np.testing.assert_array_equal(action_scale(ActionSpec(scale=0.5), 3, "k"), [0.5, 0.5, 0.5])
    np.testing.assert_array_equal(action_scale(ActionSpec(scale=[1.0, 2.0]), 2, "k"), [1.0, 2.0])
    with pytest.raises(SceneError, match=r"articulated\.actions\.scale: one number, or 6"):
        action_scale(ActionSpec(scale=[1.0, 2.0]), 6, "articulated.actions")


def test_initial_actions_beyond_reach_are_rejected_naming_the_key():
    """make_taco with an initial action that carries the right rim point outwards fails at build."""
    import yaml

    from cosim.scene.cloth import build_cloth

    cloth = yaml.safe_load((SCENES / "make_taco.yaml").read_text())["cloth"]
    cloth[0]["actions"]["sequence"] = [[2.0, 0.0, 0.0, 0.0, 0.0, 0.0]]
    scene = load_scene(SCENES / "make_taco.yaml", {"cloth": cloth})
    with pytest.raises(SceneError, match=r"cloth\[0\]\.actions: the initial actions move a control beyond reach"):
        build_cloth(scene, 0)
