"""Particles that went through a rigid body: a check on the contact models' result, per macro step.

A particle went through body b when it is outside b now, on the opposite side from where it was last
seen outside (the outward normals there and now opposed), and was inside b in between: at the start
of this step, or somewhere on its straight path over the step in b's frame (sampled every ``spacing``).
Sliding along a surface, or a particle pushed back out the way it came in, is not counted; a
particle that slips into a thin wall and out of its far side over several steps is.
"""

from __future__ import annotations

import numpy as np


class TunnelWatch:
    """Per rigid body, each particle's outward normal where it was last seen outside."""

    def __init__(self, rigid, n_particles: int, spacing: float):
        self.rigid, self.spacing = rigid, spacing
        self.last_normal = [np.zeros((n_particles, rigid.dim)) for _ in rigid.grids]

    def reset(self) -> None:
        for normals in self.last_normal:
            normals[:] = 0.0

    def step(self, x0: np.ndarray, poses0: list, x1: np.ndarray) -> dict[str, np.ndarray]:
        """Indices of the particles that went through each body over a step from positions ``x0``
        (bodies at ``poses0``) to ``x1`` (bodies where they are now)."""
        out = {}
        bodies = zip(self.rigid.names, self.rigid.grids, poses0, self.rigid.poses(), self.last_normal)
        for name, grid, (p0, R0), (p1, R1), last in bodies:
            a, b = (x0 - p0) @ R0, (x1 - p1) @ R1  # world to body frame at each end
            da, na = grid.sample(a)
            db, nb = grid.sample(b)
            last[da >= 0] = na[da >= 0]
            inside = da < 0
            travel = np.linalg.norm(b - a, axis=1)
            flipped = (db >= 0) & (np.sum(last * nb, axis=1) < 0)
            path = np.flatnonzero(flipped & ~inside & (da < travel))  # may have crossed within the step
            if len(path):
                n = int(min(64, max(2, np.ceil(travel[path].max() / self.spacing))))
                for t in np.linspace(0.0, 1.0, n + 1)[1:-1]:
                    inside[path] |= grid.sample(a[path] + t * (b[path] - a[path]))[0] < 0
            out[name] = np.flatnonzero(flipped & inside)
            last[db >= 0] = nb[db >= 0]
        return out
