"""Scene checks that span several keys, each problem a line naming its key path.

``semantic_problems`` checks vector lengths against ``dim``, body names, files,
3D-only shapes, the rigid bodies' motions, the ``articulated:`` section
(skeletons, links, joints, controls), the cloths, the loss terms and the parameter
names of ``gradient`` and ``optimize`` (``cosim.scene.params``); ``cosim.scene.loader``
calls it after the schema has validated every single key.
"""

from __future__ import annotations

import math

from cosim.engines.shapes import RIGID_SHAPE_KINDS, required_keys
from cosim.engines.urdf_tree import UrdfTree, read_urdf_tree
from cosim.errors import SceneError
from cosim.scene.params import params_problems
from cosim.scene.schema import BoxShape, CylinderShape, MeshShape, Scene, VelocityFile
from cosim.scene.shipped import resolve_asset
from cosim.scene.velocity_field import expression_problem
from cosim.scene.velocity_file import file_problems


def semantic_problems(scene: Scene) -> list[str]:
    """Checks that need more than one key: vector lengths, names, files, fit in the grid."""
    d = scene.dim
    problems: list[str] = []

    def vec(path: str, value: list | None, n: int = d) -> None:
        problems.extend(length_problems(path, value, n, d))

    cells = scene.mpm.grid.cells
    if len(cells) not in (1, d):
        problems.append(f"mpm.grid.cells: give one number or {d} (dim is {d}), got {len(cells)}")
    vec("mpm.gravity", scene.mpm.gravity)
    names = [b.name for b in scene.mpm.bodies]
    for i, body in enumerate(scene.mpm.bodies):
        base = f"mpm.bodies[{i}]"
        if names.count(body.name) > 1:
            problems.append(f"{base}.name: '{body.name}' is used by more than one body; names must be unique")
        shape = body.shape
        vec(f"{base}.shape.center", shape.center)
        if isinstance(shape, BoxShape):
            vec(f"{base}.shape.size", shape.size)
        if isinstance(shape, (CylinderShape, MeshShape)) and d != 3:
            problems.append(f"{base}.shape.type: '{shape.type}' needs dim 3; in 2D use box or sphere")
        if isinstance(shape, MeshShape):
            if isinstance(shape.scale, list):
                vec(f"{base}.shape.scale", shape.scale)
            path = (scene.source_dir / shape.file).resolve()
            if not path.is_file():
                problems.append(f"{base}.shape.file: file not found: {path}")
        if isinstance(body.velocity, VelocityFile):
            problems += file_problems(body.velocity.path(scene.source_dir), f"{base}.velocity.file")
        else:
            vec(f"{base}.velocity", body.velocity)
            for k, component in enumerate(body.velocity or []):
                if isinstance(component, str) and (problem := expression_problem(component, d)):
                    problems.append(f"{base}.velocity[{k}]: {problem}")
        if body.hydrostatic and body.material.type != "liquid":
            problems.append(f"{base}.hydrostatic: only liquids can start hydrostatic; remove the key")
        if body.spacing is not None and body.spacing > scene.dx:
            problems.append(
                f"{base}.spacing: {body.spacing} is coarser than the grid spacing dx = {scene.dx:g}; "
                "use at most dx (dx / 2 is usual)"
            )
    for i, ctl in enumerate(scene.controls):
        base = f"controls[{i}]"
        if ctl.body not in names:
            problems.append(f"{base}.body: no body named '{ctl.body}'; bodies are {names}")
        vec(f"{base}.impulse", ctl.impulse)
        if ctl.region is not None:
            vec(f"{base}.region.min", ctl.region.min)
            vec(f"{base}.region.max", ctl.region.max)
    problems += loss_problems(scene, names + [c.name for c in scene.cloth])
    if scene.rigid is not None:
        problems += rigid_problems(scene)
    if scene.articulated is not None:
        problems += articulated_problems(scene)
    problems += cloth_problems(scene)
    problems += params_problems(scene)
    if scene.steps * scene.time.frame_dt > 1e4 or not math.isfinite(scene.time.frame_dt):
        problems.append("time.frame_dt: steps * frame_dt exceeds 10^4 s; is frame_dt in seconds?")
    return problems


_SHAPE_NEEDS = {kind: required_keys(kind) for kind in RIGID_SHAPE_KINDS}  # sizes, or the mesh file


def rigid_problems(scene: Scene) -> list[str]:
    """Rigid bodies: each shape has its sizes, vectors fit dim, motions are complete."""
    d = scene.dim
    problems: list[str] = []
    names = [b.name for b in scene.rigid.bodies]
    soft = [b.name for b in scene.mpm.bodies]
    for i, body in enumerate(scene.rigid.bodies):
        base = f"rigid.bodies[{i}]"
        if names.count(body.name) > 1 or body.name in soft:
            problems.append(f"{base}.name: '{body.name}' is used twice; body names must be unique")
        problems += rigid_shape_problems(f"{base}.shape", body.shape, scene)
        if len(body.position) != d:
            problems.append(f"{base}.position: must have {d} entries (dim is {d}), got {len(body.position)}")
        problems += rotation_problems(f"{base}.rotation", body.rotation, d)
        problems += _motion_problems(f"{base}.motion", body.motion, d, body.position)
    return problems


def rigid_shape_problems(key: str, shape, scene: Scene) -> list[str]:
    """A rigid shape has its sizes for its type and dimension, and its mesh file exists."""
    d = scene.dim
    problems = [
        f"{key}.{k}: required for a {shape.type}" for k in _SHAPE_NEEDS[shape.type] if getattr(shape, k) is None
    ]
    if shape.type == "box" and shape.size is not None and len(shape.size) != d:
        problems.append(f"{key}.size: must have {d} entries (dim is {d}), got {len(shape.size)}")
    if shape.type == "ring" and d != 2:
        problems.append(f"{key}.type: a ring is 2D; in 3D use a glass or a mesh")
    if shape.type == "mesh":
        if d != 3:
            problems.append(f"{key}.type: meshes are 3D; in 2D use box, sphere, capsule, glass or ring")
        elif shape.file is not None and not (scene.source_dir / shape.file).resolve().is_file():
            problems.append(f"{key}.file: file not found: {(scene.source_dir / shape.file).resolve()}")
    sized = None not in (shape.radius, shape.thickness, shape.height)
    if shape.type == "glass" and sized and shape.thickness >= min(shape.radius, shape.height):
        problems.append(f"{key}.thickness: must be below the radius and the height")
    return problems


def rotation_problems(key: str, value, d: int) -> list[str]:
    if d == 2 and not isinstance(value, (int, float)):
        return [f"{key}: in 2D an angle in radians (a number)"]
    if d == 3 and (isinstance(value, (int, float)) and value != 0 or isinstance(value, list) and len(value) != 3):
        return [f"{key}: in 3D a rotation vector [rx, ry, rz] in radians"]
    return []


def _motion_problems(key: str, m, d: int, position) -> list[str]:
    problems: list[str] = []
    vecs = {"velocity": m.velocity, "amplitude": m.amplitude}
    for name, value in vecs.items():
        if value is not None and len(value) != d:
            problems.append(f"{key}.{name}: must have {d} entries (dim is {d}), got {len(value)}")
    problems += rotation_problems(f"{key}.angular_velocity", m.angular_velocity, d)
    if m.type == "constant" and m.velocity is None:
        problems.append(f"{key}.velocity: required for a constant motion")
    if m.type == "piecewise":
        if not m.segments:
            problems.append(f"{key}.segments: a piecewise motion needs at least one segment")
        for j, seg in enumerate(m.segments):
            if len(seg.velocity) != d:
                problems.append(f"{key}.segments[{j}].velocity: must have {d} entries (dim is {d})")
            problems += rotation_problems(f"{key}.segments[{j}].angular_velocity", seg.angular_velocity, d)
    if m.type == "shake" and (m.amplitude is None or m.frequency is None):
        problems.append(f"{key}: a shake needs amplitude and frequency")
    if m.type == "waypoints":
        if len(m.times) < 2 or len(m.times) != len(m.positions):
            problems.append(f"{key}: waypoints need as many times as positions, at least two")
        elif m.times[0] != 0 or any(b <= a for a, b in zip(m.times, m.times[1:])):
            problems.append(f"{key}.times: must start at 0 and increase")
        elif any(len(p) != d for p in m.positions):
            problems.append(f"{key}.positions: each must have {d} entries (dim is {d})")
        elif max(abs(a - b) for a, b in zip(m.positions[0], position)) > 1e-9:
            problems.append(f"{key}.positions[0]: must equal the body's position {position}")
    return problems


# ---------------------------------------------------------------- articulated:
# joint type -> (q0 entries in 2D, in 3D); 2D free is DART's planar joint (x, y, angle)
_JOINT_DOFS = {"free": (3, 6), "revolute": (1, 1), "prismatic": (1, 1), "ball": (None, 3), "weld": (0, 0)}


def articulated_problems(scene: Scene) -> list[str]:
    """Skeletons: unique names, links or a URDF file (found), joints and controls that fit ``dim``;
    colliding links DART can collide; a ground with something to carry."""
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
        for j, link in enumerate(skel.links if skel.collide else []):
            if link.shape.type == "ring":
                problems.append(
                    f"{key}.links[{j}].shape.type: a ring has no DART collision shape; "
                    f"set {key}.collide: false, or build the link from boxes"
                )
        if skel.urdf is not None:
            problems += _urdf_problems(key, skel, scene)
            continue
        problems += _links_problems(key, skel, scene)
    return problems + _ground_problems(scene.articulated)


def _ground_problems(spec) -> list[str]:
    """A ground acts only through DART collision: it needs ``collision`` and a skeleton that collides."""
    if spec.ground is None:
        return []
    if not spec.collision:
        return ["articulated.ground: the ground acts through DART collision; set articulated.collision: true"]
    if not any(s.collide for s in spec.skeletons):
        return ["articulated.ground: no skeleton collides with it; set collide: true on the skeletons it carries"]
    return []


def _urdf_problems(key: str, skel, scene: Scene) -> list[str]:
    problems = []
    if scene.dim != 3:
        problems.append(f"{key}.urdf: URDF skeletons are 3D; in 2D build the skeleton from links")
    try:
        path = resolve_asset(skel.urdf, scene.source_dir, f"{key}.urdf")
        if not path.is_file():
            problems.append(f"{key}.urdf: file not found: {path}")
        else:
            try:
                problems += _urdf_name_problems(key, skel, read_urdf_tree(path, SceneError))
            except SceneError as exc:
                problems.append(f"{key}.urdf: {exc}")
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
            problems.append(
                f"{key}.contact_shapes.{link}.shape.type: use a primitive (box, sphere, cylinder, capsule, glass)"
            )
    return problems


def _urdf_name_problems(key: str, skel, tree: UrdfTree) -> list[str]:
    """Joints and links the skeleton's keys name exist in its URDF (a typo would silently drop
    a control or a contact)."""
    joints, links = tree.joint_names, list(tree.links)
    named = [("controls", j, joints) for j in skel.controls] + [
        ("initial_positions", j, joints) for j in skel.initial_positions
    ]
    named += [("contact_shapes", lk, links) for lk in skel.contact_shapes]
    named += [("couple", lk, links) for lk in (skel.couple if isinstance(skel.couple, list) else [])]
    return [
        f"{key}.{section}.{name}: the URDF has no {'joint' if known is joints else 'link'} '{name}'; it has {known}"
        for section, name, known in named
        if name not in known
    ]


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


_CLOTH_MESH_NEEDS = {"rectangle": ("size", "resolution"), "disc": ("radius", "rings"), "file": ("file",)}
RESERVED_ENGINE_NAMES = ("mpm", "dart", "kinematic")


def cloth_problems(scene: Scene) -> list[str]:
    """The ``cloth:`` section: 3D only, unique names, each mesh type's keys, vector lengths, actions."""
    problems: list[str] = []
    if scene.cloth and scene.dim != 3:
        return ["cloth: cloth needs dim 3 (a 2D cloth would be a rod); remove the section or use dim: 3"]
    names = [c.name for c in scene.cloth]
    for i, cloth in enumerate(scene.cloth):
        base = f"cloth[{i}]"
        if names.count(cloth.name) > 1 or cloth.name in RESERVED_ENGINE_NAMES:
            problems.append(
                f"{base}.name: '{cloth.name}' is taken (names must be unique and not {list(RESERVED_ENGINE_NAMES)})"
            )
        mesh = cloth.mesh
        for key in _CLOTH_MESH_NEEDS[mesh.type]:
            if getattr(mesh, key) is None:
                problems.append(f"{base}.mesh.{key}: a {mesh.type} cloth needs it")
        for key in ("size", "resolution"):
            value = getattr(mesh, key)
            if mesh.type == "rectangle" and value is not None and len(value) != 2:
                problems.append(f"{base}.mesh.{key}: give two entries (along the two axes across the normal)")
        if len(mesh.center) != 3:
            problems.append(f"{base}.mesh.center: must have 3 entries, got {len(mesh.center)}")
        if mesh.type == "file" and mesh.file is not None:
            path = (scene.source_dir / mesh.file).resolve()
            if not path.is_file():
                problems.append(f"{base}.mesh.file: file not found: {path}")
        selections = [("fixed", cloth.fixed)] + [
            (f"controls[{j}].vertices", c.vertices) for j, c in enumerate(cloth.controls)
        ]
        for key, sel in selections:
            if sel is None:
                continue
            if not sel.points and sel.region is None:
                problems.append(f"{base}.{key}: select vertices with points or region")
            for j, point in enumerate(sel.points):
                if len(point) != 3:
                    problems.append(f"{base}.{key}.points[{j}]: must have 3 entries, got {len(point)}")
        width = 3 * len(cloth.controls)
        acts = cloth.actions
        if acts.reach is not None:
            for key in ("center", "axis"):
                problems += length_problems(f"{base}.actions.reach.{key}", getattr(acts.reach, key), 3, 3)
        for j, action in enumerate(acts.sequence + ([acts.initial] if acts.initial is not None else [])):
            if len(action) != width:
                which = f"sequence[{j}]" if j < len(acts.sequence) else "initial"
                problems.append(
                    f"{base}.actions.{which}: {len(action)} entries, the {len(cloth.controls)} controls take "
                    f"{width} (a velocity [m/s] each)"
                )
    return problems


# what each loss term type reads besides type, weight and running (``LossTermSpec``)
LOSS_KEYS = {
    "weighted_positions": {"body"},
    "com_target": {"body", "target"},
    "pose_target": {"body", "target", "rotation", "pivot"},
    "chamfer": {"body", "points"},
    "joint_target": {"skeleton", "joint", "target", "velocity", "components"},
}


def loss_problems(scene: Scene, loss_bodies: list[str]) -> list[str]:
    """Each loss term's problems (``loss_term_problems``); with ``loss.terms``, the top-level term keys
    are not read, so giving one is a problem too."""
    spec = scene.loss
    if not spec.terms:
        return loss_term_problems(spec, "loss", loss_bodies, scene)
    problems = [
        f"loss.{name}: not read when loss.terms is given; move it into a term"
        for name in sorted(spec.model_fields_set - {"terms"})
    ]
    for i, term in enumerate(spec.terms):
        problems += loss_term_problems(term, f"loss.terms[{i}]", loss_bodies, scene)
    return problems


def loss_term_problems(loss, key: str, loss_bodies: list[str], scene) -> list[str]:
    """What is wrong with one loss term (``LossTermSpec``) at ``key``."""
    problems: list[str] = []
    d = scene.dim

    def vec(path: str, value) -> None:
        problems.extend(length_problems(path, value, d, d))

    uses = LOSS_KEYS[loss.type]
    for name in sorted(loss.model_fields_set - uses - {"type", "weight", "running", "terms"}):
        problems.append(f"{key}.{name}: a {loss.type} term does not use it (it reads {sorted(uses)}); remove it")
    if loss.body is not None and loss.body not in loss_bodies:
        problems.append(f"{key}.body: no body or cloth named '{loss.body}'; there are {loss_bodies}")
    needs_body = {
        "pose_target": "whose pose is steered",
        "com_target": "whose centre of mass is steered",
        "chamfer": "whose points meet the target",
    }
    if loss.type in needs_body and loss.body is None:
        problems.append(f"{key}.body: {loss.type} needs the body or cloth {needs_body[loss.type]}")
    if loss.type == "pose_target":
        if loss.rotation is not None and (d != 3 or len(loss.rotation) != 3):
            problems.append(f"{key}.rotation: a rotation vector of 3 entries (3D scenes)")
        vec(f"{key}.pivot", loss.pivot)
    if loss.type == "com_target" and loss.target is None:
        problems.append(f"{key}.target: com_target needs a target point")
    if loss.type == "chamfer" and loss.points is None:
        problems.append(f"{key}.points: chamfer needs its target point set (file, shape or rollout)")
    elif loss.type == "chamfer":
        points = loss.points
        given = [k for k in ("file", "shape", "rollout") if getattr(points, k) is not None]
        if len(given) != 1:
            problems.append(f"{key}.points: give exactly one of file, shape or rollout (got {given or 'none'})")
        for k in ("file", "rollout"):
            name = getattr(points, k)
            if name is not None and not (scene.source_dir / name).is_file():
                hint = " (`cosim run SCENE --save-target` writes OUT/target.npz)" if k == "rollout" else ""
                problems.append(f"{key}.points.{k}: no such file: {scene.source_dir / name}{hint}")
    if loss.type == "joint_target":
        if None in (loss.skeleton, loss.joint, loss.target):
            problems.append(f"{key}: joint_target needs skeleton, joint and target (the joint's positions)")
        if scene.articulated is None:
            problems.append(f"{key}.type: joint_target needs an articulated: section")
    else:
        vec(f"{key}.target", loss.target)
    return problems


def length_problems(path: str, value: list | None, n: int, d: int) -> list[str]:
    """The problem of a vector ``value`` at ``path`` that should have n entries (none if it has)."""
    if value is not None and len(value) != n:
        return [f"{path}: must have {n} entries (dim is {d}), got {len(value)}"]
    return []
