"""Gradient-based optimisation of a rollout's inputs on the adjoint gradient: Adam, SGD or L-BFGS-B.

Every parameter steps by ``learning_rate * scales[name]`` (Adam: times its normalised
moment; SGD: times the raw gradient scaled by the parameter's size, g * scale^2), so one
learning rate serves impulses [N s], actions [m/s] and moduli [Pa] alike. No gradient is
scaled, clipped or dropped: bounds (e.g. nu < 0.5) and constraints (a cloth control's reach)
project the parameters after a step.

A step whose rollout fails (a ``SimulationError``: material leaving the domain, the CFL or
tracing bound, a NaN) is taken again at half its length from the parameters before it, up to
``MAX_HALVINGS`` times (the step-length control of a line search; the gradient is untouched);
the iteration's row records the halvings. If none passes, the run stops there with the best
parameters so far and says why (``OptimizeResult.stopped``).

With a ``checkpoint`` path the parameters, the optimiser's moments and the history are
saved after every iteration; ``resume`` continues from it, so an interrupted run ends
where an uninterrupted one does (Adam and SGD; scipy's L-BFGS-B keeps its memory inside,
so an L-BFGS run is not resumable).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cosim.errors import InputError, SimulationError

METHODS = ("adam", "sgd", "lbfgs")
MAX_HALVINGS = 6  # a failed step is retried at 1/2, 1/4, ... down to 1/64 of its length


@dataclass
class OptimizeResult:
    params: dict[str, np.ndarray]  # the best parameters seen
    losses: list[float] = field(default_factory=list)  # loss at each iteration's parameters, then the final one
    best_loss: float = float("inf")
    history: list[dict] = field(default_factory=list)  # one row per iteration (``minimise``)
    stopped: str | None = None  # why the run ended before its iterations (a step no halving could save)


class Adam:
    """Adam (beta 0.9, 0.999): the step is ``lr * scale * m_hat / (sqrt(v_hat) + eps)``."""

    beta1, beta2, eps = 0.9, 0.999, 1e-12

    def __init__(self, names: list[str], params: dict[str, np.ndarray]) -> None:
        self.state = {f"m:{k}": np.zeros_like(params[k]) for k in names}
        self.state.update({f"v:{k}": np.zeros_like(params[k]) for k in names})

    def step(self, it: int, name: str, grad: np.ndarray, lr: float, scale: float) -> np.ndarray:
        m = self.state[f"m:{name}"] = self.beta1 * self.state[f"m:{name}"] + (1 - self.beta1) * grad
        v = self.state[f"v:{name}"] = self.beta2 * self.state[f"v:{name}"] + (1 - self.beta2) * grad * grad
        m_hat, v_hat = m / (1 - self.beta1 ** (it + 1)), v / (1 - self.beta2 ** (it + 1))
        return -lr * scale * m_hat / (np.sqrt(v_hat) + self.eps)


class SGD:
    """Gradient descent with momentum 0.9 (the paper's optimiser for the Franka task): the velocity
    u = 0.9 u + g scale^2, the step ``-lr * u``."""

    momentum = 0.9

    def __init__(self, names: list[str], params: dict[str, np.ndarray]) -> None:
        self.state = {f"u:{k}": np.zeros_like(params[k]) for k in names}

    def step(self, it: int, name: str, grad: np.ndarray, lr: float, scale: float) -> np.ndarray:
        u = self.state[f"u:{name}"] = self.momentum * self.state[f"u:{name}"] + grad * scale * scale
        return -lr * u


def minimise(
    evaluate: Callable[[dict[str, np.ndarray], bool], tuple[float, dict | None]],
    params: dict[str, np.ndarray],
    names: list[str],
    scales: dict[str, float | np.ndarray],
    iterations: int,
    learning_rate: float,
    method: str = "adam",
    bounds: dict[str, tuple[float, float]] | None = None,
    projections: dict[str, Callable[[np.ndarray], np.ndarray]] | None = None,
    terms: Callable[[], dict[str, float]] | None = None,
    on_iteration: Callable[[dict, list[dict]], None] | None = None,
    checkpoint: Path | None = None,
    resume: bool = False,
) -> OptimizeResult:
    """Minimise ``evaluate`` over the parameters ``names`` for ``iterations`` iterations.

    Each iteration's row (``OptimizeResult.history``): iteration, loss, the loss terms
    (``terms()``), the gradient's norm per parameter ("grad:<name>") and seconds;
    ``on_iteration(row, history)`` after each. The loss of the final parameters is evaluated
    once more at the end. ``scales[name]`` (a number, or an array that broadcasts to the
    parameter) sets its step size; after each step the parameter is clipped to ``bounds[name]``
    and mapped by ``projections[name]``.
    """
    if method not in METHODS:
        raise InputError(f"optimize.method: '{method}' is not one of {list(METHODS)}")
    projections = projections or {}
    if method == "lbfgs":
        if projections:
            raise InputError(
                f"optimize.method: L-BFGS-B takes box bounds only, and {sorted(projections)} are constrained "
                "(e.g. a cloth's actions.reach); use adam or sgd"
            )
        if resume:
            raise InputError("--resume: an L-BFGS run cannot be resumed (scipy keeps its memory); rerun it")
        return _lbfgs(evaluate, params, names, scales, iterations, bounds, terms, on_iteration)
    params = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    optimiser = (Adam if method == "adam" else SGD)(names, params)
    result = OptimizeResult(params={k: a.copy() for k, a in params.items()})
    start, before = 0, None  # before: the parameters before the last step (None: no step taken yet)
    if resume:
        start, before = _load(Path(checkpoint), params, optimiser, result, names, method)

    def shorten(current: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        half = {k: constrain(before[k] + 0.5 * (current[k] - before[k]), k, bounds, projections) for k in names}
        return {**current, **half}

    def attempt(it: int, grad: bool):
        """``_evaluate_shortening``, or None when no halving saves the step (``result.stopped`` says why;
        the best parameters so far stand). A failure before any step is raised."""
        try:
            return _evaluate_shortening(evaluate, params, before, shorten, it, grad)
        except SimulationError as err:
            if before is None:
                raise
            result.stopped = str(err)
            return None

    for it in range(start, iterations):
        t0 = time.perf_counter()
        evaluated = attempt(it, True)
        if evaluated is None:
            return result
        loss, grads, params, halvings = evaluated
        row = {"iteration": it, "loss": loss, **(terms() if terms else {})}
        if halvings:
            row["step_halvings"] = halvings
        if loss < result.best_loss:
            result.best_loss = loss
            result.params = {k: a.copy() for k, a in params.items()}
        for k in names:
            g = grads[k]
            if not np.all(np.isfinite(g)):
                raise SimulationError(
                    f"optimize: the gradient of '{k}' is not finite at iteration {it}; "
                    "lower optimize.learning_rate or check the scene's stability"
                )
            row[f"grad:{k}"] = float(np.linalg.norm(g))
        before = {k: a.copy() for k, a in params.items()}
        for k in names:
            params[k] = constrain(
                params[k] + optimiser.step(it, k, grads[k], learning_rate, scales[k]), k, bounds, projections
            )
        row["seconds"] = time.perf_counter() - t0
        result.losses.append(loss)
        result.history.append(row)
        if checkpoint is not None:
            _save(Path(checkpoint), params, optimiser, result, it + 1, method, before)
        if on_iteration is not None:
            on_iteration(row, result.history)
    evaluated = attempt(iterations, False)
    if evaluated is None:
        return result
    final, _, params, _ = evaluated
    result.losses.append(final)
    if final < result.best_loss:
        result.best_loss = final
        result.params = {k: a.copy() for k, a in params.items()}
    return result


def _evaluate_shortening(evaluate, params, before, shorten, it: int, grad: bool = True):
    """(loss, gradients, the parameters evaluated, halvings): ``evaluate`` at ``params``, and while its
    rollout fails after a step (``before`` is not None), at ``shorten(params)``, half as far from ``before``."""
    halvings = 0
    while True:
        try:
            loss, grads = evaluate(params, grad)
            return loss, grads, params, halvings
        except SimulationError as err:
            if before is None or halvings == MAX_HALVINGS:
                tried = f" (and the step halved {halvings} times)" if halvings else ""
                raise SimulationError(f"optimize: iteration {it}: the rollout failed{tried}: {err}") from err
            params, halvings = shorten(params), halvings + 1


def constrain(value: np.ndarray, name: str, bounds: dict | None, projections: dict | None) -> np.ndarray:
    """Parameter ``name``'s ``value`` clipped to its bounds, then mapped by its projection (if any)."""
    bound = _bound(bounds, name)
    if bound:
        value = np.clip(value, *bound)
    projections = projections or {}
    return projections[name](value) if name in projections else value


def _bound(bounds: dict | None, name: str):
    """The bounds of parameter ``name``, by its full name or its engine-free one ("towel.k_bend" -> k_bend)."""
    bounds = bounds or {}
    return bounds.get(name) or bounds.get(name.split(".", 1)[-1])


def _lbfgs(evaluate, params, names, scales, iterations, bounds, terms, on_iteration) -> OptimizeResult:
    """scipy's L-BFGS-B over the parameters in units of their scales (bounds likewise); one history
    row per function evaluation (line searches evaluate more than once per iteration)."""
    from scipy.optimize import minimize

    params = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    sizes = [params[k].size for k in names]
    scales = {k: np.broadcast_to(np.asarray(scales[k], dtype=np.float64), params[k].shape) for k in names}
    result = OptimizeResult(params={k: a.copy() for k, a in params.items()})

    def unpack(z: np.ndarray) -> dict[str, np.ndarray]:
        out, start = dict(params), 0
        for k, n in zip(names, sizes, strict=True):
            out[k] = z[start : start + n].reshape(params[k].shape) * scales[k]
            start += n
        return out

    def fun(z: np.ndarray) -> tuple[float, np.ndarray]:
        t0 = time.perf_counter()
        current = unpack(z)
        loss, grads = evaluate(current, True)
        row = {"iteration": len(result.history), "loss": loss, **(terms() if terms else {})}
        for k in names:
            if not np.all(np.isfinite(grads[k])):
                raise SimulationError(f"optimize: the gradient of '{k}' is not finite at evaluation {row['iteration']}")
            row[f"grad:{k}"] = float(np.linalg.norm(grads[k]))
        row["seconds"] = time.perf_counter() - t0
        result.losses.append(loss)
        result.history.append(row)
        if loss < result.best_loss:
            result.best_loss, result.params = loss, {k: a.copy() for k, a in current.items()}
        if on_iteration is not None:
            on_iteration(row, result.history)
        return loss, np.concatenate([(grads[k] * scales[k]).ravel() for k in names])

    box = []
    for k, n in zip(names, sizes, strict=True):
        bound = _bound(bounds, k)
        lo, hi = (np.full(params[k].shape, -np.inf), np.full(params[k].shape, np.inf)) if not bound else bound
        lo = np.broadcast_to(np.asarray(lo, float), params[k].shape).ravel() / scales[k].ravel()
        hi = np.broadcast_to(np.asarray(hi, float), params[k].shape).ravel() / scales[k].ravel()
        box += [(None if np.isinf(a) else a, None if np.isinf(b) else b) for a, b in zip(lo, hi, strict=True)]
    z0 = np.concatenate([(params[k] / scales[k]).ravel() for k in names])
    # scipy's stopping tolerances are absolute (gtol 1e-5 on the projected gradient): a loss of 1e-3 m^2
    # stopped after one evaluation (measured), so only the iteration budget stops the run
    options = {"maxiter": iterations, "gtol": 0.0, "ftol": 0.0}
    minimize(fun, z0, jac=True, method="L-BFGS-B", bounds=box, options=options)
    return result


def adam(evaluate, params, names, scales, iterations, learning_rate, bounds=None, callback=None) -> OptimizeResult:
    """``minimise`` with Adam; ``callback(iteration, loss)`` after each iteration."""
    on_iteration = None if callback is None else (lambda row, _history: callback(row["iteration"], row["loss"]))
    return minimise(
        evaluate, params, names, scales, iterations, learning_rate, "adam", bounds, on_iteration=on_iteration
    )


def _save(path: Path, params, optimiser, result: OptimizeResult, done: int, method: str, before=None) -> None:
    """Everything a resumed run needs, written atomically (a crash mid-write keeps the last one); ``before``:
    the parameters before the last step, from which a failed step is shortened."""
    arrays = {f"param:{k}": v for k, v in params.items()}
    arrays.update({f"before:{k}": v for k, v in (before or {}).items()})
    arrays.update({f"best:{k}": v for k, v in result.params.items()})
    arrays.update({f"opt:{k}": v for k, v in optimiser.state.items()})
    meta = {"done": done, "method": method, "best_loss": result.best_loss, "losses": result.losses}
    meta["history"] = result.history
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, meta=np.array(json.dumps(meta)), **arrays)
    tmp.replace(path)


def _load(path: Path, params, optimiser, result: OptimizeResult, names: list[str], method: str):
    """Restore a checkpoint into ``params``, ``optimiser`` and ``result``; returns the iterations done and
    the parameters before the last step (None if the checkpoint has none)."""
    if not path.is_file():
        raise InputError(f"--resume: no checkpoint at {path}; run `cosim optimize` without --resume first")
    data = np.load(path, allow_pickle=False)
    meta = json.loads(str(data["meta"]))
    saved = sorted(k.split(":", 1)[1] for k in data.files if k.startswith("opt:"))
    if meta["method"] != method or saved != sorted(optimiser.state):
        raise InputError(
            f"--resume: {path} is a {meta['method']} run over other parameters; "
            f"resume with the same method and optimize.params ({method}, {names})"
        )
    for k in params:
        params[k] = data[f"param:{k}"].copy()
        result.params[k] = data[f"best:{k}"].copy()
    for k in optimiser.state:
        optimiser.state[k] = data[f"opt:{k}"].copy()
    result.best_loss, result.losses, result.history = meta["best_loss"], meta["losses"], meta["history"]
    before = {k: data[f"before:{k}"].copy() for k in params if f"before:{k}" in data.files}
    return int(meta["done"]), before or None


PARAM_BOUNDS = {
    "nu": (0.0, 0.49),
    "E": (1e-6, np.inf),
    "k_stretch": (1e-6, np.inf),
    "k_bend": (0.0, np.inf),
    "c_mass": (0.0, np.inf),
    "density": (1e-9, np.inf),
}
