"""2D preview pictures: the domain seen straight on, particles coloured by body, rigid bodies
as grey surface points, the domain's edges. NumPy rasterisation plus Pillow for lines and
text; the contact benchmark's figure uses it too. 3D previews use ``vtk3d``.
"""

from __future__ import annotations

import numpy as np

from cosim.render.frame import PALETTE


class Camera:
    """Maps 2D world points [m] to pixel coordinates over the whole domain, 5% margin around it."""

    def __init__(self, domain: np.ndarray, resolution: int):
        self.domain = np.asarray(domain, dtype=np.float64)
        margin = 0.05
        self.scale = resolution * (1 - 2 * margin) / self.domain.max()
        self.size = np.ceil(self.domain * self.scale + 2 * margin * resolution).astype(int)
        self.offset = margin * resolution

    def project(self, pts: np.ndarray) -> np.ndarray:
        px = np.asarray(pts, dtype=np.float64) * self.scale + self.offset
        px[:, 1] = self.size[1] - px[:, 1]  # image rows grow downwards
        return px

    def box_edges(self) -> list[tuple[np.ndarray, np.ndarray]]:
        d = self.domain
        c = np.array([[0, 0], [d[0], 0], [d[0], d[1]], [0, d[1]]])
        return [(c[i], c[(i + 1) % 4]) for i in range(4)]


RIGID_COLOR = np.array([110.0, 110.0, 110.0])


def render_frame(
    camera: Camera, positions: list[np.ndarray], radius_px: int, label: str = "", rigid: list[np.ndarray] = ()
) -> np.ndarray:
    """One RGB image (H, W, 3): particles coloured by body, rigid bodies' surface points in grey
    (later sets painted over earlier ones)."""
    from PIL import Image, ImageDraw

    w, h = int(camera.size[0]), int(camera.size[1])
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    sets = list(positions) + list(rigid)
    colors = [PALETTE[i % len(PALETTE)] for i in range(len(positions))] + [RIGID_COLOR] * len(rigid)
    pts = np.concatenate(sets) if sets else np.zeros((0, 2))
    color = np.concatenate([np.repeat(c[None], len(p), 0) for c, p in zip(colors, sets)]) if sets else np.zeros((0, 3))
    px = camera.project(pts)
    rgb = np.clip(color, 0, 255).astype(np.uint8)
    r = radius_px
    offs = [(dx, dy) for dx in range(-r, r + 1) for dy in range(-r, r + 1) if dx * dx + dy * dy <= r * r + r]
    ix, iy = np.round(px[:, 0]).astype(int), np.round(px[:, 1]).astype(int)
    for dx, dy in offs:
        cx, cy = ix + dx, iy + dy
        ok = (cx >= 0) & (cx < w) & (cy >= 0) & (cy < h)
        img[cy[ok], cx[ok]] = rgb[ok]
    pil = Image.fromarray(img)
    draw = ImageDraw.Draw(pil)
    for p, q in camera.box_edges():
        a, b = camera.project(np.array([p, q]))
        draw.line([tuple(a), tuple(b)], fill=(90, 90, 90), width=1)
    if label:
        draw.text((6, 4), label, fill=(0, 0, 0))
    return np.asarray(pil)
