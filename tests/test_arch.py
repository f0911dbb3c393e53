"""What depends on the arch is chosen in one place, and is right without a GPU to try it on."""

import shutil

import numpy as np
import pytest
from conftest import run_cli

from cosim.engines.arch import choices_for, running_arch
from cosim.errors import InputError
from cosim.runtime import init_options


def test_scatters_are_serial_on_a_cpu_and_atomic_on_a_gpu():
    assert choices_for("cpu").serial_scatter and choices_for("x64").serial_scatter
    assert not choices_for("cuda").serial_scatter  # one thread of thousands would crawl
    assert not choices_for("vulkan").serial_scatter


def test_an_engine_takes_its_scatter_from_the_running_arch_unless_told():
    from cosim.engines.mpm import MPMConfig, MPMEngine, ParticleBody

    pts = np.full((4, 2), 0.5)
    body = ParticleBody("cube", "elastic", 1e4, 0.3, 1000.0, 1e-4, pts, np.zeros_like(pts))
    assert running_arch() == "x64"
    assert MPMEngine(MPMConfig(2, (16, 16), 1 / 16, (0.0, -9.8)), [body])._serial  # the session's CPU
    assert not MPMEngine(MPMConfig(2, (16, 16), 1 / 16, (0.0, -9.8), serial_p2g=False), [body])._serial


def test_thread_cap_and_kernel_cache_are_settings(monkeypatch, tmp_path):
    monkeypatch.setenv("COSIM_CPU_THREADS", "1")
    monkeypatch.setenv("COSIM_TAICHI_CACHE", str(tmp_path))
    assert init_options("cpu") == {"cpu_max_num_threads": 1, "offline_cache_file_path": str(tmp_path)}
    assert init_options("cuda") == {"offline_cache_file_path": str(tmp_path)}  # a CPU cap means nothing there
    monkeypatch.setenv("COSIM_CPU_THREADS", "two")
    with pytest.raises(InputError, match="COSIM_CPU_THREADS"):
        init_options("cpu")


@pytest.mark.skipif(shutil.which("nvidia-smi") is not None, reason="this machine may have a CUDA GPU")
def test_cuda_without_a_gpu_is_a_clear_error():
    result = run_cli("run", "scenes/elastic_bounce_2d.yaml", "--arch", "cuda", "--steps", "1", "--no-preview")
    assert result.returncode == 2, result.stderr[-2000:]
    assert "arch: cuda" in result.stderr and "arch: cpu" in result.stderr and "Traceback" not in result.stderr
