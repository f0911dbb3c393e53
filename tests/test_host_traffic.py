"""What a coupled macro step sends between host and device: a fixed few arrays per step, none per substep
(on a GPU every host array a kernel takes is a copy and a wait), packed side by side (boundary states in,
reactions out, the tunnelling check's poses) and unpacked on the device where they belong."""

import numpy as np
from conftest import SCENES, make_scene

from cosim.bench.kernel_profile import counting_launches
from cosim.scene import load_scene
from cosim.scene.build import build_system


def test_a_macro_step_hands_the_device_the_same_few_host_arrays_whatever_its_substeps():
    """shake_container_2d at 8 and at 16 fixed substeps a frame: the same host arrays a step (boundary
    states, reactions, the survey with the energies, the tunnelling check's poses and counts), and 8
    launches more, one per extra substep, none of which takes a host array; after the first step every
    launch goes through its plan (``cosim.engines.kernel_launch``), none through Taichi's call."""
    per_step = {}
    for substeps in (8, 16):
        scene = load_scene(
            SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 6}, [f"time.substeps={substeps}"]
        )
        sim = build_system(scene)
        sim.step()  # compiles
        with counting_launches() as tally:
            for _ in range(4):
                sim.step()
        per_step[substeps] = {key: count / 4 for key, count in tally.items()}
    assert per_step[16]["arrays"] == per_step[8]["arrays"] <= 5, per_step
    assert per_step[16]["launches"] - per_step[8]["launches"] == 8, per_step
    assert all(counts["planned"] == counts["launches"] for counts in per_step.values()), per_step  # no Taichi call


def test_a_backward_substep_is_seven_launches_with_no_host_array():
    """shake_container_2d's gradient over 2 macro steps at 4 and at 8 substeps a frame: the backward's host
    arrays are the same, and each substep more adds 7 launches to each step's adjoint (the G2P adjoint,
    opening with the grid adjoints' zeroing; the scatter, closing with the hand-over to the grid hook; the
    hook's three adjoints; the grid update's; the P2G and stress adjoint) and 1 to each step's recompute
    but the last step's, whose forward is still resident: 2 * 7 + 1 = 15 per extra substep."""
    from cosim.adjoint.tape import Tape

    counts = {}
    for substeps in (4, 8):
        scene = load_scene(
            SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 2}, [f"time.substeps={substeps}"]
        )
        sim = build_system(scene, requires_grad=True)
        start = sim.state()
        seed = {engine: {k: np.ones_like(v) for k, v in s.items()} for engine, s in start.items()}
        for _ in range(2):  # the first compiles
            sim.set_state(start)
            tape = Tape()
            sim.rollout(tape=tape)
            with counting_launches() as tally:
                tape.backward(sim.vjp, seed)
        counts[substeps] = tally
    assert counts[8]["arrays"] == counts[4]["arrays"], counts
    assert counts[8]["launches"] - counts[4]["launches"] == 4 * 15, counts


def rotated_wall_scene(angle: float):
    """A 0.2 m long, one-cell thin wall at (0.6, 0.5) turned by ``angle`` [rad] from upright, a small block."""
    wall = {"name": "wall", "shape": {"type": "box", "size": [1 / 64, 0.2]}, "position": [0.6, 0.5], "rotation": angle}
    block = {
        "name": "block",
        "material": {"type": "elastic", "E": 1e4, "nu": 0.3, "density": 1000},
        "shape": {"type": "box", "center": [0.3, 0.3], "size": [0.05, 0.05]},
    }
    return make_scene(steps=2, mpm={"grid": {"cells": 64}, "bodies": [block]}, rigid={"bodies": [wall]})


def set_rows(fld, values: np.ndarray) -> None:
    """fld[:K] = values (the field holds more substeps than K)."""
    full = fld.to_numpy()
    full[: len(values)] = values
    fld.from_numpy(full)


def test_boundary_states_and_reactions_cross_between_host_and_device_in_the_layout_they_were_given():
    """Random states of 5 substeps (turns that are not their own transpose) written through the packed
    array land in the source's fields, their reactions cleared; impulses placed in its fields come back in
    the Reactions layout; the adjoints come back (states) and go in (reactions) likewise."""
    sim = build_system(rotated_wall_scene(0.3), requires_grad=True)
    source = sim.mpm.boundaries[next(iter(sim.mpm.boundaries))]
    rng = np.random.default_rng(0)
    K, n = 5, source.n
    angles = rng.uniform(-3, 3, size=(K, n))
    turns = [np.stack([np.cos(angles), -np.sin(angles)], -1), np.stack([np.sin(angles), np.cos(angles)], -1)]
    states = {
        "pos": rng.uniform(0.2, 0.8, size=(K, n, 2)),
        "rot": np.stack(turns, -2),
        "vel": rng.normal(size=(K, n, 2)),
        "omega": rng.normal(size=(K, n, 1)),
    }
    reactions = {"impulse": rng.normal(size=(K, n, 2)), "angular_impulse": rng.normal(size=(K, n, 1))}
    for key, value in reactions.items():
        set_rows(getattr(source, key), value)
    source.write(states)
    for key, value in states.items():
        np.testing.assert_array_equal(getattr(source, key).to_numpy()[:K], value, err_msg=key)
    for key in reactions:
        assert not np.any(getattr(source, key).to_numpy()[:K]), key
    for key, value in reactions.items():
        set_rows(getattr(source, key), value)
    for key, value in source.reactions(K).items():
        np.testing.assert_array_equal(value, reactions[key], err_msg=key)
    for key, value in states.items():
        set_rows(getattr(source, key).grad, 2 * value)
    for key, value in source.state_grads(K).items():
        np.testing.assert_array_equal(value, 2 * states[key], err_msg=key)
    source.seed_reaction_grads(reactions)
    for key, value in reactions.items():
        np.testing.assert_array_equal(getattr(source, key).grad.to_numpy()[:K], value, err_msg=key)


def test_a_path_through_a_turned_wall_counts_as_going_through_and_one_past_its_mirror_image_does_not():
    """The wall turned by 45 degrees spans (0.53, 0.57) to (0.67, 0.43); its mirror image (turned by -45
    degrees, which a transposed rotation would give) spans (0.53, 0.43) to (0.67, 0.57). Particles moving
    down at x = 0.55 from y = 0.6 to 0.5 cross the wall (at y = 0.55) and pass beside its mirror image,
    which they would meet at y = 0.45."""
    for angle, crossed in ((np.pi / 4, True), (-np.pi / 4, False)):
        sim = build_system(rotated_wall_scene(angle))
        tunnels, poses = sim.guard.tunnels, sim.rigid.poses()
        state = sim.mpm.state()
        n = len(state["x"])
        before = dict(state, x=np.tile([0.55, 0.6], (n, 1)), v=np.zeros((n, 2)))
        sim.mpm.set_state(before)
        tunnels.reset()
        tunnels.begin()
        sim.mpm.set_state(dict(before, x=np.tile([0.55, 0.5], (n, 1))))
        counts = tunnels.step(poses, poses)
        assert counts.tolist() == [[n if crossed else 0]], angle
