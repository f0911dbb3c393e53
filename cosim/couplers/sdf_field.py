"""``SDFField``: an ``SDFGrid`` uploaded to Taichi and looked up in kernels (the host's lookup is
``SDFGrid.sample``, the same interpolation)."""

import numpy as np
import taichi as ti

from cosim.couplers.sdf_grid import SDFGrid
from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented


@data_oriented
class SDFField:
    """An ``SDFGrid`` uploaded to Taichi (distances and node gradients), looked up in kernels."""

    def __init__(self, grid: SDFGrid):
        self.dim = grid.dim
        self.shape = tuple(grid.values.shape)
        self.origin = ti.Vector([float(o) for o in grid.origin])
        self.spacing = float(grid.spacing)
        self.values = field_pool.scalar(self, float, shape=self.shape)
        self.grads = field_pool.vector(self, self.dim, float, shape=self.shape)
        real = np.float64 if self.values.dtype == ti.f64 else np.float32
        self.values.from_numpy(grid.values.astype(real))
        self.grads.from_numpy(grid.gradients().astype(real))

    @ti.func
    def _cell(self, p):
        """The interpolation cell of body-frame point p: (base node, fraction, distance outside the grid)."""
        upper = self.origin + self.spacing * (ti.Vector(self.shape) - 1)
        clamped = ti.min(ti.max(p, self.origin), upper)
        out2 = (p - clamped).norm_sqr()
        outside = out2 / ti.sqrt(ti.max(out2, 1e-30))  # |p - clamped|, with a finite adjoint at 0
        rel = (clamped - self.origin) / self.spacing
        base = ti.min(ti.max(ti.cast(ti.floor(rel), ti.i32), 0), ti.Vector(self.shape) - 2)
        return base, rel - ti.cast(base, float), outside

    @ti.func
    def _weight(self, frac, corner):
        weight = 1.0
        for k in ti.static(range(self.dim)):
            weight *= frac[k] if corner[k] else 1.0 - frac[k]
        return weight

    @ti.func
    def distance(self, p):
        """Signed distance [m] at body-frame point p (cheaper than ``distance_normal``)."""
        base, frac, outside = self._cell(p)
        dist = 0.0
        for corner in ti.static(ti.grouped(ti.ndrange(*([2] * self.dim)))):
            dist += self._weight(frac, corner) * self.values[base + corner]
        return dist + outside

    @ti.func
    def distance_normal(self, p):
        """Signed distance [m] and unit outward normal at body-frame point p."""
        base, frac, outside = self._cell(p)
        dist = 0.0
        grad = ti.Vector.zero(float, self.dim)
        for corner in ti.static(ti.grouped(ti.ndrange(*([2] * self.dim)))):
            weight = self._weight(frac, corner)
            dist += weight * self.values[base + corner]
            grad += weight * self.grads[base + corner]
        # sqrt(|g|^2 + tiny): the normalisation keeps a finite adjoint where the
        # interpolated gradient vanishes (a box's centre, medial axes)
        return dist + outside, grad / ti.sqrt(grad.norm_sqr() + 1e-24)
