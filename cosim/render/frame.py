"""What one preview picture shows: plain arrays in world coordinates [m], no engine objects.

A ``Frame`` is the whole interface between the simulation and a renderer, so any engine (MPM,
rigid bodies, the coming cloth) hands its geometry over as NumPy arrays:

- particles: positions (N, dim) and a body id per particle (N,), an index into the colours;
- rigid: list of (vertices (V, 3), faces (F, 3)) triangle meshes, posed in the world frame
  (3D); in 2D, list of (n, 2) surface points;
- cloth: list of (vertices (V, 3), faces (F, 3)) triangle meshes in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

Mesh = tuple[np.ndarray, np.ndarray]  # vertices (V, 3) [m], faces (F, 3) vertex indices

PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
    ],
    dtype=np.float64,
)


def body_colors(n: int) -> np.ndarray:
    """(n, 3) RGB in [0, 255]: one colour per MPM body, in scene order."""
    return PALETTE[np.arange(n) % len(PALETTE)]


@dataclass
class Frame:
    """One picture's content; ``body[i]`` indexes the renderer's colour table."""

    positions: np.ndarray  # (N, dim) [m]
    body: np.ndarray  # (N,) int
    rigid: list = field(default_factory=list)  # 3D: list[Mesh]; 2D: list of (n, 2) surface points
    cloth: list[Mesh] = field(default_factory=list)
    label: str = ""

    @classmethod
    def from_bodies(cls, bodies: list[np.ndarray], **kw) -> Frame:
        """A frame from per-body position arrays (body ids = list order)."""
        dim = bodies[0].shape[1] if bodies else 3
        positions = np.concatenate(bodies) if bodies else np.zeros((0, dim))
        body = np.repeat(np.arange(len(bodies)), [len(b) for b in bodies])
        return cls(positions, body, **kw)

    def points(self) -> np.ndarray:
        """Every point the picture must show (particles, mesh vertices), (M, dim): for fitting the camera."""
        parts = [self.positions] + [m[0] if isinstance(m, tuple) else m for m in self.rigid]
        parts += [v for v, _ in self.cloth]
        return np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, self.positions.shape[1]) for p in parts])
