"""The shape vocabulary: which shape kinds exist, and which size keys each one needs.

One table, read by the DART shape specs (``rigid_build.ShapeSpec``), the rigid-body SDFs
(``cosim.couplers.sdf``) and the scene schema, so a new kind or key is added in one place. Sizes are
in metres: ``size`` = full extents of a box (one per axis), ``radius``, ``height`` = length along the
shape's axis (for a capsule the straight part only), ``thickness`` = wall thickness of a container.
A mesh has no size keys; it names its file (``file`` in scenes, ``mesh`` in ``ShapeSpec``).

Axes differ by user, not by table: our SDFs and scenes stand cylinders, capsules and glasses along
+y; DART's shapes stand along z.
"""

from __future__ import annotations

PRIMITIVE_SIZES: dict[str, tuple[str, ...]] = {
    "box": ("size",),
    "sphere": ("radius",),  # a ball in 3D, a disc in 2D
    "cylinder": ("radius", "height"),
    "capsule": ("radius", "height"),
    "glass": ("radius", "height", "thickness"),  # an open-topped cup, opening towards +y
    "ring": ("radius", "thickness"),  # 2D only; radius of the wall's middle
}
MESH = "mesh"

RIGID_SHAPE_KINDS: tuple[str, ...] = (*PRIMITIVE_SIZES, MESH)  # a rigid body's contact shape (scene, SDF)
DART_SHAPE_KINDS: tuple[str, ...] = ("box", "sphere", "cylinder", "capsule", MESH)  # shapes DART collides
PARTICLE_SHAPE_KINDS: tuple[str, ...] = ("box", "sphere", "cylinder", MESH)  # MPM bodies filled with particles
CONTAINER_KINDS: tuple[str, ...] = ("glass", "ring")  # shapes with a cavity that holds material


def required_keys(kind: str, mesh_key: str = "file") -> tuple[str, ...]:
    """The keys a shape of ``kind`` must set: its size keys, or ``mesh_key`` (the file) for a mesh.

    KeyError for an unknown kind: callers check the kind first and name the allowed ones.
    """
    return (mesh_key,) if kind == MESH else PRIMITIVE_SIZES[kind]
