"""Action sequences from a scene's ``actions:`` block (DART skeletons and cloths share the layout)."""

from __future__ import annotations

import numpy as np

from cosim.errors import SceneError
from cosim.system import ActionPlan


def action_sequence(spec, action_size: int, n_segments: int, key: str = "actions") -> np.ndarray:
    """(n_segments, action_size): ``spec.sequence`` then ``spec.initial`` (default zeros) for the rest;
    an action of another length is refused naming ``key``."""
    given = [("initial", spec.initial)] if spec.initial is not None else []
    for name, action in given + [(f"sequence[{n}]", a) for n, a in enumerate(spec.sequence)]:
        if len(action) != action_size:
            raise SceneError(f"{key}.{name}: {len(action)} entries, the action has {action_size}")
    out = np.zeros((n_segments, action_size))
    if spec.initial is not None:
        out[:] = spec.initial
    for n, act in enumerate(spec.sequence[:n_segments]):
        out[n] = act
    return out


def action_bounds(spec, action_size: int, key: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``spec.bounds`` as (lower, upper) arrays (action_size,), checked against the initial actions."""
    if spec.bounds is None:
        return None
    lower, upper = (np.asarray(b, dtype=np.float64) for b in spec.bounds)
    if lower.shape != (action_size,) or upper.shape != (action_size,):
        raise SceneError(f"{key}.bounds: two lists of {action_size} numbers (the action size), [lower, upper]")
    if np.any(lower > upper):
        raise SceneError(f"{key}.bounds: a lower bound exceeds its upper bound")
    sequence = action_sequence(spec, action_size, max(len(spec.sequence), 1), key)
    if np.any(sequence < lower) or np.any(sequence > upper):
        raise SceneError(f"{key}: the initial actions lie outside bounds; start inside [lower, upper]")
    return lower, upper


def action_plan(spec, action_size: int, n_segments: int, key: str):
    """The ``ActionPlan`` of an ``actions:`` block: its sequence of ``n_segments`` actions, held ``spec.hold``
    steps each, with the block's bounds and scale (a cloth's ``reach`` projection is added by the cloth)."""
    sequence = action_sequence(spec, action_size, n_segments, key)
    return ActionPlan(sequence, spec.hold, action_bounds(spec, action_size, key), action_scale(spec, action_size, key))


def action_scale(spec, action_size: int, key: str) -> np.ndarray | None:
    """``spec.scale`` as an (action_size,) array of each entry's natural size, or None (the default)."""
    if spec.scale is None:
        return None
    if np.ndim(spec.scale) == 0:
        return np.full(action_size, float(spec.scale))
    scale = np.asarray(spec.scale, dtype=np.float64)
    if scale.shape != (action_size,):
        raise SceneError(f"{key}.scale: one number, or {action_size} (the action size); got {len(spec.scale)}")
    return scale


class ReachProjection:
    """Keeps velocity-controlled points within ``radius`` [m] of a line: maps an action sequence
    (segments, groups x 3) [m/s] to an allowed one, unchanged when every point's position at the end
    of every segment is within reach. Segment by segment, a point that would end beyond reach ends
    instead at the nearest point within reach (its radial distance cut to ``radius``), and the
    segment's velocity is what reaches it in ``duration`` [s] (the hold times the frame dt)."""

    def __init__(self, start: np.ndarray, duration: float, center, axis, radius: float) -> None:
        self.start = np.asarray(start, dtype=np.float64).reshape(-1, 3)  # (groups, 3) [m]
        self.duration = float(duration)
        self.center = np.asarray(center, dtype=np.float64)
        self.axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        self.radius = float(radius)

    def radial(self, p: np.ndarray) -> np.ndarray:
        """(groups, 3): each point's offset from the line, perpendicular to it [m]."""
        r = p - self.center
        return r - np.outer(r @ self.axis, self.axis)

    def __call__(self, sequence: np.ndarray) -> np.ndarray:
        out = np.array(sequence, dtype=np.float64)
        p = self.start.copy()
        for k, velocity in enumerate(out):
            end = p + self.duration * velocity.reshape(-1, 3)
            radial = self.radial(end)
            distance = np.linalg.norm(radial, axis=1)
            over = distance > self.radius
            end[over] -= radial[over] * (1.0 - self.radius / distance[over])[:, None]
            out[k] = ((end - p) / self.duration).ravel()
            p = end
        return out
