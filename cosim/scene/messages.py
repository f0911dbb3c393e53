"""Pydantic's validation errors in the user's words: one ``key.path[i]: message`` line each.

``format_errors`` drops the discriminator's branch names from the key path
(``mpm.bodies[0].material.E``, not ``...material.elastic.E``) and, for an unknown
key, lists the keys allowed in that mapping.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ValidationError

from cosim.engines.shapes import PARTICLE_SHAPE_KINDS
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

_TAGS = {"elastic", "plastic", "liquid", *PARTICLE_SHAPE_KINDS}  # union tags pydantic puts in key paths
_VELOCITY_TAGS = {"components", "file"}  # a body's velocity: a list of components or {file: PATH}


def _is_tag(loc: tuple, i: int) -> bool:
    """``loc[i]`` is a discriminator's branch name, not a key of the YAML file."""
    previous = loc[i - 1] if i > 0 else None
    return (loc[i] in _TAGS and previous in ("material", "shape")) or (
        loc[i] in _VELOCITY_TAGS and previous == "velocity"
    )


def _path(loc: tuple) -> str:
    out = ""
    for i, part in enumerate(loc):
        if isinstance(part, int):
            out += f"[{part}]"
        elif _is_tag(loc, i):
            continue  # the discriminator's branch name is noise for the user
        elif isinstance(part, str) and part.startswith("function-"):
            continue
        else:
            out += ("." if out else "") + str(part)
    return out or "(top level)"


def _allowed_keys(loc: tuple) -> list[str]:
    """Keys allowed in the mapping that holds ``loc[-1]`` (for unknown-key errors)."""
    model: Any = Scene
    for i, part in enumerate(loc[:-1]):
        if isinstance(part, int) or (part in _VELOCITY_TAGS and _is_tag(loc, i)):
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
    if kind == "list_type" and loc[-2:] == ("velocity", "components"):
        return f"must be a list of numbers or expressions, one per axis, or {{file: PATH}} (got {err.get('input')!r})"
    if kind in ("list_type",):
        return f"must be a list (got {err.get('input')!r})"
    if kind == "string_type":
        return f"must be a string (got {err.get('input')!r})"
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"must be a mapping of keys (got {err.get('input')!r})"
    if kind == "too_short":
        return f"needs at least {ctx.get('min_length')} entries"
    if kind == "value_error":
        return str(ctx.get("error", err["msg"]))
    return err["msg"]


def format_errors(exc: ValidationError) -> list[str]:
    """One line per pydantic error: the key path as written in the YAML file, then what is wrong."""
    return [f"{_path(tuple(e['loc']))}: {_message(e)}" for e in exc.errors()]
