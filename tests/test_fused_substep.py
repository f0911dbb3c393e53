"""A forward-only substep is one kernel launch (``MPMKernels._substep_fused``): its passes are the
separate kernels' functions in the same order, so it gives their numbers (to round-off: fast math lets
the compiler contract differently in a larger kernel), with a grid contact hook and its reactions too."""

import numpy as np
from conftest import SCENES
from taichi.lang import kernel_impl
from test_scatter import engine

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


def test_a_liquid_in_a_shaken_container_is_one_launch_a_substep_and_moves_as_before():
    """shake_container_2d (liquid, grid contact reading the liquid, the container's reactions): fused, a
    substep takes one launch (the separate kernels took six: P2G, grid update, three contact passes, G2P),
    and over 12 macro steps the particles and the reactions on the container follow the unfused run."""
    launches, states, reactions = {}, {}, {}
    original = kernel_impl.Kernel.__call__

    def counted(self, *args, **kwargs):
        launches[fused] = launches.get(fused, 0) + 1
        return original(self, *args, **kwargs)

    for fused in (False, True):
        scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 12})
        sim = build_system(scene)
        sim.mpm.fuse_substeps = fused
        sim.step()  # compiles
        kernel_impl.Kernel.__call__ = counted
        try:
            substeps = 0
            for _ in range(11):
                sim.step()
                substeps += sim.last.substeps
        finally:
            kernel_impl.Kernel.__call__ = original
        states[fused] = sim.mpm.state()
        reactions[fused] = {k: np.asarray(v) for k, v in sim.last.outputs["reactions"]["kinematic"].items()}
        per_frame = 5 * 11  # each frame's own: boundary states, reactions, survey, energy, tunnelling
        launches[fused] = (launches[fused] - per_frame) / substeps
    assert launches == {False: 6, True: 1}
    assert_close(states[True], states[False], 1e-10)
    assert np.abs(reactions[False]["impulse"]).max() > 1e-3  # the liquid pushes on the container
    assert_close(reactions[True], reactions[False], 1e-9)
