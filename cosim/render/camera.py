"""A perspective camera fitted to what a 3D picture shows (not to the whole domain).

The camera looks at the centre of the content's bounding box from ``azimuth`` (about the up
axis, from the +z side towards +x) and ``elevation`` (above the horizon), with a vertical view
angle ``view_angle``, and stands just far enough back that every corner of the box projects
inside the frame, ``margin`` (a fraction of the half-frame) from its edges. The picture's aspect
follows the content's, between ``ASPECT_RANGE``; its longest side is ``resolution`` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ASPECT_RANGE = (0.75, 1.6)  # width / height


@dataclass
class View:
    """Camera pose [m], vertical view angle [deg] and picture size [px]."""

    position: np.ndarray  # (3,)
    focal_point: np.ndarray  # (3,)
    up: np.ndarray  # (3,) unit
    view_angle: float
    width: int
    height: int

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (n, 2) (column, row from the top-left) and distance along the view [m]."""
        forward = self.focal_point - self.position
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        rel = np.asarray(points, dtype=np.float64) - self.position
        depth = rel @ forward
        f = 0.5 * self.height / np.tan(np.radians(0.5 * self.view_angle))  # focal length [px]
        col = 0.5 * self.width + f * (rel @ right) / depth
        row = 0.5 * self.height - f * (rel @ up) / depth
        return np.stack([col, row], axis=1), depth


def view_basis(azimuth: float, elevation: float, up: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit vectors (right, up, back): back points from the content towards the camera."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    side = np.array([0.0, 0.0, 1.0]) if abs(up[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    side -= up * (side @ up)
    side /= np.linalg.norm(side)
    across = np.cross(up, side)  # completes (side, up) to a right-handed frame
    a, e = np.radians(azimuth), np.radians(elevation)
    back = np.cos(e) * (np.cos(a) * side + np.sin(a) * across) + np.sin(e) * up
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    return right, np.cross(back, right), back


def fit_view(
    points: np.ndarray,
    resolution: int,
    azimuth: float = 35.0,
    elevation: float = 25.0,
    up: np.ndarray = (0.0, 1.0, 0.0),
    view_angle: float = 30.0,
    margin: float = 0.08,
) -> View:
    """The camera that frames the bounding box of ``points`` (n, 3) [m] (see the module docstring)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.02 * max(np.linalg.norm(hi - lo), 1e-3)  # a point-like content still gets a frame
    lo, hi = lo - pad, hi + pad
    centre = 0.5 * (lo + hi)
    corners = np.array(np.meshgrid(*zip(lo, hi), indexing="ij")).reshape(3, -1).T - centre
    right, cam_up, back = view_basis(azimuth, elevation, up)
    x, y, z = corners @ right, corners @ cam_up, corners @ back
    aspect = float(np.clip(np.ptp(x) / max(np.ptp(y), 1e-12), *ASPECT_RANGE))
    width, height = (resolution, resolution / aspect) if aspect >= 1 else (resolution * aspect, resolution)
    width, height = 2 * round(width / 2), 2 * round(height / 2)  # even sizes for video encoders
    ty = np.tan(np.radians(0.5 * view_angle)) * (1 - margin)
    tx = ty * width / height
    distance = float(np.max(np.maximum(z + np.abs(x) / tx, z + np.abs(y) / ty)))
    return View(centre + distance * back, centre, cam_up, view_angle, int(width), int(height))
