"""Preview pictures of a trajectory: particles coloured by body.

2D: the domain seen straight on. 3D: an orthographic view from above and to
the side, particles drawn far-to-near and darkened with depth (the depth cue),
with the domain's box edges for orientation. Pure NumPy rasterisation plus
Pillow for lines and text; imageio writes GIF (or MP4 where imageio-ffmpeg is
installed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.engines import so3
from cosim.errors import CosimError

PALETTE = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
    ],
    dtype=np.float64,
)


class Camera:
    """Maps world points to pixel coordinates and a depth in [0, 1] (0 nearest)."""

    def __init__(self, domain: np.ndarray, resolution: int, azimuth: float = 35.0, elevation: float = 25.0):
        self.dim = len(domain)
        self.domain = domain
        if self.dim == 3:
            a, e = np.radians(azimuth), np.radians(elevation)
            self.rot = so3.about_axis(e, 0) @ so3.about_axis(-a, 1)
            corners = np.array(np.meshgrid(*[[0.0, s] for s in domain], indexing="ij")).reshape(3, -1).T
            view = (corners - domain / 2) @ self.rot.T
        else:
            view = np.array([[0.0, 0.0], domain])
        self.lo, hi = view[:, :2].min(axis=0), view[:, :2].max(axis=0)
        self.zlo, self.zhi = (view[:, 2].min(), view[:, 2].max()) if self.dim == 3 else (0.0, 1.0)
        margin = 0.05
        extent = hi - self.lo
        self.scale = resolution * (1 - 2 * margin) / extent.max()
        self.size = np.ceil(extent * self.scale + 2 * margin * resolution).astype(int)
        self.offset = margin * resolution

    def project(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.dim == 3:
            view = (pts - self.domain / 2) @ self.rot.T
            depth = (self.zhi - view[:, 2]) / max(self.zhi - self.zlo, 1e-12)  # camera looks along -z
        else:
            view, depth = pts, np.zeros(len(pts))
        px = (view[:, :2] - self.lo) * self.scale + self.offset
        px[:, 1] = self.size[1] - px[:, 1]  # image rows grow downwards
        return px, depth

    def box_edges(self) -> list[tuple[np.ndarray, np.ndarray]]:
        d = self.domain
        if self.dim == 2:
            c = np.array([[0, 0], [d[0], 0], [d[0], d[1]], [0, d[1]]])
            return [(c[i], c[(i + 1) % 4]) for i in range(4)]
        edges = []
        for axis in range(3):
            others = [k for k in range(3) if k != axis]
            for a in (0, 1):
                for b in (0, 1):
                    p = np.zeros(3)
                    p[others[0]], p[others[1]] = a * d[others[0]], b * d[others[1]]
                    q = p.copy()
                    q[axis] = d[axis]
                    edges.append((p, q))
        return edges


RIGID_COLOR = np.array([110.0, 110.0, 110.0])


def render_frame(
    camera: Camera, positions: list[np.ndarray], radius_px: int, label: str = "", rigid: list[np.ndarray] = ()
) -> np.ndarray:
    """One RGB image (H, W, 3): particles coloured by body, rigid bodies' surface points in grey."""
    from PIL import Image, ImageDraw

    w, h = int(camera.size[0]), int(camera.size[1])
    img = np.full((h, w, 3), 255, dtype=np.uint8)
    sets = list(positions) + list(rigid)
    colors = [PALETTE[i % len(PALETTE)] for i in range(len(positions))] + [RIGID_COLOR] * len(rigid)
    pts = np.concatenate(sets) if sets else np.zeros((0, camera.dim))
    color = np.concatenate([np.repeat(c[None], len(p), 0) for c, p in zip(colors, sets)])
    px, depth = camera.project(pts)
    shade = 1.0 - 0.55 * depth  # nearer is brighter
    rgb = np.clip(color * shade[:, None], 0, 255).astype(np.uint8)
    order = np.argsort(-depth, kind="stable")  # far first, near painted last
    px, rgb = px[order], rgb[order]
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
        (a, b), _ = camera.project(np.array([p, q]))
        draw.line([tuple(a), tuple(b)], fill=(90, 90, 90), width=1)
    if label:
        draw.text((6, 4), label, fill=(0, 0, 0))
    return np.asarray(pil)


def write_preview(
    path: Path,
    frames: list[list[np.ndarray]],
    times: np.ndarray,
    domain: np.ndarray,
    spacing: float,
    resolution: int = 400,
    fps: int = 30,
    rigid_frames: list[list[np.ndarray]] | None = None,
) -> Path:
    """Write an animated GIF (or MP4, by the suffix) of the saved frames.

    ``rigid_frames``: per frame, world-space surface points of each rigid body.
    """
    import imageio.v2 as imageio

    camera = Camera(np.asarray(domain, dtype=np.float64), resolution)
    radius = max(1, int(np.ceil(0.5 * spacing * camera.scale)))
    rigid_frames = rigid_frames or [[] for _ in frames]
    images = [render_frame(camera, f, radius, f"t = {t:.3f} s", r) for f, t, r in zip(frames, times, rigid_frames)]
    path = Path(path)
    if path.suffix == ".mp4":
        try:
            imageio.mimsave(path, images, fps=fps, macro_block_size=1)
        except (RuntimeError, ValueError, OSError) as exc:  # imageio's errors when no ffmpeg backend exists
            raise CosimError(f"cannot write {path}: {exc}; install imageio-ffmpeg or set output.preview: gif") from None
    else:
        imageio.mimsave(path, images, duration=1000.0 / fps, loop=0)
    return path
