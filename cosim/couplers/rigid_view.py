"""The scene's rigid bodies as one view across engines: names, shapes, SDFs, poses, particle counts.

Kinematic bodies come first, then the coupled DART links; reports and previews read
poses here without knowing which engine moves a body.
"""

from __future__ import annotations

import numpy as np


class RigidBodies:
    """Names, scene shapes (None for URDF links), SDF grids and current poses of the rigid bodies."""

    def __init__(self, names: list[str], shapes: list, grids: list, kinematic=None, coupler=None, dim: int = 3):
        self.names = names
        self.shapes = shapes
        self.grids = grids
        self.kinematic = kinematic  # KinematicEngine or None
        self.coupler = coupler  # MPMRigidCoupler or None
        self.dim = dim

    def poses(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(position, rotation) of every body now: kinematic ones, then DART links."""
        out = self.kinematic.poses() if self.kinematic is not None else []
        if self.coupler is not None:
            b = self.coupler.current_bodies()
            d = self.dim
            out += [(p[:d].copy(), R[:d, :d].copy()) for p, R in zip(b.pos, b.R)]
        return out

    def particles_inside(self, x: np.ndarray, depth: float = 0.0) -> dict[str, int]:
        """How many particles sit inside each body (signed distance < -depth) now."""
        out = {}
        for name, grid, (p, R) in zip(self.names, self.grids, self.poses()):
            d, _ = grid.sample((x - p) @ R)  # world to body frame: R^T (x - p)
            out[name] = int(np.sum(d < -depth))
        return out

    def particles_held(self, x: np.ndarray) -> dict[str, int]:
        """How many particles each container body (glass, ring) holds in its cavity now
        (not counting those inside its wall, which ``particles_inside`` counts)."""
        from cosim.couplers.sdf import in_cavity, is_container

        out = {}
        for name, shape, grid, (p, R) in zip(self.names, self.shapes, self.grids, self.poses()):
            if shape is not None and is_container(shape):
                local = (x - p) @ R
                out[name] = int(np.sum(in_cavity(shape, local) & (grid.sample(local)[0] >= 0)))
        return out
