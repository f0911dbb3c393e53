"""Fuzz of the objective's keys: random ``gradient.params``, ``optimize.params`` and ``loss`` values (valid
names, unknown names, other scene kinds' parameters, wrong types, empty lists, odd strings) on two small
scenes. `cosim validate` answers each with exit 0 or 2 (never a traceback, never another code), and a
scene it accepts builds its objective and selects its parameters without any error, and its one-step
gradcheck ends in a verdict (exit 0, 3 or 4), not a refusal or a crash.
"""

from __future__ import annotations

import random

import numpy as np
import pytest
import yaml
from conftest import scene_dict

from cosim.adjoint.objective import Objective
from cosim.cli import main
from cosim.losses import Loss
from cosim.scene import load_scene
from cosim.scene.build import build_system
from cosim.scene.params import given, select_params
from cosim.scene.start import check_start

CASES = 200  # validate only: cheap
BUILDS = 3  # accepted scenes whose objective is built (seconds each), then one 1-step gradcheck

PARAM_NAMES = ["x0", "v0", "E", "nu", "impulse", "action", "k_stretch", "k_bend", "c_mass", "density"]
ODD = ["", " ", "E ", "e", "cloth.k_stretch", "mpm.E", "v0,E", "ÿ", "null", "0", "-", "x0\n"]
WRONG_TYPES = [None, 3, 1.5, True, {"name": "E"}, [["E"]], [1, 2], "v0"]
TARGETS = [[0.5, 0.5], [0.4, 0.6], [0.5], [0.5, 0.5, 0.5], [], "up", None, [0.0, 0.0, 0.0]]


def base(kind: str) -> dict:
    """Two small 2D scenes: a block driven by impulses, and a block beside a torque-driven paddle."""
    data = scene_dict(steps=2)
    data["mpm"]["grid"]["cells"] = 16
    if kind == "controls":
        data["controls"] = [{"body": "block", "impulse": [0.0, 1e-4]}]
    else:
        paddle = {
            "name": "paddle",
            "shape": {"type": "box", "size": [0.1, 0.1]},
            "density": 500.0,
            "joint": {"type": "free", "position": [0.5, 0.75]},
        }
        data["articulated"] = {"skeletons": [{"name": "arm", "links": [paddle], "controls": {"paddle": "torque"}}]}
    return data


VALID_TERMS = {
    "controls": [
        {"type": "weighted_positions"},
        {"type": "com_target", "body": "block", "target": [0.5, 0.4]},
        {"type": "pose_target", "body": "block", "target": [0.0, 0.05]},
        {
            "type": "chamfer",
            "body": "block",
            "points": {"shape": {"type": "box", "center": [0.5, 0.4], "size": [0.2, 0.1]}},
        },
    ],
    "articulated": [
        {"type": "joint_target", "skeleton": "arm", "joint": "paddle", "target": [0.5, 0.75, 0.0]},
        {"type": "joint_target", "skeleton": "arm", "joint": "paddle", "components": [1], "target": [0.7]},
        {"type": "com_target", "body": "block", "target": [0.5, 0.4], "running": True},
    ],
}
MUTATIONS = {
    "type": ["weighted_positions", "com_target", "pose_target", "chamfer", "joint_target", "jolt", 4, None],
    "body": ["block", "ghost", "arm", "paddle", 7, ""],
    "target": TARGETS,
    "skeleton": ["arm", "leg", 1],
    "joint": ["paddle", "elbow", ""],
    "components": [[0], [2], [5], [], [-1], "all"],
    "weight": [1.0, 0.0, -2.0, "heavy"],
    "running": [True, False, "yes"],
    "rotation": [[0.0, 0.0, 0.1], [0.1]],
    "points": [{"file": "no.npy"}, {}, {"rollout": "t.npz", "file": "u.npy"}],
    "velocity": [True, "no"],
    "mass": [1.0],  # not a loss key
}


def loss_term(rng: random.Random, kind: str) -> dict:
    """A valid term of the scene ``kind`` with 0 to 2 keys changed at random."""
    term = dict(rng.choice(VALID_TERMS[kind]))
    for _ in range(rng.choice([0, 0, 1, 1, 2])):
        key = rng.choice(list(MUTATIONS))
        value = rng.choice(MUTATIONS[key] + [None])
        if value is None:
            term.pop(key, None)
        else:
            term[key] = value
    return term


def loss_value(rng: random.Random, kind: str):
    roll = rng.random()
    if roll < 0.05:
        return rng.choice(WRONG_TYPES)
    if roll < 0.25:
        return {"terms": rng.choice([[], [loss_term(rng, kind) for _ in range(rng.randint(1, 3))], "all"])}
    return loss_term(rng, kind)


def params_value(rng: random.Random):
    roll = rng.random()
    if roll < 0.1:
        return rng.choice(WRONG_TYPES)
    if roll < 0.15:
        return []
    pool = PARAM_NAMES * 3 + ODD if roll < 0.5 else ["x0", "v0", "E", "nu", "impulse", "action"]
    return [rng.choice(pool) for _ in range(rng.randint(1, 3))]


def fuzz_scene(rng: random.Random) -> dict:
    """A valid scene with one of gradient.params, optimize.params and the loss drawn at random (so that
    what validate refuses is that one change)."""
    kind = rng.choice(["controls", "articulated"])
    data = base(kind)
    data["gradient"] = {"params": ["v0", "E"]}
    data["loss"] = rng.choice(VALID_TERMS[kind])
    changed = rng.choice(["gradient", "optimize", "loss", "loss"])
    if changed == "loss":
        data["loss"] = loss_value(rng, kind)
    else:
        data[changed] = {"params": params_value(rng)}
    return data


def test_objective_keys_validate_or_are_refused_and_accepted_ones_build(tmp_path, capsys):
    rng = random.Random(20261215)
    accepted, refused = [], 0
    for i in range(CASES):
        data = fuzz_scene(rng)
        path = tmp_path / f"case{i}.yaml"
        path.write_text(yaml.safe_dump(data, allow_unicode=True))
        code = main(["validate", str(path)])  # anything but a CosimError propagates and fails the test
        err = capsys.readouterr().err
        assert code in (0, 2), (data, err)
        assert "Traceback" not in err
        if code == 0:
            accepted.append((path, data))
        else:
            refused += 1
            assert err.startswith("error: "), err
    assert refused >= CASES // 4 and len(accepted) >= CASES // 10, (refused, len(accepted))
    accepted.sort(key=lambda case: -changed(case[1]))  # the changed ones first
    for path, _data in accepted:  # validate accepted it: its loss binds to the bodies and joints (no Taichi)
        start_loss(load_scene(path, {"precision": "float64"}))
    for path, _data in accepted[:BUILDS]:  # and the whole objective builds (kernels: seconds each)
        scene = load_scene(path, {"precision": "float64"})
        objective = Objective(build_system(scene, requires_grad=True, steps=1))
        for section in [s for s in ("gradient", "optimize") if given(scene, s)]:  # defaults may select nothing
            assert select_params(objective, scene, section)
    path, data = accepted[0]
    code = main(["gradcheck", str(path), "--steps", "1", "--directions", "1"])
    assert code in (0, 3, 4), (data, capsys.readouterr().err)  # a run's verdict, never a refusal or a crash


def start_loss(scene) -> Loss:
    """The scene's loss bound to what ``check_start`` built, with the constructor the objective uses."""
    start = check_start(scene)
    x0 = np.concatenate([b.positions for b in start.bodies])
    ends = np.cumsum([len(b.positions) for b in start.bodies])
    slices = {spec.name: slice(e - len(b.positions), e) for spec, b, e in zip(scene.mpm.bodies, start.bodies, ends)}
    engine = start.articulated.engine if start.articulated is not None else None
    return Loss.for_scene(scene, slices, x0, np.ones(len(x0)), engine)


def base_kind(data: dict) -> str:
    return "articulated" if "articulated" in data else "controls"


def changed(data: dict) -> int:
    """How many of the scene's loss terms and parameter lists differ from the valid ones they were made from."""
    loss = data.get("loss")
    terms = loss.get("terms") if isinstance(loss, dict) and "terms" in loss else [loss]
    params = (data["gradient"] != {"params": ["v0", "E"]}) + ("optimize" in data)
    return params + sum(isinstance(t, dict) and t not in VALID_TERMS[base_kind(data)] for t in terms or [])


@pytest.mark.parametrize("value", [[], ["k_stretch"], ["cloth.k_stretch"], "v0", [["E"]], [None]])
def test_gradient_params_are_checked_against_the_scene(value, tmp_path, capsys):
    data = base("controls")
    data["gradient"] = {"params": value}
    path = tmp_path / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "gradient.params" in err and "Traceback" not in err
