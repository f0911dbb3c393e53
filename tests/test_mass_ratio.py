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


def test_a_frame_of_many_substeps_is_split_into_exchanges_and_the_plate_rests(blocks):
    """The plate at r = 1 with 8 substeps per 2 ms frame: its coupler rests a body at up to 4 per exchange
    (``exchange_substeps``), so each frame is two exchanges of 4 (once per frame, the plate jitters on the block
    at about 2 mm/s rms), and it meets the bar: perturbations die, within 1 mm/s rms of the block's top and a
    millimetre of its closed-form height."""
    row = run(SETUPS["plate"], 1.0, True, FRAMES, FRAMES // 2, REST, blocks["plate"], substeps=8)
    assert row["outcome"] == "ok", row
    assert row["amplification"] <= 1.0 and row["late_rms"] <= 1e-3, row
    assert abs(row["height_error"]) <= 1e-3, row


def test_the_runner_warns_when_an_exchange_takes_more_substeps_than_the_plate_rests_stably_at(blocks):
    """The exchanges per frame are chosen from the first frame (here one: auto takes 4); with the block made
    four times stiffer after the build (an optimisation may), auto substeps double, and the runner warns once,
    naming time.frame_dt and a frame that would take 4 per exchange."""
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    setup = SETUPS["plate"]
    sim = build_system(parse_scene(scene_dict(setup, 1.0, 5)))
    lay_on(setup, sim, blocks["plate"])
    assert sim.exchanges == 1
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sim.step()
        sim.step()
        assert not [w for w in caught if issubclass(w.category, CouplingWarning)]
        sim.mpm.set_parameters({"E": 4.0 * sim.mpm.material()["E"]})
        for _ in range(3):
            sim.step()
    ours = [str(w.message) for w in caught if issubclass(w.category, CouplingWarning)]
    assert len(ours) == 1 and "Lower time.frame_dt to about 0.001 s" in ours[0], ours
