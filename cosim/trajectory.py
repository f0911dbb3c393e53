"""A rollout's saved frames: the recorder that collects them, trajectory.npz's arrays, the rigid bodies'
reactions per step, and the preview drawn from a trajectory (``cosim run``, ``cosim optimize``,
``cosim render``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.scene import Scene


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

    rigid, last = sim.rigid, sim.last.exchanges[-1]  # the last exchange of the macro step
    rows = []
    if rigid.kinematic is not None:
        source = next(c.source for c in sim.couplers if c.engine == rigid.kinematic.name)
        reactions = last.outputs["reactions"][source]
        K, dt = last.substeps, last.dt
        pos_d = last.mpm.boundaries[source]["pos"][:K]  # the poses the step's substeps used
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
    from cosim.engines.contract import declares

    return [e for e in sim.engines.values() if declares(e, "mesh")]


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
