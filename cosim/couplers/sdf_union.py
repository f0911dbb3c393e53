"""The signed distance field of several rigidly joined shapes as one body, sealed at its seams.

The minimum of the members' distances is exact outside the union but wrong inside it: where
two members touch (a wall standing on a plate), a point just inside the seam is a hair from
both members' surfaces, with normals along the seam, so material reaching it is pushed
along the seam and out of the other side (water leaked from a three-link tub that way).
Inside, the union's distance is the distance to the part of the members' surfaces that no
other member covers. That is the member's own distance where its nearest surface point is
exposed, and otherwise the distance to the exposed surface, found among samples of it with a
KD-tree (``scipy.spatial.cKDTree``): the samples are the grid nodes near each member's
surface projected onto it, so the error is a small fraction of the node spacing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from cosim.couplers.sdf_grid import SDFGrid, grid_over

COVERED = 0.1  # [spacings] a surface point closer than this to another member's inside is covered
SAMPLES = 3  # exposed-surface samples per node spacing and axis
PROJECTIONS = 3  # steps p <- p - d(p) n(p) taking a sample onto its member's surface
ON_SURFACE = 0.2  # a projected sample farther than this x the cover tolerance from its surface is dropped


class Member:
    """One shape of the union: its SDF grid and its pose (R, t) in the union's frame [m]."""

    def __init__(self, grid: SDFGrid, R: np.ndarray, t: np.ndarray):
        self.grid, self.R, self.t = grid, np.asarray(R, float), np.asarray(t, float)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance [m] and outward unit normal at union-frame ``points`` (n, d)."""
        d, n = self.grid.sample((points - self.t) @ self.R)
        return d, n @ self.R.T

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The union-frame box around this member's grid."""
        g = self.grid
        hi = g.origin + g.spacing * (np.asarray(g.values.shape) - 1)
        corners = np.stack(np.meshgrid(*zip(g.origin, hi), indexing="ij"), axis=-1).reshape(-1, g.dim)
        placed = corners @ self.R.T + self.t
        return placed.min(axis=0), placed.max(axis=0)


def _exposed(points: np.ndarray, owner: np.ndarray, members: list[Member], tolerance: float) -> np.ndarray:
    """Which ``points`` lie on member ``owner[k]``'s surface (within ON_SURFACE of ``tolerance``)
    with no other member covering them (closer than ``tolerance`` [m] to its inside)."""
    keep = np.ones(len(points), bool)
    for j, m in enumerate(members):
        d, _ = m.sample(points)
        keep &= np.where(owner == j, np.abs(d) < ON_SURFACE * tolerance, d >= tolerance)
    return keep


def _exposed_surface(members: list[Member], nodes: np.ndarray, dist: np.ndarray, spacing: float, tolerance: float):
    """Points (n, d) [m] of the members' surfaces that no other member covers, about SAMPLES per
    node spacing along the surface: points of a finer lattice around the nodes near each member's
    surface, projected onto it along its normal."""
    d = nodes.shape[1]
    fine = (np.arange(SAMPLES) + 0.5) / SAMPLES - 0.5
    offsets = np.stack(np.meshgrid(*([fine] * d), indexing="ij"), axis=-1).reshape(-1, d) * spacing
    points, owners = [], []
    for i, m in enumerate(members):
        near = nodes[np.abs(dist[i]) < spacing]
        q = (near[:, None, :] + offsets[None]).reshape(-1, d)
        for _ in range(PROJECTIONS):  # interpolated normals bend near edges: one step can land inside
            di, ni = m.sample(q)
            q = q - di[:, None] * ni
        points.append(q)
        owners.append(np.full(len(q), i))
    points, owner = np.concatenate(points), np.concatenate(owners)
    return points[_exposed(points, owner, members, tolerance)]


def union_sdf(members: list[Member], spacing: float, padding: float) -> SDFGrid:
    """The union of ``members`` as one SDF grid (node ``spacing`` [m], ``padding`` [m] around the
    members' boxes) with exact node normals: sealed along the seams where members touch."""
    boxes = [m.bounds() for m in members]
    lo, hi = np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)
    origin, counts = grid_over(lo, hi, spacing, padding)
    grid = SDFGrid(origin, spacing, np.zeros(counts))
    nodes = grid.nodes().reshape(-1, grid.dim)
    samples = [m.sample(nodes) for m in members]
    dist = np.stack([d for d, _ in samples])  # (members, nodes)
    normal = np.stack([n for _, n in samples])
    nearest = np.argmin(dist, axis=0)
    index = np.arange(len(nodes))
    values, normals = dist[nearest, index], normal[nearest, index]
    if len(members) > 1:
        tolerance = COVERED * spacing
        surface = _exposed_surface(members, nodes, dist, spacing, tolerance)
        inside = np.flatnonzero(values <= 0)
        # an inside node whose nearest member surface point is covered lies by a seam
        foot = nodes[inside] - values[inside, None] * normals[inside]
        by_seam = inside[~_exposed(foot, nearest[inside], members, tolerance)]
        if len(by_seam) and len(surface):
            depth, k = cKDTree(surface).query(nodes[by_seam])
            values[by_seam] = -depth
            normals[by_seam] = (surface[k] - nodes[by_seam]) / np.maximum(depth, 1e-12)[:, None]
    grid.values = values.reshape(counts)
    grid.normals = normals.reshape(*counts, grid.dim)
    return grid
