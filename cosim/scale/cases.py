"""The cases of a sweep: every combination of ``--grid KEY.PATH=v1,v2,...`` values, or a seeded sample.

Each case is a list of ``KEY.PATH=VALUE`` assignments (``cosim.scene.assignments``), applied on
top of the scene and of any ``--set``. Values are split at commas outside brackets, so a list
value reads ``--grid mpm.bodies[0].shape.center=[0.5,0.3],[0.5,0.4]``.
"""

from __future__ import annotations

import itertools

import numpy as np

from cosim.errors import SceneError
from cosim.scene.assignments import parse_assignment


def split_values(text: str) -> list[str]:
    """``"1,[2,3],4"`` -> ["1", "[2,3]", "4"]: commas inside brackets or braces belong to a value."""
    values, depth, current = [], 0, ""
    for char in text:
        depth += char in "[{"
        depth -= char in "]}"
        if char == "," and depth == 0:
            values.append(current)
            current = ""
        else:
            current += char
    values.append(current)
    return [v.strip() for v in values]


def parse_grid(spec: str) -> tuple[str, list[str]]:
    """``"KEY.PATH=v1,v2"`` -> ("KEY.PATH", ["v1", "v2"]), each value checked as an assignment."""
    key, sep, raw = spec.partition("=")
    values = split_values(raw) if sep else []
    if not key.strip() or not values or any(not v for v in values):
        raise SceneError(f"--grid {spec!r}: expected KEY.PATH=v1,v2,..., e.g. --grid mpm.bodies[0].material.E=1e4,4e4")
    for value in values:
        parse_assignment(f"{key}={value}")
    return key.strip(), values


def grid_cases(specs: list[str], samples: int | None = None, seed: int = 0) -> list[list[str]]:
    """Every combination of the grids' values (the last grid varying fastest), or ``samples`` of them
    drawn without replacement with ``seed`` (all of them when there are fewer)."""
    grids = [parse_grid(spec) for spec in specs]
    keys = [k for k, _ in grids]
    if len(set(keys)) != len(keys):
        raise SceneError(f"--grid: a key is given twice ({', '.join(keys)}); give each key once with all its values")
    combos = [[f"{k}={v}" for k, v in zip(keys, values)] for values in itertools.product(*(vals for _, vals in grids))]
    if samples is None or samples >= len(combos):
        return combos
    rng = np.random.default_rng(seed)
    return [combos[i] for i in sorted(rng.choice(len(combos), size=samples, replace=False))]
