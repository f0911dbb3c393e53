"""`cosim bench coupling`: what the MPM-DART coupling costs, on pour_water and pull_door, and whether
it holds a light body at rest on heavy material across mass ratios (``cosim.bench.mass_ratio``).

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

And what the scene API costs over the bare engine, on `cosim bench mpm`'s elastic
block (E = 1e4 Pa, dt = 1e-4 s, fixed substeps, float32, 2D 128^2 and 3D 64^3; in
a process of its own each, Taichi's precision being per process): the same macro
steps through ``CoupledSystem.step`` (as `cosim run` steps: the NaN / CFL / domain
checks, the conservation check every step, the contract step) and through
``MPMEngine.advance`` alone (without those checks: ``GUARDS_OFF``, which the command,
coupling.md and overhead.csv state), in alternating blocks of 10 continuing one motion
(the order flipped each repeat); the overhead is the median over the pairs of
api / bare - 1, "host ms" the part of a step outside the MPM's contract step.

Each measurement is the median of ``repeat`` runs.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from cosim.guards import ENGINE_ALONE, GuardsOff, announce

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
OVERHEAD_CONFIGS = [
    {"dim": 2, "cells": 128, "side": 141},  # 19,881 particles
    {"dim": 3, "cells": 64, "side": 31},  # 29,791 particles
]
OVERHEAD_COLUMNS = [
    "dim",
    "particles",
    "substeps",
    "macro_steps",
    "api_ms",
    "bare_ms",
    "host_ms",
    "overhead",
    "guards_off",
]
# the overhead's baseline steps the engine alone (``MPMEngine.advance``), without the scene API's checks
GUARDS_OFF = GuardsOff(ENGINE_ALONE, "in the bare-engine steps the scene API's overhead is measured against")


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


def block_scene(dim: int, cells: int, side: int, substeps: int, steps: int):
    """`cosim bench mpm`'s elastic block (side^dim particles at dx / 2, E = 1e4 Pa) as a float32 scene with
    ``substeps`` fixed substeps of 1e-4 s per macro step."""
    from cosim.scene import parse_scene

    data = {
        "name": f"block_{dim}d",
        "dim": dim,
        "precision": "float32",
        "steps": steps,
        "time": {"frame_dt": substeps * 1e-4, "substeps": substeps},
        "mpm": {
            "grid": {"cells": cells},
            "bodies": [
                {
                    "name": "block",
                    "material": {"type": "elastic", "E": 1e4, "nu": 0.3, "density": 1000},
                    "shape": {"type": "box", "center": [0.5] * dim, "size": [side * 0.5 / cells] * dim},
                }
            ],
        },
    }
    return parse_scene(data, Path.cwd())


def measure_overhead(dim: int, cells: int, side: int, substeps: int, steps: int, repeat: int) -> dict:
    """In this process (float32), after a warm-up rollout from step 0 (which starts the conservation check):
    ``repeat`` times, ``steps`` macro steps through the scene API (``CoupledSystem.step``, as `cosim run`
    steps) then ``steps`` through the bare engine, continuing the same motion (a block falling freely,
    whose cost per substep does not change); per-step medians [ms]. Each API step holds a conservation check,
    as every step of a run does; the bare blocks run none of the checks (``GUARDS_OFF``)."""
    import taichi as ti

    from cosim.runtime import ensure_taichi
    from cosim.scene.build import build_system

    ensure_taichi("cpu", "float32")
    sim = build_system(block_scene(dim, cells, side, substeps, steps))
    sim.rollout()  # compiles
    dt = sim.frame_dt / substeps
    api, bare, host = [], [], []

    def api_block():
        sim.timings = {}
        t = time.perf_counter()
        for _ in range(steps):
            sim.step()
        ti.sync()
        api.append((time.perf_counter() - t) / steps)
        host.append(api[-1] - sim.timings["mpm"] / steps)
        sim.timings = None

    def bare_block():
        t = time.perf_counter()
        for _ in range(steps):
            sim.mpm.advance(dt, substeps)
        ti.sync()
        bare.append((time.perf_counter() - t) / steps)

    for i in range(repeat):  # the order flips each repeat, so a drift of the machine's speed cancels
        for block in (api_block, bare_block) if i % 2 == 0 else (bare_block, api_block):
            block()
    a, b = float(np.median(api)), float(np.median(bare))
    return {
        "dim": dim,
        "particles": sim.mpm.n_particles,
        "substeps": substeps,
        "macro_steps": steps,
        "api_ms": 1e3 * a,
        "bare_ms": 1e3 * b,
        "host_ms": 1e3 * float(np.median(host)),
        # the median of each pair's ratio: a pair runs back to back, so it shares the machine's state
        "overhead": float(np.median(np.array(api) / np.array(bare))) - 1.0,
    }


def _overhead_rows(quick: bool, repeat: int) -> list[dict]:
    """``measure_overhead`` per configuration, each in a subprocess (float32)."""
    substeps, steps = (5, 10) if quick else (20, 10)
    rows = []
    for cfg in OVERHEAD_CONFIGS:
        args = json.dumps({**cfg, "substeps": substeps, "steps": steps, "repeat": repeat})
        cmd = [sys.executable, "-m", "cosim.bench.coupling", args]
        res = subprocess.run(cmd, capture_output=True, text=True, check=False)  # a failure raises with its stderr
        if res.returncode != 0:
            raise RuntimeError(f"bench coupling, scene API overhead {cfg}: {res.stderr[-2000:]}")
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(f"  scene API over bare engine, {cfg['dim']}D: {rows[-1]['overhead']:+.1%}", flush=True)
    return rows


def run_coupling_bench(out_dir: Path, quick: bool = False, repeat: int = 3, command: str | None = None) -> int:
    """Both scenes' coupled steps and the scene API's overhead; writes coupling.csv, overhead.csv and coupling.md
    (headed by ``command``, the date and the hardware)."""
    from cosim.bench.report import bench_command, report_header
    from cosim.runtime import ensure_taichi
    from cosim.scene import load_scene
    from cosim.scene.shipped import scenes_dir

    announce(GUARDS_OFF)
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
            f"Coupling benchmark: float64; medians of {repeat} runs; forward over {steps} "
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
    overhead = _overhead_rows(quick, repeat)
    with open(out_dir / "overhead.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=OVERHEAD_COLUMNS)
        writer.writeheader()
        writer.writerows(r | {"guards_off": f"bare_ms: {GUARDS_OFF.column()}"} for r in overhead)
    lines += [
        "",
        f"Scene API over the bare MPM engine (elastic block, float32, medians of {repeat} alternating runs)",
        "",
        "| dim | particles | substeps x macro steps | API ms/step | bare ms/step | host ms/step | overhead |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in overhead:
        lines.append(
            f"| {r['dim']} | {r['particles']} | {r['substeps']} x {r['macro_steps']} | {r['api_ms']:.1f} | "
            f"{r['bare_ms']:.1f} | {r['host_ms']:.2f} | {r['overhead']:+.1%} |"
        )
    from cosim.bench.mass_ratio_report import substep_sweep, sweep, write

    lines += ["", *write(sweep(quick), substep_sweep(quick), out_dir)]
    header = report_header(command or bench_command("coupling"), guards_off=GUARDS_OFF)
    (out_dir / "coupling.md").write_text(header + "\n".join(lines) + "\n")
    print(header + "\n".join(lines))
    print(f"wrote {out_dir}/coupling.csv, overhead.csv, mass_ratio.csv, mass_ratio.png, coupling.md")
    return 0


if __name__ == "__main__":
    print(json.dumps(measure_overhead(**json.loads(sys.argv[1]))))
