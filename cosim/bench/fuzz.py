"""`cosim bench fuzz`: random valid scenes (``fuzz_scenes.random_scene``) run to an outcome each.

Every case is one seed: its scene is validated, built and run like ``cosim run`` (nothing written),
in a worker process with a wall-time limit (``fuzz_workers``). Outcomes:

- ``ran``: every step done, and the final state of every engine (particles, skeletons, cloths,
  coupler states) and every metric finite;
- ``scene-error``: a ``SceneError`` (the scene was refused, with its message);
- ``simulation-error``: a ``SimulationError`` (the run stopped, naming step, body and quantity);
- failures: ``crash`` (any other exception, or the worker died: its type, message and the last
  frames of its traceback), ``hang`` (over the time limit), ``silent-nan`` (a run that "ran" but
  left a non-finite value that no check caught).

A scene or simulation error is clear when its message names where: a scene key path
(``mpm.bodies[1].material.E``), a named body, skeleton or cloth, or a step (``names_a_place``);
an unclear one counts as a failure too. The benchmark writes ``OUT/fuzz.csv`` (one row per seed),
``OUT/fuzz.md`` (the counts per outcome, headed by the command, date and hardware) and, for every
failure, the scene as ``OUT/repros/seed_N.yaml`` (``cosim run`` reproduces it).
"""

from __future__ import annotations

import csv
import re
import time
import traceback
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from cosim.bench.fuzz_scenes import random_scene

__all__ = ["OUTCOMES", "FuzzRecord", "names_a_place", "random_scene", "run_case", "run_fuzz", "run_fuzz_bench"]

OUTCOMES = ("ran", "scene-error", "simulation-error", "crash", "hang", "silent-nan")
FAILURES = ("crash", "hang", "silent-nan")
TIMEOUT = 300.0  # [s] per case, Taichi start-up and compiles included: ample for a case, even on a loaded machine

_TOP_KEYS = "time|mpm|rigid|articulated|cloth|contact|controls|loss|gradient|optimize|output"
_PLACE = re.compile(
    rf"\b(?:{_TOP_KEYS})(?:\[\d+\]|\.[A-Za-z_]\w*)+"  # a key path: mpm.bodies[0].shape, time.substeps, cloth[0]
    r"|(?:^|\n)\s*(?:dim|steps|precision|arch|seed|name|cloth|controls):"  # a top-level key
    r"|\b(?:body|skeleton|link|joint|cloth|control) '[^']+'"  # a named thing: body 'water'
    r"|\bstep \d+"  # a step of the run
)


def names_a_place(message: str) -> bool:
    """Whether an error message says where: a scene key path, a named body/skeleton/cloth, or a step."""
    return bool(_PLACE.search(message))


@dataclass
class FuzzRecord:
    """One case: the scene's summary, its outcome and message, and the seconds it took [s]."""

    seed: int
    dim: int
    precision: str
    bodies: str  # the soft bodies, "material shape" each
    extras: str  # rigid bodies, skeleton links, cloth, controls
    contact: str  # the contact model
    outcome: str
    message: str = ""
    seconds: float = 0.0
    clear: bool = True  # an error message names a key path, a body or a step
    where: str = ""  # a crash: the last frames of its traceback

    @property
    def failed(self) -> bool:
        return self.outcome in FAILURES or not self.clear


class _SilentNaN(Exception):
    """A run ended without an error but with a non-finite value."""


def run_case(seed: int, steps: int | None = None, precision: str | None = None) -> dict:
    """Validate, build and run the scene of ``seed`` (``steps`` frames, default the scene's); returns
    {outcome, message, seconds, where}. Catches every exception: this is what a worker runs."""
    from cosim.errors import SceneError, SimulationError
    from cosim.run import run_scene
    from cosim.scale.jobs import flatten
    from cosim.scene import parse_scene

    t0 = time.perf_counter()
    out = {"outcome": "ran", "message": "", "where": ""}
    try:
        scene = parse_scene(random_scene(seed, precision), origin=f"fuzz_{seed}")
        metrics = run_scene(scene, None, steps=steps, progress=False, preview=False, after_rollout=_check_final)
        bad = [k for k, v in flatten(metrics).items() if not np.isfinite(v)]
        if bad:
            raise _SilentNaN(f"non-finite metrics: {', '.join(bad[:5])}")
    except SceneError as exc:
        out.update(outcome="scene-error", message=str(exc))
    except SimulationError as exc:
        out.update(outcome="simulation-error", message=str(exc))
    except _SilentNaN as exc:
        out.update(outcome="silent-nan", message=str(exc))
    except Exception as exc:  # noqa: BLE001 - anything else is the crash the fuzz looks for
        frames = traceback.extract_tb(exc.__traceback__)[-4:]
        where = " <- ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(frames))
        out.update(outcome="crash", message=f"{type(exc).__name__}: {exc}", where=where)
    out["seconds"] = time.perf_counter() - t0
    return out


def _check_final(sim) -> None:
    """Every array of the system's final state is finite (particles, skeletons, cloths, couplers)."""
    bad = [path for path, value in _arrays(sim.state()) if not np.all(np.isfinite(value))]
    if bad:
        raise _SilentNaN(f"non-finite final state after step {sim.step_index}: {', '.join(bad[:5])}")


def _arrays(state, prefix: str = ""):
    """(path, float array) of a nested state dict."""
    for key, value in state.items():
        if isinstance(value, dict):
            yield from _arrays(value, f"{prefix}{key}.")
        elif isinstance(value, np.ndarray) and np.issubdtype(value.dtype, np.floating):
            yield f"{prefix}{key}", value


def describe(scene: dict) -> dict:
    """The CSV's summary columns of a generated scene dict."""
    bodies = "; ".join(f"{b['material']['type']} {b['shape']['type']}" for b in scene["mpm"]["bodies"])
    extras = []
    if "rigid" in scene:
        extras.append(f"rigid {len(scene['rigid']['bodies'])}")
    if "articulated" in scene:
        extras.append(f"links {len(scene['articulated']['skeletons'][0]['links'])}")
    if "cloth" in scene:
        extras.append("cloth")
    if "controls" in scene:
        extras.append("impulses")
    return {
        "dim": scene["dim"],
        "precision": scene["precision"],
        "bodies": bodies,
        "extras": ", ".join(extras),
        "contact": scene["contact"]["model"],
    }


def run_fuzz(
    seeds: list[int],
    steps: int | None = None,
    workers: int = 1,
    timeout: float = TIMEOUT,
    precision: str | None = None,
    log_dir: Path | None = None,
    on_record: Callable[[FuzzRecord], None] | None = None,
) -> list[FuzzRecord]:
    """Run the scene of every seed on ``workers`` processes, each case within ``timeout`` [s]; returns the
    records in seed order (``on_record`` sees each as it finishes). ``steps``: frames per case (default the
    scene's); ``precision``: force one (default drawn per scene); ``log_dir``: the workers' output."""
    from cosim.bench.fuzz_workers import run_guarded

    seeds = list(seeds)
    argsets = [(seed, steps, precision) for seed in seeds]
    records: dict[int, FuzzRecord] = {}
    for index, status, value, seconds in run_guarded(run_case, argsets, workers, timeout, log_dir):
        seed = seeds[index]
        summary = describe(random_scene(seed, precision))
        if status == "ok":
            record = FuzzRecord(seed, **summary, **value)
        else:
            outcome = "hang" if status == "hang" else "crash"
            record = FuzzRecord(seed, **summary, outcome=outcome, message=str(value), seconds=seconds)
        if record.outcome in ("scene-error", "simulation-error"):
            record.clear = names_a_place(record.message)
        records[index] = record
        if on_record is not None:
            on_record(record)
    return [records[i] for i in range(len(seeds))]


def run_fuzz_bench(
    out_dir: Path, count: int = 200, seed: int = 0, workers: int | None = None, command: str | None = None
) -> int:
    """``count`` scenes from seeds ``seed``, ``seed + 1``, ... on ``workers`` processes (default: the cores);
    writes OUT/fuzz.csv, OUT/fuzz.md (headed by ``command``, the date and the hardware) and the failures' scenes,
    prints the counts per outcome; exit code 1 on any failure."""
    import os

    from cosim.bench.report import bench_command, report_header

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    workers = workers or os.cpu_count() or 1
    seeds = list(range(seed, seed + count))
    print(f"fuzz: {count} scenes (seeds {seeds[0]}..{seeds[-1]}), {workers} worker process(es), {TIMEOUT:g} s each")
    done = []

    def report(r: FuzzRecord) -> None:
        done.append(r)
        note = "" if r.outcome == "ran" else f": {r.message.splitlines()[-1][:160]}"
        case = f"seed {r.seed} {r.dim}D {r.contact}"
        print(f"  [{len(done)}/{count}] {case}: {r.outcome} ({r.seconds:.1f} s){note}", flush=True)

    t0 = time.perf_counter()
    records = run_fuzz(seeds, workers=workers, log_dir=out_dir / "logs", on_record=report)
    wall = time.perf_counter() - t0
    write_csv(records, out_dir / "fuzz.csv")
    failed = [r for r in records if r.failed]
    if failed:
        write_repros(failed, out_dir / "repros")
    counts = Counter(r.outcome for r in records)
    valid = count - counts.get("scene-error", 0)
    unclear = [r for r in records if not r.clear]
    lines = [
        (
            f"Fuzz benchmark: {count} random scenes (seeds {seeds[0]}..{seeds[-1]}), {workers} worker process(es), "
            f"{TIMEOUT:g} s limit per case; {wall:.0f} s in all"
        ),
        "",
        "| outcome | scenes |",
        "|---|---|",
        *[f"| {name} | {counts.get(name, 0)} |" for name in OUTCOMES],
        "",
        f"Passed validation and build: {valid} of {count} ({100 * valid / count:.0f}%).",
    ]
    if unclear:
        lines.append(f"Error messages naming no key, body or step: {len(unclear)} (seeds {[r.seed for r in unclear]}).")
    for r in failed:
        message = " | ".join(line.strip() for line in r.message.splitlines() if line.strip())
        lines.append(f"- FAILED seed {r.seed}: {r.outcome}: {message[:400]}" + (f" [{r.where}]" if r.where else ""))
    header = report_header(command or bench_command("fuzz", count=count, seed=seed, workers=workers))
    (out_dir / "fuzz.md").write_text(header + "\n".join(lines) + "\n")
    print(header + "\n".join(lines))
    print(f"wrote {out_dir}/fuzz.csv, fuzz.md" + (f", {len(failed)} scenes in {out_dir}/repros" if failed else ""))
    return 1 if failed else 0


def write_csv(records: list[FuzzRecord], path: Path) -> None:
    """One row per case: seed, dim, precision, bodies, extras, contact, outcome, message, seconds, clear, where."""
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(FuzzRecord.__dataclass_fields__))
        writer.writeheader()
        for r in records:
            row = asdict(r)
            row["message"] = " | ".join(line.strip() for line in r.message.splitlines())
            row["seconds"] = f"{r.seconds:.2f}"
            writer.writerow(row)


def write_repros(records: list[FuzzRecord], folder: Path) -> None:
    """The scene of each record as ``folder/seed_N.yaml`` (run it with ``cosim run``)."""
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    for r in records:
        header = f"# cosim bench fuzz, seed {r.seed}: {r.outcome}\n# {r.message.splitlines()[0] if r.message else ''}\n"
        body = yaml.safe_dump(random_scene(r.seed, r.precision), sort_keys=False, default_flow_style=None)
        (folder / f"seed_{r.seed}.yaml").write_text(header + body)
