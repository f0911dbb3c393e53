"""`cosim run`: step a scene, save its trajectory, metrics and a preview."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cosim.engines.contract import declares
from cosim.hardware import hardware_line
from cosim.scene import Scene
from cosim.trajectory import Recorder, cloth_engines

if TYPE_CHECKING:
    from cosim.system import CoupledSystem


def run_scene(
    scene: Scene,
    out_dir: Path | None,
    steps: int | None = None,
    progress: bool = True,
    preview: bool = True,
    save_target: bool = False,
    after_rollout: Callable[[CoupledSystem], None] | None = None,
) -> dict:
    """Run ``scene`` for ``steps`` macro steps and write the outputs to ``out_dir``.

    Writes ``trajectory.npz``, ``metrics.json`` and ``preview.gif|mp4`` (see
    docs/outputs.md) and returns the metrics; with ``save_target`` also ``target.npz``,
    every body's and cloth's final positions ``x_<name>`` [m] (a chamfer loss's
    ``points: {rollout: ...}``). ``out_dir`` None writes nothing (a sweep's case: metrics only).
    ``after_rollout(sim)`` is called with the system after its last step, before the metrics
    (the fuzz benchmark checks the final state there).
    """
    from tqdm import tqdm

    from cosim.kernel_cache import compile_seconds
    from cosim.scene.build import build_system

    t_build = time.perf_counter()
    sim = build_system(scene, requires_grad=False, steps=steps)
    build_s = time.perf_counter() - t_build
    recorder = Recorder(sim)
    substeps = []
    bar = tqdm(total=sim.steps, desc=scene.name, unit="step", disable=not progress, leave=False)

    first_step: list[float] = []  # [s] to the end of step 1, whose launches pay each kernel's first one

    def on_step(n: int) -> None:
        if n == 1:
            first_step.append(time.perf_counter() - t0)
        if n:
            substeps.append(sim.last.substeps)
            recorder.step(n)
            bar.update()
        if n == 0 or recorder.wants(n):
            recorder(n)

    t0 = time.perf_counter()
    sim.rollout(on_step=on_step)
    wall = time.perf_counter() - t0
    bar.close()
    if after_rollout is not None:
        after_rollout(sim)
    if out_dir is not None:  # made only now: a scene refused at build or a run stopped writes nothing
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
    if save_target and out_dir is not None:
        final = sim.state()
        targets = {f"x_{name}": final["mpm"]["x"][sl] for name, sl in sim.slices.items()}
        targets.update({f"x_{e.name}": final[e.name]["x"] for e in cloth_engines(sim)})
        np.savez_compressed(out_dir / "target.npz", **targets)

    metrics = {
        "scene": scene.name,
        "dim": scene.dim,
        "precision": scene.precision,
        "arch": scene.arch,
        "hardware": hardware_line(),
        "steps": sim.steps,
        "frame_dt": sim.frame_dt,
        "substeps_total": int(sum(substeps)),
        "substeps_per_step": {"min": int(min(substeps)), "max": int(max(substeps))},
        "exchanges_per_step": sim.exchanges,  # > 1 where a light body's coupling splits the frame
        "particles": int(sim.mpm.n_particles),
        "bodies": {b.name: {"material": b.material, "particles": b.n} for b in sim.mpm.bodies},
        "max_cfl": sim.max_cfl,
        "wall_time_s": wall,
        # the first macro step's share: every kernel's first launch (Taichi's front end, compile or cache load)
        "first_step_s": first_step[0] if first_step else wall,
        "build_time_s": build_s,
        "kernel_compile_s": compile_seconds(),  # Taichi's compiles and cache loads so far: small when warm
        "particle_substeps_per_s": sim.mpm.n_particles * sum(substeps) / max(wall, 1e-12),
        "energy_initial": recorder.energy[0],
        "energy_final": recorder.energy[-1],
        "energy_budget": {  # cosim.conservation: the runner's check, every macro step
            "work_done_J": sim.conservation.work,
            "max_excess": sim.conservation.excess,
        },
    }
    if sim.conservation.liquids:  # sum V0 det F of the liquids over its start, lowest and highest seen
        low, high = sim.conservation.volume_ratio
        metrics["liquid_volume_ratio"] = {"min": low, "max": high}
    if sim.rigid is not None:
        metrics["contact_model"] = scene.contact.model
        metrics["reactions"] = recorder.reaction_metrics()  # a list in rigid_names order: no names in keys
        x = sim.mpm.state()["x"]
        metrics["particles_inside_rigid"] = sim.rigid.particles_inside(x)
        metrics["particles_passed_through"] = dict(sim.passed_through)  # "body/rigid body": count, whole run
        held = sim.rigid.particles_held(x)
        if held:
            metrics["particles_held"] = held
            metrics["particles_elsewhere"] = (
                len(x) - sum(held.values()) - sum(metrics["particles_inside_rigid"].values())
            )
    cloths = cloth_engines(sim)
    if cloths:
        metrics["contact_model"] = scene.contact.model
        metrics["penetration_tracing"] = scene.contact.tracing
        metrics["cloth"] = {c.name: cloth_metrics(sim, c) for c in cloths}
    if "dart" in sim.engines:
        engine = sim.engines["dart"]
        metrics["joint_positions"] = {
            spec.name: skel.getPositions().tolist() for spec, skel in zip(engine.specs, engine.skeletons)
        }
    if out_dir is None:
        return metrics
    name = recorder.write(out_dir, preview)
    if name:
        metrics["preview"] = name
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def cloth_metrics(sim, cloth) -> dict:
    """Vertices, the last Newton solve, and how many particles sit on the wrong side of the sheet
    (traced ``inside``) at the end."""
    coupler = next(c for c in sim.couplers if c.engine == cloth.name and declares(c, "carried_state"))
    tracking = coupler.state()["tracking"]
    inside = 0 if tracking is None else int(np.count_nonzero(tracking["inside"]))
    return {"vertices": int(cloth.mesh.n_vertices), "last_solve": cloth.last_solve, "particles_inside": inside}
