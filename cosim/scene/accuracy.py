"""The scene's ``accuracy: coarse | default | fine`` hint: grid, CFL number and precision in one word.

Applied to the parsed YAML before validation (``cosim.scene.loader``). Each level is a point on
or near the measured work-precision front of ``cosim bench accuracy`` (docs/accuracy.md):

- the grid is refined by the level's ``grid`` factor: ``mpm.grid.cells`` times it, ``mpm.grid.dx``
  divided by it, so the domain stays (exactly along the longest axis; the others to the nearest
  cell), and the wall thickness ``mpm.boundary.thickness`` (in cells) times it, so the walls stay
  where they were as far as its 2-16 cell range allows. The grid is always written in a scene,
  so the hint scales it rather than replacing it. Body ``spacing`` set in metres stays; the default
  (dx / 2) follows the grid;
- ``time.cfl`` and ``precision`` are set to the level's values unless the scene sets them: a key
  written in the scene (or given by ``--set`` / ``--precision``) wins over the hint. A fixed
  ``time.substeps`` stays fixed (the CFL number only drives automatic substeps).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

from cosim.errors import SceneError


@dataclass(frozen=True)
class AccuracyLevel:
    """What one hint sets: grid refinement factor, CFL number, precision."""

    grid: float
    cfl: float
    precision: str


# From `cosim bench accuracy` (docs/accuracy.md): the grid moves the error far more than the CFL
# number, so the levels halve or double it; coarse grids hid the time error, so coarse takes cfl 0.6
# (0.9 was cheaper still but went unstable once, on viscous water); default is the shipped settings;
# fine keeps cfl 0.3 and takes float64, as costly here and the more accurate at the finest grids.
LEVELS: dict[str, AccuracyLevel] = {
    "coarse": AccuracyLevel(grid=0.5, cfl=0.6, precision="float32"),
    "default": AccuracyLevel(grid=1.0, cfl=0.3, precision="float32"),
    "fine": AccuracyLevel(grid=2.0, cfl=0.3, precision="float64"),
}
MAX_CELLS, MIN_CELLS = 4096, 8  # the schema's range of mpm.grid.cells
MIN_WALL, MAX_WALL = 2, 16  # the schema's range of mpm.boundary.thickness [cells]


def refine_grid(data: dict, factor: float, key: str = "accuracy") -> dict:
    """A copy of the scene data with its grid refined by ``factor`` (see the module docstring); a
    grid that is not yet valid is returned unchanged for the schema to report. ``key`` names the
    setting that asked, in errors."""
    data = copy.deepcopy(data)
    grid = (data.get("mpm") or {}).get("grid")
    if factor == 1.0 or not isinstance(grid, dict):
        return data
    cells = grid.get("cells")
    listed = isinstance(cells, list)
    values = cells if listed else [cells]
    if not values or not all(isinstance(c, int) and not isinstance(c, bool) and c > 0 for c in values):
        return data
    dx = grid.get("dx", 1.0 / max(values))
    if not isinstance(dx, (int, float)) or isinstance(dx, bool) or dx <= 0:
        return data
    refined = [max(1, round(c * factor)) for c in values]
    if not all(MIN_CELLS <= c <= MAX_CELLS for c in refined):
        raise SceneError(
            f"{key}: refining mpm.grid.cells {cells} by {factor:g} gives {refined}, outside {MIN_CELLS}-{MAX_CELLS}; "
            "choose another accuracy level or change mpm.grid.cells"
        )
    grid["cells"] = refined if listed else refined[0]
    grid["dx"] = dx * max(values) / max(refined)
    boundary = data["mpm"].setdefault("boundary", {})
    if isinstance(boundary, dict):
        wall = boundary.get("thickness", 3)
        if isinstance(wall, int) and not isinstance(wall, bool):
            boundary["thickness"] = min(MAX_WALL, max(MIN_WALL, round(wall * factor)))
    return data


def apply_accuracy_hint(data: Any) -> Any:
    """The scene data with its ``accuracy`` hint applied (unchanged without one); a value other
    than coarse, default or fine is a ``SceneError`` naming ``accuracy``."""
    if not isinstance(data, dict) or data.get("accuracy") is None:
        return data
    name = data["accuracy"]
    if not isinstance(name, str) or name not in LEVELS:
        raise SceneError(f"accuracy: must be one of {', '.join(LEVELS)} (got {name!r}); see docs/accuracy.md")
    level = LEVELS[name]
    out = refine_grid(data, level.grid)
    out.setdefault("precision", level.precision)
    time = out.setdefault("time", {})
    if isinstance(time, dict):
        time.setdefault("cfl", level.cfl)
    return out
