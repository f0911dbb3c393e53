"""Mesh files: the one place they are read (trimesh), scaled and checked.

Rigid-body inertia, DART collision shapes, the MPM's rigid SDFs and particle sampling all read mesh
files; they do it here so a missing, unreadable, empty or open mesh gets the same clear error naming
the file, the scene key when there is one, and the fix. Lengths are in the file's units times
``scale`` (the scenes are in metres).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.errors import CosimError, InputError


def load_mesh(
    path: str | Path,
    scale: float | tuple[float, float, float] | list[float] = 1.0,
    key: str | None = None,
    error: type[CosimError] = InputError,
):
    """The mesh file at ``path`` as one trimesh, scaled per axis (a scalar scales uniformly).

    ``key`` (the scene key, e.g. ``rigid.bodies[0].shape.file``) prefixes the error messages, and
    ``error`` is the error raised: ``SceneError`` for scene input, ``InputError`` for specs built in
    code. Any format trimesh reads is accepted; several objects in a file are merged into one mesh.
    """
    import trimesh

    where = f"{key}: " if key else ""
    if not Path(path).is_file():
        raise error(f"{where}mesh file not found: {path}; fix the path")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many kinds for unreadable files
        raise error(f"{where}cannot read mesh {path}: {exc}; export it as OBJ/STL") from exc
    if len(mesh.faces) == 0:
        raise error(f"{where}mesh {path} has no triangles (empty, or not a mesh file); export it as OBJ/STL with faces")
    mesh.apply_transform(np.diag([*np.broadcast_to(np.asarray(scale, dtype=np.float64), 3), 1.0]))
    return mesh


def require_watertight(mesh, name: str, why: str, fix: str, error: type[CosimError] = InputError) -> None:
    """Raise ``error`` "<name> is not watertight, so <why>; <fix>" unless the mesh is closed.

    A closed (watertight) mesh has an inside: what a volume, an inertia, a signed distance or a
    particle filling needs. ``why`` says which of these the caller needs, ``fix`` what to do.
    """
    if not mesh.is_watertight:
        raise error(f"{name} is not watertight, so {why}; {fix}")
