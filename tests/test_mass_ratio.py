"""The mass-ratio sweep's r = 25 rows (``cosim.bench.mass_ratio``): a light body resting on an elastic block 25
times heavier per cell of depth stays at rest on it under the added-mass coupling, and is thrown off under the
explicit exchange; beyond the substeps per frame at which that is measured, the runner warns."""

from __future__ import annotations

import warnings

import pytest

from cosim.bench.mass_ratio import SETUPS, lay_on, run, scene_dict, settled_block
from cosim.errors import CouplingWarning

FRAMES, REST = 200, 100  # as the bench: after 60 settling frames the block still rocks


@pytest.fixture(scope="module")
def blocks() -> dict:
    return {name: settled_block(setup, REST) for name, setup in SETUPS.items()}


def _row(blocks: dict, body: str, strong: bool) -> dict:
    setup = SETUPS[body]
    return run(setup, 25.0, strong, frames=FRAMES, perturb_at=FRAMES // 2, rest=REST, block=blocks[body])


def test_a_light_plate_rests_on_heavy_material_and_the_explicit_exchange_throws_it(blocks):
    """DART plate (2D) at r = 25: a perturbation of its velocity dies (amplification <= 1 per frame), it moves
    with the block's top within 1 mm/s rms and rests within a millimetre of its closed-form height (a cell
    is 31 mm). Exchanging the reactions alone, the energy budget stops the run (the plate is flung)."""
    row = _row(blocks, "plate", True)
    assert row["outcome"] == "ok", row
    assert row["amplification"] <= 1.0 and row["late_rms"] <= 1e-3, row
    assert abs(row["height_error"]) <= 1e-3, row
    row = _row(blocks, "plate", False)
    assert "energy grew" in row["outcome"], row


def test_a_light_sheet_rests_on_heavy_material_and_the_explicit_exchange_misses_the_bar(blocks):
    """Cloth sheet (3D) at r = 25: perturbations die, it moves with the block's top within 1 mm/s rms and rests
    within a millimetre of its closed-form height (a cell is 62 mm). Exchanging the reactions alone, the sheet
    misses the bar: it bounces on the block (its late rms several mm/s; its amplification, near 1, varies
    with the round-off of parallel sums from run to run)."""
    row = _row(blocks, "cloth", True)
    assert row["outcome"] == "ok", row
    assert row["amplification"] <= 1.0 and row["late_rms"] <= 1e-3, row
    assert abs(row["height_error"]) <= 1e-3, row
    row = _row(blocks, "cloth", False)
    assert row["outcome"] != "ok" or row["amplification"] > 1.0 or row["late_rms"] > 1e-3, row


@pytest.mark.parametrize("substeps, warned", [(4, False), (8, True)])
def test_the_runner_warns_when_a_frame_takes_more_substeps_than_the_plate_rests_stably_at(blocks, substeps, warned):
    """The plate at r = 1 on the block: its coupler's measured limit is 4 substeps per frame
    (``exchange_substeps``); a frame of 8 while it carries material warns once, naming time.frame_dt and a
    frame that would take 4; a frame of 4 does not."""
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    setup = SETUPS["plate"]
    sim = build_system(parse_scene(scene_dict(setup, 1.0, 5, substeps)))
    lay_on(setup, sim, blocks["plate"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            sim.step()
    ours = [w for w in caught if issubclass(w.category, CouplingWarning)]
    assert len(ours) == int(warned), [str(w.message) for w in caught]
    if warned:
        assert "time.frame_dt to about 0.001 s" in str(ours[0].message)
