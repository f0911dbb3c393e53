"""`cosim bench coupling`: what the MPM-DART coupling costs, on pour_water and pull_door.

Per scene, in one process (float64, as gradient runs are), after a warm-up that
compiles every kernel:

- forward: a coupled macro step's wall time, and the part of it spent in the MPM
  engine's step (K substeps, boundary writes, reaction reads), in DART's step and in
  the coupler (boundary states per substep, reaction averaging), from the coupled
  system's timing hooks inside the same run, so all see the same states: coupled /
  MPM and coupled / DART; the remainder is the system's own checks (CFL, NaN,
  domain), which an MPM-only run pays too;
- backward: the adjoint of the rollout (the tape's reverse replay, MPM vjp
  with checkpoint recompute, DART vjp, boundary vjp) against its recorded
  forward: backward / forward.

Each measurement is the median of ``repeat`` runs.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np

SCENES = ["pour_water", "pull_door"]
COLUMNS = [
    "scene",
    "macro_steps",
    "step_ms",
    "mpm_ms",
    "dart_ms",
    "coupler_ms",
    "coupled_vs_mpm",
    "coupled_vs_dart",
    "bwd_fwd",
]


def _forward(scene, steps: int, repeat: int) -> list[dict]:
    """Per repetition: per-step times of the coupled step and its parts, one system reset each time."""
    import taichi as ti

    from cosim.scene.build import build_system

    sim = build_system(scene)
    sim.step()
    sim.step()  # warm-up: compiles
    ti.sync()
    out = []
    for _ in range(repeat):
        sim.reset()
        out.append(_timed_steps(sim, steps))
    return out


def _timed_steps(sim, steps: int) -> dict:
    """The system's own timing hooks split each step into MPM, DART and coupler time."""
    import taichi as ti

    sim.timings = {}
    t = time.perf_counter()
    for _ in range(steps):
        sim.step()
    ti.sync()
    total = time.perf_counter() - t
    parts, sim.timings = sim.timings, None
    return {
        "step": total / steps,
        "mpm": parts["mpm"] / steps,
        "dart": parts["dart"] / steps,
        "coupler": parts["couplers"] / steps,
    }


def _backward(scene, steps: int, repeat: int) -> float:
    """Median backward / recorded forward time of a ``steps``-step rollout. One objective serves
    every repetition: a new one would recompile the 3D adjoint kernels (minutes each)."""
    from cosim.adjoint.objective import Objective
    from cosim.scene.build import build_system

    obj = Objective(build_system(scene, requires_grad=True, steps=steps))
    params = obj.initial_params()
    obj.evaluate(params, grad=True)  # compile
    ratios = []
    for _ in range(repeat):
        t = time.perf_counter()
        final = obj.rollout(params, record=True)
        forward = time.perf_counter() - t
        _, dstate = obj.loss(final)
        t = time.perf_counter()
        obj.tape.backward(obj.system.vjp, dstate, restore=obj.system.restore_checkpoints)
        ratios.append((time.perf_counter() - t) / forward)
    return float(np.median(ratios))


def run_coupling_bench(out_dir: Path, quick: bool = False, repeat: int = 3) -> int:
    from cosim.run import hardware_line
    from cosim.runtime import ensure_taichi
    from cosim.scene import load_scene
    from cosim.scene.shipped import scenes_dir

    ensure_taichi("cpu", "float64")
    out_dir.mkdir(parents=True, exist_ok=True)
    steps, grad_steps = (5, 3) if quick else (40, 10)
    rows = []
    for name in SCENES:
        scene = load_scene(scenes_dir() / f"{name}.yaml", {"precision": "float64"})
        fwd = _forward(scene, steps, repeat)
        med = {k: float(np.median([f[k] for f in fwd])) for k in ("step", "mpm", "dart", "coupler")}
        bwd = _backward(scene, grad_steps, repeat)
        rows.append(
            {
                "scene": name,
                "macro_steps": steps,
                "step_ms": 1e3 * med["step"],
                "mpm_ms": 1e3 * med["mpm"],
                "dart_ms": 1e3 * med["dart"],
                "coupler_ms": 1e3 * med["coupler"],
                "coupled_vs_mpm": med["step"] / med["mpm"],
                "coupled_vs_dart": med["step"] / med["dart"],
                "bwd_fwd": bwd,
            }
        )
        print(f"  {name}: " + ", ".join(f"{k} {v:.4g}" for k, v in rows[-1].items() if k != "scene"), flush=True)
    with open(out_dir / "coupling.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    lines = [
        (
            f"Coupling benchmark on {hardware_line()}; float64; medians of {repeat} runs; forward over {steps} "
            f"macro steps, backward/forward over {grad_steps}"
        ),
        "",
        "| scene | coupled step ms | MPM ms | DART ms | coupler ms | coupled / MPM | coupled / DART | backward / forward |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['step_ms']:.2f} | {r['mpm_ms']:.2f} | {r['dart_ms']:.3f} | {r['coupler_ms']:.2f} | "
            f"{r['coupled_vs_mpm']:.2f} | {r['coupled_vs_dart']:.0f} | {r['bwd_fwd']:.2f} |"
        )
    (out_dir / "coupling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {out_dir}/coupling.csv, coupling.md")
    return 0
