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
    """Collects saved frames (positions per body, energies, rigid poses and reactions) of one rollout.

    Call ``step(n)`` after every macro step n (it records the rigid bodies' reaction wrenches) and
    the recorder itself, ``recorder(n)``, for each frame to save (n = 0: the start).
    """

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
        self.reaction_steps: list[np.ndarray] = []  # per macro step, (R, 6) ``step_reactions``
        self.reaction_frames: list[np.ndarray] = []  # per frame, the mean over the steps since the last one
        self._stepped = 0  # the last macro step whose reactions are in reaction_steps
        self._frame_start = 0  # index into reaction_steps of the first step after the last saved frame

    def step(self, step_index: int) -> None:
        """After macro step ``step_index`` (1-based): record its reaction wrenches (``step_reactions``)."""
        if self.sim.rigid is not None and step_index > self._stepped:
            self.reaction_steps.append(step_reactions(self.sim))
            self._stepped = step_index

    def __call__(self, step_index: int) -> None:
        from cosim.diagnostics import summed

        state = self.sim.mpm.state()
        self.frames.append([state["x"][sl].copy() for sl in self.sim.slices.values()])
        self.times.append(step_index * self.sim.frame_dt)
        self.energy.append(summed(self.sim.mpm.energies()))  # of the current state, summed on the device
        if self.sim.rigid is not None:
            self.rigid_poses.append(self.sim.rigid.poses())
            if step_index:
                self.step(step_index)  # a caller that only reports saved frames: at least this frame's step
            since = self.reaction_steps[self._frame_start :]
            self._frame_start = len(self.reaction_steps)
            nan = np.full((len(self.sim.rigid.names), 6), np.nan)
            self.reaction_frames.append(np.mean(since, axis=0) if since else nan)
        self.cloth_frames.append([c.state()["x"].copy() for c in self.cloths])
        if self.velocities:
            bodies = [state["v"][sl].copy() for sl in self.sim.slices.values()]
            self.v_frames.append(bodies + [c.state()["v"].copy() for c in self.cloths])

    def wants(self, step_index: int) -> bool:
        """Save after macro step ``step_index`` (1-based)? Every output.every, and the last."""
        return step_index % self.sim.scene.output.every == 0 or step_index == self.sim.steps

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays of ``trajectory.npz`` (docs/outputs.md)."""
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
            skeletons, links = rigid_parts(self.sim)
            arrays.update(rigid_names=np.asarray(rigid.names), rigid_skeletons=skeletons, rigid_links=links)
            arrays["rigid_pos"] = np.asarray([[p for p, _ in poses] for poses in self.rigid_poses])
            arrays["rigid_rot"] = np.asarray([[R for _, R in poses] for poses in self.rigid_poses])
            torque, force = wrench_layout(np.stack(self.reaction_frames), rigid.dim)
            arrays.update(reaction_force=force, reaction_torque=torque)
        if self.cloths:
            arrays["cloth_names"] = np.asarray([c.name for c in self.cloths])
            for i, cloth in enumerate(self.cloths):
                arrays[f"cloth_x_{cloth.name}"] = np.stack([f[i] for f in self.cloth_frames]).astype(np.float32)
                arrays[f"cloth_faces_{cloth.name}"] = np.asarray(cloth.mesh.faces, dtype=np.int32)
        return arrays

    def write(self, out_dir: Path, preview: bool = True) -> str | None:
        """trajectory.npz (docs/outputs.md) and the preview drawn from it; returns the preview's file name."""
        arrays = self.arrays()
        np.savez_compressed(out_dir / "trajectory.npz", **arrays)
        scene = self.sim.scene
        if not preview or scene.output.preview == "none":
            return None
        return write_trajectory_preview(out_dir / f"preview.{scene.output.preview}", arrays, scene, self.sim.rigid).name

    def reaction_metrics(self) -> list[dict]:
        """metrics.json's ``reactions``: per rigid body (``rigid_names`` order) its names and the mean,
        largest magnitude and final value of the reaction force [N] and torque [N m] over every
        recorded step."""
        rigid = self.sim.rigid
        torque, force = wrench_layout(np.stack(self.reaction_steps), rigid.dim)  # (steps, R, ...)
        out = []
        for b, (name, skeleton, link) in enumerate(zip(rigid.names, *rigid_parts(self.sim))):
            entry = {"body": name, "skeleton": str(skeleton) or None, "link": str(link)}
            for key, values in (("force", force[:, b]), ("torque", torque[:, b])):
                entry[f"{key}_mean"] = values.mean(axis=0).tolist()
                entry[f"{key}_max"] = float(np.linalg.norm(values, axis=1).max())
                entry[f"{key}_final"] = values[-1].tolist()
            out.append(entry)
        return out


def step_reactions(sim) -> np.ndarray:
    """(R, 6) [torque; force], world frame: the wrench [N m; N] the material (and any cloth) exerted on
    each rigid body (``sim.rigid.names`` order) over the last macro step, averaged over it, the torque
    about the body origin at the step's start. Kinematic bodies: the MPM reactions on their boundary
    (``cosim.couplers.mpm_rigid.average_wrench``, as for DART); DART links: the wrench that step applied
    to the link (``cosim.couplers.mpm_rigid``'s average, plus a cloth pressing on it)."""
    from cosim.couplers.mpm_rigid import average_wrench, lift_reactions
    from cosim.engines.kinematic import kinematic_states

    rigid, last = sim.rigid, sim.last
    rows = []
    if rigid.kinematic is not None:
        source = next(c.source for c in sim.couplers if c.engine == rigid.kinematic.name)
        reactions = last.outputs["reactions"][source]
        K, dt = last.substeps, last.dt
        pos_d = kinematic_states(rigid.kinematic.motions, last.time, dt, K)["pos"]
        pos_k = np.zeros((*pos_d.shape[:-1], 3))
        pos_k[..., : rigid.dim] = pos_d
        J, L = lift_reactions(reactions["impulse"], reactions["angular_impulse"], rigid.dim)
        rows.append(average_wrench(J, L, pos_k, pos_k[0], K * dt))
    if rigid.coupler is not None:
        rows.append(last.engines[rigid.coupler.engine].wrenches[rigid.coupler.coupled])
    return np.concatenate(rows)


def wrench_layout(wrenches: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(..., 6) [torque; force] 3D wrenches as trajectory.npz stores them: torque (..., 3) in 3D,
    (..., 1) in 2D (its z component); force (..., dim)."""
    torque = wrenches[..., :3] if dim == 3 else wrenches[..., 2:3]
    return torque, wrenches[..., 3 : 3 + dim]


def rigid_parts(sim) -> tuple[np.ndarray, np.ndarray]:
    """Per rigid body (``sim.rigid.names`` order): its DART skeleton's name ("" for a kinematic body)
    and its link's name (a kinematic body: its own name), so no one has to split "skeleton/link"."""
    rigid = sim.rigid
    coupled = rigid.coupler.coupled if rigid.coupler is not None else []
    n_kinematic = len(rigid.names) - len(coupled)
    skeletons, links = [""] * n_kinematic, list(rigid.names[:n_kinematic])
    if coupled:
        engine = sim.engines[rigid.coupler.engine]
        parts = [(s.name, b.getName()) for s, skel in zip(engine.specs, engine.skeletons) for b in skel.getBodyNodes()]
        skeletons += [parts[i][0] for i in coupled]
        links += [parts[i][1] for i in coupled]
    return np.asarray(skeletons), np.asarray(links)


def cloth_engines(sim) -> list:
    """The system's cloth engines (those with a triangle ``mesh``), in stepping order."""
    return [e for e in sim.engines.values() if hasattr(e, "mesh")]


def trajectory_frames(traj, rigid=None) -> list:
    """``render.Frame``s of a trajectory's saved frames (``Recorder.arrays()`` or a loaded
    trajectory.npz): particles per body, the rigid bodies' surfaces at ``rigid_pos`` / ``rigid_rot``
    (``rigid``: the scene's ``RigidBodies``, for their SDF grids; None draws none) and the cloth
    meshes. ``cosim run``'s preview and ``cosim render`` both draw these."""
    from cosim.render import Frame

    times = np.asarray(traj["time"])
    bodies = [traj[f"x_{n}"] for n in traj["body_names"]]  # read each array once (an NpzFile re-reads)
    geometry = [[] for _ in times]
    if rigid is not None:
        from cosim.render.surfaces import rigid_geometry

        pos, rot = traj["rigid_pos"], traj["rigid_rot"]
        geometry = rigid_geometry(rigid.grids, [list(zip(p, R)) for p, R in zip(pos, rot)], rigid.dim)
    names = traj.get("cloth_names", [])
    cloths = [(traj[f"cloth_x_{n}"], traj[f"cloth_faces_{n}"]) for n in names]
    return [
        Frame.from_bodies(
            [x[i] for x in bodies], rigid=geometry[i], cloth=[(x[i], f) for x, f in cloths], label=f"t = {t:.3f} s"
        )
        for i, t in enumerate(times)
    ]


def write_trajectory_preview(path: Path, traj, scene: Scene, rigid=None) -> Path:
    """Draw ``trajectory_frames(traj, rigid)`` into ``path`` (GIF or MP4 by its suffix) with the
    scene's domain, particle spacing, resolution, frame rate and up axis; returns the path."""
    from cosim.render import write_preview

    spacing = min(b.spacing or 0.5 * scene.dx for b in scene.mpm.bodies)
    domain = np.asarray(scene.cells) * scene.dx
    frames = trajectory_frames(traj, rigid)
    return write_preview(
        path, frames, domain, spacing, scene.output.resolution, scene.output.fps, up_axis(scene.gravity)
    )


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

    from cosim.kernel_cache import compile_seconds
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
    coupler = next(c for c in sim.couplers if getattr(c, "engine", None) == cloth.name and hasattr(c, "state"))
    tracking = coupler.state()
    inside = 0 if tracking is None else int(np.count_nonzero(tracking["inside"]))
    return {"vertices": int(cloth.mesh.n_vertices), "last_solve": cloth.last_solve, "particles_inside": inside}
