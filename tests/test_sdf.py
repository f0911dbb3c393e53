"""Rigid-body SDFs against closed forms: distances within half a cell, normals within degrees."""

import numpy as np
import pytest
import taichi as ti
import trimesh

from cosim.couplers.sdf import SDFField, mesh_sdf, primitive_distance, primitive_sdf
from cosim.errors import SceneError

H = 0.01  # SDF node spacing [m]


def band_points(distance_fn, dim, extent, band, n=4000, seed=0):
    """Random points with |true distance| <= band around a shape of half extent ``extent``."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-extent - band, extent + band, size=(n * 20, dim))
    pts = pts[np.abs(distance_fn(pts)) <= band]
    return pts[:n]


@ti.kernel
def _lookup(f: ti.template(), pts: ti.types.ndarray(), dist: ti.types.ndarray(), nrm: ti.types.ndarray()):
    for i in range(pts.shape[0]):
        p = ti.Vector.zero(float, f.dim)
        for k in ti.static(range(f.dim)):
            p[k] = pts[i, k]
        d, n = f.distance_normal(p)
        dist[i] = d
        for k in ti.static(range(f.dim)):
            nrm[i, k] = n[k]


def taichi_lookup(grid, pts):
    field = SDFField(grid)
    dist, nrm = np.zeros(len(pts)), np.zeros_like(pts)
    _lookup(field, pts, dist, nrm)
    return dist, nrm


def numeric_normal(fn, pts, eps=1e-6):
    g = np.stack([(fn(pts + eps * e) - fn(pts - eps * e)) / (2 * eps) for e in np.eye(pts.shape[1])], axis=1)
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def test_sphere_distance_and_normal():
    """Smooth surface: trilinear error ~ h^2 / (8 R) << h / 2; normals within 3 degrees."""
    grid = primitive_sdf("sphere", 3, H, 3 * H, radius=0.1)
    fn = lambda p: primitive_distance("sphere", p, radius=0.1)
    pts = band_points(fn, 3, np.full(3, 0.1), 2 * H)
    dist, nrm = taichi_lookup(grid, pts)
    assert np.abs(dist - fn(pts)).max() <= 0.5 * H
    assert angle_deg(nrm, pts / np.linalg.norm(pts, axis=1, keepdims=True)).max() < 3.0
    host_d, host_n = grid.sample(pts)  # the host twin agrees with the kernel
    assert np.allclose(host_d, dist, atol=1e-12) and np.allclose(host_n, nrm, atol=1e-9)


def test_box_distance_and_normals_at_faces_edges_and_corners():
    """Distances within half a cell in the band. Normals: within 3 degrees off the faces; around
    edges, where the true normal turns by ~h/d radians per cell at distance d, within 5 degrees
    from one cell out (measured 4.0 at 1-1.5 cells, 2.1 at 1.5-2; it was 14 with finite-difference
    node gradients) and 20 from half a cell out (measured 16.6); along the diagonal off a corner."""
    half = np.array([0.1, 0.06, 0.08])
    grid = primitive_sdf("box", 3, H, 3 * H, half=half)
    fn = lambda p: primitive_distance("box", p, half=half)
    pts = band_points(fn, 3, half, 2 * H, n=8000)
    dist, nrm = taichi_lookup(grid, pts)
    true_d = fn(pts)
    assert np.abs(dist - true_d).max() <= 0.5 * H
    err = angle_deg(nrm, numeric_normal(fn, pts))
    beyond = np.abs(pts) > half  # per axis: outside that pair of faces
    face = (beyond.sum(axis=1) == 1) & np.all((np.abs(pts) < half - 2 * H) | beyond, axis=1) & (true_d > 0)
    assert face.sum() > 500 and err[face].max() < 3.0
    edge = (beyond.sum(axis=1) >= 2) & (true_d > H)
    assert edge.sum() > 50 and err[edge].max() < 5.0
    near_edge = (beyond.sum(axis=1) >= 2) & (true_d > 0.5 * H)
    assert err[near_edge].max() < 20.0
    corner = half + 1.5 * H / np.sqrt(3)
    _, n = taichi_lookup(grid, corner[None, :].copy())
    assert angle_deg(n, (np.ones(3) / np.sqrt(3))[None]).max() < 5.0


@pytest.mark.parametrize(
    "kind,dim,size",
    [
        ("cylinder", 3, {"radius": 0.08, "height": 0.2}),
        ("capsule", 3, {"radius": 0.05, "height": 0.1}),
        ("glass", 3, {"radius": 0.06, "height": 0.15, "thickness": 0.01}),
        ("ring", 2, {"radius": 0.2, "thickness": 1 / 32}),
    ],
)
def test_primitive_grids_reproduce_their_closed_form(kind, dim, size):
    grid = primitive_sdf(kind, dim, H, 3 * H, **size)
    fn = lambda p: primitive_distance(kind, p, **size)
    ext = grid.origin * -1 - 3 * H
    pts = band_points(fn, dim, ext, 2 * H)
    dist, _ = grid.sample(pts)
    assert len(pts) > 500 and np.abs(dist - fn(pts)).max() <= 0.5 * H


def test_glass_is_open_at_the_top_and_hollow():
    size = {"radius": 0.06, "height": 0.15, "thickness": 0.01}
    inside_cavity = np.array([[0.0, 0.0, 0.0]])
    in_wall = np.array([[0.055, 0.0, 0.0]])
    above_rim = np.array([[0.0, 0.1, 0.0]])
    assert primitive_distance("glass", inside_cavity, **size)[0] > 0.04  # the cavity is outside the body
    assert primitive_distance("glass", in_wall, **size)[0] < 0
    assert primitive_distance("glass", above_rim, **size)[0] > 0


def test_mesh_sdf_matches_the_analytic_box_and_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("COSIM_CACHE", str(tmp_path))
    half = np.array([0.1, 0.06, 0.08])
    mesh = trimesh.creation.box(extents=2 * half)
    grid = mesh_sdf(mesh, 0.02, 0.04)
    exact = primitive_distance("box", grid.nodes(), half=half)
    assert np.abs(grid.values - exact).max() < 1e-9  # exact at the nodes, sign included
    # node normals: the direction from the closest point equals the box's gradient off its
    # medial planes (inside, where two faces are equally close, any of them is right)
    analytic = primitive_sdf("box", 3, 0.02, 0.04, half=half).normals
    assert analytic.shape == grid.normals.shape
    outside = exact > 1e-9
    assert np.abs(grid.normals[outside] - analytic[outside]).max() < 1e-6
    off_surface = np.abs(exact) > 1e-9  # nodes on the surface fall back to finite differences
    assert np.allclose(np.linalg.norm(grid.normals[off_surface], axis=-1), 1.0)
    files = list((tmp_path / "sdf").glob("*.npz"))
    assert len(files) == 1
    again = mesh_sdf(mesh, 0.02, 0.04)
    assert np.array_equal(again.values, grid.values) and np.array_equal(again.normals, grid.normals)
    # a changed setting or mesh is a new key, never a stale hit
    mesh_sdf(mesh, 0.025, 0.04)
    mesh_sdf(trimesh.creation.box(extents=2 * half + 0.01), 0.02, 0.04)
    assert len(list((tmp_path / "sdf").glob("*.npz"))) == 3


def test_non_watertight_mesh_is_refused(tmp_path):
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    with pytest.raises(SceneError, match="not watertight"):
        mesh_sdf(open_box, 0.02, 0.04, key="rigid.bodies[0].mesh", use_cache=False)


def test_urdf_link_geometry_sdfs_match_their_closed_forms(tmp_path, monkeypatch):
    """A URDF link's collision shapes in its body frame: a transformed mesh file (exact) and a
    union of two primitives (the minimum of their closed forms), cylinders along DART's z."""
    from cosim.couplers.sdf import shape_spec_sdf
    from cosim.engines.rigid_build import ShapeSpec, make_transform

    monkeypatch.setenv("COSIM_CACHE", str(tmp_path))
    half = np.array([0.05, 0.03, 0.04])
    path = tmp_path / "box.obj"
    trimesh.creation.box(extents=2 * half).export(path)
    T = make_transform((0.1, 0.0, 0.02), (0.0, 0.0, 90.0))  # turned about z, moved
    grid = shape_spec_sdf([(ShapeSpec("mesh", mesh=str(path)), T)], 0.01, 0.03, key="link")
    pts = grid.nodes().reshape(-1, 3)
    local = (pts - T[:3, 3]) @ T[:3, :3]
    assert np.abs(grid.values.ravel() - primitive_distance("box", local, half=half)).max() < 1e-9

    cyl = ShapeSpec("cylinder", radius=0.03, height=0.2)  # along z
    ball = ShapeSpec("sphere", radius=0.05, position=(0.0, 0.0, 0.12))
    union = shape_spec_sdf([(cyl, cyl.transform()), (ball, ball.transform())], 0.01, 0.03, key="link")
    pts = union.nodes().reshape(-1, 3)
    q = np.stack([np.linalg.norm(pts[:, :2], axis=1) - 0.03, np.abs(pts[:, 2]) - 0.1], axis=1)
    z_cylinder = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    exact = np.minimum(z_cylinder, np.linalg.norm(pts - [0, 0, 0.12], axis=1) - 0.05)
    assert np.abs(union.values.ravel() - exact).max() < 1e-12
