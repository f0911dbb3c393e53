"""Cloth contact planes from python-fcl against the closed-form signed distances of our primitives."""

from types import SimpleNamespace

import numpy as np
import pytest

from cosim.couplers.cloth_rigid import RigidObstacles
from cosim.couplers.sdf import primitive_distance
from cosim.engines import so3

SHAPES = {
    "box": (SimpleNamespace(type="box", size=[0.2, 0.1, 0.3]), 1e-12),
    "sphere": (SimpleNamespace(type="sphere", radius=0.1), 2e-4),  # fcl's GJK on round shapes: ~1e-4 m
    "cylinder": (SimpleNamespace(type="cylinder", radius=0.05, height=0.3), 2e-4),
    "capsule": (SimpleNamespace(type="capsule", radius=0.05, height=0.2), 2e-4),
}
RADIUS = 0.03


def _size(shape) -> dict:
    if shape.type == "box":
        return {"half": 0.5 * np.asarray(shape.size)}
    return {k: v for k, v in vars(shape).items() if k != "type"}


@pytest.mark.parametrize("kind", list(SHAPES))
def test_planes_match_primitive_distances_on_a_moved_body(kind):
    """Every point within RADIUS of the rotated, moved body gets a plane, and the plane's offset
    n . (x - p) is the signed distance (negative inside: the normal points out of the body)."""
    shape, tol = SHAPES[kind]
    obstacles = RigidObstacles([shape], ".", ["shape"])
    pos, R = np.array([0.5, 0.4, 0.6]), so3.exp(np.array([0.3, -0.5, 0.7]))
    points = pos + np.random.default_rng(0).uniform(-0.25, 0.25, (3000, 3))
    planes = obstacles.planes(points, [(pos, R)], RADIUS)
    exact = primitive_distance(kind, (points - pos) @ R, **_size(shape))
    assert set(planes.index) == set(np.flatnonzero(exact < RADIUS))
    offset = np.einsum("ij,ij->i", points[planes.index] - planes.point, planes.normal)
    np.testing.assert_allclose(offset, exact[planes.index], atol=tol)
    np.testing.assert_allclose(np.linalg.norm(planes.normal, axis=1), 1.0, atol=1e-12)


def test_glass_wall_is_a_sheet_with_planes_on_both_sides():
    """A glass is an fcl triangle mesh: points just inside and just outside its wall both get a plane
    whose normal points back to their own side, at their distance from the wall."""
    shape = SimpleNamespace(type="glass", radius=0.1, height=0.2, thickness=0.02)
    obstacles = RigidObstacles([shape], ".", ["glass"])
    heights = np.linspace(-0.05, 0.05, 5)
    outside = np.stack([np.full(5, 0.11), heights, np.zeros(5)], axis=1)  # 1 cm outside the outer wall
    inside = np.stack([np.full(5, 0.07), heights, np.zeros(5)], axis=1)  # 1 cm inside the cavity
    planes = obstacles.planes(np.concatenate([outside, inside]), [(np.zeros(3), np.eye(3))], RADIUS)
    assert sorted(planes.index) == list(range(10))
    order = np.argsort(planes.index)
    normal_x = planes.normal[order, 0]
    assert np.all(normal_x[:5] > 0.99) and np.all(normal_x[5:] < -0.99)
    offset = np.einsum("ij,ij->i", np.concatenate([outside, inside]) - planes.point[order], planes.normal[order])
    np.testing.assert_allclose(offset, 0.01, atol=3e-4)  # 64 sections: the polygon sits 1.2e-4 m inside the circle
