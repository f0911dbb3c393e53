"""A soft body's initial velocity as a field: each component a number [m/s] or an expression in the
particle's position x, y, z [m] (``mpm.bodies[i].velocity``), e.g. a disc spinning at 2 rad/s about
(0.5, 0.5): ``velocity: ["-2 * (y - 0.5)", "2 * (x - 0.5)"]``.

Expressions are NumPy arithmetic only: numbers, x, y, z (z only in 3D), pi, + - * / ** and
parentheses, comparisons, and the functions in ``FUNCTIONS``; anything else (attributes, other
names, calls of other things, subscripts, lambdas) is refused with the key path, so a scene file
cannot run code. NumPy only: ``cosim validate`` evaluates it too.

The particles also start with the field's gradient as their APIC affine velocity,
C[i, j] = d v_i / d x_j [1/s] (``velocity_gradient``): the MLS-MPM transfer reproduces a
linear field exactly only with it, so a disc started spinning keeps its spin instead of
handing a share of its angular momentum to C at the first transfer. Numbers give C = 0
exactly. A velocity read from a file is ``cosim.scene.velocity_file``.
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
GRADIENT_STEP = 1e-6  # the difference step of ``velocity_gradient``, a fraction of the domain's size
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


def velocity_gradient(velocity: list[float | str] | None, pts: np.ndarray, step: float) -> np.ndarray:
    """(n, dim, dim) [1/s] the gradient C[p, i, j] = d v_i / d x_j of ``velocity_field`` at the
    particles ``pts`` (n, dim) [m], by differences with ``step`` [m] on either side of each particle.

    Central differences where the two one-sided differences agree; where they differ by more than
    half their size (a jump of ``where`` or a comparison within ``step``, a kink of ``abs``) the
    smaller one, or 0 if their signs differ, so a jump next to a particle does not become a huge
    C. Zero without expressions."""
    n, dim = pts.shape
    if velocity is None or not any(isinstance(c, str) for c in velocity):
        return np.zeros((n, dim, dim))
    here = velocity_field(velocity, pts)
    out = np.empty((n, dim, dim))
    for j in range(dim):
        ahead, behind = pts.copy(), pts.copy()
        ahead[:, j] += step
        behind[:, j] -= step
        # the steps as represented: (x + h) - x is exact, h itself may not be
        h_ahead, h_behind = ahead[:, j] - pts[:, j], pts[:, j] - behind[:, j]
        forward = (velocity_field(velocity, ahead) - here) / h_ahead[:, None]
        backward = (here - velocity_field(velocity, behind)) / h_behind[:, None]
        out[:, :, j] = _difference(forward, backward)
    return out


def _difference(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """The central difference of two one-sided ones, or the smaller (0 across a sign change) where
    they disagree by more than half their size; one side alone where the other is not finite."""
    forward, backward = (
        np.where(np.isfinite(forward), forward, backward),
        np.where(np.isfinite(backward), backward, forward),
    )
    central = 0.5 * (forward + backward)
    smaller = np.where(np.abs(forward) < np.abs(backward), forward, backward)
    limited = np.where(forward * backward > 0, smaller, 0.0)
    smooth = np.abs(forward - backward) <= 0.5 * (np.abs(forward) + np.abs(backward))
    return np.where(smooth, central, limited)
