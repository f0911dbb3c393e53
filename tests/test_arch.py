"""What depends on the arch is chosen in one place, and is right without a GPU to try it on."""

import shutil

import numpy as np
import pytest
from conftest import run_cli

from cosim.engines.arch import choices_for, running_arch
from cosim.errors import InputError
from cosim.runtime import init_options


def test_scatters_are_serial_on_a_few_cpu_threads_coloured_on_more_and_atomic_on_a_gpu():
    assert choices_for("cpu").scatter == choices_for("x64", 2).scatter == "serial"
    assert choices_for("cpu", 4).scatter == choices_for("arm64", 16).scatter == "coloured"
    assert (
        choices_for("cuda").scatter == choices_for("vulkan").scatter == "atomic"
    )  # one thread of thousands would crawl


def test_an_engine_takes_its_scatter_from_the_running_arch_unless_told():
    from cosim.engines.mpm import MPMConfig, MPMEngine, ParticleBody

    pts = np.full((4, 2), 0.5)
    body = ParticleBody("cube", "elastic", 1e4, 0.3, 1000.0, 1e-4, pts, np.zeros_like(pts))
    assert running_arch() == "x64"
    assert MPMEngine(MPMConfig(2, (16, 16), 1 / 16, (0.0, -9.8)), [body]).scatter == "serial"  # few particles
    told = MPMEngine(MPMConfig(2, (16, 16), 1 / 16, (0.0, -9.8), scatter="atomic"), [body])
    assert told.scatter == "atomic"
    with pytest.raises(ValueError, match="scatter: 'parallel' is none of serial, coloured, atomic"):
        MPMEngine(MPMConfig(2, (16, 16), 1 / 16, (0.0, -9.8), scatter="parallel"), [body])


def test_thread_cap_and_kernel_cache_are_settings(monkeypatch, tmp_path):
    monkeypatch.setenv("COSIM_CPU_THREADS", "1")
    monkeypatch.setenv("COSIM_TAICHI_CACHE", str(tmp_path))
    monkeypatch.setenv("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES", "1000")  # Taichi's own variable: no cap from us
    assert init_options("cpu") == {"cpu_max_num_threads": 1, "offline_cache_file_path": str(tmp_path)}
    assert init_options("cuda") == {"offline_cache_file_path": str(tmp_path)}  # a CPU cap means nothing there
    monkeypatch.delenv("TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES")
    assert init_options("cuda")["offline_cache_max_size_of_files"] >= 2**30  # the suite's kernels outgrow 100 MB
    monkeypatch.setenv("COSIM_CPU_THREADS", "two")
    with pytest.raises(InputError, match="COSIM_CPU_THREADS"):
        init_options("cpu")
    monkeypatch.setenv("COSIM_CPU_THREADS", "1")
    monkeypatch.setenv("COSIM_ARCH_CHOICES", "cuda")  # only "gpu" (a GPU's loop choices) means something
    with pytest.raises(InputError, match="COSIM_ARCH_CHOICES='cuda': set it to gpu"):
        init_options("cpu")


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="this machine may have a CUDA GPU")
def test_cuda_without_a_gpu_is_a_clear_error():
    result = run_cli("run", "scenes/elastic_bounce_2d.yaml", "--arch", "cuda", "--steps", "1", "--no-preview")
    assert result.returncode == 2, result.stderr[-2000:]
    assert "arch: cuda" in result.stderr and "arch: cpu" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="this machine may have a CUDA GPU")
def test_the_gpu_benchmarks_without_a_gpu_are_a_clear_error(tmp_path):
    for what in ("mpm", "contact"):
        result = run_cli("bench", what, "--arch", "cuda", "--quick", "--out", str(tmp_path))
        assert result.returncode == 2, result.stderr[-2000:]
        assert "arch: cuda" in result.stderr and "Traceback" not in result.stderr


FLOAT32_ADJOINT = """
import numpy as np
import taichi as ti
from cosim.runtime import ensure_taichi

ensure_taichi("cpu", "float32", gradients=True)
F = ti.Matrix.field(2, 2, float, shape=1, needs_grad=True)
out = ti.Matrix.field(2, 2, float, shape=1, needs_grad=True)


@ti.kernel
def clamped():
    for p in range(1):
        Fp = F[p]  # through a local copy, as the material kernels do
        out[p] = Fp * ti.max(Fp[0, 0], 0.5)


F.from_numpy(np.eye(2, dtype=np.float32)[None] * 1.1)
clamped()
out.grad.fill(1.0)
clamped.grad()
print(*F.grad.to_numpy().ravel())
"""


def test_float32_gradients_get_a_taichi_whose_adjoints_are_right(tmp_path):
    """Taichi 1.7.4's unoptimised float32 reverse mode gives d/dF sum(F max(F00, 0.5)) = 0 (it made every
    dL/dF of a plastic body NaN); a float32 gradient start-up must get the right 3.3, 1.1, 1.1, 1.1."""
    import subprocess
    import sys

    script = tmp_path / "adjoint.py"
    script.write_text(FLOAT32_ADJOINT)
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, check=True)
    grad = [float(v) for v in res.stdout.split()[-4:]]
    assert grad == pytest.approx([3.3, 1.1, 1.1, 1.1], rel=1e-6), res.stdout


def test_short_loops_run_on_one_thread_and_give_the_parallel_results(monkeypatch):
    """A tiny scene's particle and grid loops are serial on a CPU (a thread-pool dispatch costs more than
    their work); forced parallel, the same scene gives the same loss and gradients (float64, atomic adds
    in another order: 1e-9)."""
    from conftest import pushed_block_scene

    from cosim.adjoint.objective import Objective
    from cosim.engines import arch
    from cosim.scene.build import build_system

    scene = pushed_block_scene("forecast")
    serial = Objective(build_system(scene, requires_grad=True))
    assert serial.system.mpm.serial_particle_loops and serial.system.mpm.serial_grid_loops
    monkeypatch.setattr(arch, "PARALLEL_MIN_PARTICLES", 0)
    monkeypatch.setattr(arch, "PARALLEL_MIN_NODES", 0)
    parallel = Objective(build_system(scene, requires_grad=True))
    assert not (parallel.system.mpm.serial_particle_loops or parallel.system.mpm.serial_grid_loops)
    assert not arch.choices_for("cuda").serial_particles(1) and not arch.choices_for("cuda").serial_nodes(1)
    params = serial.initial_params()
    (value_s, grads_s), (value_p, grads_p) = (o.evaluate(params, grad=True) for o in (serial, parallel))
    reactions = serial.system.last.outputs["reactions"]["kinematic"]["impulse"]
    assert np.abs(reactions).sum() > 0  # the plate pushed the block: the contact kernels ran
    assert value_p == pytest.approx(value_s, rel=1e-9)
    for key in grads_s:
        scale = np.abs(grads_s[key]).max()
        assert scale > 0 and np.abs(grads_p[key] - grads_s[key]).max() <= 1e-9 * scale, key
