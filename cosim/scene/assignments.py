"""``--set KEY.PATH=VALUE``: edit a scene's parsed YAML before it is validated.

A path names mapping keys separated by dots, list items by ``[index]``
(``mpm.bodies[0].material.E=4e4``); the value is read as YAML (``[0, 1]``,
``true``, ``float64``), with exponent numbers such as ``4e4`` taken as floats
(YAML 1.1 reads them as strings). Missing mappings on the way are created; a
wrong key then fails validation like a wrong key in the file, which names the
key and the keys allowed there. An index past a list's end, or a path through a
number, is reported here, naming the assignment.
"""

from __future__ import annotations

import copy
import re
from typing import Any

import yaml

from cosim.errors import SceneError

_PART = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[\d+\])*)")
EXAMPLE = "e.g. --set mpm.bodies[0].material.E=4e4"


def parse_assignment(text: str) -> tuple[list[str | int], Any]:
    """``"a.b[0].c=1"`` -> (["a", "b", 0, "c"], 1)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise SceneError(f"--set {text!r}: expected KEY.PATH=VALUE, {EXAMPLE}")
    path: list[str | int] = []
    for part in key.strip().split("."):
        match = _PART.fullmatch(part)
        if match is None:
            raise SceneError(f"--set {key}: '{part}' is not a key with optional [index] parts, {EXAMPLE}")
        path.append(match.group(1))
        path += [int(i) for i in re.findall(r"\[(\d+)\]", match.group(2))]
    try:
        value = yaml.safe_load(raw) if raw.strip() else None
    except yaml.YAMLError as exc:
        raise SceneError(f"--set {key}: the value {raw!r} is not valid YAML: {exc}") from None
    if value is None:
        raise SceneError(f"--set {key}: no value given, {EXAMPLE}")
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            pass
    return path, value


def _label(path: list[str | int]) -> str:
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path).lstrip(".")


def apply_assignments(data: dict, assignments: list[str]) -> dict:
    """A copy of the scene data with every ``KEY.PATH=VALUE`` of ``assignments`` set, in order."""
    data = copy.deepcopy(data)
    for text in assignments:
        path, value = parse_assignment(text)
        node: Any = data
        for i, part in enumerate(path):
            last = i == len(path) - 1
            where = _label(path[:i]) or "the top level"
            if isinstance(part, int):
                if not isinstance(node, list):
                    raise SceneError(f"--set {_label(path)}: {where} is not a list, so [{part}] does not apply")
                if part >= len(node):
                    raise SceneError(
                        f"--set {_label(path)}: {where} has {len(node)} items (indices 0..{len(node) - 1})"
                    )
            elif isinstance(node, list):
                raise SceneError(f"--set {_label(path)}: {where} is a list: give an index, e.g. {where}[0].{part}")
            elif not isinstance(node, dict):
                raise SceneError(f"--set {_label(path)}: {where} is a value, not a mapping with key '{part}'")
            if last:
                node[part] = value
            else:
                if isinstance(node, dict) and node.get(part) is None:
                    if isinstance(path[i + 1], int):
                        raise SceneError(f"--set {_label(path)}: {_label(path[: i + 1])} is not in the scene")
                    node[part] = {}
                node = node[part]
    return data
