"""Particle sampling: a body's particles x spacing^d approximate the shape's exact volume.

The lattice error is about surface area x spacing / 2, so for shapes of 20+
spacings across the relative error stays below 5%.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from cosim.sampling import sample_shape
from cosim.scene import BoxShape, CylinderShape, SphereShape


@pytest.mark.parametrize(
    "shape,dim,exact",
    [
        (BoxShape(type="box", center=[0.5, 0.5], size=[0.3, 0.2]), 2, 0.06),
        (SphereShape(type="sphere", center=[0.5, 0.5], radius=0.15), 2, math.pi * 0.15**2),
        (SphereShape(type="sphere", center=[0.5, 0.5, 0.5], radius=0.15), 3, 4 / 3 * math.pi * 0.15**3),
        (
            CylinderShape(type="cylinder", center=[0.5, 0.5, 0.5], radius=0.1, height=0.3, axis="z"),
            3,
            math.pi * 0.01 * 0.3,
        ),
    ],
    ids=["box2d", "disc", "ball", "cylinder"],
)
def test_sampled_volume_matches_the_shape(shape, dim, exact):
    spacing = 0.01
    pts = sample_shape(shape, dim, spacing, 0.0, np.random.default_rng(0), "shape", Path("."))
    assert abs(len(pts) * spacing**dim - exact) / exact < 0.05
    assert np.allclose(pts.mean(axis=0), shape.center, atol=spacing)


def test_cylinder_axis_is_respected():
    shape = CylinderShape(type="cylinder", center=[0.5, 0.5, 0.5], radius=0.05, height=0.4, axis="x")
    pts = sample_shape(shape, 3, 0.01, 0.0, np.random.default_rng(0), "shape", Path("."))
    extent = pts.max(axis=0) - pts.min(axis=0)
    assert extent[0] > 0.35 and extent[1] < 0.11 and extent[2] < 0.11


def test_jitter_stays_within_its_fraction_of_the_spacing():
    shape = BoxShape(type="box", center=[0.5, 0.5], size=[0.2, 0.2])
    plain = sample_shape(shape, 2, 0.01, 0.0, np.random.default_rng(1), "s", Path("."))
    jittered = sample_shape(shape, 2, 0.01, 0.4, np.random.default_rng(1), "s", Path("."))
    offset = np.abs(jittered - plain)
    assert offset.max() <= 0.2 * 0.01 + 1e-12 and offset.max() > 0.15 * 0.01
