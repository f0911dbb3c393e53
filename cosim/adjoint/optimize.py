"""Gradient-based optimisation of a rollout's inputs (Adam on the adjoint gradient)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from cosim.errors import SimulationError


@dataclass
class OptimizeResult:
    params: dict[str, np.ndarray]  # the best parameters seen
    losses: list[float] = field(default_factory=list)  # loss at each iteration's parameters
    best_loss: float = float("inf")


def adam(
    evaluate: Callable[[dict[str, np.ndarray], bool], tuple[float, dict | None]],
    params: dict[str, np.ndarray],
    names: list[str],
    scales: dict[str, float],
    iterations: int,
    learning_rate: float,
    bounds: dict[str, tuple[float, float]] | None = None,
    callback: Callable[[int, float], None] | None = None,
) -> OptimizeResult:
    """Minimise ``evaluate`` over the parameters ``names`` with Adam (beta 0.9, 0.999).

    The step of each parameter is ``learning_rate * scales[name]`` (Adam's
    normalised step), so one learning rate serves impulses [N s] and moduli
    [Pa] alike. ``bounds`` clip a parameter after each step (e.g. nu < 0.5).
    """
    beta1, beta2, eps = 0.9, 0.999, 1e-12
    params = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    m = {k: np.zeros_like(params[k]) for k in names}
    v = {k: np.zeros_like(params[k]) for k in names}
    result = OptimizeResult(params={k: a.copy() for k, a in params.items()})
    for it in range(iterations):
        loss, grads = evaluate(params, True)
        result.losses.append(loss)
        if loss < result.best_loss:
            result.best_loss = loss
            result.params = {k: a.copy() for k, a in params.items()}
        if callback is not None:
            callback(it, loss)
        for k in names:
            g = grads[k]
            if not np.all(np.isfinite(g)):
                raise SimulationError(
                    f"optimize: the gradient of '{k}' is not finite at iteration {it}; "
                    "lower optimize.learning_rate or check the scene's stability"
                )
            m[k] = beta1 * m[k] + (1 - beta1) * g
            v[k] = beta2 * v[k] + (1 - beta2) * g * g
            m_hat = m[k] / (1 - beta1 ** (it + 1))
            v_hat = v[k] / (1 - beta2 ** (it + 1))
            params[k] = params[k] - learning_rate * scales[k] * m_hat / (np.sqrt(v_hat) + eps)
            bound = (bounds or {}).get(k) or (bounds or {}).get(k.split(".", 1)[-1])  # "towel.k_bend" -> k_bend
            if bound:
                params[k] = np.clip(params[k], *bound)
    final, _ = evaluate(params, False)
    result.losses.append(final)
    if final < result.best_loss:
        result.best_loss = final
        result.params = {k: a.copy() for k, a in params.items()}
    return result


PARAM_BOUNDS = {
    "nu": (0.0, 0.49),
    "E": (1e-6, np.inf),
    "k_stretch": (1e-6, np.inf),
    "k_bend": (0.0, np.inf),
    "c_mass": (0.0, np.inf),
    "density": (1e-9, np.inf),
}
