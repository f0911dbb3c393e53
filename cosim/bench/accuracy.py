"""`cosim bench accuracy`: run time against error for reference problems (work-precision diagrams).

Every problem of ``accuracy_problems`` is run over its sweep (grid cells per metre x
``time.cfl`` at the shipped precision and contact model, plus the other precision and the other
contact models), and the reference-run problems once more at their reference setting. Each case's
cost is the CPU time of its macro steps after the first (which compiles) per simulated second,
with one Taichi thread per case: on a shared machine that is what the case needs, where its wall
time (also recorded) stretches with whatever else runs. Its error is the problem's relative error.
Cases run with ``--workers`` > 1 (or an ``--address``) as Ray jobs (``cosim.scale.pool.run_jobs``),
otherwise one after another in a child process; either way each precision has processes of its own
(Taichi runs one precision per process). Writes
``OUT/accuracy.csv`` (one row per case, the hardware and load averages in ``#`` lines above),
``OUT/accuracy.md`` (the summary), ``OUT/accuracy_<problem>.png`` (one diagram per problem) and
``OUT/accuracy_raw.json`` (every case's setting and whole observation, histories included).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import astuple, dataclass
from pathlib import Path

from cosim.bench.accuracy_problem import Problem, Setting


@dataclass(frozen=True)
class Case:
    """One run of the sweep: a problem's name, its setting, and whether it is the problem's reference."""

    problem: str
    setting: Setting
    reference: bool = False


def sweep_cases(problems: dict[str, Problem], quick: bool = False) -> list[Case]:
    """Every problem's reference case (if it has one) and sweep, the costliest first (so that two
    workers finish together and the references are there early)."""
    cases = []
    for name, problem in problems.items():
        ref = problem.reference_setting(quick)
        cases += [Case(name, ref, True)] if ref is not None else []
        cases += [Case(name, s) for s in problem.settings(quick)]

    def cost(case: Case) -> float:  # particles x substeps ~ cells^(d + 1) / cfl
        p = problems[case.problem]
        return case.setting.cells ** (p.dim + 1) / case.setting.cfl * p.duration / p.base_cells ** (p.dim + 1)

    return sorted(cases, key=cost, reverse=True)


def run_sweep(cases: list[Case], workers: int | None, address: str | None, log: Path) -> list[dict | str]:
    """Each case's observation (a dict) or its error message, in the order of ``cases``; one group of
    processes per precision: Ray actors with ``workers`` > 1 or an ``address``, else one child process."""
    from tqdm import tqdm

    results: list[dict | str] = [""] * len(cases)
    with tqdm(total=len(cases), desc="accuracy", unit="case") as bar:
        for precision in sorted({c.setting.precision for c in cases}):
            group = [i for i, c in enumerate(cases) if c.setting.precision == precision]
            argsets = [(cases[i].problem, astuple(cases[i].setting)) for i in group]
            for k, ok, value in _outcomes(argsets, workers, address, log):
                results[group[k]] = value if ok else str(value)
                c = cases[group[k]]
                what = "reference " if c.reference else ""
                status = f"{value['cost']:.3g} CPU s/sim s" if ok else f"failed: {value}"
                bar.write(f"  {c.problem} {what}{c.setting.label()}: {status}")
                bar.update()
    return results


def _outcomes(argsets: list[tuple], workers: int | None, address: str | None, log: Path):
    """(index into argsets, ok, observation or message) as cases finish."""
    from cosim.scale.pool import on_ray

    if on_ray(workers, address):
        from cosim.bench.accuracy_worker import run_case
        from cosim.scale.pool import run_jobs

        for outcome in run_jobs(run_case, argsets, workers, address):
            yield outcome.index, outcome.ok, _with_rate(outcome.value) if outcome.ok else outcome.value
        return
    from cosim.bench.accuracy_worker import MARK

    with open(log, "a") as err:
        cmd = [sys.executable, "-m", "cosim.bench.accuracy_worker"]
        env = os.environ | {"COSIM_CPU_THREADS": "1"}  # one Taichi thread per case, as on Ray with 2+ workers
        child = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True, env=env)
        child.stdin.write(json.dumps([list(a) for a in argsets]))
        child.stdin.close()
        for line in child.stdout:
            if line.startswith(MARK):
                r = json.loads(line[len(MARK) :])
                yield r["index"], r["ok"], _with_rate(r["value"]) if r["ok"] else r["value"]
        if child.wait() != 0:
            print(f"the accuracy worker exited with {child.returncode}; see {log}", file=sys.stderr)


def _with_rate(observation: dict) -> dict:
    """The observation with its cost, CPU seconds per simulated second, and its wall seconds per simulated second."""
    sim = observation["sim_seconds"]
    return observation | {"cost": observation["cpu_seconds"] / sim, "wall_cost": observation["seconds"] / sim}


def run_accuracy_bench(
    out_dir: Path,
    quick: bool = False,
    workers: int | None = None,
    address: str | None = None,
    command: str | None = None,
) -> int:
    """Run the sweep (quick: each problem's coarsest default setting and the references at 2x it), write
    accuracy.csv, accuracy.md (headed by ``command``) and one diagram per problem into ``out_dir``; returns 0,
    or 3 if a case failed (as ``cosim sweep`` does: the others are reported)."""
    from datetime import datetime

    from cosim.bench.accuracy_problems import PROBLEMS
    from cosim.bench.accuracy_report import Measurement, write_report
    from cosim.hardware import hardware_line

    out_dir.mkdir(parents=True, exist_ok=True)
    log = out_dir / "accuracy_worker.log"
    log.write_text("")
    cases = sweep_cases(PROBLEMS, quick)
    load_start = os.getloadavg()
    started = datetime.now().isoformat(timespec="minutes")
    mode = f"Ray, {workers or 'all'} workers" if address or (workers or 1) > 1 else "one child process per precision"
    results = run_sweep(cases, workers, address, log)
    measurement = Measurement(
        hardware=hardware_line(), started=started, load_start=load_start, load_end=os.getloadavg(), mode=mode
    )
    raw = {"cases": [[c.problem, astuple(c.setting), c.reference] for c in cases], "results": results}
    (out_dir / "accuracy_raw.json").write_text(json.dumps(raw | {"measurement": measurement.lines()}))
    failed = write_report(out_dir, PROBLEMS, cases, results, measurement, quick, command)
    print(f"wrote {out_dir}/accuracy.csv, accuracy.md, accuracy_raw.json and accuracy_<problem>.png")
    return 3 if failed else 0
