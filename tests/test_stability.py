"""Unstable or invalid runs stop at the step where they go wrong, naming body and quantity."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_scene, scene_dict

from cosim.errors import SceneError, SimulationError
from cosim.scene.build import build_system


def block(**material):
    b = scene_dict()["mpm"]["bodies"][0]
    b["material"] = {"type": "elastic", "E": 2e3, **material}
    return b


def test_fixed_substeps_below_the_elastic_bound_is_refused_naming_the_body():
    """E = 1e8 Pa gives c ~ 370 m/s; 2 substeps of 1 ms put c dt / dx >> 1."""
    bodies = [block(E=1e8) | {"name": "steel"}]
    scene = make_scene(time={"frame_dt": 2e-3, "substeps": 2}, mpm={"grid": {"cells": 32}, "bodies": bodies})
    with pytest.raises(SceneError, match=r"time.substeps: .*body 'steel'.*use at least \d+ substeps"):
        build_system(scene)


def test_auto_substeps_follow_the_cfl_bound():
    """Auto substeps: K = ceil(frame_dt (v + |g| frame_dt + c) / (cfl dx)) from the state before each
    step, v the largest velocity component and c = sqrt((lam + 2 mu) / rho) the P-wave speed (1.64 m/s
    here), so that (v + c) dt / dx <= cfl. The count is an integer, so any other rule shows."""
    bodies = [block() | {"velocity": [6.0, 0.0]}]
    scene = make_scene(
        time={"frame_dt": 4e-3, "substeps": "auto", "cfl": 0.3}, mpm={"grid": {"cells": 32}, "bodies": bodies}, steps=5
    )
    sim = build_system(scene)
    E, nu, rho, dx, frame_dt = 2e3, 0.3, 1000.0, 1 / 32, 4e-3
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    c = math.sqrt((lam + 2 * mu) / rho)
    infos = []
    for _ in range(5):
        v = float(np.abs(sim.mpm.state()["v"]).max()) + 9.81 * frame_dt
        infos.append(sim.step())
        assert infos[-1].substeps == math.ceil(frame_dt * (v + c) / (0.3 * dx))
    # 6 m/s over 4 ms is 0.77 cells; at CFL 0.3 that needs at least 3 substeps
    assert min(i.substeps for i in infos) >= 3


def test_fixed_substeps_cfl_violation_names_body_and_step():
    bodies = [
        block()
        | {
            "name": "bullet",
            "velocity": [30.0, 0.0],
            "shape": {"type": "box", "center": [0.3, 0.5], "size": [0.1, 0.1]},
        }
    ]
    scene = make_scene(time={"frame_dt": 4e-3, "substeps": 4}, mpm={"grid": {"cells": 32}, "bodies": bodies})
    sim = build_system(scene)
    with pytest.raises(SimulationError, match=r"step 0: CFL number .* in body 'bullet'"):
        sim.step()


def test_nan_is_caught_at_the_step_it_appears_with_body_and_quantity():
    bodies = [
        block() | {"name": "a"},
        block() | {"name": "b", "shape": {"type": "box", "center": [0.5, 0.2], "size": [0.1, 0.1]}},
    ]
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "bodies": bodies}))
    sim.step()
    state = sim.mpm.state()
    state["F"][sim.slices["b"].start + 3] = np.nan  # a corrupted deformation gradient in body b
    sim.mpm.set_state(state)
    with pytest.raises(SimulationError, match=r"step 1: body 'b': non-finite"):
        sim.step()


def test_nan_is_reported_at_the_substep_it_appears():
    """A NaN written into one particle's velocity before substep 5 of 8 (a substep hook standing in for a
    blow-up) spreads through the grid in that substep; the device watch names substep 5 and body 'b', and
    its count is the host's count of the particles with a non-finite velocity."""
    bodies = [
        block() | {"name": "a"},
        block() | {"name": "b", "shape": {"type": "box", "center": [0.5, 0.2], "size": [0.1, 0.1]}},
    ]
    sim = build_system(
        make_scene(time={"frame_dt": 2e-3, "substeps": 8}, mpm={"grid": {"cells": 32}, "bodies": bodies})
    )
    p = sim.slices["b"].start + 3

    def poison(src: int, s: int) -> None:
        if s == 5:
            sim.mpm.v[src, p] = [np.nan, 0.0]

    sim.step()
    sim.mpm.substep_preparers.append(poison)
    with pytest.raises(SimulationError) as err:
        sim.step()
    bad = ~np.isfinite(sim.mpm.state()["v"]).all(axis=1)
    assert bad[sim.slices["b"]].sum() > 1 and not bad[sim.slices["a"]].any()
    assert (
        f"step 1: body 'b': non-finite velocity (v) in {bad.sum()} particles, first in substep 5 (0-based) of 8"
        in str(err.value)
    )


def test_particles_leaving_the_grid_stop_the_run_with_their_count():
    """Without walls a block thrown at 5 m/s towards x = 1 m crosses L - dx within a few steps; the device
    survey's count is the host's count of particles beyond [dx, L - dx], and its largest velocity component
    (the CFL input) is the host's."""
    runner = block() | {
        "name": "runner",
        "velocity": [5.0, 0.0],
        "shape": {"type": "box", "center": [0.88, 0.5], "size": [0.1, 0.1]},
    }
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "boundary": {"type": "none"}, "bodies": [runner]}))
    with pytest.raises(SimulationError) as err:
        for _ in range(10):
            sim.step()
    x, v = sim.mpm.state()["x"], sim.mpm.state()["v"]
    dx = sim.dx
    outside = int(np.any((x < dx) | (x > 1.0 - dx), axis=1).sum())
    assert outside > 0
    assert f"body 'runner': {outside} particles left the grid domain" in str(err.value)
    assert sim.mpm.max_speed() == np.abs(v).max()


def test_survey_chunks_tile_every_body_in_enough_short_chunks_and_a_bounded_table():
    """The survey's and energy sums' chunks (one thread's serial loop each, a row of the host's table)
    cover each body's particles once, in order; a small engine gets chunks of ``MIN_CHUNK`` (1,485 particles:
    93 threads, not 2 of 1,024), a large one at most ``MAX_CHUNKS`` rows (2M particles: 4,096 + a last
    partial chunk per body), all within the device table's rows, which its bucket fixes."""
    from cosim.engines.mpm_inputs import particle_capacity
    from cosim.engines.mpm_watch import MAX_CHUNKS, MIN_CHUNK, body_chunks, chunk_rows

    for ranges in ([(0, 1485)], [(0, 10), (10, 5000), (5000, 5001)], [(0, 1_000_000), (1_000_000, 2_000_000)]):
        chunks = body_chunks(ranges)
        for b, (lo, hi) in enumerate(ranges):
            rows = chunks[chunks[:, 2] == b]
            assert rows[0, 0] == lo and rows[-1, 1] == hi and np.array_equal(rows[1:, 0], rows[:-1, 1])
        assert len(chunks) <= MAX_CHUNKS + len(ranges)
        assert len(chunks) <= chunk_rows(particle_capacity(ranges[-1][1]), len(ranges))  # the device table's
        assert (chunks[:, 1] - chunks[:, 0]).max() == max(MIN_CHUNK, -(-ranges[-1][1] // MAX_CHUNKS))
    assert len(body_chunks([(0, 1485)])) == 93


def test_a_step_redone_after_a_cfl_violation_restarts_from_its_state():
    """A block at 4 m/s gets two substeps of 1 ms (CFL bound: (4 + 1.64 + 0.02) m/s * 2 ms / (0.3 dx) = 1.2)
    but a control impulse the count does not foresee takes it to 14 m/s: CFL 14 * 1e-3 * 32 = 0.45 > 0.3,
    so the step is redone with four substeps from the state it started from (kept on the device while the
    first try's two substeps ran), and ends where four fixed substeps from the start end. A record kept
    while the engine steps on keeps its state (read before its slot is overwritten)."""
    mass = 1000.0 / 64**2  # [kg] density times the particle's area, (dx / 2)^2
    body = block() | {"velocity": [4.0, 0.0]}
    controls = [{"body": "block", "impulse": [10.0 * mass, 0.0]}]
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "bodies": [body]}, controls=controls, steps=1))
    sim.rollout()
    assert sim.last.substeps == 4  # not 2: redone
    redone = sim.mpm.state()
    sim.reset()
    sim.stepping.fixed = 4
    sim.rollout()
    for key, value in sim.mpm.state().items():
        np.testing.assert_allclose(redone[key], value, rtol=1e-12, atol=1e-12, err_msg=key)
    start = sim.mpm.state()
    record = sim.step().mpm
    for _ in range(3):
        sim.step()
    for key, value in start.items():
        assert np.array_equal(record.state[key], value), key


def test_a_forward_run_reads_no_particle_state():
    """Twelve macro steps through the loop of `cosim run` read no particle back: the NaN, CFL and domain
    checks and the conservation check (its start and its check after every step) run on the device, and
    the loop's records are dropped before their slots are reused."""
    sim = build_system(make_scene(steps=12))
    reads, read_slot = [], sim.mpm.read_slot
    sim.mpm.read_slot = lambda key, slot: reads.append(key) or read_slot(key, slot)
    sim.rollout()
    assert sim.conservation.excess is not None  # the checks ran
    assert reads == []


def test_a_state_view_about_to_be_overwritten_reads_its_missing_keys_in_one_launch():
    """A forward step's state is a view of its slot (``SlotState``); one still held when the engine is about to
    overwrite the slot reads the keys nobody read yet: together in one launch (on a GPU every read is a wait),
    a last one alone by itself, and the view keeps the slot's numbers."""
    from cosim.engines.slot_state import SlotState

    sim = build_system(make_scene(steps=2))
    sim.step()
    expected = sim.mpm.state()
    reads, read_slot = [], sim.mpm.read_slot
    sim.mpm.read_slot = lambda key, slot: reads.append(key) or read_slot(key, slot)
    fresh, partly = SlotState(sim.mpm, sim.mpm._slot), SlotState(sim.mpm, sim.mpm._slot)
    for key in ("x", "v", "C"):
        partly[key]
    reads.clear()
    fresh.detach()
    partly.detach()
    assert reads == [None, "F"]
    for key, value in expected.items():
        assert np.array_equal(fresh[key], value) and np.array_equal(partly[key], value), key


def test_forward_run_allocates_no_gradient_buffers():
    sim = build_system(make_scene(controls=[{"body": "block"}]))
    assert sim.mpm.n_slots == 4  # four particle slots (a step keeps its start and the last one's), one grid
    assert not sim.mpm.gradient_buffers_allocated()
    assert build_system(make_scene(controls=[{"body": "block"}]), requires_grad=True).mpm.gradient_buffers_allocated()


def test_state_round_trip_replays_bit_for_bit():
    """set_state(state()) then the same steps reproduce the same numbers exactly."""
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "bodies": [block() | {"velocity": [1.0, -1.0]}]}))
    s0 = sim.mpm.state()
    for _ in range(3):
        sim.step()
    a = sim.mpm.state()
    sim.mpm.set_state(s0)
    for _ in range(3):
        sim.step()
    b = sim.mpm.state()
    for key in a:
        assert np.array_equal(a[key], b[key]), key


def test_a_rigid_body_leaving_the_domain_stops_the_run():
    """A DART free box thrown at 40 m/s towards x = 1 m (clear of the material) leaves the grid's box
    within 3 steps of 4 ms; the run stops there naming the engine and the body (it used to go on
    silently, as a plate thrown off an elastic block did)."""
    data = make_scene(
        mpm={"grid": {"cells": 16}, "boundary": {"type": "slip"}, "bodies": [block()]},
    ).model_dump(exclude_unset=True)
    link = {"name": "box", "shape": {"type": "box", "size": [0.05, 0.05]}, "density": 500}
    link["joint"] = {"type": "free", "position": [0.9, 0.8], "qd0": [40.0, 0.0, 0.0]}  # planar: x, y, angle
    data["articulated"] = {"skeletons": [{"name": "thrown", "links": [link]}]}
    data["time"] = {"frame_dt": 4e-3, "substeps": "auto"}
    from cosim.scene import parse_scene

    sim = build_system(parse_scene(data))
    with pytest.raises(SimulationError) as err:
        for _ in range(5):
            sim.step()
    x = sim.engines["dart"].points()[0, 0]
    assert sim.step_index == 0 and x > 1.0  # the step that crossed x = 1 m (0.9 m + 40 m/s * 4 ms)
    assert "engine 'dart': body 'thrown/box' left the grid domain" in str(err.value)


def test_a_driven_body_may_leave_the_domain_where_its_actions_take_it():
    """The same box velocity-driven out of the grid at 40 m/s (its planar joint under velocity control): a
    driven body goes where its actions take it (an optimiser's trial moves a held bottle below the floor),
    so the run goes on; the guard watches the bodies no action drives."""
    data = make_scene(
        mpm={"grid": {"cells": 16}, "boundary": {"type": "slip"}, "bodies": [block()]},
    ).model_dump(exclude_unset=True)
    link = {"name": "box", "shape": {"type": "box", "size": [0.05, 0.05]}, "density": 500}
    link["joint"] = {"type": "free", "position": [0.9, 0.8]}
    data["articulated"] = {
        "skeletons": [{"name": "driven", "links": [link], "controls": {"box": "velocity"}}],
        "actions": {"initial": [40.0, 0.0, 0.0]},
    }
    data["time"] = {"frame_dt": 4e-3, "substeps": "auto"}
    from cosim.scene import parse_scene

    sim = build_system(parse_scene(data))
    for _ in range(5):
        sim.step()
    assert sim.engines["dart"].body_states()["position"][0, 0] > 1.0
