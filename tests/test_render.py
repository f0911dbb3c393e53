"""3D previews: the fitted camera, SDF isosurfaces, and what the rendered picture shows.

The picture checks read pixels of a real off-screen VTK render (Mesa's software rasteriser
here): the frame's size, particles seen through a closed translucent box, and one colour
cluster per body.
"""

from __future__ import annotations

import numpy as np
import pytest

from cosim.render import Frame, render_frames
from cosim.render.camera import fit_view
from cosim.render.frame import body_colors


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """A closed axis-aligned box as 12 triangles."""
    import trimesh

    box = trimesh.creation.box(extents=np.subtract(hi, lo))
    box.apply_translation(0.5 * (np.asarray(lo) + np.asarray(hi)))
    return np.asarray(box.vertices), np.asarray(box.faces)


@pytest.mark.parametrize("extent", [(0.3, 0.1, 0.2), (0.05, 0.6, 0.05), (0.5, 0.5, 0.5)])
def test_fitted_camera_frames_the_content_tightly(extent):
    """Every corner of the content's box projects inside the picture, and the box spans most of
    the picture along one axis (fit: the limiting corner lands at the margin, 8% of the half-frame;
    perspective leaves the opposite side short of it: 0.69-0.9 measured)."""
    rng = np.random.default_rng(1)
    pts = rng.random((500, 3)) * extent + [0.2, 0.1, 0.3]
    view = fit_view(pts, 640)
    assert max(view.width, view.height) == 640
    corners = np.array(np.meshgrid(*zip(pts.min(0), pts.max(0)), indexing="ij")).reshape(3, -1).T
    px, depth = view.project(corners)
    assert (depth > 0).all()
    assert (px >= 0).all() and (px[:, 0] <= view.width).all() and (px[:, 1] <= view.height).all()
    span = np.ptp(px, axis=0) / [view.width, view.height]
    assert span.max() > 0.65, span


def test_sdf_isosurface_has_the_box_extents_on_each_axis():
    """Marching cubes of a box SDF (half extents 0.1, 0.2, 0.3 m): the vertices' bounding box is
    the box to within a grid spacing on each axis (catches a swapped axis order)."""
    from cosim.couplers.sdf import primitive_sdf
    from cosim.render.surfaces import sdf_surface

    half = np.array([0.1, 0.2, 0.3])
    grid = primitive_sdf("box", 3, 0.02, 0.06, half=half)
    vertices, faces = sdf_surface(grid)
    assert len(faces) > 100 and faces.max() < len(vertices)
    assert np.allclose(vertices.max(axis=0), half, atol=grid.spacing)
    assert np.allclose(vertices.min(axis=0), -half, atol=grid.spacing)


def saturated(img: np.ndarray) -> np.ndarray:
    """Saturation (max - min) / max > 0.35: particle colours, also shaded or seen through the grey
    translucent surface (its own colour (140, 158, 184) has 0.24)."""
    rgb = img.astype(float)
    return (rgb.max(axis=-1) - rgb.min(axis=-1)) > 0.35 * np.maximum(rgb.max(axis=-1), 1.0)


def blue(img: np.ndarray) -> np.ndarray:
    """Pixels of body 0's hue (31, 119, 180)."""
    return saturated(img) & (img[..., 2].astype(int) > img[..., 0])


def orange(img: np.ndarray) -> np.ndarray:
    """Pixels of body 1's hue (255, 127, 14)."""
    return saturated(img) & (img[..., 0].astype(int) > img[..., 2])


def test_particles_inside_a_closed_translucent_box_stay_visible_and_keep_their_body_colour():
    """Two bodies (left half, right half) sealed in a closed box: the 640 px picture shows both
    colours inside the box's silhouette, the left body left of the right one; the empty box
    itself has neither colour."""
    rng = np.random.default_rng(0)
    n = 4000
    pts = rng.random((n, 3)) * [0.3, 0.1, 0.2] + [0.35, 0.2, 0.4]
    body = (pts[:, 0] > 0.5).astype(int)
    box = box_mesh([0.3, 0.15, 0.35], [0.7, 0.35, 0.65])
    with_particles, box_only, empty = render_frames(
        [Frame(pts, body, rigid=[box]), Frame(pts[:0], body[:0], rigid=[box]), Frame(pts[:0], body[:0])],
        np.ones(3),
        spacing=0.006,
        resolution=640,
    )
    assert max(with_particles.shape[:2]) >= 640
    background = empty[0, 0]
    silhouette = np.abs(box_only.astype(int) - empty.astype(int)).sum(axis=-1) > 10
    assert silhouette.mean() > 0.2  # the box fills a good part of the fitted frame
    assert blue(box_only).sum() == 0 and orange(box_only).sum() == 0
    b, o = blue(with_particles) & silhouette, orange(with_particles) & silhouette
    assert b.sum() > 2000 and o.sum() > 2000, (b.sum(), o.sum())
    assert np.nonzero(b)[1].mean() < np.nonzero(o)[1].mean()  # body 0 (x < 0.5) on the left
    assert not (with_particles == background).all(axis=-1)[silhouette].all()


def test_body_colours_are_distinct():
    colors = body_colors(8)
    assert len({tuple(c) for c in colors}) == 8
