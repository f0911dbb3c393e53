"""`cosim bench mpm`: MPM throughput, backward/forward cost and peak memory.

Each configuration runs in its own process (Taichi's precision is fixed per process, and
the process's peak RSS is the configuration's memory): ``cosim/bench/mpm_measure.py``, run by
path with a given interpreter, so that the same measurement also runs against a baseline
checkout (``--baseline``, ``cosim.bench.mpm_baseline``). Reported: forward and
forward+backward particle-substeps per second (compile excluded), the backward/forward time
ratio, peak resident memory and the hardware; each mode writes a CSV and a markdown report headed by the
command line, the date and the hardware (``cosim.bench.report``).

Modes: the four ``CONFIGS`` (default); ``--sizes``, 3D float32 from 10k to 1M particles
(``SIZES``, grid from ``sized_grid``); ``--particles N``, one 3D float32 block of about N;
``--arch cuda``, the GPU's ``GPU_CONFIGS`` (30k, 250k, 2M particles; or the sizes asked for);
``--threads 1,2,...`` and ``--scatter serial,coloured``, every configuration on each CPU thread
count and with each scatter (the many-core curve); ``--baseline DIR``, current/baseline ratios of
either set; ``--profile``, Taichi's kernel profiler over a forward and a backward pass of 3D 64³ float32.

The engine is timed alone, without the runner's checks (CFL, NaN, domain, energy budget: ``GUARDS_OFF``);
every mode says so when it starts, in its reports' headers and in its CSVs' ``guards_off`` column.
"""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from cosim.bench.kernel_profile import by_kernel, by_task
from cosim.guards import ENGINE_ALONE, GuardsOff

# the engine is stepped alone (``mpm_measure``), without ``CoupledSystem.step``'s checks
GUARDS_OFF = GuardsOff(ENGINE_ALONE, "the MPM engine timed alone at a fixed dt = 1e-4 s")
CONFIGS = [
    {"dim": 2, "cells": 128, "side": 141, "precision": "float32"},  # 19,881 particles
    {"dim": 2, "cells": 128, "side": 141, "precision": "float64"},
    {"dim": 3, "cells": 64, "side": 31, "precision": "float32"},  # 29,791 particles
    {"dim": 3, "cells": 64, "side": 31, "precision": "float64"},
]
# (particles wanted, substeps, macro steps): fewer steps at large N keep the sweep short,
# and fewer substeps bound the gradient engine's K grids (K x 8 M nodes at 1M particles).
SIZES = [(10_000, 20, 10), (30_000, 20, 10), (100_000, 20, 4), (300_000, 10, 3), (1_000_000, 5, 2)]
# the GPU's sizes: 30k particles on 64³ (the CPU's 3D CONFIGS, the peers' comparison), 250k on 128³, and
# 2.05M filling half of 128³'s side; float32, 10 substeps a macro step
GPU_CONFIGS = [
    {"dim": 3, "cells": 64, "side": 31, "precision": "float32", "substeps": 10, "macro_steps": 10},
    {"dim": 3, "cells": 128, "side": 63, "precision": "float32", "substeps": 10, "macro_steps": 5},
    {"dim": 3, "cells": 128, "side": 127, "precision": "float32", "substeps": 10, "macro_steps": 3},
]
FILL = 0.25  # the block's side over the domain's: 64³ for the 31³ block of CONFIGS
MEASURE = Path(__file__).with_name("mpm_measure.py")
# Taichi's kernel cache for the children (any version reads TI_* variables; ours win if set): a
# folder of its own, since the shared ~/.cache/taichi is capped at 100 MB with LRU eviction and,
# with other processes compiling, can evict a baseline's slow-to-compile 3D adjoint kernels between runs.
CACHE_ENV = {
    "TI_OFFLINE_CACHE_FILE_PATH": str(Path.home() / ".cache" / "cosim" / "taichi_bench_mpm"),
    "TI_OFFLINE_CACHE_MAX_SIZE_OF_FILES": str(2**30),  # a C int in Taichi: under 2 GiB
}
# (key, header, format) of the printed table; the CSV has every key
CONFIG_COLUMNS = [
    ("dim", "dim", ">3"),
    ("precision", "precision", ">9"),
    ("grid", "grid", ">7"),
    ("particles", "particles", ">9"),
]
TABLE = [
    *CONFIG_COLUMNS,
    ("steps", "steps", ">6"),
    ("arch", "arch", ">4"),
    ("threads", "threads", ">7"),
    ("scatter", "scatter", ">8"),
    ("fwd_Mpss", "fwd M/s", ">8.2f"),
    ("fwd_GBps", "fwd GB/s", ">8.1f"),
    ("fwd_bwd_Mpss", "f+b M/s", ">8.3f"),
    ("bwd_fwd_ratio", "bwd/fwd", ">7.2f"),
    ("fb_over_fwd", "f+b/fwd", ">7.2f"),
    ("peak_MiB", "peak MiB", ">8.0f"),
    ("field_MiB", "field MiB", ">9.0f"),
    ("device_MiB", "GPU MiB", ">8.0f"),
    ("fwd_B_per_particle", "fwd B/p", ">7.0f"),
    ("grad_B_per_particle", "grad B/p", ">8.0f"),
    ("compile_s", "compile s", ">9.1f"),
]


@dataclass
class Interpreter:
    """A Python that runs a measurement script (``mpm_measure.py``, or a peer's): its executable,
    environment, and the package it must import (``root/package``: the cosim, or the peer's)."""

    python: str
    root: Path  # the folder holding the package it imports
    env: dict = field(default_factory=dict)
    label: str = "current"
    measure: Path = MEASURE
    package: str = "cosim"


def current_interpreter() -> Interpreter:
    """This interpreter, importing this process's cosim (put first on PYTHONPATH)."""
    import cosim

    root = Path(cosim.__file__).resolve().parents[1]
    path = os.pathsep.join([str(root)] + [p for p in [os.environ.get("PYTHONPATH", "")] if p])
    return Interpreter(sys.executable, root, dict(os.environ, PYTHONPATH=path))


def sized_grid(particles: int, fill: float = FILL) -> dict:
    """3D grid and block for about ``particles`` particles at 8 per cell.

    The block is sampled at 2 particles per axis per cell (8 per cell), ``side`` = round(N^(1/3))
    particles per axis, so it spans side/2 cells; the grid's ``cells`` per axis grow with
    N^(1/3) so that the block spans ``fill`` of the domain's side (rounded up to a multiple of 8).
    """
    side = round(particles ** (1 / 3))
    cells = 8 * math.ceil(side / (2 * fill) / 8)
    return {"dim": 3, "cells": cells, "side": side, "precision": "float32"}


def size_configs(quick: bool = False) -> list[dict]:
    """The ``--sizes`` configurations (``--quick``: up to 30k particles, 5 x 2 steps)."""
    if quick:
        return [{**sized_grid(n), "substeps": 5, "macro_steps": 2} for n, _, _ in SIZES[:2]]
    return [{**sized_grid(n), "substeps": k, "macro_steps": m} for n, k, m in SIZES]


def fixed_configs(quick: bool = False) -> list[dict]:
    """The four ``CONFIGS`` with their steps (``--quick``: 5 x 2)."""
    substeps, macro = (5, 2) if quick else (20, 10)
    return [{**cfg, "substeps": substeps, "macro_steps": macro} for cfg in CONFIGS]


def gpu_configs(quick: bool = False) -> list[dict]:
    """``GPU_CONFIGS`` (``--quick``: the 30k block, 5 x 2)."""
    if quick:
        return [{**GPU_CONFIGS[0], "substeps": 5, "macro_steps": 2}]
    return [dict(cfg) for cfg in GPU_CONFIGS]


def particle_config(particles: int, quick: bool = False) -> dict:
    """``--particles N``: one 3D float32 block of about N particles (``sized_grid``), 10 x 3 steps (``--quick``: 5 x 2)."""
    substeps, macro = (5, 2) if quick else (10, 3)
    return {**sized_grid(particles), "substeps": substeps, "macro_steps": macro}


def expand(configs: list[dict], arch: str, threads: list[int] | None, scatters: list[str] | None) -> list[dict]:
    """Every configuration on ``arch``, on each of ``threads`` (Taichi's CPU threads; None: its default)
    and with each of ``scatters`` (None: the engine's choice), threads outermost."""
    out = []
    for n in threads or [None]:
        for scatter in scatters or [None]:
            extra = {"arch": arch} | ({"threads": n} if n else {}) | ({"scatter": scatter} if scatter else {})
            out += [{**cfg, **extra} for cfg in configs]
    return out


def run_config(cfg: dict, interp: Interpreter | None = None) -> dict:
    """Measure one configuration in a fresh process of ``interp`` (default: this cosim); a RuntimeError
    with the child's stderr if it fails, or if it imported another package than ``interp``'s."""
    interp = interp or current_interpreter()
    cfg = dict(cfg)
    threads = cfg.pop("threads", None)  # a setting of the process, not of the measurement
    cmd = [interp.python, str(interp.measure), json.dumps(cfg)]
    env = {**CACHE_ENV, **interp.env} | ({"COSIM_CPU_THREADS": str(threads)} if threads else {})
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=interp.root, check=False)
    if res.returncode != 0:
        refused = [line for line in res.stderr.splitlines() if line.startswith("cosim.errors.InputError: ")]
        if refused:  # the child's input was refused (e.g. --arch cuda without a GPU): the reason, not its traceback
            from cosim.errors import InputError

            raise InputError(refused[-1].removeprefix("cosim.errors.InputError: "))
        raise RuntimeError(f"{interp.label} run of {cfg} failed (exit {res.returncode}):\n{res.stderr[-2000:]}")
    row = json.loads(res.stdout.strip().splitlines()[-1])
    if Path(row["package"]).resolve() != (interp.root / interp.package).resolve():
        raise RuntimeError(f"the {interp.label} run imported {row['package']}, not {interp.root / interp.package}")
    return row


def print_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> None:
    """Rows as a fixed-width table of the given (key, header, format) columns."""
    widths = [int(fmt[1:].split(".")[0]) for _, _, fmt in columns]  # formats are ">W" or ">W.Pf"
    print(" ".join(f"{h:>{w}}" for (_, h, _), w in zip(columns, widths, strict=True)))
    for r in rows:
        print(" ".join(format(r[k], fmt) for k, _, fmt in columns))


def write_report(path: Path, command: str | None, title: str, rows: list[dict], columns: list) -> None:
    """``rows`` as a markdown table of ``columns`` under the report header of ``command`` and ``title``."""
    from cosim.bench.report import bench_command, markdown_table, report_header

    lines = [title, "", *markdown_table(rows, columns)]
    path.write_text(report_header(command or bench_command("mpm"), guards_off=GUARDS_OFF) + "\n".join(lines) + "\n")
    print(f"wrote {path}")


def write_csv(path: Path, rows: list[dict]) -> None:
    """Rows (dicts with the same keys) to a CSV file, with the guards the measurement ran without (``guards_off``)."""
    rows = [r | {"guards_off": GUARDS_OFF.column()} for r in rows]
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")


def particle_bytes(dim: int, precision: str, scatter: str) -> int:
    """Bytes of particle arrays one forward substep moves per particle (one body, no hooks). P2G reads x, v,
    F and C (2 d + 2 d^2 floats); beside the serial scatter the stress is its own loop, which reads F and C
    and writes the affine momentum that the scatter reads back (2 d^2 more: ``stress_in_scatter``). G2P
    with the advection reads x and F and writes x, v, C and F (3 d + 3 d^2). The grid's nodes (an eighth
    as many as the particles in 3D at 8 per cell) are left out: a particle's stencil mostly hits what its
    neighbours brought into cache. Times the forward rate: the memory bandwidth the forward would need if
    it were bound by it (``fwd_GBps``), against the machine's peak."""
    floats = 5 * dim * dim + 5 * dim + (2 * dim * dim if scatter == "serial" else 0)
    return floats * (4 if precision == "float32" else 8)


def run_throughput(out_dir: Path, configs: list[dict], name: str, command: str | None = None) -> int:
    """Every configuration in its own process; prints a table and writes ``out_dir/<name>.csv`` and ``<name>.md``."""
    from cosim.hardware import hardware_line

    rows = []
    for cfg in configs:
        rows.append({k: v for k, v in run_config(cfg).items() if k != "package"})
        r = rows[-1]
        r["fwd_GBps"] = r["fwd_Mpss"] * 1e6 * particle_bytes(r["dim"], r["precision"], r["scatter"]) / 1e9
        print(f"  done {r['dim']}D {r['precision']} {r['particles']:,} {r['arch']} {r['threads']} threads "
              f"{r['scatter']}: {r['fwd_Mpss']:.2f} M/s forward", flush=True)  # fmt: skip
    print(f"\nMPM benchmark on {hardware_line()}; steps = substeps x macro steps, elastic block, dt 1e-4 s")
    print_table(rows, TABLE)
    write_csv(out_dir / f"{name}.csv", rows)
    title = "MPM benchmark: elastic block, dt 1e-4 s; steps = substeps x macro steps; rates in M particle-substeps/s"
    write_report(out_dir / f"{name}.md", command, title, rows, TABLE)
    return 0


def run_profile(out_dir: Path, config: dict | None = None, top: int = 10, command: str | None = None) -> int:
    """Taichi's kernel profiler over a forward and a backward pass of ``config`` (default 3D 64³ float32 on
    the CPU): ms per substep of the top kernels, and of each kernel's parallel loops (its tasks, in the
    order of the kernel's code: the fused substep's clear, stress, scatter, grid update, G2P)."""
    from cosim.hardware import hardware_line

    interp = current_interpreter()
    interp.env["COSIM_KERNEL_PROFILER"] = "1"
    config = config or {**CONFIGS[2], "substeps": 20, "macro_steps": 3}
    row = run_config({**config, "profile": True}, interp)
    what = (f"{row['dim']}D {row['grid']} {row['precision']}, {row['particles']:,} particles, {row['arch']}, "
            f"{config['substeps']} substeps x {config['macro_steps']}")  # fmt: skip
    print(f"\nKernel profile, {what}, on {hardware_line()}")
    print("ms per substep in each kernel (backward: its forward-named kernels are the checkpoint recompute)")
    rows = []
    for phase, records in row["profile"].items():
        kernels = by_kernel(records)
        total = sum(k[1] for k in kernels)
        print(f"\n{phase}: {total:.2f} ms per substep in kernels")
        for name, ms, launches in kernels[:top]:
            print(f"  {ms:8.3f} ms {100 * ms / total:5.1f}% {launches:6.2f} launches  {name}")
            tasks = [(task, task_ms) for task, task_ms in by_task(records, name) if task_ms >= 0.01 * total]
            for task, task_ms in tasks if len(tasks) > 1 else []:  # its loops of 1 % of the phase or more
                print(f"  {task_ms:8.3f} ms {100 * task_ms / total:5.1f}%                   {task}")
        rows += [{"phase": phase, "kernel": k, "ms_per_substep": ms, "launches_per_substep": n} for k, ms, n in kernels]
    write_csv(out_dir / "mpm_profile.csv", rows)
    title = (
        f"Kernel profile, {what} macro steps: ms per substep in each kernel (backward: its forward-named "
        "kernels are the checkpoint recompute)"
    )
    columns = [("phase", "phase", ""), ("kernel", "kernel", ""), ("ms_per_substep", "ms per substep", ".3f"),
               ("launches_per_substep", "launches per substep", ".2f")]  # fmt: skip
    write_report(out_dir / "mpm_profile.md", command, title, rows, columns)
    return 0
