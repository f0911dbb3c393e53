"""A signed distance field on a compact body-frame grid, looked up on the host (NumPy only).

Distances are in metres, negative inside the body. A field is sampled at the
nodes of a regular grid covering the body's bounding box plus ``padding``
(node spacing ``spacing``), then looked up anywhere by multilinear
interpolation. The normal is the SDF's gradient: the exact gradient at the
nodes (closed form for primitives, the direction to the closest surface point
for meshes), interpolated the same way and normalised, so it turns smoothly
around edges and corners instead of jumping between face normals (finite
differences of the node distances were 3-4x less accurate one cell from a box
edge: 14 against 4 degrees, measured). Outside the grid the distance grows by
the distance to the grid's box.

What fills a grid: ``cosim.couplers.sdf`` (primitives, shapes) and
``cosim.couplers.sdf_mesh`` (meshes); its Taichi twin, looked up in kernels, is
``cosim.couplers.sdf_field.SDFField`` (so that ``cosim validate`` builds grids without Taichi).
"""

from dataclasses import dataclass

import numpy as np


@dataclass
class SDFGrid:
    """Signed distances ``values`` at nodes origin + spacing * index (body frame)."""

    origin: np.ndarray  # (d,) [m]
    spacing: float  # [m]
    values: np.ndarray  # (n_0, ..., n_{d-1}) [m], negative inside
    normals: np.ndarray | None = None  # (*values.shape, d) exact gradient at the nodes, if known

    def gradients(self) -> np.ndarray:
        """SDF gradient at the nodes, (*shape, d): the exact one when known, else central
        differences (one-sided at the border)."""
        if self.normals is not None:
            return self.normals
        return np.stack(np.gradient(self.values, self.spacing), axis=-1)

    @property
    def dim(self) -> int:
        return self.values.ndim

    def nodes(self) -> np.ndarray:
        """Body-frame node positions, shape (*values.shape, d)."""
        axes = [self.origin[k] + self.spacing * np.arange(n) for k, n in enumerate(self.values.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance and unit normal at body-frame ``points`` (n, d) (host-side twin of ``SDFField``)."""
        d = self.dim
        shape = np.asarray(self.values.shape)
        upper = self.origin + self.spacing * (shape - 1)
        clamped = np.clip(points, self.origin, upper)
        outside = np.linalg.norm(points - clamped, axis=1)
        rel = (clamped - self.origin) / self.spacing
        base = np.clip(np.floor(rel).astype(int), 0, shape - 2)
        frac = rel - base
        node_grad = self.gradients()
        dist = np.zeros(len(points))
        grad = np.zeros((len(points), d))
        for corner in np.ndindex(*([2] * d)):
            c = np.asarray(corner)
            index = tuple((base + c).T)
            weight = np.prod(np.where(c, frac, 1.0 - frac), axis=1)
            dist += weight * self.values[index]
            grad += weight[:, None] * node_grad[index]
        normal = grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
        return dist + outside, normal


def grid_over(lo: np.ndarray, hi: np.ndarray, spacing: float, padding: float) -> tuple[np.ndarray, tuple]:
    """Origin (d,) [m] and node counts of a grid of node ``spacing`` covering [lo, hi] plus ``padding`` [m]."""
    origin = lo - padding
    counts = np.ceil((hi + padding - origin) / spacing).astype(int) + 1
    return origin, tuple(int(c) for c in counts)
