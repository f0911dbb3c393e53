"""Reading a scene: YAML file -> ``accuracy`` hint -> schema -> checks that span several keys -> ``Scene``.

Every problem raises ``SceneError`` with one line per problem, each naming the
key path, e.g. ``mpm.bodies[1].material.E: must be > 0``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from cosim.errors import SceneError
from cosim.scene.accuracy import apply_accuracy_hint
from cosim.scene.assignments import apply_assignments
from cosim.scene.checks import semantic_problems
from cosim.scene.messages import format_errors
from cosim.scene.schema import Scene


def parse_scene(data: Any, source_dir: Path | str = ".", origin: str = "scene") -> Scene:
    """Validate a scene given as Python data (the parsed YAML); ``source_dir`` anchors its relative paths."""
    if not isinstance(data, dict):
        raise SceneError(f"{origin}: the top level must be a mapping of keys, got {type(data).__name__}")
    try:
        data = apply_accuracy_hint(data)  # grid, CFL and precision of an ``accuracy:`` level
    except SceneError as exc:
        raise SceneError(f"{origin}: invalid scene\n  {exc}") from None
    try:
        scene = Scene.model_validate(data)
    except ValidationError as exc:
        raise SceneError(f"{origin}: invalid scene\n  " + "\n  ".join(format_errors(exc))) from None
    scene.source_dir = Path(source_dir)
    problems = semantic_problems(scene)
    if problems:
        raise SceneError(f"{origin}: invalid scene\n  " + "\n  ".join(problems))
    return scene


def load_scene(path: str | Path, overrides: dict | None = None, assignments: Sequence[str] = ()) -> Scene:
    """Read, parse and validate a YAML scene file; ``overrides`` replace top-level keys, then each
    ``KEY.PATH=VALUE`` of ``assignments`` sets one value (``cosim.scene.assignments``, the CLI's ``--set``)."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise SceneError(f"{path}: not valid YAML: {yaml_problem(exc)}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: cannot read the scene file: {exc}") from None
    if isinstance(data, dict) and overrides:
        data = {**data, **overrides}
    if isinstance(data, dict) and assignments:
        data = apply_assignments(data, list(assignments))
    return parse_scene(data, path.parent, origin=str(path))


def yaml_problem(exc: yaml.YAMLError) -> str:
    """One line: where the YAML parser stopped (line, column, 1-based) and why."""
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return f"{where}{problem}; fix the syntax there"
