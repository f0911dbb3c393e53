"""The accuracy benchmark's outputs from its cases' observations: errors, fronts, CSV, plots, summary.

``write_report`` turns (case, observation) pairs into rows (the error against the closed form or
the problem's reference observation), finds each problem's Pareto front (``work_precision``) and
writes ``accuracy.csv``, ``accuracy_<problem>.png`` and ``accuracy.md``: where each shipped
default sits against the front, the observed convergence order in dx, and the cheapest measured
setting for each error target.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from cosim.bench import work_precision as wp
from cosim.bench.accuracy_measures import convergence_order

TARGETS = (0.2, 0.1, 0.05, 0.02, 0.01, 0.001)  # relative errors of the recommendation table
COLUMNS = [
    "problem", "cells", "dx", "cfl", "precision", "contact", "reference", "default", "on_front", "status",
    "error", "cost", "wall_cost", "cpu_seconds", "seconds", "sim_seconds", "total_s", "particles", "substeps", "load1",
]  # fmt: skip
_OWN = {"seconds", "cpu_seconds", "sim_seconds", "cost", "wall_cost", "total_s", "particles", "substeps", "load1"}


@dataclass
class Measurement:
    """Under what the cases ran: hardware line, start time, load averages (1, 5, 15 min), how."""

    hardware: str
    started: str
    load_start: tuple[float, float, float]
    load_end: tuple[float, float, float]
    mode: str

    def lines(self) -> list[str]:
        def load(v: tuple[float, float, float]) -> str:
            return " / ".join(f"{x:.2f}" for x in v)

        return [
            f"hardware: {self.hardware}",
            f"started {self.started}; cases run {self.mode}; Taichi with advanced kernel optimisation",
            f"load average (1 / 5 / 15 min): {load(self.load_start)} at the start, {load(self.load_end)} at the end",
        ]


def rows_of(problems: dict, cases: list, results: list) -> list[dict]:
    """One row per case: its setting, status, error, cost and the scalars of its observation (``obs_*``)."""
    refs = {c.problem: r for c, r in zip(cases, results) if c.reference and isinstance(r, dict)}
    rows = []
    for case, result in zip(cases, results):
        p, s = problems[case.problem], case.setting
        row = {
            "problem": case.problem, "cells": s.cells, "dx": 1.0 / s.cells, "cfl": s.cfl, "precision": s.precision,
            "contact": s.contact, "reference": case.reference, "default": s == p.default and not case.reference,
            "on_front": False, "error": math.nan, "cost": math.nan,
        }  # fmt: skip
        if not isinstance(result, dict):
            rows.append(row | {"status": result or "not run"})
            continue
        row |= {k: v for k, v in result.items() if k in _OWN}
        row |= {f"obs_{k}": v for k, v in result.items() if k not in _OWN and not isinstance(v, list)}
        reference = refs.get(case.problem)
        if case.reference:
            row["status"] = "reference"
        elif p.closed_form or reference is not None:
            row["status"], row["error"] = "ok", float(p.error(result, reference))
        else:
            row["status"] = "no reference"
        rows.append(row)
    return rows


def write_report(
    out_dir: Path, problems: dict, cases: list, results: list, measurement, quick: bool, command: str | None = None
) -> int:
    """Write accuracy.csv, the diagrams and accuracy.md (headed by ``command``, the date and the hardware:
    ``cosim.bench.report``); returns the number of failed cases."""
    from cosim.bench.report import bench_command, report_header

    rows = rows_of(problems, cases, results)
    sections, summary, targets = [], [], []
    for name, problem in problems.items():
        mine = [r for r in rows if r["problem"] == name and r["status"] == "ok" and math.isfinite(r["error"])]
        if not mine:
            continue
        front = wp.pareto_front([r["cost"] for r in mine], [r["error"] for r in mine])
        for i in front:
            mine[i]["on_front"] = True
        default = next((i for i, r in enumerate(mine) if r["default"]), None)
        title = f"{problem.title}: {problem.error_measure}"
        wp.plot(out_dir / f"accuracy_{name}.png", title, mine, front, default, _cost_label(problem))
        summary.append(_summary_row(problem, mine, front, default))
        targets.append(_target_row(name, mine))
        sections += _section(problem, mine)
    extra = sorted({k for r in rows for k in r if k.startswith("obs_")})
    wp.write_csv(out_dir / "accuracy.csv", rows, COLUMNS + extra, measurement.lines())
    failed = [r for r in rows if r["status"] not in ("ok", "reference")]
    lines = ["Accuracy benchmark" + (" (--quick: a smoke run, not a measurement)" if quick else ""), ""]
    lines += [f"{line}  " for line in measurement.lines()[1:]] + [""]  # [0], the hardware, is in the header
    lines += [
        "Cost (`s / sim s`): CPU seconds of the macro steps after the first (which compiles) per simulated",
        "second, one Taichi thread per case (gradient: one forward + backward over the rollout); the wall",
        "time, which stretches with the machine's load, is in accuracy.csv. Errors are relative; see",
        f"docs/accuracy.md. A setting beats the default only by more than {wp.COST_TIE:g}x in cost",
        f"or {wp.ERROR_TIE:g}x in error.",
        "",
        "## Problems",
        "",
        "| problem | error | compared with | shipped default |",
        "|---|---|---|---|",
    ]
    lines += [f"| {p.name} | {p.error_measure} | {p.source} | {p.default.label()} |" for p in problems.values()]
    lines += ["", "## Where the shipped defaults sit", "", *_SUMMARY_HEAD, *summary, ""]
    lines += ["## Cheapest measured setting per error target", ""]
    lines += ["| problem | " + " | ".join(f"{t:.3g}" for t in TARGETS) + " |", "|---" * (len(TARGETS) + 1) + "|"]
    lines += [*targets, "", *sections]
    if failed:
        lines += ["## Failed cases", ""] + [f"- {r['problem']} {_setting(r)}: {r['status']}" for r in failed] + [""]
    header = report_header(command or bench_command("accuracy", quick=quick))
    (out_dir / "accuracy.md").write_text(header + "\n".join(lines))
    print("\n".join(lines[: lines.index("## Cheapest measured setting per error target") + 4 + len(targets)]))
    return len(failed)


_SUMMARY_HEAD = [
    (
        "| problem | default | error | s / sim s | on the front | cheapest setting at least as accurate "
        "| most accurate setting at most as costly | observed order in dx |"
    ),
    "|---|---|---|---|---|---|---|---|",
]


def _cost_label(problem) -> str:
    what = "forward + backward" if problem.name == "gradient" else "forward"
    return f"CPU seconds per simulated second ({what}, one thread, compile excluded)"


def _setting(r: dict) -> str:
    contact = f", {r['contact']}" if r["contact"] else ""
    return f"{r['cells']} cells/m, cfl {r['cfl']:g}, {r['precision']}{contact}"


def _summary_row(problem, rows: list[dict], front: list[int], default: int | None) -> str:
    order = _order(problem, rows)
    if default is None:
        return f"| {problem.name} | {problem.default.label()} (not measured) | | | | | | {order} |"
    d, pos = rows[default], wp.default_position(rows, front, default, wp.COST_TIE, wp.ERROR_TIE)
    cheaper = "the default" if pos["cheaper"] == default else (
        f"{_setting(rows[pos['cheaper']])}: {rows[pos['cheaper']]['cost']:.3g} s ({pos['speedup']:.2g}x cheaper)"
    )  # fmt: skip
    better = "the default" if pos["better"] == default else (
        f"{_setting(rows[pos['better']])}: {rows[pos['better']]['error']:.2g} ({pos['error_ratio']:.2g}x smaller)"
    )  # fmt: skip
    return (
        f"| {problem.name} | {_setting(d)} | {d['error']:.2g} | {d['cost']:.3g} | "
        f"{'yes' if pos['on_front'] else 'no'} | {cheaper} | {better} | {order} |"
    )


def _order(problem, rows: list[dict]) -> str:
    """Slope of log error against log dx at the default CFL number, precision and contact model."""
    d = problem.default
    line = sorted(
        (r for r in rows if (r["cfl"], r["precision"], r["contact"]) == (d.cfl, d.precision, d.contact)),
        key=lambda r: r["cells"],
    )
    if len(line) < 2:
        return ""
    p = convergence_order([r["dx"] for r in line], [r["error"] for r in line])
    errors = ", ".join(f"{r['error']:.2g}" for r in line)
    return f"{p:.2f} ({'/'.join(str(r['cells']) for r in line)} cells/m: {errors})"


def _target_row(name: str, rows: list[dict]) -> str:
    costs, errors = [r["cost"] for r in rows], [r["error"] for r in rows]
    cells = []
    for t in TARGETS:
        i = wp.cheapest_within(costs, errors, t)
        cells.append("none measured" if i is None else f"{_setting(rows[i])} ({costs[i]:.3g} s)")
    return f"| {name} | " + " | ".join(cells) + " |"


def _section(problem, rows: list[dict]) -> list[str]:
    out = [
        f"## {problem.name}: {problem.title}",
        "",
        f"Error: {problem.error_measure}. Compared with: {problem.source}.",
        "",
        f"![{problem.name}](accuracy_{problem.name}.png)",
        "",
        "| cells/m | cfl | precision | contact | error | s / sim s | front | observed |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(rows, key=lambda r: (r["contact"], r["precision"], r["cells"], r["cfl"])):
        seen = ", ".join(f"{k[4:]} {_num(v)}" for k, v in r.items() if k.startswith("obs_"))
        mark = "default" if r["default"] else ""
        out.append(
            f"| {r['cells']} | {r['cfl']:g} | {r['precision']} | {r['contact']} | {r['error']:.3g} | "
            f"{r['cost']:.3g} | {'yes' if r['on_front'] else ''} {mark} | {seen} |"
        )
    return out + [""]


def _num(v) -> str:
    return f"{v:.5g}" if isinstance(v, float) else str(v)
