"""`cosim gradcheck` over each shipped scene's full horizon (float64, 1e-5): the 2D scenes with a loss in
the default suite, the 3D ones under ``-m full_horizon`` (tens of minutes on two cores; the latest
figures are in docs/contact.md)."""

from __future__ import annotations

import pytest
from conftest import run_cli

# scene: its full horizon (the scene's `steps`), or where its differences stop resolving the gradient:
# dam_break_2d's water splashes against the far wall between steps 175 and 200, where the spread of two
# rollouts 1e-9 apart in v0 grows 100x, and central differences at step h and h/2 differ by 5-10 % at 200
SCENES_2D = {"pull_door": 150, "elastic_bounce_2d": 150, "dam_break_2d": 150}
SCENES_3D = {
    "cloth_catch": 120,
    "make_taco": 200,
    "towel_squash": 100,
    "push_towel": 100,
    "squeeze_plasticine": 150,
    "pour_water": 200,
    "pour_franka": 250,
    "jelly_torus_3d": 120,
    "plastic_squash_3d": 100,
}


def _gradcheck(scene: str, steps: int) -> None:
    result = run_cli("gradcheck", scene, "--steps", str(steps), "--tolerance", "1e-5")
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert f"{steps} steps" in result.stdout


@pytest.mark.parametrize("scene", sorted(SCENES_2D))
def test_2d_scene_gradients_hold_over_the_full_horizon(scene):
    _gradcheck(scene, SCENES_2D[scene])


@pytest.mark.full_horizon
@pytest.mark.parametrize("scene", sorted(SCENES_3D))
def test_3d_scene_gradients_hold_over_the_full_horizon(scene):
    _gradcheck(scene, SCENES_3D[scene])
