"""Scene validation beyond single keys, and pydantic errors in the user's words.

``format_errors`` turns pydantic's errors into ``key.path[i]: message`` lines;
``semantic_problems`` checks what spans several keys (vector lengths against
``dim``, body names, files, 3D-only shapes).
"""

from __future__ import annotations

import math
from typing import Any

from pydantic import BaseModel, ValidationError

from cosim.scene.schema import (
    BoxShape,
    CylinderShape,
    ElasticMaterial,
    LiquidMaterial,
    MeshShape,
    PlasticMaterial,
    Scene,
    SphereShape,
)

_TAGS = {"elastic", "plastic", "liquid", "box", "sphere", "cylinder", "mesh"}


def _path(loc: tuple) -> str:
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif part in _TAGS and i > 0 and loc[i - 1] in ("material", "shape"):
            continue  # the discriminator's branch name is noise for the user
        elif isinstance(part, str) and part.startswith("function-"):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _allowed_keys(loc: tuple) -> list[str]:
    """Keys allowed in the mapping that holds ``loc[-1]`` (for unknown-key errors)."""
    model: Any = Scene
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        if part in _TAGS:
            model = next(m for m in _UNION_MEMBERS if m.model_fields["type"].annotation.__args__[0] == part)
            continue
        if not (isinstance(model, type) and issubclass(model, BaseModel)) or part not in model.model_fields:
            return []
        ann = model.model_fields[part].annotation
        model = _model_in(ann)
        if model is None:
            return []
    if isinstance(model, type) and issubclass(model, BaseModel):
        return sorted(k for k, f in model.model_fields.items() if not f.exclude)
    return []


_UNION_MEMBERS = (ElasticMaterial, PlasticMaterial, LiquidMaterial, BoxShape, SphereShape, CylinderShape, MeshShape)


def _model_in(annotation: Any) -> Any:
    """The BaseModel class inside an annotation such as list[X], X | None, Annotated[...]."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()) or ():
        found = _model_in(arg)
        if found is not None:
            return found
    for arg in getattr(annotation, "__metadata__", ()) or ():
        found = _model_in(arg)
        if found is not None:
            return found
    origin = getattr(annotation, "__origin__", None)
    if origin is not None and origin is not annotation:
        return _model_in(origin)
    return None


def _message(err: dict) -> str:
    kind, ctx = err["type"], err.get("ctx", {})
    loc = tuple(err["loc"])
    if kind == "extra_forbidden":
        allowed = _allowed_keys(loc)
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return f"unknown key{hint}"
    if kind == "missing":
        return "required key is missing"
    ops = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in ops:
        bound = next(iter(ctx.values()))
        return f"must be {ops[kind]} {bound} (got {err.get('input')!r})"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected')} (got {err.get('input')!r})"
    if kind == "union_tag_invalid":
        return f"unknown type {ctx.get('tag')!r}; choose one of {ctx.get('expected_tags')}"
    if kind == "union_tag_not_found":
        return "missing 'type' key"
    if kind == "finite_number":
        return "must be a finite number"
    if kind in ("float_parsing", "float_type"):
        return f"must be a number (got {err.get('input')!r})"
    if kind in ("int_parsing", "int_type", "int_from_float"):
        return f"must be an integer (got {err.get('input')!r})"
    if kind in ("list_type",):
        return f"must be a list (got {err.get('input')!r})"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"must be a mapping of keys (got {err.get('input')!r})"
    if kind == "too_short":
        return f"needs at least {ctx.get('min_length')} entries"
    if kind == "value_error":
        return str(ctx.get("error", err["msg"]))
    return err["msg"]


def format_errors(exc: ValidationError) -> list[str]:
    return [f"{_path(tuple(e['loc']))}: {_message(e)}" for e in exc.errors()]


def semantic_problems(scene: Scene) -> list[str]:
    """Checks that need more than one key: vector lengths, names, files, fit in the grid."""
    d = scene.dim
    problems: list[str] = []

    def vec(path: str, value: list | None, n: int = d) -> None:
        if value is not None and len(value) != n:
            problems.append(f"{path}: must have {n} entries (dim is {d}), got {len(value)}")

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
        vec(f"{base}.velocity", body.velocity)
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
    loss = scene.loss
    if loss.body is not None and loss.body not in names:
        problems.append(f"loss.body: no body named '{loss.body}'; bodies are {names}")
    if loss.type == "com_target":
        if loss.body is None:
            problems.append("loss.body: com_target needs the body whose centre of mass is steered")
        if loss.target is None:
            problems.append("loss.target: com_target needs a target point")
    if loss.type == "joint_target":
        if None in (loss.skeleton, loss.joint, loss.target):
            problems.append("loss: joint_target needs skeleton, joint and target (the joint's positions)")
        if scene.articulated is None:
            problems.append("loss.type: joint_target needs an articulated: section")
    else:
        vec("loss.target", loss.target)
    if scene.rigid is not None:
        problems += rigid_problems(scene)
    if scene.articulated is not None:
        from cosim.scene.articulated_checks import articulated_problems

        problems += articulated_problems(scene)
    for section in ("gradient", "optimize"):
        if "action" in getattr(scene, section).params and section in scene.model_fields_set:
            if scene.articulated is None or not any(s.controls for s in scene.articulated.skeletons):
                problems.append(f"{section}.params: 'action' needs a skeleton with controls under articulated:")
    if "impulse" in scene.gradient.params and not scene.controls and "gradient" in scene.model_fields_set:
        problems.append("gradient.params: 'impulse' needs at least one entry under controls")
    if "impulse" in scene.optimize.params and not scene.controls and "optimize" in scene.model_fields_set:
        problems.append("optimize.params: 'impulse' needs at least one entry under controls")
    if scene.steps * scene.time.frame_dt > 1e4 or not math.isfinite(scene.time.frame_dt):
        problems.append("time.frame_dt: steps * frame_dt exceeds 10^4 s; is frame_dt in seconds?")
    return problems


_SHAPE_NEEDS = {
    "box": ("size",),
    "sphere": ("radius",),
    "cylinder": ("radius", "height"),
    "capsule": ("radius", "height"),
    "glass": ("radius", "height", "thickness"),
    "ring": ("radius", "thickness"),
    "mesh": ("file",),
}


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
    problems = [f"{key}.{k}: required for a {shape.type}" for k in _SHAPE_NEEDS[shape.type] if getattr(shape, k) is None]
    if shape.type == "box" and shape.size is not None and len(shape.size) != d:
        problems.append(f"{key}.size: must have {d} entries (dim is {d}), got {len(shape.size)}")
    if shape.type == "ring" and d != 2:
        problems.append(f"{key}.type: a ring is 2D; in 3D use a glass or a mesh")
    if shape.type == "mesh":
        if d != 3:
            problems.append(f"{key}.type: meshes are 3D; in 2D use box, sphere, capsule, glass or ring")
        elif shape.file is not None and not (scene.source_dir / shape.file).resolve().is_file():
            problems.append(f"{key}.file: file not found: {(scene.source_dir / shape.file).resolve()}")
    if shape.type == "glass" and None not in (shape.radius, shape.thickness, shape.height):
        if shape.thickness >= min(shape.radius, shape.height):
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
