"""Cloth against rigid bodies: the scene's rigid shapes as python-fcl collision objects.

Once per cloth step (``cosim.couplers.cloth_rigid_coupler``), every cloth contact point (vertices and face centroids) near a rigid
body asks fcl for its distance to the body's surface and the nearest surface point. A point
within ``radius`` (the cloth's contact thickness [m]) of a surface gets a contact plane
through the nearest point p with normal n towards the point: the cloth solve keeps
n . (x - p) >= radius for that step (``cosim.engines.cloth`` adds it as a stiff penalty
inside its implicit step, so the contact is as stable as the cloth itself).

Shapes: box, sphere, cylinder and capsule are fcl primitives (signed distances, so a point
that ends inside is pushed out through the nearest face); glass and mesh shapes are fcl
triangle meshes (unsigned distance: the surface is a two-sided sheet of thickness
``radius``, which is what a thin glass wall is). Cylinders, capsules and glasses stand
along +y in our scenes and along z in fcl. Rigid bodies without a scene shape (URDF links
with their own meshes) are not cloth obstacles.

Gradients: each plane comes with how its point and normal move with the queried point (in the
body frame, ``feature_jacobians``): exact for boxes (a face, edge or corner), spheres and capsules;
zero, i.e. the plane held fixed in the body's frame, on cylinders, glasses and meshes (exact on their
flat faces; on their curved or edge features first order in the cloth's motion over one step).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cosim.engines.cloth_contact import ContactPlanes
from cosim.engines.meshes import load_mesh
from cosim.errors import SceneError

Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # fcl's z axis onto our y axis


def fcl_geometry(shape, source_dir: Path, key: str):
    """(fcl geometry, rotation of it in the body frame, bounding radius [m]) of a scene RigidShape."""
    import fcl

    kind = shape.type
    if kind == "box":
        size = np.asarray(shape.size, dtype=np.float64)
        return fcl.Box(*size), np.eye(3), 0.5 * float(np.linalg.norm(size))
    if kind == "sphere":
        return fcl.Sphere(shape.radius), np.eye(3), shape.radius
    if kind == "cylinder":
        return fcl.Cylinder(shape.radius, shape.height), Z_TO_Y, float(np.hypot(shape.radius, 0.5 * shape.height))
    if kind == "capsule":
        return fcl.Capsule(shape.radius, shape.height), Z_TO_Y, 0.5 * shape.height + shape.radius
    if kind == "glass":
        mesh = glass_mesh(shape.radius, shape.height, shape.thickness)
    elif kind == "mesh":
        mesh = load_mesh(Path(source_dir) / shape.file, shape.scale, f"{key}.file", SceneError)
    else:
        raise SceneError(f"{key}: a {kind} cannot touch cloth (3D shapes only)")
    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.vertices), len(mesh.faces))
    bvh.addSubModel(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int32))
    bvh.endModel()
    return bvh, np.eye(3), float(np.linalg.norm(mesh.vertices, axis=1).max())


def glass_mesh(radius: float, height: float, thickness: float):
    """A glass (open cup along +y, centred at the origin, wall and bottom ``thickness`` thick) as triangles."""
    import trimesh

    r, h, t = radius, height, thickness
    profile = [
        [0.0, -0.5 * h],
        [r, -0.5 * h],
        [r, 0.5 * h],
        [r - t, 0.5 * h],
        [r - t, -0.5 * h + t],
        [0.0, -0.5 * h + t],
    ]
    mesh = trimesh.creation.revolve(profile, sections=64)  # about z, the cup's axis
    mesh.apply_transform(np.block([[Z_TO_Y, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    return mesh


class RigidObstacles:
    """Rigid shapes as fcl objects; ``planes(points, poses, radius)`` gives the contact planes."""

    def __init__(self, shapes: list, source_dir: Path, keys: list[str]):
        import fcl

        self._fcl = fcl
        self.geometries = [fcl_geometry(s, source_dir, k) for s, k in zip(shapes, keys)]
        self.objects = [fcl.CollisionObject(g, fcl.Transform(R, np.zeros(3))) for g, R, _ in self.geometries]
        self.signed = [not isinstance(g, fcl.BVHModel) for g, _, _ in self.geometries]
        self.shapes = list(shapes)
        self._probe = fcl.CollisionObject(fcl.Sphere(0.0), fcl.Transform())
        self._request = fcl.DistanceRequest(enable_nearest_points=True, enable_signed_distance=True)

    def planes(self, points: np.ndarray, poses: list[tuple[np.ndarray, np.ndarray]], radius: float) -> ContactPlanes:
        """Contact planes of ``points`` (n, 3) [m] within ``radius`` of a body placed at ``poses``
        [(position (3,), rotation (3, 3) body to world)], one per (point, body) pair."""
        fcl = self._fcl
        index, body, point, normal, jp, jn = [], [], [], [], [], []
        for b, ((_geom, local_R, bound), obj, signed) in enumerate(zip(self.geometries, self.objects, self.signed)):
            pos, R = (np.asarray(a, dtype=np.float64) for a in poses[b])
            near = np.flatnonzero(np.linalg.norm(points - pos, axis=1) < bound + radius)
            local = (points[near] - pos) @ R  # queried in the body frame: fcl meshes answer in their own frame
            for i, q in zip(near, local):
                self._probe.setTranslation(q)
                result = fcl.DistanceResult()
                d = fcl.distance(obj, self._probe, self._request, result)
                if d >= radius:
                    continue
                p = np.asarray(result.nearest_points[0], dtype=np.float64)
                offset = q - p
                length = np.linalg.norm(offset)
                if length < 1e-12:  # on the surface: no direction; the next step will have one
                    continue
                n = offset / length if (d >= 0 or not signed) else -offset / length
                index.append(i)
                body.append(b)
                point.append(R @ p + pos)
                normal.append(R @ n)
                J_p, J_n = feature_jacobians(self.shapes[b], q, p, n, d < 0)
                jp.append(R @ J_p @ R.T)
                jn.append(R @ J_n @ R.T)
        if not index:
            return ContactPlanes.empty()
        arrays = (np.array(a) for a in (index, body, point, normal, jp, jn))
        return ContactPlanes(*arrays)


def feature_jacobians(
    shape, q: np.ndarray, p: np.ndarray, n: np.ndarray, inside: bool
) -> tuple[np.ndarray, np.ndarray]:
    """(dp/dq, dn/dq) (3, 3) in the body frame: how the nearest surface point p and the normal n of a
    query point q move with q. Box: p = clamp(q) outside (a face, edge or corner), q moved onto the
    nearest face inside; sphere and capsule: p on the ray from the nearest axis point. Other shapes:
    zeros (the plane held fixed in the body frame)."""
    eye = np.eye(3)
    tangent = eye - np.outer(n, n)
    if shape.type == "box":
        if inside:
            return tangent, np.zeros((3, 3))
        free = (np.abs(q) < 0.5 * np.asarray(shape.size)).astype(np.float64)  # coordinates p follows
        return np.diag(free), tangent @ np.diag(1.0 - free) / np.linalg.norm(q - p)
    if shape.type in ("sphere", "capsule"):
        half = 0.0 if shape.type == "sphere" else 0.5 * shape.height
        along = np.zeros((3, 3))
        if abs(q[1]) < half:
            along[1, 1] = 1.0  # the nearest axis point (0, y, 0) follows q's y
        axis_point = np.array([0.0, np.clip(q[1], -half, half), 0.0])
        J_n = tangent @ (eye - along) / np.linalg.norm(q - axis_point)
        return along + shape.radius * J_n, J_n
    return np.zeros((3, 3)), np.zeros((3, 3))
