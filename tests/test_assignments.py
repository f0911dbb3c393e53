"""`--set KEY.PATH=VALUE` (cosim.scene.assignments): values land where the path says, bad paths name the key."""

from __future__ import annotations

import pytest

from cosim.cli import main
from cosim.errors import SceneError
from cosim.scene import load_scene
from cosim.scene.assignments import apply_assignments, parse_assignment
from cosim.scene.shipped import scenes_dir


def test_path_parts_and_values():
    """List indices become ints; exponent numbers (strings in YAML 1.1) become floats; YAML lists stay lists."""
    assert parse_assignment("mpm.bodies[0].material.E=4e4") == (["mpm", "bodies", 0, "material", "E"], 4e4)
    assert parse_assignment("a.b[1][2]=[1, 2]") == (["a", "b", 1, 2], [1, 2])
    assert parse_assignment("precision=float64") == (["precision"], "float64")


def test_assignments_edit_a_copy_and_create_missing_mappings():
    data = {"mpm": {"bodies": [{"material": {"E": 1.0}}, {"material": {"E": 2.0}}]}}
    out = apply_assignments(data, ["mpm.bodies[1].material.E=3", "contact.friction=0.5"])
    assert out["mpm"]["bodies"][1]["material"]["E"] == 3 and out["mpm"]["bodies"][0]["material"]["E"] == 1.0
    assert out["contact"] == {"friction": 0.5}
    assert data["mpm"]["bodies"][1]["material"]["E"] == 2.0  # the input is untouched


@pytest.mark.parametrize(
    "text, says",
    [
        ("mpm.bodies[2].material.E=1", "mpm.bodies has 1 items"),
        ("mpm.grid.dx.x=1", "mpm.grid.dx is a value"),
        ("mpm.bodies.material=1", "mpm.bodies is a list: give an index"),
        ("mpm..grid=1", "is not a key"),
        ("mpm.grid", "expected KEY.PATH=VALUE"),
        ("mpm.grid=", "no value given"),
    ],
)
def test_bad_paths_name_the_assignment(text, says):
    with pytest.raises(SceneError, match=says.replace("[", r"\[").replace(".", r"\.")):
        load_scene(scenes_dir() / "dam_break_2d.yaml", assignments=[text])


def test_set_reaches_the_scene_and_wins_over_command_defaults():
    """A shipped scene with E changed, and --precision over a command's float64 default."""
    scene = load_scene(scenes_dir() / "elastic_bounce_2d.yaml", assignments=["mpm.bodies[0].material.E=4e4"])
    assert scene.mpm.bodies[0].material.E == 4e4
    scene = load_scene(scenes_dir() / "dam_break_2d.yaml", {"precision": "float64"}, ["precision=float32"])
    assert scene.precision == "float32"


def test_cli_wrong_key_exits_2_naming_it_and_the_allowed_keys(capsys):
    code = main(["validate", "dam_break_2d", "--set", "mpm.bodies[0].material.EE=4"])
    err = capsys.readouterr().err
    assert code == 2
    assert "mpm.bodies[0].material.EE: unknown key" in err and "E, density, nu" in err


def test_cli_set_changes_what_validate_counts(capsys):
    """Halving the grid spacing (twice the cells over the same tank) quadruples a 2D body's particle count."""
    assert main(["validate", "dam_break_2d"]) == 0
    before = capsys.readouterr().out
    assert (
        main(["validate", "dam_break_2d", "--set", "mpm.grid.cells=[256, 128]", "--set", "mpm.grid.dx=0.00390625"]) == 0
    )
    after = capsys.readouterr().out
    n = [int(text.split(" particles")[0].rsplit(" ", 1)[1]) for text in (before, after)]
    assert n[1] == pytest.approx(4 * n[0], rel=0.02), (before, after)


def test_gradcheck_says_when_it_overrides_the_scene_precision(tmp_path, capsys):
    """The tiny scene written in float32: gradcheck runs it in float64 and says so; with --precision
    float32 it says that was asked for."""
    import yaml
    from conftest import run_cli, scene_dict

    path = tmp_path / "tiny32.yaml"
    path.write_text(
        yaml.safe_dump(
            scene_dict(precision="float32", loss={"type": "com_target", "body": "block", "target": [0.5, 0.4]})
        )
    )
    from cosim.cli import main

    main(["gradcheck", str(path), "--steps", "1", "--directions", "1"])  # in this process: float64 as well
    out = capsys.readouterr().out
    assert "precision: float64, not the scene's float32 (gradcheck's default" in out, out
    res = run_cli(
        "gradcheck", str(path), "--steps", "1", "--directions", "1", "--precision", "float32", "--tolerance", "1"
    )
    assert "precision: float32" not in res.stdout and "gradcheck tiny: 1 steps" in res.stdout, res.stdout + res.stderr
