"""Placing the bodies of a random scene (``cosim.bench.fuzz_scenes``): apart, or just beside a soft body."""

from __future__ import annotations

import math

import numpy as np


def log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A number drawn uniformly in log between lo and hi."""
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def rounded(values, digits: int = 5):
    """Floats as the YAML file would hold them (short, and plain Python floats)."""
    if isinstance(values, (list, tuple, np.ndarray)):
        return [rounded(v, digits) for v in values]
    return float(round(float(values), digits))


class Space:
    """The domain [m] and the boxes taken so far, to place bodies apart from each other, or next to a
    soft body (a gap of up to a cell: in a few frames they meet, and the contact code runs)."""

    def __init__(self, rng: np.random.Generator, domain: np.ndarray, margin: float, dx: float):
        self.rng, self.domain, self.margin, self.dx = rng, domain, margin, dx
        self.taken: list[tuple[np.ndarray, np.ndarray]] = []
        self.soft: list[int] = []  # which of ``taken`` are soft bodies
        self.target: np.ndarray | None = None  # [m] the centre of the soft body the last place_near chose

    def _free(self, center: np.ndarray, half: np.ndarray, clearance: float) -> bool:
        lo, hi = center - half - clearance, center + half + clearance
        return all(np.any(hi <= a) or np.any(lo >= b) for a, b in self.taken)

    def _take(self, center: np.ndarray, half: np.ndarray, soft: bool) -> np.ndarray:
        if soft:
            self.soft.append(len(self.taken))
        self.taken.append((center - half, center + half))
        return center

    def place(self, half: np.ndarray, wall: bool = False, soft: bool = False, tries: int = 40) -> np.ndarray | None:
        """A centre for a body of half extents ``half`` [m] inside the usable domain and clear (by a
        cell) of the bodies placed so far; ``wall``: flush against one wall's margin. None: no room."""
        lo, hi = self.margin + half, self.domain - self.margin - half
        if np.any(lo > hi):
            return None
        for _ in range(tries):
            center = self.rng.uniform(lo, hi)
            if wall:
                axis = int(self.rng.integers(len(half)))
                center[axis] = lo[axis] if self.rng.random() < 0.7 else hi[axis]
            if self._free(center, half, self.dx):
                return self._take(center, half, soft)
        return None

    def place_near(self, half: np.ndarray, soft: bool = False, tries: int = 40) -> np.ndarray | None:
        """A centre beside a soft body placed before, ``half`` [m] apart by a gap of 0.05-1 cell along
        one axis (below it twice in three: gravity brings them together), overlapping it across."""
        self.target = None
        if not self.soft:
            return self.place(half, soft=soft)
        d = len(half)
        margin = self.margin if soft else 0.0  # soft bodies keep out of the walls
        lo, hi = margin + half, self.domain - margin - half
        for _ in range(tries):
            a, b = self.taken[self.soft[int(self.rng.integers(len(self.soft)))]]
            gap = self.rng.uniform(0.05, 1.0) * self.dx
            axis = 1 if self.rng.random() < 0.5 else int(self.rng.integers(d))
            below = self.rng.random() < 0.67
            center = self.rng.uniform(np.minimum(a, b - half), np.maximum(b, a + half))
            center[axis] = a[axis] - gap - half[axis] if below else b[axis] + gap + half[axis]
            if np.all(center >= lo) and np.all(center <= hi) and self._free(center, half, 0.99 * gap):
                self.target = 0.5 * (a + b)
                return self._take(center, half, soft)
        return self.place(half, soft=soft)
