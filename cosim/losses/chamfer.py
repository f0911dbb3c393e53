"""Symmetric Chamfer distance between two point sets, with its gradient, on KD-trees (scipy).

C(X, T) = mean_i |x_i - T(x_i)|^2 + mean_j |t_j - X(t_j)|^2  [m^2]

where T(x) is the target point nearest to x and X(t) the point of X nearest to t. Squared
distances keep C differentiable wherever the nearest neighbours do not change (it is
piecewise quadratic and continuous). Cost O((N + M) log(N + M)) per evaluation: the
target's tree is built once, the points' tree once per call, never an O(N M) loop.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from cosim.errors import SceneError


class Chamfer:
    """C(X, target) and dC/dX for a fixed target point set (M, d) [m]."""

    def __init__(self, target: np.ndarray) -> None:
        self.target = np.asarray(target, dtype=np.float64)
        self.tree = cKDTree(self.target)

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(C [m^2], dC/dx (N, d))."""
        x = np.asarray(x, dtype=np.float64)
        n, m = len(x), len(self.target)
        _, to_target = self.tree.query(x)
        forward = x - self.target[to_target]  # each point to its nearest target point
        _, to_points = cKDTree(x).query(self.target)
        backward = x[to_points] - self.target  # each target point's nearest point, from it
        value = float((forward * forward).sum() / n + (backward * backward).sum() / m)
        grad = 2.0 * forward / n
        np.add.at(grad, to_points, 2.0 * backward / m)
        return value, grad


def target_points(spec, body: str, dim: int, dx: float, seed: int, source_dir: Path, key: str) -> np.ndarray:
    """The point set (M, dim) [m] a ``TargetPointsSpec`` describes, for a term on ``body``."""
    if sum(v is not None for v in (spec.file, spec.shape, spec.rollout)) != 1:
        raise SceneError(f"{key}: give exactly one of file, shape or rollout")
    if spec.shape is not None:
        from cosim.sampling import sample_shape

        rng = np.random.default_rng(seed)
        return sample_shape(spec.shape, dim, spec.spacing or 0.5 * dx, 0.0, rng, f"{key}.shape", source_dir)
    path = (source_dir / (spec.file or spec.rollout)).resolve()
    if not path.is_file():
        what = "file" if spec.file else "rollout"
        hint = "" if spec.file else " (`cosim run SCENE --save-target` writes OUT/target.npz)"
        raise SceneError(f"{key}.{what}: no such file: {path}{hint}")
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):  # not a .npy / .npz, or a pickle
        what = "file" if spec.file else "rollout"
        raise SceneError(
            f"{key}.{what}: cannot read {path}: not a .npy or .npz file of numbers; save the points with numpy.save"
        ) from None
    if isinstance(data, np.ndarray):
        points = data
    else:
        names = list(data.keys())
        name = f"x_{body}" if f"x_{body}" in names else (names[0] if len(names) == 1 and spec.file else None)
        if name is None:
            raise SceneError(f"{key}: {path} holds no array 'x_{body}' (it has {names})")
        points = data[name]
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != dim or len(points) == 0:
        raise SceneError(f"{key}: {path} must hold points of shape (M, {dim}), not {points.shape}")
    return points
