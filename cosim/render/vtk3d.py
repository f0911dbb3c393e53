"""3D preview frames rendered off-screen with VTK (through pyvista).

Particles are lit spheres coloured by body and darkened with distance from the camera (the
depth cue); rigid bodies and cloth are smooth-shaded translucent surfaces, so what a glass
holds stays visible; a light floor under the content gives the eye a reference. The camera is
fitted once to the content of all frames (``camera.fit_view``) so it holds still over an
animation. Headless machines need no X server: VTK's EGL window renders with Mesa's software
rasteriser where no GPU exists.
"""

from __future__ import annotations

import os

import numpy as np

from cosim.render.camera import View, fit_view
from cosim.render.frame import Frame

BACKGROUND = (1.0, 1.0, 1.0)
FLOOR_COLOR = (0.93, 0.935, 0.94)
RIGID_COLOR = (0.55, 0.62, 0.72)
CLOTH_COLOR = (0.85, 0.45, 0.55)
SURFACE_OPACITY = 0.3
DEPTH_DARKENING = 0.45  # the farthest particle is this much darker than the nearest


def _pyvista():
    """pyvista, off-screen; without a display VTK goes straight to EGL (no failed X attempt, no warning)."""
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    pv.OFF_SCREEN = True
    return pv


class Renderer3D:
    """Renders ``Frame``s of one animation with one camera, fitted to ``frames`` (all of them)."""

    def __init__(
        self,
        frames: list[Frame],
        colors: np.ndarray,
        spacing: float,
        resolution: int = 640,
        up: np.ndarray = (0.0, 1.0, 0.0),
        floor: float | None = None,
    ):
        """``colors`` (B, 3) RGB in [0, 255] per body id; ``spacing`` [m] between particles (their
        drawn diameter); ``floor``: height [m] along ``up`` of the ground plane, None for none."""
        pv = _pyvista()
        self.colors = np.asarray(colors, dtype=np.float64)
        self.up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
        points = np.concatenate([f.points() for f in frames])
        self.view: View = fit_view(points, resolution, up=self.up)
        depth = self.view.project(points)[1]
        self.near, self.far = float(depth.min()), float(depth.max())
        self.plotter = pv.Plotter(off_screen=True, window_size=(self.view.width, self.view.height))
        self.plotter.set_background(BACKGROUND)
        self.plotter.ren_win.SetMultiSamples(0)  # 8x MSAA cost ~40% of a frame in software
        self.plotter.camera_position = [tuple(self.view.position), tuple(self.view.focal_point), tuple(self.view.up)]
        self.plotter.camera.view_angle = self.view.view_angle
        f = 0.5 * self.view.height / np.tan(np.radians(0.5 * self.view.view_angle))
        self.point_px = max(2.0, 1.15 * spacing * f / np.linalg.norm(self.view.position - self.view.focal_point))
        if floor is not None:
            self._add_floor(points, floor)
        self._actors: list = []
        self._label = self.plotter.add_text("", position="upper_left", font_size=10, color="black")

    def _add_floor(self, points: np.ndarray, height: float) -> None:
        pv = _pyvista()
        lo, hi = points.min(axis=0), points.max(axis=0)
        size = 20.0 * np.linalg.norm(hi - lo)  # edges out of sight: a horizon, not a tile
        centre = 0.5 * (lo + hi)
        centre = centre - self.up * (centre @ self.up - height)
        plane = pv.Plane(center=centre, direction=self.up, i_size=size, j_size=size)
        self.plotter.add_mesh(plane, color=FLOOR_COLOR, ambient=0.6, diffuse=0.4, specular=0.0)

    def render(self, frame: Frame) -> np.ndarray:
        """One RGB image (height, width, 3) uint8 of ``frame``."""
        pv = _pyvista()
        for actor in self._actors:
            self.plotter.remove_actor(actor, render=False)
        self._actors = []
        if len(frame.positions):
            depth = self.view.project(frame.positions)[1]
            t = np.clip((depth - self.near) / max(self.far - self.near, 1e-12), 0.0, 1.0)
            rgb = self.colors[frame.body] * (1.0 - DEPTH_DARKENING * t)[:, None]
            cloud = pv.PolyData(np.asarray(frame.positions, dtype=np.float64))
            cloud["rgb"] = np.clip(rgb, 0, 255).astype(np.uint8)
            self._actors.append(
                self.plotter.add_points(
                    cloud,
                    scalars="rgb",
                    rgb=True,
                    render_points_as_spheres=True,
                    point_size=self.point_px,
                    ambient=0.25,
                    diffuse=0.8,
                    specular=0.2,
                    render=False,
                )
            )
        for meshes, color in ((frame.rigid, RIGID_COLOR), (frame.cloth, CLOTH_COLOR)):
            for vertices, faces in meshes:
                if len(faces) == 0:
                    continue
                cells = np.hstack([np.full((len(faces), 1), 3), np.asarray(faces)]).astype(np.int64)
                surface = pv.PolyData(np.asarray(vertices, dtype=np.float64), cells.ravel()).compute_normals(
                    auto_orient_normals=False, split_vertices=False
                )
                self._actors.append(
                    self.plotter.add_mesh(
                        surface,
                        color=color,
                        opacity=SURFACE_OPACITY,
                        smooth_shading=True,
                        specular=0.4,
                        specular_power=20,
                        render=False,
                    )
                )
        self._label.SetText(2, frame.label)  # 2: the upper-left corner
        self.plotter.renderer.ResetCameraClippingRange()
        self.plotter.render()  # pyvista renders by itself only before the first screenshot
        return np.asarray(self.plotter.screenshot(return_img=True))[..., :3]

    def close(self) -> None:
        self.plotter.close()
