"""Cloth step cost: forward (Newton) and adjoint milliseconds per step, with where the time goes.

A square 1 m sheet, horizontal (normal y), pinned along one edge, falling under gravity: dt 2e-3 s,
k_stretch 1000 N/m, k_bend 0.015 N m, density 0.2 kg/m^2. Per size: the median forward and adjoint
time per step (JAX compilation excluded by warm-up steps), Newton iterations, and a cProfile split
of the forward steps (element Hessians in JAX, PSD projection, sparse assembly, LU factorisation,
preconditioned conjugate gradients, energies and gradients for the line search). Part of `cosim bench
cloth` (``cosim.bench.cloth``).
"""

from __future__ import annotations

import cProfile
import math
import os
import platform
import pstats
import time

import numpy as np

from cosim.engines.cloth_linear import REFACTOR_AFTER

SPLIT = {  # label -> (file suffix, function name) of the profiled calls
    "hessians_jax_s": ("cloth_energy.py", "hessians"),
    "psd_projection_s": ("cloth_energy.py", "project_psd"),
    "assembly_s": ("cloth_energy.py", "matrix"),
    "factorisation_s": ("_dsolve/linsolve.py", "splu"),
    "conjugate_gradients_s": ("cloth_linear.py", "preconditioned_cg"),
    "energies_s": ("cloth_energy.py", "energies"),
    "gradients_s": ("cloth_energy.py", "gradients"),
}


def _cpu_model() -> str:
    """The CPU model name (as ``lscpu`` reports it), else the machine type."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.machine()


def _sheet(vertices: int, cg_iterations: int):
    from cosim.engines import cloth_mesh
    from cosim.engines.cloth import ClothEngine, ClothMaterial

    n = max(2, round(math.sqrt(vertices)))
    mesh = cloth_mesh.rectangle((1.0, 1.0), (n, n), normal="y")
    edge = np.flatnonzero(np.isclose(mesh.vertices[:, 2], mesh.vertices[:, 2].min()))
    material = ClothMaterial(k_stretch=1000.0, k_bend=0.015, c_mass=0.0, density=0.2)
    return ClothEngine(mesh, material, fixed=edge, frame_dt=2e-3, cg_iterations=cg_iterations)


def _split(profile: cProfile.Profile) -> dict[str, float]:
    stats = pstats.Stats(profile).stats
    out = dict.fromkeys(SPLIT, 0.0)
    for (path, _, name), (_, _, _, cumtime, _) in stats.items():
        for label, (suffix, func) in SPLIT.items():
            if name == func and path.endswith(suffix):
                out[label] += cumtime
    return out


def measure(vertices: int, steps: int = 10, warmup: int = 2, cg_iterations: int = REFACTOR_AFTER) -> dict:
    """One sheet of about ``vertices`` vertices: medians over ``steps`` steps after ``warmup``, with the
    engine's linear solves (``cg_iterations`` 0: a fresh LU for every solve, as before ``cloth_linear``)."""
    engine = _sheet(vertices, cg_iterations)
    for _ in range(warmup):
        engine.step({})
    factorised = engine.factorisations
    forward, iterations, records = [], [], []
    profile = cProfile.Profile()
    for _ in range(steps):
        t = time.perf_counter()
        profile.enable()
        _, record = engine.step({})
        profile.disable()
        forward.append(time.perf_counter() - t)
        iterations.append(record.iterations)
        records.append(record)
    rng = np.random.default_rng(0)
    grad = {"x": rng.standard_normal(engine.x.shape), "v": rng.standard_normal(engine.x.shape)}
    backward = []
    for record in reversed(records):
        t = time.perf_counter()
        grad = engine.vjp(record, {"state": grad})["state"]
        backward.append(time.perf_counter() - t)
    split = {k: v / steps * 1e3 for k, v in _split(profile).items()}
    return {
        "vertices": engine.mesh.n_vertices,
        "faces": len(engine.mesh.faces),
        "hinges": len(engine.mesh.hinges),
        "forward_ms": 1e3 * float(np.median(forward)),
        "newton_iterations": float(np.mean(iterations)),
        "adjoint_ms": 1e3 * float(np.median(backward)),
        "factorisations_per_step": (engine.factorisations - factorised) / steps,
        **{k.replace("_s", "_ms_per_step"): v for k, v in split.items()},
    }


def run_cloth_step_bench(vertices: list[int], steps: int = 10) -> dict:
    """Forward/adjoint cost per step for square sheets of about the given vertex counts, each with the
    engine's linear solves and with a fresh LU for every solve ("direct")."""
    return {
        "hardware": f"{_cpu_model()}, {os.cpu_count()} logical CPUs",
        "settings": "1 m sheet, pinned edge, gravity, dt 2e-3 s, k_stretch 1000 N/m, k_bend 0.015 N m, 0.2 kg/m^2",
        "results": [measure(v, steps=steps) | _direct(measure(v, steps=steps, cg_iterations=0)) for v in vertices],
    }


def _direct(result: dict) -> dict:
    return {f"direct_{key}": result[key] for key in ("forward_ms", "adjoint_ms", "factorisations_per_step")}


if __name__ == "__main__":
    import json
    import sys

    sizes = [int(a) for a in sys.argv[1:]] or [400, 2000, 10000]
    print(json.dumps(run_cloth_step_bench(sizes), indent=1))
