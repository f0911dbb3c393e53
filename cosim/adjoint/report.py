"""What `cosim optimize` writes per iteration: a CSV of the history and a loss-curve PNG."""

from __future__ import annotations

import csv
from pathlib import Path


def write_history(out_dir: Path, rows: list[dict]) -> Path:
    """``optimization.csv``: one row per iteration (iteration, loss, each loss term, the gradient's
    norm per parameter "grad:<name>", seconds), columns in first-seen order."""
    path = Path(out_dir) / "optimization.csv"
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    return path


def plot_losses(out_dir: Path, losses: list[float], title: str) -> Path:
    """``loss.png``: the loss per iteration (log scale when it is positive), like the paper's Fig. 5g."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(out_dir) / "loss.png"
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ax.plot(range(len(losses)), losses, marker="o", markersize=3)
    if all(v > 0 for v in losses):
        ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
