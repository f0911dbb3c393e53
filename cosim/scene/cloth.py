"""The ``cloth:`` section made runnable: a cloth engine per entry, its action plan, and its vertex sets.

Meshes come from ``cosim.engines.cloth_mesh`` (rectangle, disc or a file, scaled and moved
to ``mesh.center``); pinned and controlled vertices are picked by rest position (the vertex
nearest to each point, every vertex in a box). A selection that picks nothing, or the same
vertex twice, is a ``SceneError`` naming the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cosim.errors import SceneError
from cosim.scene.actions import ReachProjection, action_plan


def build_mesh(spec, source_dir, key: str):
    """The ``ClothMesh`` of a validated ``cloth[i].mesh`` section."""
    from cosim.engines import cloth_mesh

    try:
        if spec.type == "rectangle":
            return cloth_mesh.rectangle(spec.size, spec.resolution, spec.center, spec.normal)
        if spec.type == "disc":
            return cloth_mesh.disc(spec.radius, spec.rings, spec.center, spec.normal)
        loaded = cloth_mesh.from_file((source_dir / spec.file).resolve())
        vertices = loaded.vertices * spec.scale + np.asarray(spec.center, dtype=np.float64)
        return cloth_mesh.build(vertices, loaded.faces, loaded.source)
    except ValueError as exc:
        raise SceneError(f"{key}: {exc}") from exc


def select_vertices(spec, rest: np.ndarray, key: str) -> np.ndarray:
    """Indices of the vertices ``spec`` (points, region) picks from the rest positions (V, 3) [m]."""
    picked = [int(np.argmin(np.linalg.norm(rest - np.asarray(p, dtype=np.float64), axis=1))) for p in spec.points]
    if spec.region is not None:
        inside = np.all((rest >= spec.region.min) & (rest <= spec.region.max), axis=1)
        if not inside.any():
            raise SceneError(f"{key}.region: selects no vertex; the cloth spans {rest.min(0)} to {rest.max(0)} m")
        picked += np.flatnonzero(inside).tolist()
    return np.unique(np.asarray(picked, dtype=np.int64))


def cloth_selection(scene, index: int) -> tuple:
    """(mesh, pinned vertex indices, each control's vertex indices) of ``scene.cloth[index]``, in NumPy
    (the mesh's faces and the selections, checked before anything is built)."""
    spec = scene.cloth[index]
    key = f"cloth[{index}]"
    mesh = build_mesh(spec.mesh, scene.source_dir, f"{key}.mesh")
    fixed = select_vertices(spec.fixed, mesh.vertices, f"{key}.fixed") if spec.fixed is not None else []
    controls = [
        select_vertices(c.vertices, mesh.vertices, f"{key}.controls[{j}].vertices") for j, c in enumerate(spec.controls)
    ]
    chosen = np.concatenate([np.asarray(fixed, dtype=np.int64), *controls]) if controls else np.asarray(fixed)
    if len(np.unique(chosen)) != len(chosen):
        raise SceneError(
            f"{key}: a vertex is both pinned and controlled, or in two controls; make the selections disjoint"
        )
    return mesh, fixed, controls


@dataclass
class ClothStart:
    """What a cloth is built from, checked in NumPy (``cloth_start``): its mesh, pinned and controlled
    vertex indices, and the action plan of its controls (None without controls)."""

    mesh: object  # ClothMesh
    fixed: np.ndarray | list
    controls: list[np.ndarray]
    plan: object | None  # ActionPlan


def cloth_start(scene, index: int) -> ClothStart:
    """``scene.cloth[index]``'s mesh and selections (``cloth_selection``) and its action plan (``action_plan``,
    with the ``reach`` projection), each refused with a ``SceneError`` naming its key; no cloth engine yet
    (``cosim.scene.start`` runs it before anything is built)."""
    spec = scene.cloth[index]
    key = f"cloth[{index}]"
    mesh, fixed, controls = cloth_selection(scene, index)
    plan = None
    if controls:
        hold = spec.actions.hold
        plan = action_plan(spec.actions, 3 * len(controls), math.ceil(scene.steps / hold), f"{key}.actions")
        if spec.actions.reach is not None:
            duration = hold * scene.time.frame_dt
            plan.project = _reach(spec.actions.reach, mesh, controls, duration, plan.sequence, f"{key}.actions")
    return ClothStart(mesh, fixed, controls, plan)


def build_cloth(scene, index: int, start: ClothStart | None = None, step_length: float | None = None):
    """(ClothEngine, ActionPlan or None) of ``scene.cloth[index]``, from its ``cloth_start`` (made here if not given),
    stepping ``step_length`` [s] (default ``time.frame_dt``; less with several exchanges per frame)."""
    from cosim.engines.cloth import ClothEngine, ClothMaterial

    spec = scene.cloth[index]
    start = start or cloth_start(scene, index)
    m = spec.material
    material = ClothMaterial(k_stretch=m.stretch, k_bend=m.bend, c_mass=m.damping, density=m.density)
    engine = ClothEngine(
        start.mesh,
        material,
        fixed=start.fixed,
        controls=start.controls,
        gravity=scene.gravity,
        frame_dt=step_length or scene.time.frame_dt,
        name=spec.name,
        rtol=spec.tolerance,
        max_iterations=spec.max_iterations,
    )
    return engine, start.plan


def _reach(spec, mesh, controls, duration: float, sequence: np.ndarray, key: str) -> ReachProjection:
    """The projection keeping each control's centroid within ``reach``, checked against the initial actions."""
    if np.linalg.norm(spec.axis) == 0:
        raise SceneError(f"{key}.reach.axis: a direction, not zero")
    start = np.stack([mesh.vertices[group].mean(axis=0) for group in controls])
    project = ReachProjection(start, duration, spec.center, spec.axis, spec.radius)
    beyond = np.linalg.norm(project.radial(start), axis=1) > spec.radius * (1 + 1e-9)
    if beyond.any():
        raise SceneError(f"{key}.reach: control {int(np.argmax(beyond))} starts beyond reach.radius of the line")
    if not np.allclose(project(sequence), sequence, rtol=1e-9, atol=1e-12):
        raise SceneError(f"{key}: the initial actions move a control beyond reach.radius; start within reach")
    return project
