"""Work-precision diagrams: the Pareto front of (cost, error) points, the CSV, the plot, the summary.

A point is a measured setting of one problem: its cost in wall seconds per simulated second and
its relative error. The front holds the points no other point beats on both (as in the
work-precision diagrams of ODE solvers, e.g. Hairer and Wanner); the summary says where the
shipped default setting sits against it and which measured setting reaches an error target cheapest.
"""

from __future__ import annotations

import csv
import math
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

ERROR_FLOOR = 1e-7  # errors below this are drawn at it (a log axis has no zero)
# The summary names a setting better than the default only by more than these factors: cost, because
# the same work can measure up to about 2x apart on a loaded machine; error, because
# smaller differences are not worth a change of setting (the errors themselves are reproducible).
COST_TIE, ERROR_TIE = 2.0, 1.2


def pareto_front(costs: Sequence[float], errors: Sequence[float]) -> list[int]:
    """Indices of the non-dominated points, by increasing cost: no other point has a cost and an error
    both at most its own with one strictly lower. Points with a non-finite cost or error are left out;
    of exact duplicates the first is kept."""
    points = [(c, e, i) for i, (c, e) in enumerate(zip(costs, errors)) if math.isfinite(c) and math.isfinite(e)]
    points.sort(key=lambda p: (p[0], p[1], p[2]))
    front, best = [], math.inf
    for cost, error, index in points:
        if error < best:
            front.append(index)
            best = error
    return front


def cheapest_within(costs: Sequence[float], errors: Sequence[float], target: float) -> int | None:
    """Index of the cheapest point whose error is at most ``target`` (None if none is)."""
    ok = [i for i, (c, e) in enumerate(zip(costs, errors)) if math.isfinite(c) and e <= target]
    return min(ok, key=lambda i: costs[i]) if ok else None


def best_within(costs: Sequence[float], errors: Sequence[float], budget: float) -> int | None:
    """Index of the most accurate point costing at most ``budget`` (None if none does)."""
    ok = [i for i, (c, e) in enumerate(zip(costs, errors)) if c <= budget and math.isfinite(e)]
    return min(ok, key=lambda i: errors[i]) if ok else None


def write_csv(path: Path, rows: list[dict], columns: list[str], header: list[str]) -> None:
    """``rows`` as CSV under ``header`` lines written as ``# ...`` comments (hardware, load, date)."""
    with open(path, "w", newline="") as f:
        f.writelines(f"# {line}\n" for line in header)
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def plot(path: Path, title: str, rows: list[dict], front: list[int], default: int | None, xlabel: str) -> None:
    """Error against cost, log-log: every setting (colour: grid cells per metre; marker: contact model
    or precision; CFL number written beside it), the Pareto front as a line, the default ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 5.0), dpi=110)
    cells = sorted({r["cells"] for r in rows})
    colours = dict(zip(cells, plt.cm.viridis(np.linspace(0.0, 0.85, len(cells)))))
    kinds = sorted({_kind(r) for r in rows})
    markers = dict(zip(kinds, "osD^vP*X"))
    shown = set()
    for r in rows:
        x, y = r["cost"], max(r["error"], ERROR_FLOOR)
        label = f"{r['cells']} cells/m, {_kind(r)}"
        ax.scatter(
            x, y, color=colours[r["cells"]], marker=markers[_kind(r)], s=36, zorder=3,
            label=None if label in shown else label,
        )  # fmt: skip
        shown.add(label)
        ax.annotate(f"{r['cfl']:g}", (x, y), textcoords="offset points", xytext=(4, 3), fontsize=6, color="0.35")
    if front:
        fx = [rows[i]["cost"] for i in front]
        fy = [max(rows[i]["error"], ERROR_FLOOR) for i in front]
        ax.step(fx, fy, where="post", color="crimson", lw=1.2, zorder=2, label="Pareto front")
    if default is not None:
        d = rows[default]
        ax.scatter(
            d["cost"], max(d["error"], ERROR_FLOOR), s=260, facecolors="none", edgecolors="crimson",
            linewidths=1.6, zorder=4, label="shipped default",
        )  # fmt: skip
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # minor labels collide on short ranges
    ax.set_xlabel(xlabel)
    ax.set_ylabel("relative error")
    ax.set_title(textwrap.fill(title, 90), fontsize=9)
    ax.grid(True, which="both", lw=0.3, alpha=0.5)
    ax.legend(fontsize=6, loc="best")
    fig.text(0.99, 0.01, "numbers beside points: time.cfl", ha="right", fontsize=6, color="0.35")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _kind(row: dict) -> str:
    return f"{row['contact']}, {row['precision']}" if row.get("contact") else row["precision"]


def default_position(
    rows: list[dict], front: list[int], default: int, cost_tie: float = 1.0, error_tie: float = 1.0
) -> dict:
    """Where the default sits: on the front or not; the cheapest setting at least as accurate and how
    much cheaper; the most accurate setting at most as costly and how much more accurate. An
    alternative counts only when it is cheaper by more than the factor ``cost_tie`` (the timing's
    spread on a shared machine) or more accurate by more than ``error_tie``; else the entry is the
    default itself."""
    costs = [r["cost"] for r in rows]
    errors = [r["error"] for r in rows]
    d = rows[default]
    cheaper = cheapest_within(costs, errors, d["error"])
    if cheaper is None or costs[cheaper] * cost_tie >= d["cost"]:
        cheaper = default
    better = best_within(costs, errors, d["cost"])
    if better is None or errors[better] * error_tie >= d["error"]:
        better = default
    return {
        "on_front": default in front,
        "cheaper": cheaper,
        "speedup": d["cost"] / costs[cheaper],
        "better": better,
        "error_ratio": d["error"] / errors[better] if errors[better] > 0 else math.inf,
    }
