"""`cosim bench mpm`: MPM throughput, backward/forward cost and peak memory.

Each configuration runs in its own process (Taichi's precision is fixed per
process, and the process's peak RSS is the configuration's memory). Reported:
forward and forward+backward particle-substeps per second (compile excluded),
the backward/forward time ratio, peak resident memory and the hardware.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
import time
from pathlib import Path

CONFIGS = [
    {"dim": 2, "cells": 128, "side": 141, "precision": "float32"},  # 19,881 particles
    {"dim": 2, "cells": 128, "side": 141, "precision": "float64"},
    {"dim": 3, "cells": 64, "side": 31, "precision": "float32"},  # 29,791 particles
    {"dim": 3, "cells": 64, "side": 31, "precision": "float64"},
]
COLUMNS = [
    "dim",
    "precision",
    "grid",
    "particles",
    "fwd_Mpss",
    "fwd_bwd_Mpss",
    "bwd_fwd_ratio",
    "peak_MiB",
    "compile_s",
]


def measure(dim: int, cells: int, side: int, precision: str, substeps: int, macro_steps: int) -> dict:
    """One configuration, in this process: an elastic block falling onto the floor."""
    import resource

    import numpy as np

    from cosim.runtime import ensure_taichi

    ensure_taichi("cpu", precision)
    from cosim.engines.mpm import MPMConfig, MPMEngine, ParticleBody

    dx = 1.0 / cells
    h = 0.5 * dx
    axis = 0.5 - 0.5 * side * h + h * np.arange(side)
    pts = np.stack(np.meshgrid(*([axis] * dim), indexing="ij"), -1).reshape(-1, dim)
    pts[:, 1] -= 0.1
    body = ParticleBody("block", "elastic", 1e4, 0.3, 1000.0, h**dim, pts, np.zeros_like(pts))
    gravity = (0.0, -9.81) + (0.0,) * (dim - 2)
    dt = 1e-4

    fwd = MPMEngine(MPMConfig(dim, (cells,) * dim, dx, gravity), [body])
    t = time.perf_counter()
    fwd.advance(dt, 1)
    fwd.state()
    compile_s = time.perf_counter() - t
    t = time.perf_counter()
    for _ in range(macro_steps):
        fwd.advance(dt, substeps)
    fwd.state()  # synchronise
    fwd_s = time.perf_counter() - t

    grad = MPMEngine(MPMConfig(dim, (cells,) * dim, dx, gravity, requires_grad=True, grad_substeps=substeps), [body])
    zero = {k: np.zeros_like(v) for k, v in grad.state().items()}
    seed = {"state": dict(zero, x=np.ones_like(zero["x"]))}
    inputs = {"dt": dt, "substeps": substeps}
    t = time.perf_counter()
    _, rec0 = grad.step(inputs)
    rec0.token = -1  # force the recompute path too
    grad.vjp(rec0, seed)
    compile_s += time.perf_counter() - t
    records = []
    t = time.perf_counter()
    for _ in range(macro_steps):
        records.append(grad.step(inputs)[1])
    tape_fwd_s = time.perf_counter() - t
    t = time.perf_counter()
    g = seed
    for rec in reversed(records):
        g = {"state": grad.vjp(rec, g)["state"]}
    bwd_s = time.perf_counter() - t
    n = len(pts)
    work = n * substeps * macro_steps
    return {
        "dim": dim,
        "precision": precision,
        "grid": f"{cells}^{dim}",
        "particles": n,
        "fwd_Mpss": work / fwd_s / 1e6,
        "fwd_bwd_Mpss": work / (tape_fwd_s + bwd_s) / 1e6,
        "bwd_fwd_ratio": bwd_s / tape_fwd_s,
        "peak_MiB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "compile_s": compile_s,
    }


def run_mpm_bench(out_dir: Path, quick: bool = False) -> int:
    """Run every configuration in a subprocess; write DIR/mpm.csv and print a table."""
    from cosim.run import hardware_line

    out_dir.mkdir(parents=True, exist_ok=True)
    substeps, macro = (5, 2) if quick else (20, 10)
    rows = []
    for cfg in CONFIGS:
        args = json.dumps({**cfg, "substeps": substeps, "macro_steps": macro})
        cmd = [sys.executable, "-m", "cosim.bench.mpm", args]
        res = subprocess.run(cmd, capture_output=True, text=True, check=False)  # a failure prints its stderr
        if res.returncode != 0:
            print(res.stderr[-2000:], file=sys.stderr)
            return 1
        rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
        r = rows[-1]
        print(f"  done {r['dim']}D {r['precision']}: {r['fwd_Mpss']:.2f} M particle-substeps/s forward", flush=True)
    with open(out_dir / "mpm.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    print(f"\nMPM benchmark on {hardware_line()}; {substeps} substeps x {macro} macro steps, elastic block, dt 1e-4 s")
    print(
        f"{'dim':>3} {'precision':>9} {'grid':>6} {'particles':>9} {'fwd M/s':>8} {'f+b M/s':>8} "
        f"{'bwd/fwd':>7} {'peak MiB':>8} {'compile s':>9}"
    )
    for r in rows:
        print(
            f"{r['dim']:>3} {r['precision']:>9} {r['grid']:>6} {r['particles']:>9} {r['fwd_Mpss']:>8.2f} "
            f"{r['fwd_bwd_Mpss']:>8.2f} {r['bwd_fwd_ratio']:>7.2f} {r['peak_MiB']:>8.0f} {r['compile_s']:>9.1f}"
        )
    print(f"wrote {out_dir / 'mpm.csv'}")
    return 0


if __name__ == "__main__":
    print(json.dumps(measure(**json.loads(sys.argv[1]))))
