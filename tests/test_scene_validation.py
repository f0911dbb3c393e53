"""Bad scenes give one clear message naming the key path; good ones load."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from conftest import ROOT, make_scene, run_cli, scene_dict, shipped_scenes

from cosim.errors import SceneError
from cosim.scene import load_scene, parse_scene


def error_of(data) -> str:
    with pytest.raises(SceneError) as info:
        parse_scene(data, ROOT)
    return str(info.value)


def with_body(**body_changes):
    data = scene_dict()
    body = data["mpm"]["bodies"][0]
    for key, value in body_changes.items():
        body[key] = value
    return data


@pytest.mark.parametrize("path", shipped_scenes())
def test_shipped_scenes_are_valid(path):
    scene = load_scene(path)
    assert scene.dim == yaml.safe_load(path.read_text())["dim"]
    assert len(scene.cells) == len(scene.gravity) == scene.dim


def test_negative_young_modulus_names_the_key():
    data = scene_dict()
    data["mpm"]["bodies"].append(dict(data["mpm"]["bodies"][0], name="second"))
    data["mpm"]["bodies"][1]["material"] = {"type": "plastic", "E": -5.0, "yield_stress": 100}
    assert "mpm.bodies[1].material.E: must be > 0" in error_of(data)


def test_unknown_key_lists_allowed_keys():
    msg = error_of(with_body(material={"type": "elastic", "E": 1e3, "youngs": 3}))
    assert "mpm.bodies[0].material.youngs: unknown key" in msg
    assert "E, density, nu, type" in msg


def test_unknown_top_level_key():
    assert "stepz: unknown key" in error_of(scene_dict(stepz=3))


def test_wrong_type_and_literal():
    assert "mpm.grid.cells: must be an integer or a list of integers" in error_of(
        scene_dict(mpm={**scene_dict()["mpm"], "grid": {"cells": "big"}})
    )
    assert "precision: must be one of" in error_of(scene_dict(precision="float16"))
    assert "time.substeps: must be 'auto' or a positive integer" in error_of(scene_dict(time={"substeps": "many"}))


def test_unknown_material_type():
    msg = error_of(with_body(material={"type": "rubber", "E": 1e3}))
    assert "mpm.bodies[0].material: unknown type 'rubber'" in msg


def test_missing_required_key():
    data = scene_dict()
    del data["dim"]
    assert "dim: required key is missing" in error_of(data)


def test_vector_length_must_match_dim():
    msg = error_of(with_body(shape={"type": "box", "center": [0.5, 0.5, 0.5], "size": [0.2, 0.2]}))
    assert "mpm.bodies[0].shape.center: must have 2 entries (dim is 2), got 3" in msg


def test_nan_is_rejected():
    assert "mpm.bodies[0].velocity[0]: must be a finite number" in error_of(with_body(velocity=[float("nan"), 0.0]))


def test_control_must_name_an_existing_body():
    msg = error_of(scene_dict(controls=[{"body": "nobody", "impulse": [0, 1]}]))
    assert "controls[0].body: no body named 'nobody'" in msg


def test_missing_mesh_file():
    data = scene_dict(dim=3)
    data["mpm"]["bodies"][0]["shape"] = {"type": "mesh", "file": "no/such/bunny.obj", "center": [0.5, 0.5, 0.5]}
    assert "mpm.bodies[0].shape.file: file not found" in error_of(data)


def test_mesh_in_2d_is_rejected():
    data = with_body(shape={"type": "mesh", "file": "x.obj", "center": [0.5, 0.5]})
    assert "needs dim 3" in error_of(data)


def test_body_outside_grid_is_rejected_when_sampled():
    from cosim.scene.particles import body_positions

    scene = parse_scene(with_body(shape={"type": "box", "center": [0.05, 0.5], "size": [0.2, 0.2]}), ROOT)
    with pytest.raises(SceneError, match=r"mpm.bodies\[0\] \('block'\): \d+ particles lie outside"):
        body_positions(scene)


def test_non_watertight_mesh_is_rejected(tmp_path):
    import trimesh

    from cosim.scene.particles import body_positions

    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)  # drop one side
    open_box.export(tmp_path / "open.obj")
    data = scene_dict(dim=3)
    data["mpm"]["bodies"][0]["shape"] = {"type": "mesh", "file": "open.obj", "center": [0.5, 0.5, 0.5]}
    scene = parse_scene(data, tmp_path)
    with pytest.raises(SceneError, match="not watertight"):
        body_positions(scene)


def test_mesh_sampling_fills_its_volume(tmp_path):
    """Particles x spacing^3 approximate the mesh volume (lattice error ~ surface x spacing)."""
    import trimesh

    from cosim.scene.particles import body_positions

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.15)
    ball.export(tmp_path / "ball.stl")
    data = scene_dict(dim=3, mpm={"grid": {"cells": 32}, "bodies": [dict(scene_dict()["mpm"]["bodies"][0])]})
    data["mpm"]["bodies"][0]["shape"] = {"type": "mesh", "file": "ball.stl", "center": [0.5, 0.5, 0.5]}
    scene = parse_scene(data, tmp_path)
    points = body_positions(scene)[0]
    sampled = len(points) * (0.5 * scene.dx) ** 3  # each particle stands for a lattice cell of dx / 2
    assert abs(sampled - ball.volume) / ball.volume < 0.05
    assert np.allclose(points.mean(axis=0), 0.5, atol=1e-3)


def test_sampling_is_seeded():
    from cosim.scene.particles import body_positions

    a = body_positions(
        make_scene(seed=3, mpm={**scene_dict()["mpm"], "bodies": [dict(scene_dict()["mpm"]["bodies"][0], jitter=0.4)]})
    )
    b = body_positions(
        make_scene(seed=3, mpm={**scene_dict()["mpm"], "bodies": [dict(scene_dict()["mpm"]["bodies"][0], jitter=0.4)]})
    )
    c = body_positions(
        make_scene(seed=4, mpm={**scene_dict()["mpm"], "bodies": [dict(scene_dict()["mpm"]["bodies"][0], jitter=0.4)]})
    )
    assert np.array_equal(a[0], b[0])
    assert not np.array_equal(a[0], c[0])


def test_cli_validate_bad_scene_exit_2_without_traceback(tmp_path):
    data = scene_dict()
    data["mpm"]["bodies"][0]["material"]["E"] = 0
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    res = run_cli("validate", str(path))
    assert res.returncode == 2
    assert "mpm.bodies[0].material.E: must be > 0" in res.stderr
    assert "Traceback" not in res.stderr


def test_cli_missing_scene_file_exit_2(tmp_path):
    res = run_cli("run", str(tmp_path / "nope.yaml"))
    assert res.returncode == 2 and "scene file not found" in res.stderr and "Traceback" not in res.stderr


def test_cli_invalid_yaml_exit_2(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("dim: [2\nmpm: {")
    res = run_cli("validate", str(path))
    assert res.returncode == 2 and "not valid YAML" in res.stderr


def rigid_scene(body):
    return scene_dict(rigid={"bodies": [body]})


def test_rigid_body_errors_name_the_key():
    base = {"name": "wall", "shape": {"type": "box", "size": [0.1, 0.2]}, "position": [0.5, 0.5]}
    assert "rigid.bodies[0].shape.radius: required for a sphere" in error_of(
        rigid_scene(base | {"shape": {"type": "sphere"}})
    )
    assert "rigid.bodies[0].motion.velocity: required for a constant motion" in error_of(
        rigid_scene(base | {"motion": {"type": "constant"}})
    )
    assert "rigid.bodies[0].position: must have 2 entries" in error_of(
        rigid_scene(base | {"position": [0.5, 0.5, 0.5]})
    )
    moved = {"type": "waypoints", "times": [0, 1], "positions": [[0.4, 0.5], [0.6, 0.5]]}
    assert "motion.positions[0]: must equal the body's position" in error_of(rigid_scene(base | {"motion": moved}))
    assert "rigid.bodies[0].shape.type: must be one of" in error_of(rigid_scene(base | {"shape": {"type": "torus"}}))
    ring3d = scene_dict(
        dim=3,
        rigid={
            "bodies": [
                {"name": "r", "shape": {"type": "ring", "radius": 0.2, "thickness": 0.02}, "position": [0.5, 0.5, 0.5]}
            ]
        },
    )
    ring3d["mpm"]["bodies"][0]["shape"] = {"type": "box", "center": [0.5, 0.5, 0.5], "size": [0.1, 0.1, 0.1]}
    assert "a ring is 2D" in error_of(ring3d)
