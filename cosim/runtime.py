"""Taichi start-up, once per process, with the scene's architecture and precision.

Taichi can be initialised only once at a time; a scene asking for another
precision or architecture re-initialises it, which invalidates every Taichi
field made before. One process therefore runs one configuration at a time,
and tests group themselves by precision.

Kernel optimisation: Taichi's advanced IR optimisation is off unless asked for: it makes
compiles several times longer (a 3D adjoint most) for kernels that run only somewhat
faster. Runs that are long enough to win it back, and every
benchmark, turn it on: ``optimize_kernels(True)``, ``cosim run --optimize-kernels`` or the
environment variable ``COSIM_OPTIMIZE_KERNELS=1``.

Threads: Taichi's CPU backend uses every core unless ``COSIM_CPU_THREADS`` caps it (set by
the scale-out workers, ``cosim.scale``, so that W workers on C cores do not run W x C threads).
Kernel cache: Taichi keeps compiled kernels in its offline cache (``~/.cache/taichi`` by
default, capped here at 1 GiB instead of Taichi's 100 MB unless ``TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES``
says otherwise); ``COSIM_TAICHI_CACHE=DIR`` puts it elsewhere (a shared disk on a cluster, a scratch
folder in CI); processes sharing it take turns at its lock, and a lock left by a killed process is
cleared (``cosim.kernel_cache``). Kernel profile: ``COSIM_KERNEL_PROFILER=1`` turns on Taichi's kernel profiler (each
launch timed; ``ti.profiler.print_kernel_profiler_info()``), used by ``cosim bench mpm --profile``.
These options are chosen by arch in ``init_options``; what the engines choose by
arch is in ``cosim.engines.arch``.

Gradients in float32 always compile with advanced optimisation: without it Taichi 1.7.4's
reverse mode returns wrong adjoints in float32 (zero or NaN through ``ti.max``, ``ti.min``,
``ti.select`` and branches: measured on one-line kernels, float64 and the optimised build
are right), which made every dL/dF of a plastic body NaN.

``arch: cuda`` on a machine without a CUDA GPU is an error (Taichi would fall back to the CPU
with a warning, and a run meant for a GPU would crawl without saying why).
"""

from __future__ import annotations

import os

from cosim.errors import InputError

_current: tuple[str, str, bool] | None = None
# Taichi trims its kernel cache to 100 MB by default, least recently used first; the project's kernels
# (one test-suite run: 113 MB) outgrow that, and a trimmed 3D adjoint then compiles again
KERNEL_CACHE_BYTES = 2**30
_optimize = os.environ.get("COSIM_OPTIMIZE_KERNELS", "") == "1"


def optimize_kernels(enabled: bool = True) -> None:
    """Compile the kernels of the next Taichi start-up with (True) or without advanced optimisation
    (see the module docstring); a running Taichi re-initialises at the next ``ensure_taichi``.
    Child processes inherit the choice (the benchmarks run each configuration in its own process;
    before, theirs compiled without it)."""
    global _optimize
    _optimize = bool(enabled)
    os.environ["COSIM_OPTIMIZE_KERNELS"] = "1" if _optimize else ""


def kernels_optimized() -> bool:
    """Whether the next Taichi start-up compiles with advanced optimisation."""
    return _optimize


def taichi_precision(precision: str):
    import taichi as ti

    return {"float32": ti.f32, "float64": ti.f64}[precision]


def ensure_taichi(arch: str = "cpu", precision: str = "float64", gradients: bool = False) -> None:
    """Initialise Taichi for ``arch`` ('cpu' or 'cuda') and ``precision``; ``gradients`` in float32
    needs advanced optimisation (module docstring).

    A no-op when Taichi already runs with the same settings (or with optimisation where none is
    needed). An ``InputError`` when the arch is a GPU's and Taichi finds none (it would fall back to
    the CPU).
    """
    global _current
    optimize = _optimize or (gradients and precision == "float32")
    if _current is not None and _current[:2] == (arch, precision) and _current[2] >= optimize:
        return  # an optimised start-up serves a request without: re-initialising would drop every field
    key = (arch, precision, optimize)
    import taichi as ti

    from cosim import kernel_cache
    from cosim.engines import field_pool
    from cosim.engines.taichi_frontend import memoise_front_end

    memoise_front_end()  # Taichi's own kernels (from_numpy, fill, ...) compile through it too
    if _current is not None:
        field_pool.clear()  # ti.reset frees every field
        kernel_cache.finish()  # ti.reset, Taichi writing its kernel cache in a window of its own
        _current = None
    arch_obj = {"cpu": ti.cpu, "cuda": ti.cuda, "gpu": ti.gpu}[arch]
    debug = os.environ.get("COSIM_TAICHI_DEBUG", "") == "1"
    ti.init(
        arch=arch_obj,
        default_fp=taichi_precision(precision),
        default_ip=ti.i32,
        debug=debug,
        log_level=ti.WARN,
        random_seed=0,
        advanced_optimization=optimize,
        **init_options(arch),
    )
    from cosim.engines.arch import CPU_ARCHES, running_arch

    if arch not in CPU_ARCHES and running_arch() in CPU_ARCHES:
        field_pool.clear()
        ti.reset()
        _current = None
        raise InputError(
            f"arch: {arch}: Taichi found no usable {arch} GPU on this machine and would run on the CPU; "
            "set arch: cpu (scene key, or --arch cpu), or run where an NVIDIA GPU and its driver are installed"
        )
    kernel_cache.start()  # the cache index loaded in a window, a stale lock cleared first
    _current = key


def init_options(arch: str) -> dict:
    """The ``ti.init`` options that depend on the arch and the environment (see the module docstring):
    ``cpu_max_num_threads`` from ``COSIM_CPU_THREADS`` on a CPU, ``offline_cache_file_path`` from
    ``COSIM_TAICHI_CACHE``, ``kernel_profiler`` from ``COSIM_KERNEL_PROFILER=1``, and the cache's
    size cap (``KERNEL_CACHE_BYTES``); a bad ``COSIM_ARCH_CHOICES`` is named here too, before anything starts."""
    from cosim.engines.arch import CPU_ARCHES, gpu_choices_asked

    gpu_choices_asked()  # a bad COSIM_ARCH_CHOICES named before anything starts
    options = {}
    threads = os.environ.get("COSIM_CPU_THREADS", "")
    if threads and (not threads.isdigit() or int(threads) == 0):
        raise InputError(f"COSIM_CPU_THREADS={threads!r}: give a whole number of threads, at least 1, or unset it")
    if threads and arch in CPU_ARCHES:
        options["cpu_max_num_threads"] = int(threads)
    cache = os.environ.get("COSIM_TAICHI_CACHE", "")
    if cache:
        options["offline_cache_file_path"] = cache
    if "TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES" not in os.environ:  # Taichi's own variable wins
        options["offline_cache_max_size_of_files"] = KERNEL_CACHE_BYTES
    if os.environ.get("COSIM_KERNEL_PROFILER", "") == "1":
        options["kernel_profiler"] = True
    return options


def current() -> tuple[str, str] | None:
    """The (arch, precision) Taichi runs with, or None before start-up."""
    return None if _current is None else _current[:2]
