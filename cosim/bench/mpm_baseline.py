"""`cosim bench mpm --baseline DIR`: speed of the current code over a baseline's, in one run on one machine.

DIR is one of:
- the folder made by ``scripts/baseline_env.sh COMMIT DIR`` (``DIR/venv/bin/python``, with the
  checkout ``DIR/src`` installed in it): the usual case;
- any virtualenv with a ``cosim`` installed (``DIR/bin/python``);
- a bare checkout (``DIR/cosim/``), run with this interpreter and ``PYTHONPATH=DIR``.

Both versions run the same ``mpm_measure.py`` by path (it adapts to the baseline's engine API),
each configuration ``repeat`` times per version, each run in its own process. The versions
alternate run by run and their order flips between repeats (baseline first, then current
first, ...), so that the load of a shared machine falls on both alike. Reported: medians per
version and configuration, and the ratios of the medians (current / baseline).
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
from pathlib import Path

from cosim.bench.mpm import (
    CONFIG_COLUMNS,
    Interpreter,
    current_interpreter,
    print_table,
    run_config,
    write_csv,
    write_report,
)
from cosim.errors import InputError

MEASURES = ["fwd_Mpss", "fwd_bwd_Mpss", "bwd_fwd_ratio", "peak_MiB"]


def table(short: str) -> list[tuple[str, str, str]]:
    """The printed columns: the reference's (``ref_``, headed ``short``), the current's and their ratios."""
    return [
        *CONFIG_COLUMNS,
        ("setting", "setting", ">18"),
        ("ref_fwd_Mpss", f"fwd {short}", ">8.2f"),
        ("cur_fwd_Mpss", "fwd cur", ">8.2f"),
        ("ratio_fwd_Mpss", "ratio", ">6.2f"),
        ("ref_fwd_bwd_Mpss", f"f+b {short}", ">8.3f"),
        ("cur_fwd_bwd_Mpss", "f+b cur", ">8.3f"),
        ("ratio_fwd_bwd_Mpss", "ratio", ">6.2f"),
        ("ref_bwd_fwd_ratio", f"b/f {short}", ">8.2f"),
        ("cur_bwd_fwd_ratio", "b/f cur", ">8.2f"),
        ("ref_peak_MiB", f"MiB {short}", ">8.0f"),
        ("cur_peak_MiB", "MiB cur", ">8.0f"),
    ]


HOW = "create one with scripts/baseline_env.sh b24c315 DIR (a git worktree of the commit and a virtualenv)"


def baseline_interpreter(folder: Path) -> Interpreter:
    """The interpreter that runs the baseline in ``folder`` (module docstring); an InputError naming
    what is missing, or if it would import the current cosim."""
    folder = folder.resolve()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # ours would shadow the baseline's cosim
    pythons = [folder / "venv" / "bin" / "python", folder / "bin" / "python"]
    python = next((p for p in pythons if p.exists()), None)
    if python is None and (folder / "cosim" / "__init__.py").exists():
        python, env["PYTHONPATH"] = Path(sys.executable), str(folder)
    if python is None:
        raise InputError(
            f"--baseline {folder}: no python in {folder}/venv/bin or {folder}/bin, and no cosim/ checkout; {HOW}"
        )
    probe = [str(python), "-c", "import cosim; print(cosim.__file__)"]
    res = subprocess.run(probe, capture_output=True, text=True, env=env, cwd=folder, check=False)
    if res.returncode != 0:
        raise InputError(f"--baseline {folder}: {python} cannot import cosim ({res.stderr.strip()[-300:]}); {HOW}")
    root = Path(res.stdout.strip().splitlines()[-1]).resolve().parents[1]
    if root == current_interpreter().root:
        raise InputError(f"--baseline {folder}: {python} imports the current cosim ({root}), not a baseline; {HOW}")
    return Interpreter(str(python), root, env, label="baseline")


def interleaved_runs(configs: list[dict], interps: list[Interpreter], repeat: int) -> list[dict]:
    """Every configuration ``repeat`` times with each interpreter, alternating, the order flipped each repeat."""
    runs = []
    for i in range(repeat):
        for cfg in configs:
            for interp in interps if i % 2 == 0 else interps[::-1]:
                row = {"version": interp.label, "repeat": i, **run_config(cfg, interp), "setting": setting(cfg)}
                runs.append(row)
                print(f"  {i + 1}/{repeat} {interp.label:>8} {row['dim']}D {row['precision']} {row['grid']}: "
                      f"fwd {row['fwd_Mpss']:.2f}, f+b {row['fwd_bwd_Mpss']:.3f} M/s", flush=True)  # fmt: skip
    return runs


def setting(cfg: dict) -> str:
    """The CPU threads and scatter a configuration asks for (``--threads``, ``--scatter``), e.g.
    "2 threads, atomic", or "default": what its runs are grouped by besides the sizes (both versions
    run it so, whatever either reports)."""
    asked = [f"{cfg['threads']} threads"] if "threads" in cfg else []
    asked += [cfg["scatter"]] if "scatter" in cfg else []
    return ", ".join(asked) or "default"


def medians(runs: list[dict], reference: str) -> list[dict]:
    """Per configuration: the median of each measure per version and the current/reference ratios
    (``reference``: the other version's label)."""
    rows = {}
    for r in runs:
        names = ["dim", "precision", "grid", "particles", "setting"]
        key = tuple(r[k] for k in names)
        row = rows.setdefault(key, dict(zip(names, key, strict=True)))
        row.setdefault(r["version"], []).append(r)
    for row in rows.values():
        ref, cur = row.pop(reference), row.pop("current")
        row["reference"] = reference
        for m in MEASURES:
            row[f"ref_{m}"] = statistics.median(r[m] for r in ref)
            row[f"cur_{m}"] = statistics.median(r[m] for r in cur)
            row[f"ratio_{m}"] = row[f"cur_{m}"] / row[f"ref_{m}"]
        row["runs_per_version"] = len(cur)
    return list(rows.values())


def run_baseline_bench(
    out_dir: Path, configs: list[dict], folder: Path, repeat: int, name: str, command: str | None = None
) -> int:
    """Measure ``configs`` with the baseline in ``folder`` and with this cosim (``run_comparison``)."""
    from cosim.bench.report import git_commit

    base = baseline_interpreter(folder)
    print(f"baseline: {base.python} importing {base.root}/cosim; current: {current_interpreter().root}")
    commit = git_commit(base.root)  # the report names the baseline's commit, not only its folder
    described = f"baseline (commit {commit})" if commit else "baseline"
    return run_comparison(out_dir, configs, base, "base", repeat, f"{name}_baseline", command, described)


def run_comparison(
    out_dir: Path, configs: list[dict], reference: Interpreter, short: str, repeat: int, name: str,
    command: str | None = None, described: str | None = None,
) -> int:  # fmt: skip
    """Measure ``configs`` with ``reference`` and with this cosim, interleaved; print and write
    ``out_dir/<name>.csv`` (medians, ratios), ``<name>.md`` (the same, headed by ``command``, the date
    and the hardware) and ``<name>_runs.csv`` (every run). ``short``: the reference in column headers;
    ``described``: the reference in the report's sentence (default its label)."""
    from cosim.hardware import hardware_line

    runs = interleaved_runs(configs, [reference, current_interpreter()], repeat)
    rows = medians(runs, reference.label)
    columns = table(short)
    what = f"Current / {described or reference.label}: medians of {repeat} interleaved runs per version, rates in M/s"
    print(f"\n{what}, on {hardware_line()}")
    print_table(rows, columns)
    write_csv(out_dir / f"{name}.csv", rows)
    write_report(out_dir / f"{name}.md", command, what, rows, columns)
    write_csv(out_dir / f"{name}_runs.csv", runs)
    return 0
