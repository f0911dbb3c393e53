"""The three scatters (``cosim.engines.arch.SCATTERS``): the coloured one conserves what P2G hands the
grid, agrees with the serial one to round-off forward and backward, and sums in an order the particles
alone fix: bit for bit the same result on one thread and on two."""

import os
import subprocess
import sys

import numpy as np
from conftest import ROOT, SCENES

from cosim.engines.mpm import STATE_KEYS, MPMConfig, MPMEngine, ParticleBody
from cosim.scene import load_scene
from cosim.scene.build import build_system

CELLS = 24
DX = 1.0 / CELLS


def engine(scatter: str, dim: int = 3, n: int = 3000, grad_substeps: int = 0) -> MPMEngine:
    """``n`` particles at random over many grid blocks (about 15 cells a side), moving in random directions."""
    rng = np.random.default_rng(7)
    pts = rng.uniform(0.15, 0.75, (n, dim))
    vel = rng.normal(0.0, 0.3, (n, dim))
    body = ParticleBody("blob", "elastic", 2e4, 0.3, 1000.0, (0.5 * DX) ** dim, pts, vel)
    grad = {"requires_grad": True, "grad_substeps": grad_substeps} if grad_substeps else {}
    gravity = (0.0, -9.81, 0.0)[:dim]
    return MPMEngine(MPMConfig(dim, (CELLS,) * dim, DX, gravity, scatter=scatter, **grad), [body])


def test_the_parallel_scatters_hand_the_grid_every_particles_mass_and_momentum_once():
    """After P2G the grid holds sum m_p and sum m_p v_p (the affine and stress parts sum to zero over a
    B-spline stencil), node by node the serial scatter's grid to round-off: a particle left out of the
    block lists, or listed twice, would move the totals by 1/3000 of them; a stress the parallel scatters
    compute themselves (``stress_in_scatter``) other than the serial one's separate loop would move nodes."""
    grids = {}
    for scatter in ("serial", "coloured", "atomic"):
        mpm = engine(scatter)
        mpm.advance(1e-4, 1)  # a step, so that C and F are not trivial
        mpm.pre_coupling(mpm.slot, 0, 1e-4)
        grid = mpm.grid_mm.to_numpy()[0]
        grids[scatter] = grid
        x = mpm.state()
        m = mpm.mass
        totals = grid.reshape(-1, 4).sum(axis=0)
        np.testing.assert_allclose(totals[3], m.sum(), rtol=1e-12)
        np.testing.assert_allclose(totals[:3], (m[:, None] * x["v"]).sum(axis=0), rtol=0, atol=1e-12 * m.sum())
    scale = np.abs(grids["serial"]).max()
    for scatter in ("coloured", "atomic"):
        np.testing.assert_allclose(grids[scatter], grids["serial"], rtol=0, atol=1e-13 * scale)


def test_every_particle_stays_listed_in_a_block_its_stencil_is_within_drift_of():
    """The block lists stand while each particle's stencil base is within ``DRIFT`` cells of its listed
    block (what keeps one colour's stencils apart): after moves of a tenth of a cell up to three cells,
    every particle is listed in such a block, and each block's particles in ascending index."""
    from cosim.engines.mpm_bins import BLOCK, DRIFT

    mpm = engine("coloured")
    rng = np.random.default_rng(5)
    x0 = mpm.state()["x"]
    rebuilt = []
    for shift in (0.1, 0.5, 1.5, 0.2, 3.0):
        state = mpm.state()
        state["x"] = np.clip(x0 + rng.uniform(-shift, shift, x0.shape) * DX, 0.0, 1.0)
        mpm.set_state(state)
        before = mpm.block_of.to_numpy()[: mpm.n_particles].copy()
        mpm.bin_particles(mpm.slot, 0, mpm.n_particles)
        listed = mpm.block_of.to_numpy()[: mpm.n_particles]
        rebuilt.append(not np.array_equal(before, listed))
        base = np.clip((state["x"] / DX - 0.5).astype(int), 0, CELLS + 1 - 3)
        corner = np.stack(np.unravel_index(listed, mpm.bin_blocks), axis=-1) * BLOCK
        assert np.all((base >= corner - DRIFT) & (base < corner + BLOCK + DRIFT)), shift
        order, start, count = mpm.bin_order.to_numpy(), mpm.block_start.to_numpy(), mpm.block_count.to_numpy()
        for blk in np.unique(listed):
            members = order[start[blk] : start[blk] + count[blk]]
            assert np.array_equal(members, np.flatnonzero(listed == blk)), blk
    # first lists; kept through moves within a cell of where they were made; rebuilt after larger ones
    assert rebuilt[:3] == [True, False, True] and rebuilt[4], rebuilt


def test_the_scatters_agree_forward_and_backward_and_the_coloured_one_repeats_bit_for_bit():
    """Three substeps and their adjoint (a random seed on every key) by each scatter: the same to round-off
    (relative 1e-11); the coloured scatter run twice gives the same bits."""
    results = {}
    for scatter in ("serial", "coloured", "atomic", "coloured"):
        mpm = engine(scatter, dim=2, n=4000, grad_substeps=3)
        out, record = mpm.step({"dt": 1e-4, "substeps": 3})
        seed_rng = np.random.default_rng(11)
        seed = {k: seed_rng.normal(size=v.shape) for k, v in out["state"].items()}
        grads = mpm.vjp(record, {"state": seed})
        arrays = [out["state"][k] for k in STATE_KEYS] + [grads["state"][k] for k in STATE_KEYS] + [grads["E"]]
        if scatter in results:
            assert all(np.array_equal(a, b) for a, b in zip(arrays, results[scatter], strict=True)), scatter
        results[scatter] = arrays
    for scatter in ("coloured", "atomic"):
        for got, want in zip(results[scatter], results["serial"], strict=True):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-11 * np.abs(want).max())


def test_a_recompute_with_the_coloured_scatter_repeats_the_forward_bit_for_bit():
    """Block lists are made afresh where each macro step begins, so a step's sums follow from its start
    state alone: replaying three recorded steps after a backward pass (which listed the particles at
    other positions) gives the forward's states bit for bit."""
    mpm = engine("coloured", grad_substeps=3)
    state = mpm.state()
    state["v"] *= 20.0  # up to about half a cell a substep: the lists are remade within steps
    mpm.set_state(state)
    records, after = [], []
    for _ in range(3):
        out, record = mpm.step({"dt": 1e-3, "substeps": 3})
        records.append(record)
        after.append({k: np.array(out["state"][k]) for k in STATE_KEYS})
    mpm.vjp(records[-1], {"state": {k: np.ones_like(v) for k, v in after[-1].items()}})
    replayed = mpm.replay(records[0].state, records)
    for want, got in zip(after, replayed, strict=True):
        assert all(np.array_equal(want[k], got[k]) for k in STATE_KEYS)


def test_a_scene_with_grid_contact_runs_the_same_with_the_coloured_scatter():
    """shake_container_2d (grid contact, whose hook widens the box by a margin) with the coloured scatter
    follows the serial run to round-off over 12 macro steps."""
    states = {}
    for scatter in ("serial", "coloured"):
        scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 12},
                           [f"mpm.scatter={scatter}"])  # fmt: skip
        sim = build_system(scene)
        assert sim.mpm.scatter == scatter
        for _ in range(12):
            sim.step()
        states[scatter] = sim.mpm.state()
    for key in STATE_KEYS:
        want = states["serial"][key]
        np.testing.assert_allclose(states["coloured"][key], want, rtol=0, atol=1e-10 * max(np.abs(want).max(), 1.0))


def test_a_gradient_through_grid_contact_is_the_same_with_every_scatter(monkeypatch):
    """shake_container_2d's gradient (the grid contact hook sits between the grid and G2P, so the G2P adjoint
    scatters onto the hook's gathered adjoint and hands it over) over 2 macro steps: the initial state's
    adjoint with the coloured and the atomic scatter, and with a GPU's loops (``COSIM_ARCH_CHOICES=gpu``:
    atomic, whole-grid passes, the particles' adjoint loops over every slot), is the serial one's to
    round-off. A hand-over left out, done before the scatter or twice, or a grid adjoint not zeroed,
    would change it at every node."""
    from cosim.adjoint.tape import Tape

    grads = {}
    for scatter in ("serial", "coloured", "atomic", "gpu"):
        if scatter == "gpu":
            monkeypatch.setenv("COSIM_ARCH_CHOICES", "gpu")
        scene = load_scene(SCENES / "shake_container_2d.yaml", {"precision": "float64", "steps": 2},
                           [f"mpm.scatter={'atomic' if scatter == 'gpu' else scatter}", "time.substeps=4"])  # fmt: skip
        sim = build_system(scene, requires_grad=True)
        assert sim.mpm.constant_loop_bounds == (scatter == "gpu")
        start = sim.state()
        tape = Tape()
        sim.rollout(tape=tape)
        rng = np.random.default_rng(3)
        seed = {engine: {k: rng.normal(size=v.shape) for k, v in s.items()} for engine, s in start.items()}
        grads[scatter] = tape.backward(sim.vjp, seed).state0["mpm"]
    for scatter in ("coloured", "atomic", "gpu"):
        for key in STATE_KEYS:
            want = grads["serial"][key]
            np.testing.assert_allclose(grads[scatter][key], want, rtol=0, atol=1e-9 * np.abs(want).max(), err_msg=key)


THREADS_RUN = """
import hashlib, sys
import numpy as np
sys.path.insert(0, {tests!r})
from cosim.runtime import ensure_taichi
ensure_taichi("cpu", "float64")
from cosim.engines.arch import running_threads
from test_scatter import engine
mpm = engine("coloured", dim=2, n=4000, grad_substeps=3)
out, record = mpm.step({{"dt": 1e-4, "substeps": 3}})
seed = {{k: np.ones_like(v) for k, v in out["state"].items()}}
grads = mpm.vjp(record, {{"state": seed}})["state"]
digest = hashlib.sha256()
for k in sorted(out["state"]):
    digest.update(out["state"][k].tobytes())
    digest.update(grads[k].tobytes())
print(running_threads(), digest.hexdigest())
"""


def test_the_coloured_scatter_gives_the_same_bits_on_one_thread_and_on_two():
    """The block lists and each block's sums do not depend on which thread ran what: forward and
    adjoint hash the same with Taichi on 1 and on 2 threads."""
    script = THREADS_RUN.format(tests=str(ROOT / "tests"))
    threads, lines = (1, 2), []
    for n in threads:
        env = dict(os.environ, COSIM_CPU_THREADS=str(n))
        run = subprocess.run(
            [sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=ROOT, check=False
        )
        assert run.returncode == 0, run.stderr[-2000:]
        lines.append(run.stdout.strip().splitlines()[-1].split())
    assert [int(t) for t, _ in lines] == list(threads)  # each ran on the threads asked for
    assert lines[0][1] == lines[1][1]
