"""``cosim optimize`` for one scene: build, minimise, write the outputs (one start of ``--starts``).

Outputs in ``out``: ``optimization.csv`` and ``checkpoint.npz`` after every iteration, then
``params.npz``, ``optimization.json``, ``loss.png`` and the optimised rollout's trajectory and
preview (see docs/outputs.md).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def perturb(params: dict, names: list[str], scales: dict, fraction: float, seed: int, bounds, projections) -> dict:
    """A copy of ``params`` with each of ``names`` moved by ``fraction`` x its scale x N(0, 1) noise
    (``seed``), then clipped to its bounds and projected like an optimiser step."""
    from cosim.adjoint.optimize import constrain

    rng = np.random.default_rng(seed)
    out = {k: np.array(v, dtype=np.float64, copy=True) for k, v in params.items()}
    for k in names:
        out[k] = out[k] + fraction * np.asarray(scales[k]) * rng.standard_normal(out[k].shape)
        out[k] = constrain(out[k], k, bounds, projections)
    return out


def optimize_scene(
    scene,
    out: Path,
    iterations: int | None = None,
    lr: float | None = None,
    method: str | None = None,
    steps: int | None = None,
    resume: bool = False,
    progress: bool = True,
    preview: bool = True,
    announce: bool = True,
    perturbation: float = 0.0,
    seed: int = 0,
) -> dict:
    """Minimise ``scene``'s loss over ``optimize.params`` from its initial guess (moved by
    ``perturbation``, a fraction of each parameter's scale, with ``seed``: see ``perturb``).
    ``progress``: a progress bar; ``announce``: print what is optimised first.
    Returns the summary written to ``optimization.json`` plus ``best_params`` (name -> array)."""
    from tqdm import tqdm

    from cosim.adjoint.objective import Objective
    from cosim.adjoint.optimize import PARAM_BOUNDS, minimise
    from cosim.adjoint.report import plot_losses, write_history
    from cosim.scene.build import build_system
    from cosim.scene.params import select_params
    from cosim.trajectory import Recorder

    spec = scene.optimize
    sim = build_system(scene, requires_grad=True, steps=steps)
    obj = Objective(sim)
    names = select_params(obj, scene, "optimize")
    iterations = iterations or spec.iterations
    lr = lr or spec.learning_rate
    method = method or spec.method
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bounds, projections, scales = {**PARAM_BOUNDS, **obj.bounds()}, obj.projections(), obj.natural_scales()
    initial = obj.initial_params()
    if perturbation:
        initial = perturb(initial, names, scales, perturbation, seed, bounds, projections)
    if announce:
        print(
            f"optimize {scene.name}: {', '.join(names)}; loss {' + '.join(obj.loss.values)}; {sim.steps} steps; "
            f"{method} lr {lr:g} x scale" + ("; resuming" if resume else "")
        )
        print(obj.memory_estimate().describe(), flush=True)
    bar = tqdm(total=iterations, desc="optimize", unit="it", disable=not progress)

    def on_iteration(row: dict, history: list[dict]) -> None:
        write_history(out, history)  # every iteration: an interrupted run keeps its log
        bar.update(row["iteration"] + 1 - bar.n)
        bar.set_postfix(loss=f"{row['loss']:.4e}")

    result = minimise(
        obj.evaluate,
        initial,
        names,
        scales,
        iterations,
        lr,
        method,
        bounds,
        projections,
        terms=lambda: dict(obj.loss.values),
        on_iteration=on_iteration,
        checkpoint=out / "checkpoint.npz",
        resume=resume,
    )
    bar.close()
    wall = sum(r["seconds"] for r in result.history)
    np.savez(out / "params.npz", **{k: result.params[k] for k in names})  # the optimised ones, not x0 etc.
    write_history(out, result.history)
    plot_losses(out, result.losses, f"{scene.name}: {method}, {', '.join(names)}")
    summary = {
        "params": names,
        "method": method,
        "losses": result.losses,
        "best_loss": result.best_loss,
        "wall_time_s": wall,
        "stopped": result.stopped,
        "perturbation": perturbation,
        "seed": seed,
    }
    (out / "optimization.json").write_text(json.dumps(summary, indent=2))
    recorder = Recorder(sim)

    def record(n: int) -> None:  # every step's reactions, the saved frames' states
        if n > 0:
            recorder.step(n)
        if n == 0 or recorder.wants(n):
            recorder(n)

    obj.rollout(result.params, on_step=record)
    shown = recorder.write(out, preview=preview)
    written = ["params.npz", "optimization.json", "optimization.csv", "loss.png", "trajectory.npz"]
    written += ["checkpoint.npz"] if method != "lbfgs" else []  # scipy's L-BFGS-B is not checkpointed
    summary["written"] = [str(out / name) for name in written + ([shown] if shown else [])]
    summary["best_params"] = {k: result.params[k] for k in names}
    return summary
