"""The fan-out commands: ``cosim sweep`` and ``cosim optimize --starts`` (see docs/scale-out.md).

Both validate every case in this process first (a wrong key exits 2 before any worker
starts), then hand the cases to Ray (``pool.run_jobs``) and gather what comes back.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from cosim.errors import SimulationError
from cosim.scale.cases import grid_cases
from cosim.scale.jobs import optimize_start, run_case
from cosim.scale.pool import run_jobs
from cosim.scale.results import SweepTable, write_starts
from cosim.scene import load_scene


def sweep(
    scene_path: Path,
    assignments: list[str],
    grid: list[str],
    samples: int | None,
    seed: int,
    loss: bool,
    steps: int | None,
    out: str | None,
    workers: int | None,
    address: str | None,
    quiet: bool,
) -> int:
    """Every ``grid`` combination (or ``samples`` of them) of the scene with ``assignments`` as one Ray
    job each, into OUT/sweep.csv; the exit code is 3 when a case failed."""
    defaults = {"precision": "float64"} if loss else None
    cases = grid_cases(grid, samples, seed)
    for case in cases:
        load_scene(scene_path, defaults, assignments + case)
    name = load_scene(scene_path, defaults, assignments).name
    table = SweepTable(Path(out or f"out/{name}_sweep") / "sweep.csv", [g.partition("=")[0].strip() for g in grid])
    argsets = [(str(scene_path), defaults, assignments + case, steps, loss) for case in cases]
    print(f"sweep {name}: {len(cases)} cases" + (" (loss and gradient)" if loss else ""))
    with tqdm(total=len(cases), desc="sweep", unit="case", disable=quiet) as bar:
        try:
            for outcome in run_jobs(run_case, argsets, workers, address):
                table.add(outcome.index, cases[outcome.index], outcome.ok, outcome.value)
                bar.update()
                if not outcome.ok:
                    tqdm.write(f"case {outcome.index} ({', '.join(cases[outcome.index])}) failed: {outcome.value}")
        except KeyboardInterrupt:
            print(f"{len(table.rows)} of {len(cases)} cases had finished; kept in {table.path}", file=sys.stderr)
            raise
    print(f"{len(cases) - table.failed} of {len(cases)} cases ok; wrote {table.path}")
    return 0 if table.failed == 0 else 3


def optimize_starts(
    scene_name: str,
    scene_path: Path,
    assignments: list[str],
    starts: int,
    perturbation: float,
    iterations: int | None,
    lr: float | None,
    method: str | None,
    steps: int | None,
    out: str | None,
    preview: bool,
    workers: int | None,
    address: str | None,
    quiet: bool,
) -> int:
    """``starts`` optimisations on Ray of the scene ``scene_name`` at ``scene_path`` (validated by the
    caller, with ``assignments``): start 0 from the scene's initial guess, start k from it moved by
    ``perturbation`` x each parameter's scale (seed k); keeps the best start's parameters and writes
    every start's curve (docs/outputs.md). The exit code is 3 when a start failed."""
    defaults = {"precision": "float64"}
    out = Path(out or f"out/{scene_name}_optimize").resolve()
    argsets = []
    for k in range(starts):
        settings = {"iterations": iterations, "lr": lr, "method": method, "steps": steps, "preview": preview}
        settings.update({"perturbation": perturbation if k else 0.0, "seed": k})
        argsets.append((str(scene_path), defaults, assignments, settings, str(out / f"start_{k}")))
    print(
        f"optimize {scene_name}: {starts} starts on Ray (start 0: the scene's guess, others moved by {perturbation:g} x scale)"
    )
    results, errors = {}, {}
    with tqdm(total=starts, desc="starts", unit="start", disable=quiet) as bar:
        for outcome in run_jobs(optimize_start, argsets, workers, address):
            (results if outcome.ok else errors)[outcome.index] = outcome.value
            bar.update()
    for k, message in sorted(errors.items()):
        print(f"start {k} failed: {message}")
    if not results:
        raise SimulationError(f"every one of the {starts} starts failed (first: {errors[min(errors)]})")
    out.mkdir(parents=True, exist_ok=True)
    write_starts(out, results, f"{scene_name}: {starts} starts")
    best = min(results, key=lambda k: results[k]["best_loss"])
    np.savez(out / "params.npz", **results[best]["best_params"])
    summary = {k: v for k, v in results[best].items() if k not in ("best_params", "written")}
    summary.update({"best_start": best, "starts": {k: r["best_loss"] for k, r in sorted(results.items())}})
    summary["failed_starts"] = {k: errors[k] for k in sorted(errors)}
    (out / "optimization.json").write_text(json.dumps(summary, indent=2))
    for k in sorted(results):
        print(f"start {k}: loss {results[k]['losses'][0]:.6e} -> {results[k]['best_loss']:.6e}")
    print(f"best: start {best} ({results[best]['best_loss']:.6e}), its outputs in {out}/start_{best}")
    print(f"wrote {out}/params.npz, {out}/optimization.json, {out}/starts.csv, {out}/starts.png")
    return 0 if not errors else 3
