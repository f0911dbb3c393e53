"""Malformed inputs, each a case: `cosim validate` and `cosim run` exit 2 with a message that names
the key path or the file (and says what to do), no traceback, and `run` writes nothing.

Every case is checked by `validate`, which makes every check `run` makes before its first step
(``cosim.scene.start``; the build-time ones are in test_start_checks.py); `run` then refuses the
same input at the same place.
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml
from conftest import scene_dict

from cosim.cli import main

URDF_HEAD = '<?xml version="1.0"?>\n<robot name="r">\n'
LINK = '  <link name="{0}"><collision><geometry><box size="0.05 0.05 0.05"/></geometry></collision></link>\n'
JOINT = (
    '  <joint name="{0}" type="revolute"><parent link="{1}"/><child link="{2}"/>'
    '<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="10" velocity="1"/></joint>\n'
)


def urdf_text(links: list[str], joints: list[tuple[str, str, str]]) -> str:
    body = "".join(LINK.format(n) for n in links) + "".join(JOINT.format(*j) for j in joints)
    return URDF_HEAD + body + "</robot>\n"


CHAIN = urdf_text(["base", "arm"], [("j1", "base", "arm")])


def base_3d() -> dict:
    """The 2D base scene made 3D: a cube of jelly low in the box."""
    data = scene_dict(dim=3)
    data["mpm"]["bodies"][0]["shape"] = {"type": "box", "center": [0.5, 0.3, 0.5], "size": [0.2, 0.2, 0.2]}
    return data


def scene_3d(urdf: str = "robot.urdf", **skeleton) -> dict:
    """A small 3D scene with a URDF skeleton (the file written by the case)."""
    data = base_3d()
    skel = {"name": "robot", "urdf": urdf, "fixed_base": True, "position": [0.5, 0.7, 0.5]}
    skel.update(skeleton)
    data["articulated"] = {"skeletons": [skel]}
    return data


def at(data: dict, path: str, value) -> dict:
    """``data`` with the value at dotted ``path`` (list items by integer) replaced."""
    data = copy.deepcopy(data)
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    node = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return data


BODY = "mpm.bodies.0"
# id -> (scene data or raw text, extra files {name: text}, what the message must name)
CASES = {
    "yaml_syntax": ("name: [unclosed\ndim: 2\n", {}, "not valid YAML"),
    "yaml_tab_indent": ("name: x\n\tdim: 2\n", {}, "not valid YAML"),
    "top_level_list": ("- name\n- dim\n", {}, "top level must be a mapping"),
    "empty_file": ("", {}, "top level must be a mapping"),
    "E_wrong_type": (at(scene_dict(), f"{BODY}.material.E", "soft"), {}, "mpm.bodies[0].material.E"),
    "cells_wrong_type": (at(scene_dict(), "mpm.grid.cells", "big"), {}, "mpm.grid.cells"),
    "bodies_not_a_list": (at(scene_dict(), "mpm.bodies", {"name": "x"}), {}, "mpm.bodies"),
    "E_nan": (at(scene_dict(), f"{BODY}.material.E", float("nan")), {}, "mpm.bodies[0].material.E"),
    "density_inf": (at(scene_dict(), f"{BODY}.material.density", float("inf")), {}, "material.density"),
    "E_huge": (at(scene_dict(), f"{BODY}.material.E", 1e300), {}, "mpm.bodies[0].material.E"),
    "velocity_huge": (at(scene_dict(), f"{BODY}.velocity", [1e9, 0.0]), {}, "mpm.bodies[0].velocity"),
    "size_negative": (at(scene_dict(), f"{BODY}.shape.size", [-0.1, 0.2]), {}, "mpm.bodies[0].shape.size"),
    "radius_zero": (
        at(scene_dict(), f"{BODY}.shape", {"type": "sphere", "center": [0.5, 0.5], "radius": 0}),
        {},
        "shape.radius",
    ),
    "cells_too_few": (at(scene_dict(), "mpm.grid.cells", 2), {}, "mpm.grid.cells"),
    "grid_too_large": (at(base_3d(), "mpm.grid.cells", 4096), {}, "mpm.grid.cells"),
    "frame_dt_negative": (at(scene_dict(), "time.frame_dt", -1e-3), {}, "time.frame_dt"),
    "steps_negative": (at(scene_dict(), "steps", -5), {}, "steps"),
    "nu_half": (at(scene_dict(), f"{BODY}.material.nu", 0.5), {}, "material.nu"),
    "precision_unknown": (at(scene_dict(), "precision", "float16"), {}, "precision"),
    "unknown_key": (at(scene_dict(), f"{BODY}.materail", {}), {}, "materail"),
    "unknown_material": (at(scene_dict(), f"{BODY}.material.type", "rubber"), {}, "material"),
    "missing_section": ({k: v for k, v in scene_dict().items() if k != "mpm"}, {}, "mpm"),
    "center_wrong_length": (at(scene_dict(), f"{BODY}.shape.center", [0.5]), {}, "mpm.bodies[0].shape.center"),
    "body_outside_grid": (at(scene_dict(), f"{BODY}.shape.center", [0.95, 0.5]), {}, "mpm.bodies[0]"),
    "body_smaller_than_spacing": (
        at(scene_dict(), f"{BODY}.shape.size", [1e-4, 1e-4]),
        {},
        "mpm.bodies[0].shape",
    ),
    "duplicate_body_names": (
        at(scene_dict(), "mpm.bodies", scene_dict()["mpm"]["bodies"] * 2),
        {},
        "mpm.bodies[1].name",
    ),
    "control_unknown_body": (at(scene_dict(), "controls", [{"body": "ghost"}]), {}, "controls[0].body"),
    "control_region_empty": (
        at(scene_dict(), "controls", [{"body": "block", "region": {"min": [0.0, 0.0], "max": [0.1, 0.1]}}]),
        {},
        "controls[0].region",
    ),
    "loss_missing_body": (
        at(scene_dict(), "loss", {"type": "com_target", "body": "ghost", "target": [0.5, 0.5]}),
        {},
        "loss.body",
    ),
    "loss_points_file_missing": (
        at(scene_dict(), "loss", {"type": "chamfer", "body": "block", "points": {"file": "nope.npz"}}),
        {},
        "loss.points.file",
    ),
    "loss_points_file_garbage": (
        at(scene_dict(), "loss", {"type": "chamfer", "body": "block", "points": {"file": "target.npz"}}),
        {"target.npz": "not an npz archive"},
        "loss.points.file",
    ),
    "fixed_substeps_unstable": (
        at(at(scene_dict(), "time.substeps", 1), f"{BODY}.material.E", 1e6),
        {},
        "time.substeps",
    ),
    "horizon_too_long": (at(scene_dict(), "steps", 10**9), {}, "time.frame_dt"),
    "mesh_file_missing": (
        at(base_3d(), f"{BODY}.shape", {"type": "mesh", "file": "nope.obj", "center": [0.5] * 3}),
        {},
        "mpm.bodies[0].shape.file",
    ),
    "mesh_file_garbage": (
        at(base_3d(), f"{BODY}.shape", {"type": "mesh", "file": "bad.obj", "center": [0.5] * 3}),
        {"bad.obj": "this is not a mesh\n\x00\x01"},
        "mpm.bodies[0].shape",
    ),
    "mesh_empty": (
        at(base_3d(), f"{BODY}.shape", {"type": "mesh", "file": "empty.obj", "center": [0.5] * 3}),
        {"empty.obj": "# no vertices\n"},
        "mpm.bodies[0].shape",
    ),
    "mesh_not_watertight": (
        at(base_3d(), f"{BODY}.shape", {"type": "mesh", "file": "open.obj", "center": [0.5] * 3}),
        {"open.obj": "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\n"},
        "mpm.bodies[0].shape",
    ),
    "mesh_is_a_folder": (
        at(base_3d(), f"{BODY}.shape", {"type": "mesh", "file": "folder.obj/", "center": [0.5] * 3}),
        {"folder.obj/x": ""},
        "mpm.bodies[0].shape.file",
    ),
    "rigid_mesh_missing": (
        at(
            base_3d(),
            "rigid",
            {"bodies": [{"name": "w", "shape": {"type": "mesh", "file": "nope.stl"}, "position": [0.5, 0.8, 0.5]}]},
        ),
        {},
        "rigid.bodies[0].shape.file",
    ),
    "cloth_mesh_zero_area_face": (
        at(base_3d(), "cloth", [{"name": "c", "mesh": {"type": "file", "file": "c.obj", "center": [0.5, 0.7, 0.5]}}]),
        {"c.obj": "v 0 0 0\nv 0.1 0 0\nv 0 0 0.1\nv 0.2 0 0\nf 1 3 2\nf 1 2 4\n"},
        "cloth[0].mesh",
    ),
    "cloth_mesh_sliver_face": (
        at(base_3d(), "cloth", [{"name": "c", "mesh": {"type": "file", "file": "c.obj", "center": [0.5, 0.7, 0.5]}}]),
        {"c.obj": "v 0 0 0\nv 0.2 0 0\nv 0.1 0 0.1\nv 0.1 0 0.0000001\nf 1 3 2\nf 1 2 4\n"},
        "sliver faces",
    ),
    "cloth_in_2d": (
        at(scene_dict(), "cloth", [{"name": "c", "mesh": {"type": "rectangle", "center": [0.5, 0.8, 0.5]}}]),
        {},
        "cloth needs dim 3",
    ),
    "urdf_missing": (scene_3d(), {}, "articulated.skeletons[0].urdf"),
    "urdf_not_xml": (scene_3d(), {"robot.urdf": "<robot name='r'><link name='a'>"}, "robot.urdf"),
    "urdf_cyclic": (
        scene_3d(),
        {"robot.urdf": urdf_text(["a", "b"], [("j1", "a", "b"), ("j2", "b", "a")])},
        "articulated.skeletons[0].urdf",
    ),
    "urdf_cycle_beside_the_root": (
        scene_3d(),
        {"robot.urdf": urdf_text(["root", "b", "c"], [("j1", "b", "c"), ("j2", "c", "b")])},
        "the joints form a cycle",
    ),
    "urdf_joint_unknown_link": (
        scene_3d(),
        {"robot.urdf": urdf_text(["base"], [("j1", "base", "ghost")])},
        "robot.urdf",
    ),
    "urdf_two_roots": (
        scene_3d(),
        {"robot.urdf": urdf_text(["a", "b", "c"], [("j1", "a", "b")])},
        "robot.urdf",
    ),
    "urdf_control_unknown_joint": (
        scene_3d(controls={"elbow": "velocity"}),
        {"robot.urdf": CHAIN},
        "articulated.skeletons[0].controls.elbow",
    ),
    "urdf_couple_unknown_link": (
        scene_3d(couple=["gripper"]),
        {"robot.urdf": CHAIN},
        "articulated.skeletons[0].couple",
    ),
    "urdf_initial_position_unknown_joint": (
        scene_3d(initial_positions={"elbow": 0.1}),
        {"robot.urdf": CHAIN},
        "articulated.skeletons[0].initial_positions.elbow",
    ),
}


def write_case(case: str, folder: Path) -> Path:
    data, files, _ = CASES[case]
    for name, text in files.items():
        path = folder / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if not name.endswith("/"):
            path.write_text(text)
    path = folder / "scene.yaml"
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def test_there_are_at_least_30_cases():
    assert len(CASES) >= 30


@pytest.mark.parametrize("case", sorted(CASES))
def test_validate_and_run_refuse_with_a_named_key(case, tmp_path, capsys):
    path = write_case(case, tmp_path)
    expected = CASES[case][2]
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    problems = [line.strip() for line in err.splitlines()[1:]] or [err]
    assert any(expected in line for line in problems), err
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--no-preview", "--quiet"]) == 2
    assert capsys.readouterr().err == err  # the same message, from the same checks
    assert not out.exists()


def test_valid_bases_pass(tmp_path):
    """The cases' bases are valid, so each case's one change is what is refused."""
    (tmp_path / "robot.urdf").write_text(CHAIN)
    for i, data in enumerate((scene_dict(), base_3d(), scene_3d())):
        path = tmp_path / f"base{i}.yaml"
        path.write_text(yaml.safe_dump(data))
        assert main(["validate", str(path)]) == 0


def test_an_uncaught_crash_is_not_possible_from_the_cli(tmp_path):
    """The CLI in a fresh process: a bad scene's error is one block on stderr, no traceback."""
    from conftest import run_cli

    path = write_case("urdf_cyclic", tmp_path)
    proc = run_cli("validate", str(path))
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and "cycle" in proc.stderr
