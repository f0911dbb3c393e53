"""A scene's soft bodies as particle positions, without the MPM engine (so without Taichi).

``cosim validate`` uses it to count particles and to check that every body
fits in the grid; ``cosim.scene.build.build_bodies`` samples the same way (same
seed, same body order) and adds the materials.
"""

from __future__ import annotations

import numpy as np

from cosim.errors import SceneError
from cosim.sampling import sample_shape
from cosim.scene.schema import Scene


def body_positions(scene: Scene) -> list[np.ndarray]:
    """Particle positions [m], one (n, dim) array per ``mpm.bodies`` entry, in order.

    Raises ``SceneError`` naming the body when a shape holds no particle, a mesh
    cannot be read, or particles lie in the walls/margin of the domain.
    """
    rng = np.random.default_rng(scene.seed)
    domain = np.asarray(scene.cells) * scene.dx
    margin = (scene.mpm.boundary.thickness if scene.mpm.boundary.type != "none" else 2) * scene.dx
    positions = []
    for i, spec in enumerate(scene.mpm.bodies):
        spacing = spec.spacing or 0.5 * scene.dx
        key = f"mpm.bodies[{i}].shape"
        pts = sample_shape(spec.shape, scene.dim, spacing, spec.jitter, rng, key, scene.source_dir)
        outside = np.any((pts < margin) | (pts > domain - margin), axis=1)
        if outside.any():
            raise SceneError(
                f"mpm.bodies[{i}] ('{spec.name}'): {int(outside.sum())} particles lie outside the usable grid "
                f"[{margin:g}, {domain.tolist()} - {margin:g}] m (walls/margin of the domain); move or shrink the shape"
            )
        positions.append(pts)
    return positions
