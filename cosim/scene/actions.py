"""Action sequences from a scene's ``actions:`` block (DART skeletons and cloths share the layout)."""

from __future__ import annotations

import numpy as np


def action_sequence(spec, action_size: int, n_segments: int) -> np.ndarray:
    """(n_segments, action_size): ``spec.sequence`` then ``spec.initial`` (default zeros) for the rest."""
    out = np.zeros((n_segments, action_size))
    if spec.initial is not None:
        out[:] = spec.initial
    for n, act in enumerate(spec.sequence[:n_segments]):
        out[n] = act
    return out
