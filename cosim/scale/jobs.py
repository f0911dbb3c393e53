"""What one worker runs for one case (module-level functions: Ray ships them by reference).

Every job loads the scene itself from its path and assignments, so a worker needs the
package and the scene's files, not the driver's objects.
"""

from __future__ import annotations

import time
from numbers import Number
from pathlib import Path

import numpy as np


def flatten(metrics: dict, prefix: str = "") -> dict[str, float]:
    """The numbers in nested ``metrics``, keyed by their path joined with '/'
    (``bodies/water/particles``, ``joint_positions/door/0``); strings are left out."""
    out: dict[str, float] = {}
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(flatten(value, f"{name}/"))
        elif isinstance(value, (list, tuple)):
            out.update(flatten({str(i): v for i, v in enumerate(value)}, f"{name}/"))
        elif isinstance(value, (Number, np.number, np.bool_)):
            out[name] = float(value)
    return out


def run_case(scene_path: str, defaults: dict, assignments: list[str], steps: int | None, loss: bool) -> dict:
    """One sweep case: ``cosim run``'s metrics (nothing written), or with ``loss`` the scene's loss,
    its terms and the gradient's norm per optimised parameter (``optimize.params``)."""
    from cosim.scene import load_scene

    scene = load_scene(scene_path, defaults or None, assignments)
    if not loss:
        from cosim.run import run_scene

        return flatten(run_scene(scene, None, steps=steps, progress=False, preview=False))
    from cosim.adjoint.objective import Objective
    from cosim.scene.build import build_system

    sim = build_system(scene, requires_grad=True, steps=steps)
    objective = Objective(sim)
    names = objective.select(scene.optimize.params)
    t0 = time.perf_counter()
    value, grads = objective.evaluate(objective.initial_params(), grad=True)
    row = {"loss": float(value), **{f"loss/{k}": float(v) for k, v in objective.loss.values.items()}}
    row.update({f"grad_norm/{n}": float(np.linalg.norm(grads[n])) for n in names})
    row["wall_time_s"] = time.perf_counter() - t0
    return row


def optimize_start(scene_path: str, defaults: dict, assignments: list[str], settings: dict, out: str) -> dict:
    """One start of ``cosim optimize --starts``: ``optimize_scene`` with ``settings`` (iterations, lr,
    method, steps, perturbation, seed), its outputs in ``out``; returns its losses and best parameters."""
    from cosim.adjoint.optimize_scene import optimize_scene
    from cosim.scene import load_scene

    scene = load_scene(scene_path, defaults or None, assignments)
    return optimize_scene(scene, Path(out), progress=False, announce=False, **settings)
