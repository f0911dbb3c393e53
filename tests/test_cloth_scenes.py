"""Shipped cloth scenes checked by numbers: towel_squash with and without penetration tracing."""

import numpy as np
import pytest
from conftest import SCENES
from scipy.interpolate import LinearNDInterpolator

from cosim.scene import load_scene
from cosim.scene.build import build_system


def _squash(contact: dict):
    """Run towel_squash (float64) under ``contact``; returns (plasticine x at start, at end, towel x at end)."""
    scene = load_scene(SCENES / "towel_squash.yaml", {"precision": "float64", "contact": contact})
    sim = build_system(scene)
    x0 = sim.mpm.state()["x"].copy()
    sim.rollout()
    return x0, sim.mpm.state()["x"], sim.engines["towel"].state()["x"], sim


def _above_sheet(x: np.ndarray, towel: np.ndarray) -> int:
    """Particles above the towel (the towel as a height field over x, z; particles start below it)."""
    height = LinearNDInterpolator(towel[:, [0, 2]], towel[:, 1])(x[:, [0, 2]])
    return int(np.sum(x[:, 1] > np.nan_to_num(height, nan=np.inf)))


@pytest.mark.slow
def test_towel_squash_squashes_with_tracing_and_passes_through_without():
    """Forecast contact with tracing: no particle ends above the sheet, the traced count agrees, the
    block's top is pressed down by more than a grid cell (dx = 1/32 m) and the towel's centre stays on
    top of it. Particle contact with tracing off (a particle's legal side is wherever it is): the towel
    sinks through the block, its centre ends below the block's initial mid-height, and most particles
    end above the sheet."""
    x0, x, towel, sim = _squash({"model": "forecast", "friction": 0.2})
    top0, top = x0[:, 1].max(), x[:, 1].max()
    centre = towel[len(towel) // 2]
    assert _above_sheet(x, towel) == 0
    assert int(np.count_nonzero(sim.couplers[0].state()["inside"])) == 0
    assert top < top0 - 1.0 / 32
    assert centre[1] > top - 1.0 / 32  # the sheet rests on the squashed block
    x0, x, towel, _ = _squash({"model": "particle", "friction": 0.2, "tracing": False})
    centre = towel[len(towel) // 2]
    assert centre[1] < 0.5 * (x0[:, 1].min() + x0[:, 1].max())
    assert _above_sheet(x, towel) > 0.5 * len(x)
