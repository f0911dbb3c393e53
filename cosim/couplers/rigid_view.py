"""The scene's rigid bodies as one view across engines: names, shapes, SDFs, poses, particle counts.

Kinematic bodies come first, then the coupled DART links; reports and previews read
poses here without knowing which engine moves a body.
"""

from __future__ import annotations

import numpy as np


def _reach(grid) -> float:
    """Largest distance [m] from the body origin to a corner of its SDF grid's box (bounds its surface)."""
    lo = np.asarray(grid.origin, dtype=np.float64)
    hi = lo + grid.spacing * (np.asarray(grid.values.shape) - 1)
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), axis=-1).reshape(-1, len(lo))
    return float(np.linalg.norm(corners, axis=1).max())


class RigidBodies:
    """Names, scene shapes (None for URDF links), SDF grids and current poses of the rigid bodies."""

    def __init__(
        self, names: list[str], shapes: list, grids: list, kinematic=None, coupler=None, dim: int = 3, sources=None
    ):
        self.names = names
        self.shapes = shapes
        self.grids = grids
        self.sources = list(sources or [])  # the MPM's rigid boundary sources: the same SDFs on the device
        self.kinematic = kinematic  # KinematicEngine or None
        self.coupler = coupler  # MPMRigidCoupler or None
        self.dim = dim
        self.reach = [_reach(g) for g in grids]  # [m] farthest point of each body's SDF box from its origin

    def surface_speed(self, frame_dt: float) -> float:
        """[m/s] The fastest any body's surface moves over the next frame: |v| + |w| reach per body, the
        kinematic ones' twists taken at the frame's start and end (a segment may change inside it)."""
        twists = []
        if self.kinematic is not None:
            t = self.kinematic.time
            for motion in self.kinematic.motions:
                _, _, v, w = motion.states([t, t + frame_dt])
                end = np.argmax(np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1))
                twists.append((v[end], w[end]))
        if self.coupler is not None:
            b = self.coupler.current_bodies()
            twists += list(zip(b.v, b.w))
        speeds = [np.linalg.norm(v) + np.linalg.norm(w) * r for (v, w), r in zip(twists, self.reach)]
        return float(max(speeds, default=0.0))

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
