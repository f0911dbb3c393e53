"""Grid passes cover only the nodes the particles reach: the box P2G bounds, widened by the hooks' margin.

The clear, the grid update, the contact hooks (grid and forecast models) and their adjoints loop over
that box instead of the whole grid, which would dominate a small scene's step on a large grid. Widening
the box to the whole grid must change nothing the particles see.
"""

import numpy as np
import pytest
from conftest import SCENES

from cosim.engines import arch
from cosim.scene import load_scene
from cosim.scene.build import build_system

WHOLE_GRID = 10**6  # a margin that widens any box to the whole grid


def rollout(name: str, steps: int, margin: int | None):
    """The particle state after ``steps`` macro steps of a shipped scene (float64), and the extent of the
    last substep's box; ``margin`` replaces the hooks' box margin before anything compiles."""
    scene = load_scene(SCENES / f"{name}.yaml", {"precision": "float64", "steps": steps})
    sim = build_system(scene)
    if margin is not None:
        sim.mpm.box_margin = margin
    for _ in range(steps):
        sim.step()
    extent = sim.mpm.active_hi.to_numpy()[0] - sim.mpm.active_lo.to_numpy()[0]
    return sim.mpm.state(), extent, np.array(sim.mpm.nodes)


@pytest.mark.parametrize(
    "name",
    [
        "shake_container_2d",  # grid model with liquid (box margin 1: it reads a node's neighbours)
        "pull_door",  # forecast model (margin 0)
    ],
)
def test_the_box_loses_nothing_against_the_whole_grid(name):
    boxed, extent, nodes = rollout(name, 12, None)
    whole, extent_whole, _ = rollout(name, 12, WHOLE_GRID)
    assert (extent_whole == nodes).all()
    assert np.prod(extent) < 0.5 * np.prod(nodes)  # the box is the smaller: the comparison means something
    for key, values in boxed.items():
        np.testing.assert_allclose(values, whole[key], rtol=0, atol=1e-12 * max(np.abs(whole[key]).max(), 1.0))


def test_a_gpu_passes_over_the_whole_grid_with_the_same_result(monkeypatch):
    """On a GPU the scatter does not bound the box (every thread's atomic min / max would contend on
    two entries): the grid passes cover the whole grid. That path, forced on the CPU, gives the same
    particles as the bounded one."""
    assert not arch.choices_for("cuda").bounded_grid_passes and arch.choices_for("cpu").bounded_grid_passes
    boxed, extent, nodes = rollout("shake_container_2d", 12, None)
    cpu = arch.choices_for("cpu")
    unbounded = arch.ArchChoices(cpu.scatter, cpu.parallel_min_particles, cpu.parallel_min_nodes)
    monkeypatch.setattr(arch, "choices_for", lambda name, threads=1: unbounded)
    whole, extent_whole, _ = rollout("shake_container_2d", 12, None)
    assert (extent_whole == nodes).all() and np.prod(extent) < 0.5 * np.prod(nodes)
    for key, values in boxed.items():
        np.testing.assert_allclose(values, whole[key], rtol=0, atol=1e-12 * max(np.abs(whole[key]).max(), 1.0))
