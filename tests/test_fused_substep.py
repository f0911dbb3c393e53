"""A substep is one kernel launch (``MPMKernels._substep_fused``): its passes are the
separate kernels' functions in the same order, so it gives their numbers (to round-off: fast math lets
the compiler contract differently in a larger kernel), with a grid contact hook and its reactions too."""

import numpy as np
import pytest
from conftest import SCENES
from test_scatter import engine

from cosim.bench.kernel_profile import counting_launches
from cosim.scene import load_scene
from cosim.scene.build import build_system


def assert_close(got: dict, want: dict, rel: float) -> None:
    for key, value in want.items():
        scale = max(np.abs(value).max(), 1.0)
        np.testing.assert_allclose(got[key], value, rtol=0, atol=rel * scale, err_msg=key)


def test_a_fused_substep_gives_the_separate_kernels_numbers():
    """3D elastic particles moving over many grid blocks, 5 macro steps of 4 substeps, fused and not."""
    states = {}
    for fused in (False, True):
        mpm = engine("serial")
        mpm.fuse_substeps = fused
        for _ in range(5):
            mpm.advance(1e-4, 4)
        states[fused] = mpm.state()
    assert_close(states[True], states[False], 1e-12)


@pytest.mark.parametrize("model, separate, steps", [("grid", 6, 12), ("particle", 4, 30), ("forecast", 4, 12)])
def test_a_liquid_in_a_shaken_container_is_one_launch_a_substep_and_moves_as_before(model, separate, steps):
    """shake_container_2d (liquid, the container's reactions) in each contact model: fused, a substep is one
    launch (the separate kernels: P2G, grid update, G2P and the model's: grid contact's three passes,
    the penalty before P2G, the forecast after the grid update), and over 12 macro steps (30 for the
    penalty, which first touches near step 25) the particles and the reactions on the container follow
    the unfused run."""
    launches, states, reactions = {}, {}, {}
    for fused in (False, True):
        scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": steps},
                           [f"contact.model={model}"])  # fmt: skip
        sim = build_system(scene)
        sim.mpm.fuse_substeps = fused
        sim.step()  # compiles
        substep, substeps = sim.mpm._substep, []

        def counted_substep(*args, substep=substep, substeps=substeps):
            with counting_launches() as tally:  # only the substep's launches
                substep(*args)
            substeps.append(tally["launches"])

        sim.mpm._substep = counted_substep
        given = []  # each step's impulses on the container [N s], per substep
        for _ in range(steps - 1):
            sim.step()
            given.append(np.asarray(sim.last.outputs["reactions"]["kinematic"]["impulse"]))
        states[fused] = sim.mpm.state()
        reactions[fused] = {"impulse": np.concatenate(given)}
        launches[fused] = sum(substeps) / len(substeps)
    assert launches == {False: separate, True: 1}
    assert_close(states[True], states[False], 1e-10)
    assert np.abs(reactions[False]["impulse"]).max() > 1e-4  # the liquid pushes on the container
    assert_close(reactions[True], reactions[False], 1e-9)
