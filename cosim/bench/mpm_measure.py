"""One `cosim bench mpm` configuration, measured in this process: run by path, ``python mpm_measure.py JSON``.

The file is run by path, not imported from the ``cosim`` it measures, so that a baseline
interpreter (``cosim bench mpm --baseline DIR``) measures its own ``cosim`` with this same
code: it imports only the standard library, numpy and ``cosim.runtime`` / ``cosim.engines.mpm``,
and adapts to both engine APIs it knows:

- the engine contract (``advance(dt, n)``; ``step(inputs) -> (outputs, record)``;
  ``vjp(record, {"state": g})``), the current one;
- the older API of commit b24c315 (``step(dt, n) -> StepInfo``; a record dict holding the state
  before the step, dt, substeps, impulse and the step's token; ``vjp(record, g)``).

The scene: an elastic block (E = 1e4 Pa, nu = 0.3, 1000 kg/m^3) of ``side``^dim particles
sampled at 2 per axis per cell (8 per cell in 3D, 4 in 2D), centred in a unit box of ``cells``
cells per axis and 0.1 m below its centre, falling under gravity, dt = 1e-4 s. Prints one JSON
line: rates in M particle-substeps/s (from the median macro step), memory in MiB and bytes per
particle, times in s, and which ``cosim`` ran. Optional keys: ``arch`` ("cpu" or "cuda"), ``scatter``
(an ``MPMConfig.scatter``; only the current API has it), ``threads`` (Taichi's CPU threads: set by the
parent through ``COSIM_CPU_THREADS``, read back here). On a GPU the process's RSS is not the device's
memory: ``field_MiB`` (the engines' Taichi fields, adjoints included, from ``cosim.adjoint.memory``
where the cosim has it) and ``device_MiB`` (``nvidia-smi``'s used memory after the runs) say it. With ``"profile": true`` (and Taichi's kernel profiler on, see
``cosim.runtime``) it also returns ms per substep of each kernel, forward and backward.
"""

import json
import resource
import statistics
import sys
import time
from pathlib import Path

DT = 1e-4  # [s] substep


def block_points(dim: int, cells: int, side: int):
    """(side^dim, dim) particle positions [m]: a cube at spacing dx/2 centred in the unit box, 0.1 m low."""
    import numpy as np

    h = 0.5 / cells
    axis = 0.5 - 0.5 * side * h + h * np.arange(side)
    pts = np.stack(np.meshgrid(*([axis] * dim), indexing="ij"), -1).reshape(-1, dim)
    pts[:, 1] -= 0.1
    return pts


def _peak_mib() -> float:
    """This process's peak resident memory so far [MiB] (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _engine(dim: int, cells: int, pts, substeps: int | None, scatter: str | None = None):
    """An MPM engine over the block; with gradients (``substeps`` per macro step) unless None."""
    import numpy as np

    from cosim.engines.mpm import MPMConfig, MPMEngine, ParticleBody

    dx = 1.0 / cells
    body = ParticleBody("block", "elastic", 1e4, 0.3, 1000.0, (0.5 * dx) ** dim, pts, np.zeros_like(pts))
    gravity = (0.0, -9.81) + (0.0,) * (dim - 2)
    grad = {} if substeps is None else {"requires_grad": True, "grad_substeps": substeps}
    if scatter is not None:
        grad["scatter"] = scatter
    return MPMEngine(MPMConfig(dim, (cells,) * dim, dx, gravity, **grad), [body])


# ------------------------------------------------------------ the two engine APIs
def _start_taichi(precision: str, arch: str) -> None:
    """Taichi for a run with gradients (newer versions start float32 gradient runs optimised)."""
    import inspect

    from cosim.runtime import ensure_taichi

    grad = {"gradients": True} if "gradients" in inspect.signature(ensure_taichi).parameters else {}
    ensure_taichi(arch, precision, **grad)


def _threads() -> int:
    """Taichi's CPU threads."""
    from taichi.lang import impl

    return int(impl.current_cfg().cpu_max_num_threads)


def _field_mib(engine) -> float:
    """The engine's Taichi fields with their adjoints [MiB], or NaN where the cosim cannot count them."""
    try:
        from cosim.adjoint.memory import taichi_field_bytes
    except ImportError:
        return float("nan")
    return taichi_field_bytes([engine]) / 2**20


def _device_mib(arch: str) -> float:
    """Memory used on the GPU [MiB] (``nvidia-smi``), NaN on a CPU or without the tool."""
    import shutil
    import subprocess

    if arch == "cpu" or shutil.which("nvidia-smi") is None:
        return float("nan")
    query = ["nvidia-smi", "--query-gpu=memory.used", "--format=csv,noheader,nounits"]
    res = subprocess.run(query, capture_output=True, text=True, check=False)
    return float(res.stdout.split()[0]) if res.returncode == 0 and res.stdout.strip() else float("nan")


def _contract(engine) -> bool:
    """True for the engine contract, False for b24c315's API (no ``advance`` there)."""
    return hasattr(engine, "advance")


def _forward(engine, substeps: int) -> None:
    """``substeps`` substeps without a record."""
    (engine.advance if _contract(engine) else engine.step)(DT, substeps)


def _record(engine, substeps: int):
    """One recorded macro step; returns its record."""
    if _contract(engine):
        return engine.step({"dt": DT, "substeps": substeps})[1]
    rec = {"state": engine.state(), "dt": DT, "substeps": substeps, "impulse": None}
    rec["token"] = engine.step(DT, substeps).token
    return rec


def _vjp(engine, rec, g: dict) -> dict:
    """The adjoint of the state before ``rec``'s step, given that of the state after it."""
    if _contract(engine):
        return engine.vjp(rec, {"state": g})["state"]
    return engine.vjp(rec, g)["state"]


def _forget(rec):
    """The record with its token cleared, so that ``vjp`` recomputes its substeps."""
    if isinstance(rec, dict):
        return dict(rec, token=-1)
    rec.token = -1
    return rec


# ------------------------------------------------------------ kernel profile
def _profile_start(profile: bool) -> None:
    if profile:
        import taichi as ti

        ti.profiler.clear_kernel_profiler_info()


def _profile_read(profile: bool, substeps: int) -> list:
    """[kernel, ms per substep, launches per substep], most time first, since ``_profile_start``."""
    if not profile:
        return []
    import taichi as ti

    ti.sync()
    prof = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    prof.get_total_time()  # collects the records into _statistical_results
    stats = prof._statistical_results.values()  # Taichi 1.7 has no public per-kernel list
    rows = [[s.name, s.total_time / substeps, s.counter / substeps] for s in stats]
    return sorted(rows, key=lambda r: -r[1])


# ------------------------------------------------------------ measurements
def _timed(fn) -> float:
    """Seconds ``fn()`` takes, its kernels finished (Taichi's CPU launches are synchronous; ti.sync for a GPU)."""
    import taichi as ti

    t = time.perf_counter()
    fn()
    ti.sync()
    return time.perf_counter() - t


def _time_forward(engine, substeps: int, macro_steps: int, profile: bool) -> tuple[float, float, list]:
    """(compile s, median s of a macro step, kernel profile) of ``macro_steps`` x ``substeps`` substeps.
    The median of the macro steps, not their mean: a shared machine's bursts of load hit a few steps of a
    run, and would move a whole short run's mean."""
    compile_s = _timed(lambda: (_forward(engine, 1), engine.state()))
    _profile_start(profile)
    step_s = [_timed(lambda: _forward(engine, substeps)) for _ in range(macro_steps)]
    return compile_s, statistics.median(step_s), _profile_read(profile, substeps * macro_steps)


def _time_gradient(engine, substeps: int, macro_steps: int, profile: bool) -> tuple[float, float, float, list]:
    """(compile s, median s of a recorded macro step, median s of a macro step's backward with its
    checkpoint recompute, backward kernel profile) of a seeded rollout. The last step's backward, which
    needs no recompute, is left out of the median when there are more."""
    import numpy as np
    import taichi as ti

    zero = {k: np.zeros_like(v) for k, v in engine.state().items()}
    seed = dict(zero, x=np.ones_like(zero["x"]))
    t = time.perf_counter()
    rec0 = _record(engine, substeps)
    _vjp(engine, _forget(rec0), seed)  # compiles the recompute path too
    compile_s = time.perf_counter() - t
    records, tape_s = [], []
    for _ in range(macro_steps):
        tape_s.append(_timed(lambda: records.append(_record(engine, substeps))))
    _profile_start(profile)
    g, bwd_s = seed, []
    for rec in reversed(records):
        t = time.perf_counter()
        g = _vjp(engine, rec, g)  # the adjoint may stay on the device (``DeviceState``): wait for it
        ti.sync()
        bwd_s.append(time.perf_counter() - t)
    recomputed = bwd_s[1:] or bwd_s
    return (
        compile_s,
        statistics.median(tape_s),
        statistics.median(recomputed),
        _profile_read(profile, substeps * macro_steps),
    )


def measure(
    dim: int,
    cells: int,
    side: int,
    precision: str,
    substeps: int,
    macro_steps: int,
    profile: bool = False,
    arch: str = "cpu",
    scatter: str | None = None,
) -> dict:
    """One configuration: forward alone, then a recorded forward and its backward (see the module docstring)."""
    import cosim

    _start_taichi(precision, arch)
    base = _peak_mib()
    pts = block_points(dim, cells, side)
    n = len(pts)
    forward = _engine(dim, cells, pts, None, scatter)
    c_fwd, fwd_s, prof_fwd = _time_forward(forward, substeps, macro_steps, profile)
    fwd_peak = _peak_mib()
    gradient = _engine(dim, cells, pts, substeps, scatter)
    c_grad, tape_s, bwd_s, prof_bwd = _time_gradient(gradient, substeps, macro_steps, profile)
    row = result_row(
        dim, precision, cells, n, substeps, macro_steps, arch, (fwd_s, tape_s, bwd_s), (base, fwd_peak, _peak_mib())
    )
    return row | {
        "threads": _threads() if arch == "cpu" else 0,
        "scatter": getattr(gradient, "scatter", "serial" if arch == "cpu" else "atomic"),
        "field_MiB": _field_mib(forward) + _field_mib(gradient),
        "compile_s": c_fwd + c_grad,
        "package": str(Path(cosim.__file__).parent),
        **({"profile": {"forward": prof_fwd, "backward": prof_bwd}} if profile else {}),
    }


def result_row(
    dim: int, precision: str, cells: int, n: int, substeps: int, macro_steps: int, arch: str,
    times: tuple[float, float, float], peaks: tuple[float, float, float],
) -> dict:  # fmt: skip
    """The row's configuration, rates and memory from the median seconds of a macro step (forward alone,
    recorded forward, backward) and the process's peak MiB (at the start, after the forward, at the end)."""
    fwd_s, tape_s, bwd_s = times
    base, fwd_peak, peak = peaks
    work = n * substeps  # per macro step: the times are medians of a macro step
    return {
        "dim": dim,
        "precision": precision,
        "grid": f"{cells}^{dim}",
        "particles": n,
        "steps": f"{substeps}x{macro_steps}",
        "arch": arch,
        "fwd_Mpss": work / fwd_s / 1e6,
        "fwd_bwd_Mpss": work / (tape_s + bwd_s) / 1e6,
        "bwd_fwd_ratio": bwd_s / tape_s,
        "fb_over_fwd": (tape_s + bwd_s) / fwd_s,
        "peak_MiB": peak,
        "fwd_B_per_particle": (fwd_peak - base) * 2**20 / n,
        "grad_B_per_particle": (peak - fwd_peak) * 2**20 / n,
        "device_MiB": _device_mib(arch),
    }


if __name__ == "__main__":
    # Run by path, Python puts this file's folder first on sys.path; take it off so that none of
    # its modules (mpm.py, contact.py, ...) can shadow a top-level one.
    here = str(Path(__file__).resolve().parent)
    sys.path[:] = [p for p in sys.path if str(Path(p or ".").resolve()) != here]
    print(json.dumps(measure(**json.loads(sys.argv[1]))))
