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
    assert first > 20  # the engine, the forecast contact and the ring's boundary were compiled and cached
    assert kernels_after_run(cache, 0.16) == first
    assert kernels_after_run(cache, 0.125) > first + 20
