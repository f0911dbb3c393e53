"""The scene's ``accuracy: coarse | default | fine`` hint: what it sets, what wins over it, what it refuses."""

from __future__ import annotations

import pytest
from conftest import ROOT, SCENES, scene_dict

from cosim.errors import SceneError
from cosim.scene import load_scene, parse_scene
from cosim.scene.accuracy import LEVELS


def without_time_and_precision(**overrides) -> dict:
    data = scene_dict(**overrides)
    data.pop("precision")
    data["time"].pop("cfl", None)
    return data


@pytest.mark.parametrize("level", list(LEVELS))
def test_each_level_sets_grid_cfl_and_precision(level):
    """32 cells of 1/32 m with 3-cell walls, refined by the level's factor: the domain (1 m) and the
    walls (3/32 m) stay, cfl and precision are the level's."""
    want = LEVELS[level]
    scene = parse_scene(without_time_and_precision(accuracy=level), ROOT)
    cells = round(32 * want.grid)
    assert scene.cells == (cells, cells)
    assert scene.dx == pytest.approx(1.0 / cells)
    assert scene.mpm.boundary.thickness * scene.dx == pytest.approx(3 / 32, abs=0.5 / cells)
    assert scene.time.cfl == want.cfl
    assert scene.precision == want.precision
    assert scene.accuracy == level


def test_keys_written_in_the_scene_win_over_the_hint():
    data = scene_dict(accuracy="coarse", precision="float64")
    data["time"]["cfl"] = 0.2
    data["mpm"]["grid"] = {"cells": [64, 32], "dx": 1 / 32}  # a 2 m x 1 m domain
    data["mpm"]["bodies"][0]["shape"] = {"type": "box", "center": [1.0, 0.5], "size": [0.25, 0.25]}
    scene = parse_scene(data, ROOT)
    assert scene.precision == "float64" and scene.time.cfl == 0.2  # explicit keys kept
    factor = LEVELS["coarse"].grid
    assert scene.cells == (round(64 * factor), round(32 * factor))
    assert scene.cells[0] * scene.dx == pytest.approx(2.0)  # the domain kept


def test_a_shipped_scene_loads_with_a_hint_given_by_set():
    plain = load_scene(SCENES / "elastic_bounce_2d.yaml")
    fine = load_scene(SCENES / "elastic_bounce_2d.yaml", assignments=["accuracy=fine"])
    factor = LEVELS["fine"].grid
    assert fine.cells[0] == round(plain.cells[0] * factor)
    assert fine.cells[0] * fine.dx == pytest.approx(plain.cells[0] * plain.dx)
    assert fine.time.cfl == plain.time.cfl  # elastic_bounce_2d writes cfl: 0.3 itself
    assert fine.precision == plain.precision  # and precision: float32


@pytest.mark.parametrize("value", ["ultra", 3, True])
def test_a_wrong_level_is_a_scene_error_naming_accuracy(value):
    with pytest.raises(SceneError) as info:
        parse_scene(scene_dict(accuracy=value), ROOT)
    message = str(info.value)
    assert "accuracy: must be one of coarse, default, fine" in message
    assert repr(value) in message


def test_a_refinement_past_the_grid_limit_names_accuracy():
    data = scene_dict(accuracy="fine")
    data["mpm"]["grid"] = {"cells": 4000}
    with pytest.raises(SceneError, match=r"accuracy: refining mpm.grid.cells 4000"):
        parse_scene(data, ROOT)
