"""`cosim bench mpm --sizes`: the grid grows with the block so that it keeps 8 particles per cell
(2 per axis) and fills the same share of the domain, at every size of the sweep."""

from __future__ import annotations

import numpy as np

from cosim.bench.mpm import FILL, SIZES, sized_grid
from cosim.bench.mpm_measure import block_points


def test_sized_grid_keeps_8_particles_per_cell():
    for particles, _, _ in SIZES:
        cfg = sized_grid(particles)
        pts = block_points(3, cfg["cells"], cfg["side"])
        assert abs(len(pts) / particles - 1) < 0.1, cfg  # the size asked for, within 10%
        cell = np.floor(pts * cfg["cells"]).astype(np.int64) @ cfg["cells"] ** np.arange(3)  # flat cell index
        counts = np.bincount(cell)
        assert abs(np.median(counts[counts > 0]) / 8 - 1) < 0.1, cfg  # a cell inside holds 2 x 2 x 2
        span = np.ptp(pts, axis=0).max() + 0.5 / cfg["cells"]  # [m] the block's side; the domain's is 1
        assert abs(span / FILL - 1) < 0.1, cfg  # the same share of the domain at every size
