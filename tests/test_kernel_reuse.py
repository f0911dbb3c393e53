"""Compiled kernels serve every particle count of a capacity bucket: a scene run again with another
particle count (same bucket) compiles nothing new, one in another bucket does."""

import itertools
import os
import subprocess
import sys
from pathlib import Path

from conftest import ROOT

from cosim.engines.mpm_inputs import MIN_CAPACITY, particle_capacity


def test_capacity_leaves_at_most_a_quarter_spare_and_grows_with_n():
    counts = range(1, 70_000)
    caps = [particle_capacity(n) for n in counts]
    assert all(n <= c <= max(MIN_CAPACITY, 1.25 * n) for n, c in zip(counts, caps))
    assert all(a <= b for a, b in itertools.pairwise(caps))
    assert len(set(caps)) < 40  # buckets, not one size per count: 256, then 4 per doubling up to 2^16


def kernels_after_run(cache: Path, radius: float) -> int:
    """Cached kernels after a fresh process ran 2 steps of the 2D shaken container (liquid disc of
    ``radius`` [m], forecast contact against the ring) with its kernel cache in ``cache``."""
    args = ["run", "shake_container_2d", "--steps", "2", "--quiet", "--no-preview", "--contact", "forecast"]
    args += ["--set", f"mpm.bodies[0].shape.radius={radius}", "--out", str(cache.parent / f"out_{radius}")]
    code = f"from cosim.cli import main\nassert main({args!r}) == 0\n"
    env = {**os.environ, "COSIM_TAICHI_CACHE": str(cache)}
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    return len(list(cache.glob("*.tic")))


def test_another_particle_count_in_the_bucket_reuses_the_compiled_kernels(tmp_path):
    # discs sampled at dx/2 (dx = 1/64 m): 1,485 and 1,313 particles, both in the 1,536 bucket; 812
    # particles fall in the 896 one (the code before the buckets compiled 30 new kernels for 1,313)
    cache = tmp_path / "kernels"
    first = kernels_after_run(cache, 0.17)
    assert first > 15  # the engine, the forecast contact and the ring's boundary were compiled and cached
    assert kernels_after_run(cache, 0.16) == first
    assert kernels_after_run(cache, 0.125) > first + 15  # the engine and its hooks, for the new bucket


REBUILD = """
import gc, sys
from cosim.runtime import ensure_taichi
ensure_taichi("cpu", "float64")
from cosim.adjoint.objective import Objective
from cosim.scene import load_scene
from cosim.scene.build import build_system
for _ in range(int(sys.argv[1])):
    obj = Objective(build_system(load_scene(sys.argv[2], {"precision": "float64"}), requires_grad=True, steps=2))
    obj.evaluate(obj.initial_params(), grad=True)
    del obj
    gc.collect()
from cosim.engines import field_pool
print(sum(len(fields) * (1 + key[4]) for key, fields in field_pool._free.items()))  # with their adjoints
"""


def kernels_compiled(cache: Path, builds: int, scene: str) -> tuple[int, int]:
    """Kernels in a fresh cache after one process built ``scene`` ``builds`` times over (each build
    dropped before the next) and took a gradient of 2 steps with each; and the fields one build holds,
    an adjoint field counted as one more."""
    env = {**os.environ, "COSIM_TAICHI_CACHE": str(cache)}
    args = [sys.executable, "-c", REBUILD, str(builds), str(ROOT / "scenes" / f"{scene}.yaml")]
    res = subprocess.run(args, capture_output=True, text=True, cwd=ROOT, env=env, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    return len(list(cache.glob("*.tic"))), int(res.stdout.split()[-1])


def test_an_engine_built_again_in_the_process_compiles_nothing_new(tmp_path):
    """The second build of a scene takes the first one's fields (``cosim.engines.field_pool``), so its
    kernels lower to the same IR and come from Taichi's in-process cache: three builds compile what one
    does, plus at most one kernel per field and per adjoint field (the fill that zeroes it when it is first handed on).
    Without the pool every build compiled its own set."""
    once, fields = kernels_compiled(tmp_path / "once", 1, "elastic_bounce_2d")
    assert once > 25  # the MPM forward, its adjoint, the NaN watch with the energy sums
    thrice, _ = kernels_compiled(tmp_path / "thrice", 3, "elastic_bounce_2d")
    assert thrice <= once + fields, (once, fields, thrice)


def test_an_engine_on_reused_fields_gives_bitwise_the_same_gradients():
    """Fields handed on are zeroed as new ones are: a scene built again after a gradient run (its
    fields, adjoints included, left full) gives the first build's loss and gradients bit for bit."""
    import gc

    import numpy as np

    from cosim.adjoint.objective import Objective
    from cosim.engines import field_pool
    from cosim.scene import load_scene
    from cosim.scene.build import build_system

    def loss_and_gradients():
        scene = load_scene(ROOT / "scenes" / "pull_door.yaml", {"precision": "float64"})
        obj = Objective(build_system(scene, requires_grad=True, steps=2))
        x = obj.system.mpm.x
        value, grads = obj.evaluate(obj.initial_params(), grad=True)
        return value, grads, x

    first, first_grads, first_x = loss_and_gradients()
    gc.collect()
    free = {id(fld) for fields in field_pool._free.values() for fld in fields}  # what the pool can hand on
    assert id(first_x) in free  # the first build's fields went back to the pool
    second, second_grads, second_x = loss_and_gradients()
    # handed on, left full by a gradient run: the first build's, or (where an earlier test in this process
    # left more than one of that layout) an older one
    assert id(second_x) in free
    assert second == first
    for key, g in first_grads.items():
        assert np.array_equal(second_grads[key], g), key


def test_a_field_handed_on_is_zeroed_and_keeps_to_its_layout():
    """The next owner of a class gets its predecessor's fields, zeroed with their adjoints, in the same
    order; a live owner's fields and another layout's are never handed out."""
    import gc

    import numpy as np

    from cosim.engines import field_pool

    class Owner:
        def __init__(self, n: int):
            self.a = field_pool.vector(self, 2, float, shape=n, needs_grad=True)
            self.b = field_pool.scalar(self, float, shape=n)

    first = Owner(4)
    first.a.from_numpy(np.ones((4, 2)))
    first.a.grad.from_numpy(np.ones((4, 2)))
    first.b.from_numpy(np.ones(4))
    a, b = first.a, first.b
    alive = Owner(4)  # first is alive: new fields
    assert alive.a is not a and alive.b is not b
    other = Owner(5)  # another layout
    del first
    gc.collect()
    second = Owner(4)
    assert second.a is a and second.b is b
    assert not a.to_numpy().any() and not a.grad.to_numpy().any() and not b.to_numpy().any()
    assert other.a is not a and alive.a is not a
