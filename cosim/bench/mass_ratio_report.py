"""The mass-ratio sweep's rows, table and plot (``cosim.bench.mass_ratio``), for `cosim bench coupling`."""

from __future__ import annotations

import csv
import itertools
import warnings
from pathlib import Path

from cosim.bench.mass_ratio import RATIOS, SETUPS, run, settled_block
from cosim.errors import CouplingWarning

COLUMNS = ["body", "ratio", "scheme", "substeps", "exchanges", "amplification", "late_rms", "height_error", "outcome"]
SUBSTEPS = (4, 8, 20, 40)  # per frame, in the second sweep
# what every strong-coupling row must meet (the bar): perturbations die, the body rests on the
# material within 1 mm/s rms and within one cell of its closed-form height
LIMITS = {"amplification": 1.0, "late_rms": 1e-3}


def sweep(quick: bool = False, schemes: tuple[bool, ...] = (True, False)) -> list[dict]:
    """Every body x ratio x scheme (strong, explicit); ``quick``: r = 1 and 25, fewer frames."""
    ratios = (1.0, 25.0) if quick else RATIOS
    frames, rest = (120, 60) if quick else (200, 100)
    rows = []
    for setup in SETUPS.values():
        block = settled_block(setup, rest)
        for strong in schemes:
            for ratio in ratios:
                row = run(setup, ratio, strong, frames=frames, perturb_at=frames // 2, rest=rest, block=block)
                row["cell"] = setup.dx
                rows.append(row)
                print("  mass ratio: " + ", ".join(f"{k} {_cell(row.get(k))}" for k in COLUMNS), flush=True)
    return rows


def substep_sweep(quick: bool = False) -> list[dict]:
    """The strong coupling at r = 1 and 5 with a fixed number of substeps per frame (``SUBSTEPS``), in the
    exchanges the system chooses and, where that is more than one, once per frame; ``quick``: r = 1 at 4 and 20
    substeps, fewer frames."""
    ratios, counts = ((1.0,), (4, 20)) if quick else ((1.0, 5.0), SUBSTEPS)
    frames, rest = (120, 60) if quick else (200, 100)
    rows = []
    for setup in SETUPS.values():
        block = settled_block(setup, rest)
        for ratio, K in itertools.product(ratios, counts):
            for exchanges in ("auto", 1):  # once per frame only where the system splits the frame
                with warnings.catch_warnings():  # the runner's warning beyond the limit is what this measures
                    warnings.simplefilter("ignore", CouplingWarning)
                    row = run(setup, ratio, True, frames, frames // 2, rest, block, substeps=K, exchanges=exchanges)
                row["cell"], row["chosen"] = setup.dx, exchanges == "auto"
                rows.append(row)
                print("  substeps: " + ", ".join(f"{k} {_cell(row.get(k))}" for k in COLUMNS), flush=True)
                if row["exchanges"] == 1:
                    break
    return rows


def verdict(row: dict) -> str:
    """ "meets" or what it misses of ``LIMITS`` and the one-cell height bound."""
    if row["outcome"] != "ok":
        return "stopped"
    missed = [key for key, limit in LIMITS.items() if row[key] > limit]
    if abs(row["height_error"]) > row["cell"]:
        missed.append("height")
    return "meets" if not missed else "misses " + ", ".join(missed)


def write(rows: list[dict], by_substeps: list[dict], out_dir: Path) -> list[str]:
    """mass_ratio.csv (both sweeps) and mass_ratio.png in ``out_dir``; returns the markdown lines of the tables."""
    with open(out_dir / "mass_ratio.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows + by_substeps)
    _plot(rows, by_substeps, out_dir / "mass_ratio.png")
    lines = [
        (
            "Mass-ratio sweep: a light body resting on an elastic block (1000 kg/m^3), r = block density x dx / "
            "the body's areal density; strong = the added-mass coupling, explicit = the reactions alone "
            "(`cosim.bench.mass_ratio`); bar: amplification <= 1, late rms <= 1 mm/s, height within one cell"
        ),
        "",
        "| body | r | scheme | amplification | late rms [mm/s] | height error [mm] | verdict |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['body']} | {r['ratio']:g} | {r['scheme']} | {_measures(r)} | {verdict(r)} |")
    lines += [
        "",
        (
            "Substeps per frame: the strong coupling with a fixed number of MPM substeps per 2 ms frame (auto takes "
            "4 for the plate's block, 2-3 for the sheet's; a stiffer material takes more), exchanging once per "
            "frame and in the exchanges the system chooses (each within its coupler's `exchange_substeps`)"
        ),
        "",
        "| body | r | substeps per frame | exchanges | amplification | late rms [mm/s] | height error [mm] | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in by_substeps:
        cells = f"{r['body']} | {r['ratio']:g} | {r['substeps']} | {r['exchanges']}"
        lines.append(f"| {cells} | {_measures(r)} | {verdict(r)} |")
    return lines


def _measures(row: dict) -> str:
    if row["outcome"] != "ok":
        return f"- | - | - (stopped: {row['outcome'][:80]})"
    return f"{row['amplification']:.3f} | {1e3 * row['late_rms']:.3g} | {1e3 * row['height_error']:+.2f}"


def _plot(rows: list[dict], by_substeps: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for body in SETUPS:
        for scheme, style in (("strong", "-o"), ("explicit", "--x")):
            sel = [r for r in rows if r["body"] == body and r["scheme"] == scheme and r["outcome"] == "ok"]
            if not sel:
                continue
            ratio = [r["ratio"] for r in sel]
            axes[0].plot(ratio, [r["amplification"] for r in sel], style, label=f"{body}, {scheme}")
            axes[1].plot(ratio, [1e3 * r["late_rms"] for r in sel], style, label=f"{body}, {scheme}")
    axes[0].axhline(1.0, color="gray", lw=0.8)
    axes[1].axhline(1.0, color="gray", lw=0.8)
    axes[0].set(xscale="log", xlabel="r", ylabel="amplification per frame")
    axes[1].set(xscale="log", yscale="log", xlabel="r", ylabel="late rms velocity vs material [mm/s]")
    axes[0].legend(fontsize=8)
    for body, ratio in sorted({(r["body"], r["ratio"]) for r in by_substeps}):
        for chosen, style in ((True, "-o"), (False, "--x")):
            sel = [
                r
                for r in by_substeps
                if (r["body"], r["ratio"]) == (body, ratio) and r["outcome"] == "ok" and r["chosen"] == chosen
            ]
            label = f"{body}, r {ratio:g}, " + ("exchanges as chosen" if chosen else "once per frame")
            axes[2].plot([r["substeps"] for r in sel], [1e3 * r["late_rms"] for r in sel], style, label=label)
    axes[2].axhline(1.0, color="gray", lw=0.8)
    axes[2].set(xscale="log", yscale="log", xlabel="substeps per frame (strong)", ylabel="late rms [mm/s]")
    axes[2].set_xticks(SUBSTEPS, [str(k) for k in SUBSTEPS])
    axes[2].minorticks_off()
    if by_substeps:
        axes[2].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _cell(value) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)[:60]


if __name__ == "__main__":  # `python -m cosim.bench.mass_ratio_report OUT [--quick]`: the sweep alone
    import sys

    from cosim.runtime import ensure_taichi

    ensure_taichi("cpu", "float64")
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    quick = "--quick" in sys.argv
    print("\n".join(write(sweep(quick), substep_sweep(quick), out)))
    print(f"wrote {out}/mass_ratio.csv, mass_ratio.png")
