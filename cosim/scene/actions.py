"""Action sequences from a scene's ``actions:`` block (DART skeletons and cloths share the layout)."""

from __future__ import annotations

import numpy as np

from cosim.errors import SceneError


def action_sequence(spec, action_size: int, n_segments: int) -> np.ndarray:
    """(n_segments, action_size): ``spec.sequence`` then ``spec.initial`` (default zeros) for the rest."""
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
    sequence = action_sequence(spec, action_size, max(len(spec.sequence), 1))
    if np.any(sequence < lower) or np.any(sequence > upper):
        raise SceneError(f"{key}: the initial actions lie outside bounds; start inside [lower, upper]")
    return lower, upper
