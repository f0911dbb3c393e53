"""The checks `cosim run` makes while building (``cosim.scene.start``), each a case: `validate` and `run`
refuse the same file with exit 2 and the same error, before anything is stepped or written.

The cases test_bad_input.py holds are the loader's and ``preflight``'s; these are the ones that
needed the build before: rigid SDFs, the DART engine, cloth and skeleton action plans, material
starting inside a rigid body, the loss's joint targets, and the gradient and optimize parameters.
"""

from __future__ import annotations

import copy
import os
import shutil
import subprocess
import sys

import pytest
import yaml
from conftest import scene_dict

from cosim.cli import main

BLOCK_2D = {"type": "box", "center": [0.5, 0.5], "size": [0.25, 0.25]}
CUBE_OBJ = (
    "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n"
    "f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8\n"
)
OPEN_OBJ = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\n"


def tiny(**overrides) -> dict:
    """The conftest scene at 16 cells, one step: a 2D block in the middle."""
    data = scene_dict(steps=1)
    data["mpm"]["grid"]["cells"] = 16
    data.update(copy.deepcopy(overrides))
    return data


def tiny_3d(**overrides) -> dict:
    data = tiny()
    data.update(dim=3)
    data["mpm"]["bodies"][0]["shape"] = {"type": "box", "center": [0.5, 0.3, 0.5], "size": [0.25, 0.25, 0.25]}
    data.update(copy.deepcopy(overrides))
    return data


def link(name: str = "paddle", **joint) -> dict:
    """A 2D box link on a planar (free) joint at ``joint['position']`` (default far from the block)."""
    joint = {"type": "free", "position": [0.5, 0.85], **joint}
    return {"name": name, "shape": {"type": "box", "size": [0.1, 0.1]}, "density": 500.0, "joint": joint}


def skeleton(*links, **extra) -> dict:
    return {"skeletons": [{"name": "arm", "links": list(links) or [link()], **extra.pop("skel", {})}], **extra}


def cloth(**extra) -> list[dict]:
    """A 3D rectangle cloth above the block, its two corners controlled (or ``extra`` replacing keys)."""
    spec = {
        "name": "sheet",
        "mesh": {"type": "rectangle", "center": [0.5, 0.7, 0.5], "size": [0.4, 0.4], "resolution": [5, 5]},
        "controls": [
            {"name": "a", "vertices": {"points": [[0.3, 0.7, 0.3]]}},
            {"name": "b", "vertices": {"points": [[0.7, 0.7, 0.7]]}},
        ],
    }
    spec.update(copy.deepcopy(extra))
    return [spec]


def urdf(collisions: str = '<collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision>') -> str:
    return (
        '<?xml version="1.0"?>\n<robot name="r">\n'
        f'  <link name="base">{collisions}</link>\n'
        '  <link name="arm"><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision></link>\n'
        '  <joint name="j1" type="revolute"><parent link="base"/><child link="arm"/>'
        '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="10" velocity="1"/></joint>\n</robot>\n'
    )


def urdf_scene(**skel) -> dict:
    spec = {"name": "robot", "urdf": "robot.urdf", "fixed_base": True, "position": [0.5, 0.8, 0.5], **skel}
    return tiny_3d(articulated={"skeletons": [spec]})


def joint_target(**term) -> dict:
    loss = {"type": "joint_target", "skeleton": "arm", "joint": "paddle", "target": [0.5, 0.85, 0.0], **term}
    return tiny(articulated=skeleton(), loss=loss)


# id -> (scene data, extra files {name: text}, what the error must say)
CASES = {
    "block_inside_static_box": (
        tiny(
            rigid={"bodies": [{"name": "wall", "shape": {"type": "box", "size": [0.1, 0.1]}, "position": [0.5, 0.5]}]}
        ),
        {},
        "rigid.bodies[0]: 2 particles of body 'block' start more than dx/2 inside rigid body 'wall'",
    ),
    "block_inside_dart_link": (
        tiny(articulated=skeleton(link(position=[0.5, 0.5]))),
        {},
        "articulated.skeletons[0]: 2 particles of body 'block' start more than dx/2 inside rigid body 'arm/paddle'",
    ),
    "rigid_box_thinner_than_its_sdf": (
        tiny(
            rigid={"bodies": [{"name": "foil", "shape": {"type": "box", "size": [0.5, 0.005]}, "position": [0.5, 0.9]}]}
        ),
        {},
        "rigid.bodies[0].shape: no SDF node lies inside the shape",
    ),
    "link_thinner_than_its_sdf": (
        tiny(articulated=skeleton({**link(), "shape": {"type": "box", "size": [0.5, 0.005]}})),
        {},
        "articulated.skeletons[0].links[0].shape: no SDF node lies inside the shape",
    ),
    "rigid_mesh_not_watertight": (
        tiny_3d(
            rigid={
                "bodies": [{"name": "cup", "shape": {"type": "mesh", "file": "open.obj"}, "position": [0.5, 0.8, 0.5]}]
            }
        ),
        {"open.obj": OPEN_OBJ},
        "rigid.bodies[0].shape.file (open.obj): the mesh is not watertight",
    ),
    "joint_limits_crossed": (
        tiny(articulated=skeleton(link(type="revolute", lower=1.0, upper=-1.0))),
        {},
        "articulated: skeleton 'arm', link 'paddle'",
    ),
    "dart_action_of_the_wrong_length": (
        tiny(articulated=skeleton(skel={"controls": {"paddle": "torque"}}, actions={"sequence": [[1.0, 2.0]]})),
        {},
        "articulated.actions.sequence[0]: 2 entries, the action has 3",
    ),
    "dart_bounds_crossed": (
        tiny(articulated=skeleton(skel={"controls": {"paddle": "torque"}}, actions={"bounds": [[1, 1, 1], [0, 0, 0]]})),
        {},
        "articulated.actions.bounds: a lower bound exceeds its upper bound",
    ),
    "dart_initial_action_outside_bounds": (
        tiny(
            articulated=skeleton(
                skel={"controls": {"paddle": "torque"}}, actions={"initial": [2, 0, 0], "bounds": [[-1] * 3, [1] * 3]}
            )
        ),
        {},
        "articulated.actions: the initial actions lie outside bounds",
    ),
    "urdf_mesh_package_unknown": (
        urdf_scene(),
        {"robot.urdf": urdf('<collision><geometry><mesh filename="package://parts/m.obj"/></geometry></collision>')},
        "uses package 'parts'; add it to package_dirs",
    ),
    "urdf_link_mesh_and_box": (
        urdf_scene(),
        {
            "robot.urdf": urdf(
                '<collision><geometry><mesh filename="cube.obj" scale="0.05 0.05 0.05"/></geometry></collision>'
                '<collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision>'
            ),
            "cube.obj": CUBE_OBJ,
        },
        "a link with a mesh must have no other collision shapes",
    ),
    "urdf_wrench_on_a_hinge": (
        urdf_scene(controls={"j1": "wrench"}),
        {"robot.urdf": urdf()},
        "articulated: skeleton 'robot', joint 'j1': 'wrench' control needs a free joint",
    ),
    "cloth_region_selects_nothing": (
        tiny_3d(cloth=cloth(fixed={"region": {"min": [0.0, 0.0, 0.0], "max": [0.1, 0.1, 0.1]}})),
        {},
        "cloth[0].fixed.region: selects no vertex",
    ),
    "cloth_vertex_pinned_and_controlled": (
        tiny_3d(cloth=cloth(fixed={"points": [[0.3, 0.7, 0.3]]})),
        {},
        "cloth[0]: a vertex is both pinned and controlled",
    ),
    "cloth_control_beyond_reach": (
        tiny_3d(cloth=cloth(actions={"reach": {"center": [0.5, 0.7, 0.5], "axis": [1, 0, 0], "radius": 0.01}})),
        {},
        "cloth[0].actions.reach: control 0 starts beyond reach.radius",
    ),
    "cloth_actions_leave_reach": (
        tiny_3d(
            cloth=cloth(
                actions={
                    "sequence": [[0, 0, 0, 0, 0, 500.0]],
                    "reach": {"center": [0.5, 0.7, 0.5], "axis": [1, 0, 0], "radius": 0.3},
                }
            )
        ),
        {},
        "cloth[0].actions: the initial actions move a control beyond reach.radius",
    ),
    "cloth_scale_of_the_wrong_length": (
        tiny_3d(cloth=cloth(actions={"scale": [1.0, 2.0]})),
        {},
        "cloth[0].actions.scale: one number, or 6 (the action size); got 2",
    ),
    "cloth_reach_axis_of_two": (
        tiny_3d(cloth=cloth(actions={"reach": {"center": [0.5, 0.7, 0.5], "axis": [1, 0], "radius": 0.3}})),
        {},
        "cloth[0].actions.reach.axis: must have 3 entries",
    ),
    "loss_joint_unknown": (joint_target(joint="elbow"), {}, "loss.joint: skeleton 'arm' has no joint 'elbow'"),
    "loss_skeleton_unknown": (joint_target(skeleton="leg"), {}, "loss.skeleton: no skeleton 'leg'; skeletons: ['arm']"),
    "loss_components_out_of_range": (
        joint_target(components=[3], target=[0.0]),
        {},
        "loss.components: joint 'paddle' has 3 coordinates",
    ),
    "loss_joint_target_of_the_wrong_length": (joint_target(target=[0.5]), {}, "loss.target: 3 numbers"),
    "gradient_cloth_parameter_without_cloth": (
        tiny(gradient={"params": ["k_stretch"]}),
        {},
        "gradient.params: 'k_stretch' is not a parameter of this scene (k_stretch is a cloth's material",
    ),
    "optimize_impulse_without_controls": (
        tiny(optimize={"params": ["impulse", "E"]}),
        {},
        "optimize.params: 'impulse' is not a parameter of this scene (impulse needs an entry under controls:)",
    ),
    "gradient_params_empty": (tiny(gradient={"params": []}), {}, "gradient.params: an empty list"),
    "action_without_controls": (
        tiny(articulated=skeleton(), gradient={"params": ["action"]}),
        {},
        "gradient.params: 'action' is not a parameter of this scene (action needs a skeleton with controls",
    ),
}


def write_case(case: str, folder) -> str:
    data, files, _ = CASES[case]
    for name, text in files.items():
        (folder / name).write_text(text)
    path = folder / "scene.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


@pytest.mark.parametrize("case", sorted(CASES))
def test_validate_and_run_refuse_with_the_same_error(case, tmp_path, capsys):
    path = write_case(case, tmp_path)
    assert main(["validate", path]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and CASES[case][2] in err, err
    out = tmp_path / "out"
    assert main(["run", path, "--out", str(out), "--steps", "1", "--no-preview", "--quiet"]) == 2
    assert capsys.readouterr().err == err  # the same message, from the same check
    assert not out.exists()


def test_the_bases_are_valid(tmp_path, capsys):
    """Each case changes one thing of a valid scene: the bases pass."""
    (tmp_path / "robot.urdf").write_text(urdf())
    bases = [tiny(), tiny_3d(), tiny(articulated=skeleton()), tiny_3d(cloth=cloth()), urdf_scene(), joint_target()]
    bases.append(tiny(articulated=skeleton(skel={"controls": {"paddle": "torque"}}), gradient={"params": ["action"]}))
    for i, data in enumerate(bases):
        path = tmp_path / f"base{i}.yaml"
        path.write_text(yaml.safe_dump(data))
        assert main(["validate", str(path)]) == 0, capsys.readouterr().err


def test_gradcheck_refuses_a_cloth_parameter_without_a_cloth(tmp_path, capsys):
    """The reported case: validate passed it, gradcheck said "every gradient is zero" and crashed."""
    path = write_case("gradient_cloth_parameter_without_cloth", tmp_path)
    assert main(["validate", path]) == 2
    err = capsys.readouterr().err
    assert main(["gradcheck", path]) == 2
    assert capsys.readouterr().err == err and "Traceback" not in err


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="a GPU is here: arch cuda is fine")
def test_machine_checks_refuse_in_both_commands(tmp_path):
    """What run checks of the machine at Taichi's start-up, validate checks too (each in a fresh
    process): ``arch: cuda`` without a GPU, and a bad ``COSIM_CPU_THREADS``."""
    cuda, cpu = tmp_path / "cuda.yaml", tmp_path / "cpu.yaml"
    cuda.write_text(yaml.safe_dump(tiny(arch="cuda")))
    cpu.write_text(yaml.safe_dump(tiny()))
    run = ["--out", str(tmp_path / "o"), "--no-preview", "--quiet"]
    cases = [(cuda, {}, "arch: cuda: Taichi found no usable cuda GPU"), (cpu, {"COSIM_CPU_THREADS": "two"}, "'two'")]
    for path, env, message in cases:
        errors = []
        for args in (["validate", str(path)], ["run", str(path), *run]):
            res = subprocess.run(
                [sys.executable, "-m", "cosim.cli", *args], capture_output=True, text=True, env={**os.environ, **env},
                check=False, timeout=300,
            )  # fmt: skip
            assert res.returncode == 2 and message in res.stderr, res.stderr
            errors.append(res.stderr.splitlines()[-1])
        assert errors[0] == errors[1]
    assert not (tmp_path / "o").exists()
