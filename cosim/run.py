"""`cosim run`: step a scene, save its trajectory, metrics and a preview."""

from __future__ import annotations

import json
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from cosim.scene import Scene

if TYPE_CHECKING:
    from cosim.system import CoupledSystem


def hardware_line() -> str:
    """CPU model, core count and memory of this machine, for reports."""
    import os

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        import psutil

        mem = f", {psutil.virtual_memory().total / 2**30:.0f} GiB"
    except ImportError:
        pass
    return f"{cpu}, {os.cpu_count()} cores{mem}, Python {platform.python_version()}"


class Recorder:
    """Collects saved frames (positions per body, energies) of one rollout."""

    def __init__(self, sim):
        self.sim = sim
        self.frames: list[list[np.ndarray]] = []
        self.times: list[float] = []
        self.energy: list[dict] = []
        self.rigid_poses: list[list[tuple[np.ndarray, np.ndarray]]] = []
        self.cloths = cloth_engines(sim)
        self.cloth_frames: list[list[np.ndarray]] = []  # per frame, each cloth's vertex positions
        self.velocities = sim.scene.output.velocities
        self.v_frames: list[list[np.ndarray]] = []  # per frame, each body's then each cloth's velocities

    def __call__(self, step_index: int) -> None:
        from cosim.diagnostics import energies

        state = self.sim.mpm.state()
        self.frames.append([state["x"][sl].copy() for sl in self.sim.slices.values()])
        self.times.append(step_index * self.sim.frame_dt)
        self.energy.append(energies(self.sim.mpm, state, self.sim.scene.gravity))
        if self.sim.rigid is not None:
            self.rigid_poses.append(self.sim.rigid.poses())
        self.cloth_frames.append([c.state()["x"].copy() for c in self.cloths])
        if self.velocities:
            bodies = [state["v"][sl].copy() for sl in self.sim.slices.values()]
            self.v_frames.append(bodies + [c.state()["v"].copy() for c in self.cloths])

    def wants(self, step_index: int) -> bool:
        """Save after macro step ``step_index`` (1-based)? Every output.every, and the last."""
        return step_index % self.sim.scene.output.every == 0 or step_index == self.sim.steps

    def write(self, out_dir: Path, preview: bool = True) -> str | None:
        """trajectory.npz (docs/outputs.md) and the preview; returns the preview's file name."""
        scene = self.sim.scene
        names = list(self.sim.slices)
        arrays = {"time": np.asarray(self.times), "body_names": np.asarray(names)}
        for i, name in enumerate(names):
            arrays[f"x_{name}"] = np.stack([f[i] for f in self.frames]).astype(np.float32)
        if self.velocities:
            keys = [f"v_{name}" for name in names] + [f"cloth_v_{c.name}" for c in self.cloths]
            for i, key in enumerate(keys):
                arrays[key] = np.stack([f[i] for f in self.v_frames]).astype(np.float32)
        for key in ("kinetic", "gravity", "strain", "total"):
            arrays[f"energy_{key}"] = np.asarray([e[key] for e in self.energy])
        rigid = self.sim.rigid
        if rigid is not None:
            arrays["rigid_names"] = np.asarray(rigid.names)
            for b, name in enumerate(rigid.names):
                arrays[f"rigid_pos_{name}"] = np.stack([poses[b][0] for poses in self.rigid_poses])
                arrays[f"rigid_rot_{name}"] = np.stack([poses[b][1] for poses in self.rigid_poses])
        if self.cloths:
            arrays["cloth_names"] = np.asarray([c.name for c in self.cloths])
            for i, cloth in enumerate(self.cloths):
                arrays[f"cloth_x_{cloth.name}"] = np.stack([f[i] for f in self.cloth_frames]).astype(np.float32)
                arrays[f"cloth_faces_{cloth.name}"] = np.asarray(cloth.mesh.faces, dtype=np.int32)
        np.savez_compressed(out_dir / "trajectory.npz", **arrays)
        if not preview or scene.output.preview == "none":
            return None
        from cosim.render import write_preview

        spacing = min(b.spacing or 0.5 * scene.dx for b in scene.mpm.bodies)
        path = write_preview(
            out_dir / f"preview.{scene.output.preview}",
            preview_frames(
                self.frames,
                self.times,
                self.sim.rigid,
                self.rigid_poses,
                [[(x, c.mesh.faces) for x, c in zip(xs, self.cloths)] for xs in self.cloth_frames],
            ),
            np.asarray(scene.cells) * scene.dx,
            spacing,
            scene.output.resolution,
            scene.output.fps,
            up_axis(scene.gravity),
        )
        return path.name


def cloth_engines(sim) -> list:
    """The system's cloth engines (those with a triangle ``mesh``), in stepping order."""
    return [e for e in sim.engines.values() if hasattr(e, "mesh")]


def preview_frames(frames: list[list[np.ndarray]], times, rigid=None, rigid_poses=None, cloths=None) -> list:
    """``render.Frame``s of saved frames: particle positions per body, and the rigid bodies'
    surfaces (``rigid``: a ``RigidBodies`` with its SDF grids; ``rigid_poses``: per frame, their poses)
    and cloth meshes (``cloths``: per frame, a list of (vertices, faces))."""
    from cosim.render import Frame

    geometry = [[] for _ in frames]
    if rigid is not None and rigid_poses:
        from cosim.render.surfaces import rigid_geometry

        geometry = rigid_geometry(rigid.grids, rigid_poses, rigid.dim)
    cloths = cloths or [[] for _ in frames]
    return [
        Frame.from_bodies(f, rigid=g, cloth=c, label=f"t = {t:.3f} s")
        for f, t, g, c in zip(frames, times, geometry, cloths)
    ]


def up_axis(gravity) -> np.ndarray:
    """The picture's up: against gravity, +y without it."""
    g = np.asarray(gravity, dtype=np.float64)
    n = np.linalg.norm(g)
    up = -g / n if n > 0 else np.eye(len(g))[1]
    return up if len(up) == 3 else np.append(up, 0.0)


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

    from cosim.scene.build import build_system

    t_build = time.perf_counter()
    sim = build_system(scene, requires_grad=False, steps=steps)
    build_s = time.perf_counter() - t_build
    recorder = Recorder(sim)
    substeps = []
    bar = tqdm(total=sim.steps, desc=scene.name, unit="step", disable=not progress, leave=False)

    def on_step(n: int) -> None:
        if n:
            substeps.append(sim.last.substeps)
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
        targets.update({f"x_{name}": final[name]["x"] for name, e in sim.engines.items() if hasattr(e, "mesh")})
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
        "particles": int(sim.mpm.n_particles),
        "bodies": {b.name: {"material": b.material, "particles": b.n} for b in sim.mpm.bodies},
        "max_cfl": sim.max_cfl,
        "wall_time_s": wall,
        "build_time_s": build_s,
        "particle_substeps_per_s": sim.mpm.n_particles * sum(substeps) / max(wall, 1e-12),
        "energy_initial": recorder.energy[0],
        "energy_final": recorder.energy[-1],
        "energy_budget": {  # cosim.conservation: the runner's check, every 10 steps
            "work_done_J": sim.conservation.work,
            "max_excess": sim.conservation.excess,
        },
    }
    if sim.conservation.liquids:  # sum V0 det F of the liquids over its start, lowest and highest seen
        low, high = sim.conservation.volume_ratio
        metrics["liquid_volume_ratio"] = {"min": low, "max": high}
    if sim.rigid is not None:
        metrics["contact_model"] = scene.contact.model
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
    coupler = next(c for c in sim.couplers if getattr(c, "engine", None) == cloth.name and hasattr(c, "state"))
    tracking = coupler.state()
    inside = 0 if tracking is None else int(np.count_nonzero(tracking["inside"]))
    return {"vertices": int(cloth.mesh.n_vertices), "last_solve": cloth.last_solve, "particles_inside": inside}
