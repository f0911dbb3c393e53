"""A soft body's initial velocity as a field: each component a number [m/s] or an expression in the
particle's position x, y, z [m] (``mpm.bodies[i].velocity``), e.g. a disc spinning at 2 rad/s about
(0.5, 0.5): ``velocity: ["-2 * (y - 0.5)", "2 * (x - 0.5)"]``.

Expressions are NumPy arithmetic only: numbers, x, y, z (z only in 3D), pi, + - * / ** and
parentheses, comparisons, and the functions in ``FUNCTIONS``; anything else (attributes, other
names, calls of other things, subscripts, lambdas) is refused with the key path, so a scene file
cannot run code. NumPy only: ``cosim validate`` evaluates it too.
"""

from __future__ import annotations

import ast
import math
from typing import Any

import numpy as np

FUNCTIONS = {
    name: getattr(np, name)
    for name in ("sin", "cos", "tan", "exp", "log", "sqrt", "abs", "tanh", "arctan2", "minimum", "maximum", "where")
}
AXES = ("x", "y", "z")
_NODES = (
    ast.Expression,
    ast.BinOp,
    ast.UnaryOp,
    ast.Compare,
    ast.Call,
    ast.Name,
    ast.Load,
    ast.Constant,
    ast.operator,
    ast.unaryop,
    ast.cmpop,
)


def velocity_component(value: Any) -> float | str:
    """A component of ``mpm.bodies[i].velocity`` as read from YAML: a finite number or an expression."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(  # noqa: TRY004 (pydantic reports ValueError, not TypeError, as a scene error)
            f"must be a number [m/s] or an expression in x, y, z given as a string (got {value!r})"
        )
    if not math.isfinite(value):
        raise ValueError("must be a finite number")
    return float(value)


def expression_problem(text: str, dim: int) -> str | None:
    """Why ``text`` is not an allowed expression of the position in ``dim`` dimensions (None if it is)."""
    try:
        tree = ast.parse(text, mode="eval")
    except SyntaxError as exc:
        return f"not a valid expression ({exc.msg}): {text!r}"
    names = {*AXES[:dim], "pi", *FUNCTIONS}
    for node in ast.walk(tree):
        if not isinstance(node, _NODES):
            return f"{type(node).__name__} is not allowed in {text!r}; use numbers, {', '.join(AXES[:dim])}, pi, arithmetic and {', '.join(FUNCTIONS)}"
        if isinstance(node, ast.Name) and node.id not in names:
            return f"unknown name '{node.id}' in {text!r}; allowed: {', '.join(sorted(names))}"
        if isinstance(node, ast.Call) and not (isinstance(node.func, ast.Name) and node.func.id in FUNCTIONS):
            return f"only {', '.join(FUNCTIONS)} can be called in {text!r}"
        if isinstance(node, ast.Constant) and not isinstance(node.value, (int, float)):
            return f"only numbers are allowed as constants in {text!r}"
    return None


def velocity_field(velocity: list[float | str] | None, pts: np.ndarray) -> np.ndarray:
    """(n, dim) [m/s] initial velocities of the particles at ``pts`` (n, dim) [m]: zero without a
    velocity, each component a number or an expression checked by ``expression_problem``."""
    n, dim = pts.shape
    out = np.zeros((n, dim))
    if velocity is None:
        return out
    scope = {"__builtins__": {}, "pi": np.pi, **FUNCTIONS, **{a: pts[:, k] for k, a in enumerate(AXES[:dim])}}
    for k, component in enumerate(velocity):
        if isinstance(component, str):
            value = eval(compile(ast.parse(component, mode="eval"), "<velocity>", "eval"), scope)  # checked above
            out[:, k] = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,))
        else:
            out[:, k] = float(component)
    return out
