"""Preview pictures of a trajectory: ``write_preview`` turns ``Frame``s into a GIF or MP4.

3D frames go to the VTK renderer (``vtk3d``: fitted camera, translucent shaded surfaces,
depth-shaded particles), imported only when a 3D preview is drawn; 2D frames to the small
raster view of the whole domain (``raster2d``). ``Frame`` (``frame``) is the data-only interface.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.errors import CosimError
from cosim.render.frame import Frame, body_colors

__all__ = ["Frame", "render_frames", "write_preview"]


def render_frames(
    frames: list[Frame],
    domain: np.ndarray,
    spacing: float,
    resolution: int = 640,
    up: np.ndarray = (0.0, 1.0, 0.0),
) -> list[np.ndarray]:
    """RGB images (H, W, 3) uint8 of ``frames``; ``domain`` (dim,) [m], ``spacing`` [m] between particles."""
    if not frames:
        return []
    n_bodies = max(int(f.body.max()) + 1 if len(f.body) else 0 for f in frames)
    colors = body_colors(max(n_bodies, 1))
    if len(domain) == 2:
        from cosim.render.raster2d import Camera, render_frame

        camera = Camera(np.asarray(domain, dtype=np.float64), resolution)
        radius = max(1, int(np.ceil(0.5 * spacing * camera.scale)))
        return [
            render_frame(camera, [f.positions[f.body == b] for b in range(n_bodies)], radius, f.label, f.rigid)
            for f in frames
        ]
    from cosim.render.vtk3d import Renderer3D

    renderer = Renderer3D(frames, colors, spacing, resolution, up=up, floor=0.0)
    try:
        return [renderer.render(f) for f in frames]
    finally:
        renderer.close()


def write_preview(
    path: Path,
    frames: list[Frame],
    domain: np.ndarray,
    spacing: float,
    resolution: int = 640,
    fps: int = 30,
    up: np.ndarray = (0.0, 1.0, 0.0),
) -> Path:
    """Write an animated GIF (or MP4, by the suffix) of ``frames``; returns the path."""
    import imageio.v2 as imageio

    images = render_frames(frames, domain, spacing, resolution, up)
    path = Path(path)
    if path.suffix == ".mp4":
        try:
            imageio.mimsave(path, images, fps=fps, macro_block_size=1)
        except (RuntimeError, ValueError, OSError) as exc:  # imageio's errors when no ffmpeg backend exists
            raise CosimError(f"cannot write {path}: {exc}; install imageio-ffmpeg or set output.preview: gif") from None
    else:
        imageio.mimsave(path, images, duration=1000.0 / fps, loop=0)
    return path
