"""Checks of a scene's ``articulated:`` section that span several keys (messages name key paths)."""

from __future__ import annotations

from cosim.errors import SceneError
from cosim.scene.schema import Scene
from cosim.scene.checks import rigid_shape_problems, rotation_problems

# joint type -> (q0 entries in 2D, in 3D); 2D free is DART's planar joint (x, y, angle)
_JOINT_DOFS = {"free": (3, 6), "revolute": (1, 1), "prismatic": (1, 1), "ball": (None, 3), "weld": (0, 0)}


def articulated_problems(scene: Scene) -> list[str]:
    d = scene.dim
    problems: list[str] = []
    skeletons = scene.articulated.skeletons
    names = [s.name for s in skeletons]
    taken = {b.name for b in scene.mpm.bodies} | {b.name for b in (scene.rigid.bodies if scene.rigid else [])}
    for i, skel in enumerate(skeletons):
        key = f"articulated.skeletons[{i}]"
        if names.count(skel.name) > 1 or skel.name in taken:
            problems.append(f"{key}.name: '{skel.name}' is used twice; names must be unique")
        if (skel.urdf is None) == (not skel.links):
            problems.append(f"{key}: give either links (primitives) or urdf (a file), not both or neither")
        if skel.collide and d == 2:
            problems.append(f"{key}.collide: DART rigid-rigid collision is 3D only; set it false in 2D")
        if skel.urdf is not None:
            problems += _urdf_problems(key, skel, scene)
            continue
        problems += _links_problems(key, skel, scene)
    return problems


def _urdf_problems(key: str, skel, scene: Scene) -> list[str]:
    problems = []
    if scene.dim != 3:
        problems.append(f"{key}.urdf: URDF skeletons are 3D; in 2D build the skeleton from links")
    from cosim.articulated import resolve_asset  # imports the SDF code (Taichi): only for URDF scenes

    try:
        path = resolve_asset(skel.urdf, scene.source_dir, f"{key}.urdf")
        if not path.is_file():
            problems.append(f"{key}.urdf: file not found: {path}")
        for name, folder in skel.package_dirs.items():
            found = resolve_asset(folder, scene.source_dir, f"{key}.package_dirs.{name}")
            if not found.is_dir():
                problems.append(f"{key}.package_dirs.{name}: folder not found: {found}")
    except SceneError as exc:
        problems.append(str(exc))
    if skel.position is not None and len(skel.position) != 3:
        problems.append(f"{key}.position: must have 3 entries, got {len(skel.position)}")
    problems += rotation_problems(f"{key}.rotation", skel.rotation, 3)
    for link, placed in skel.contact_shapes.items():
        problems += rigid_shape_problems(f"{key}.contact_shapes.{link}.shape", placed.shape, scene)
        if placed.shape.type in ("mesh", "ring"):
            problems.append(f"{key}.contact_shapes.{link}.shape.type: use a primitive (box, sphere, cylinder, capsule, glass)")
    return problems


def _links_problems(key: str, skel, scene: Scene) -> list[str]:
    d = scene.dim
    problems = []
    links = [lk.name for lk in skel.links]
    for j, link in enumerate(skel.links):
        base = f"{key}.links[{j}]"
        if links.count(link.name) > 1:
            problems.append(f"{base}.name: '{link.name}' is used twice in skeleton '{skel.name}'")
        problems += rigid_shape_problems(f"{base}.shape", link.shape, scene)
        if (link.density is None) == (link.mass is None):
            problems.append(f"{base}: give density [kg/m^3] or mass [kg] (one of them)")
        joint = link.joint
        if joint.parent is not None and joint.parent not in links[:j]:
            problems.append(
                f"{base}.joint.parent: '{joint.parent}' is not a link listed before '{link.name}' "
                f"(parents come first; links: {links})"
            )
        if joint.type == "ball" and d == 2:
            problems.append(f"{base}.joint.type: a ball joint is 3D; in 2D use revolute")
        if link.offset is not None and len(link.offset) != d:
            problems.append(f"{base}.offset: must have {d} entries (dim is {d}), got {len(link.offset)}")
        if joint.position is not None and len(joint.position) != d:
            problems.append(f"{base}.joint.position: must have {d} entries (dim is {d}), got {len(joint.position)}")
        problems += rotation_problems(f"{base}.joint.rotation", joint.rotation, d)
        if joint.type in ("revolute", "prismatic") and d == 3 and joint.axis is None:
            problems.append(f"{base}.joint.axis: a {joint.type} joint needs its axis in 3D")
        if joint.axis is not None and len(joint.axis) != d:
            problems.append(f"{base}.joint.axis: must have {d} entries (dim is {d}), got {len(joint.axis)}")
        dofs = _JOINT_DOFS[joint.type][0 if d == 2 else 1]
        for name in ("q0", "qd0"):
            value = getattr(joint, name)
            n = 1 if isinstance(value, (int, float)) else len(value or [])
            if value is not None and n != dofs:
                problems.append(f"{base}.joint.{name}: a {joint.type} joint in {d}D has {dofs} coordinates, got {n}")
    for joint, mode in skel.controls.items():
        if joint not in links:
            problems.append(f"{key}.controls.{joint}: no such joint (joints are named after their links: {links})")
            continue
        link = skel.links[links.index(joint)]
        if mode in ("wrench", "twist") and (link.joint.type != "free" or link.joint.parent or d == 2):
            problems.append(
                f"{key}.controls.{joint}: '{mode}' needs a 3D free joint on the world; use torque or velocity"
            )
    return problems
