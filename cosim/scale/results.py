"""Tables of fanned-out runs: a sweep's CSV (rewritten as cases finish) and multi-start loss curves."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


class SweepTable:
    """``out/sweep.csv``: one row per finished case (case, the grid keys' values, status, error, then
    every metric), sorted by case and rewritten after each one, so an interrupted sweep keeps what
    finished."""

    def __init__(self, path: Path, keys: list[str]) -> None:
        self.path, self.keys = Path(path), keys
        self.rows: dict[int, dict] = {}

    def add(self, index: int, assignments: list[str], ok: bool, value) -> None:
        row = {"case": index, **{a.split("=", 1)[0]: a.split("=", 1)[1] for a in assignments}}
        row.update({"status": "ok", "error": ""} if ok else {"status": "failed", "error": str(value)})
        if ok:
            row.update(value)
        self.rows[index] = row
        self.write()

    def write(self) -> None:
        fixed = ["case", *self.keys, "status", "error"]
        metrics = sorted({k for row in self.rows.values() for k in row} - set(fixed))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=fixed + metrics)
            writer.writeheader()
            for index in sorted(self.rows):
                writer.writerow(self.rows[index])

    @property
    def failed(self) -> int:
        return sum(row["status"] != "ok" for row in self.rows.values())


def write_starts(out: Path, starts: dict[int, dict], title: str) -> None:
    """``starts.csv`` (start, perturbation seed, iteration, loss) and ``starts.png``, every start's loss curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    with (out / "starts.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["start", "seed", "iteration", "loss"])
        for k in sorted(starts):
            for it, loss in enumerate(starts[k]["losses"]):
                writer.writerow([k, starts[k]["seed"], it, loss])
    fig, ax = plt.subplots(figsize=(6, 4))
    for k in sorted(starts):
        losses = np.asarray(starts[k]["losses"])
        ax.plot(np.arange(len(losses)), losses, marker=".", label=f"start {k}")
    ax.set_yscale("log" if all(np.all(np.asarray(s["losses"]) > 0) for s in starts.values()) else "linear")
    ax.set_xlabel("iteration")
    ax.set_ylabel("loss")
    ax.set_title(title)
    ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(out / "starts.png", dpi=100)
    plt.close(fig)
