"""The YAML scene format: a validated, typed description of one simulation.

``load_scene(path)`` parses and validates; any problem raises ``SceneError``
with one line per problem, each naming the key path, e.g.
``mpm.bodies[1].material.E: must be > 0``. The reference of every key is
``docs/scene-format.md``. Building engines from a scene is ``cosim.build``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from cosim.errors import SceneError

Vec = list[float]
Positive = Annotated[float, Field(gt=0)]


class Strict(BaseModel):
    """Unknown keys are errors, not silently ignored."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ---------------------------------------------------------------- time, grid
def _auto_or_int(value: Any) -> Any:
    if value == "auto" or value is None:
        return 0
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError("must be 'auto' or a positive integer")
    if value < 1:
        raise ValueError("must be 'auto' or a positive integer")
    return value


class TimeSpec(Strict):
    frame_dt: Positive = 4e-3  # [s] one macro step: what `steps` counts and frames show
    substeps: Annotated[int, BeforeValidator(_auto_or_int)] = 0  # 0 = auto (CFL)
    cfl: Annotated[float, Field(gt=0, le=1)] = 0.3
    max_substeps: Annotated[int, Field(ge=1, le=100000)] = 2000


def _int_or_list(value: Any) -> Any:
    if isinstance(value, int) and not isinstance(value, bool):
        return [value]
    if not isinstance(value, list):
        raise ValueError(f"must be an integer or a list of integers (got {value!r})")
    return value


class GridSpec(Strict):
    cells: Annotated[list[Annotated[int, Field(ge=8, le=4096)]], BeforeValidator(_int_or_list)]
    dx: Positive | None = None  # [m]; default 1 / max(cells): a unit-sized domain


class BoundarySpec(Strict):
    type: Literal["slip", "sticky", "none"] = "slip"
    thickness: Annotated[int, Field(ge=2, le=16)] = 3  # [cells]


# ---------------------------------------------------------------- materials
class _MaterialBase(Strict):
    E: Positive  # Young's modulus [Pa] (liquids: stiffness of the pressure law)
    nu: Annotated[float, Field(ge=0, lt=0.5)] = 0.3
    density: Positive = 1000.0  # [kg/m^3]


class ElasticMaterial(_MaterialBase):
    type: Literal["elastic"]


class PlasticMaterial(_MaterialBase):
    type: Literal["plastic"]
    yield_stress: Positive  # [Pa], von Mises


class LiquidMaterial(_MaterialBase):
    type: Literal["liquid"]
    viscosity: Annotated[float, Field(ge=0)] = 0.0  # [Pa s]; water is 1e-3


Material = Annotated[Union[ElasticMaterial, PlasticMaterial, LiquidMaterial], Field(discriminator="type")]


# ---------------------------------------------------------------- shapes
class BoxShape(Strict):
    type: Literal["box"]
    center: Vec
    size: list[Positive]


class SphereShape(Strict):
    """A ball in 3D, a disc in 2D."""

    type: Literal["sphere"]
    center: Vec
    radius: Positive


class CylinderShape(Strict):
    """3D only."""

    type: Literal["cylinder"]
    center: Vec
    radius: Positive
    height: Positive
    axis: Literal["x", "y", "z"] = "y"


class MeshShape(Strict):
    """A watertight mesh file (any format trimesh reads), 3D only.

    The mesh is scaled, then moved so its bounding-box centre sits at ``center``.
    """

    type: Literal["mesh"]
    file: str
    center: Vec
    scale: Positive | list[Positive] = 1.0


Shape = Annotated[Union[BoxShape, SphereShape, CylinderShape, MeshShape], Field(discriminator="type")]


class BodySpec(Strict):
    name: str
    material: Material
    shape: Shape
    velocity: Vec | None = None  # [m/s], default at rest
    spacing: Positive | None = None  # [m] particle lattice spacing, default dx / 2
    jitter: Annotated[float, Field(ge=0, le=0.5)] = 0.0  # fraction of spacing
    hydrostatic: bool = False  # liquids: start compressed by their own weight (at rest)


class MPMSpec(Strict):
    grid: GridSpec
    boundary: BoundarySpec = BoundarySpec()
    gravity: Vec | None = None  # [m/s^2], default -9.81 along y
    bodies: Annotated[list[BodySpec], Field(min_length=1)]


# ---------------------------------------------------------------- controls, loss
class RegionSpec(Strict):
    min: Vec
    max: Vec


class ControlSpec(Strict):
    """An impulse on selected particles, applied in P2G (the soft-gripper action)."""

    body: str
    region: RegionSpec | None = None  # particles of the body inside this box (initially)
    impulse: Vec | None = None  # [N s] per particle per macro step, the initial action


class LossSpec(Strict):
    """Scalar loss on the final state.

    - weighted_positions: mean over particles of w_p . x_p with fixed seeded
      normal weights w_p: a generic probe of every particle's final position;
    - com_target: squared distance [m^2] of a body's centre of mass to ``target``.
    """

    type: Literal["weighted_positions", "com_target"] = "weighted_positions"
    body: str | None = None  # restrict to one body (required for com_target)
    target: Vec | None = None


class GradientSpec(Strict):
    params: list[Literal["x0", "v0", "impulse", "E", "nu"]] = ["v0", "impulse", "E"]
    tolerance: Positive = 1e-4  # relative error allowed by `cosim gradcheck`
    directions: Annotated[int, Field(ge=1, le=64)] = 3


class OptimizeSpec(Strict):
    """`cosim optimize`: Adam on the loss's adjoint gradient."""

    params: list[Literal["x0", "v0", "impulse", "E", "nu"]] = ["impulse"]
    iterations: Annotated[int, Field(ge=1, le=100000)] = 30
    learning_rate: Positive = 0.05  # a fraction of each parameter's natural scale per step


class OutputSpec(Strict):
    every: Annotated[int, Field(ge=1)] = 1  # save a frame every N macro steps
    preview: Literal["gif", "mp4", "none"] = "gif"
    fps: Annotated[int, Field(ge=1, le=120)] = 30
    resolution: Annotated[int, Field(ge=64, le=2048)] = 400  # preview pixels (longest side)


class Scene(Strict):
    name: str = "scene"
    description: str = ""
    dim: Literal[2, 3]
    precision: Literal["float32", "float64"] = "float32"
    arch: Literal["cpu", "cuda"] = "cpu"
    seed: int = 0
    steps: Annotated[int, Field(ge=1)] = 100
    time: TimeSpec = TimeSpec()
    mpm: MPMSpec
    controls: list[ControlSpec] = []
    loss: LossSpec = LossSpec()
    gradient: GradientSpec = GradientSpec()
    optimize: OptimizeSpec = OptimizeSpec()
    output: OutputSpec = OutputSpec()

    # Set by the loader, not by the YAML file.
    source_dir: Path = Field(default=Path("."), exclude=True)

    @property
    def dx(self) -> float:
        return self.mpm.grid.dx or 1.0 / max(self.cells)

    @property
    def cells(self) -> tuple[int, ...]:
        c = self.mpm.grid.cells
        return tuple(c * self.dim if len(c) == 1 else c)

    @property
    def gravity(self) -> tuple[float, ...]:
        g = self.mpm.gravity
        if g is None:
            return (0.0, -9.81) + (0.0,) * (self.dim - 2)
        return tuple(g)


# ---------------------------------------------------------------- error text
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


def _format_errors(exc: ValidationError) -> list[str]:
    return [f"{_path(tuple(e['loc']))}: {_message(e)}" for e in exc.errors()]


# ---------------------------------------------------------------- semantic checks
def _semantic_problems(scene: Scene) -> list[str]:
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
    vec("loss.target", loss.target)
    if "impulse" in scene.gradient.params and not scene.controls and "gradient" in scene.model_fields_set:
        problems.append("gradient.params: 'impulse' needs at least one entry under controls")
    if "impulse" in scene.optimize.params and not scene.controls and "optimize" in scene.model_fields_set:
        problems.append("optimize.params: 'impulse' needs at least one entry under controls")
    if scene.steps * scene.time.frame_dt > 1e4 or not math.isfinite(scene.time.frame_dt):
        problems.append("time.frame_dt: steps * frame_dt exceeds 10^4 s; is frame_dt in seconds?")
    return problems


# ---------------------------------------------------------------- loading
def parse_scene(data: Any, source_dir: Path | str = ".", origin: str = "scene") -> Scene:
    """Validate a scene given as Python data (the parsed YAML)."""
    if not isinstance(data, dict):
        raise SceneError(f"{origin}: the top level must be a mapping of keys, got {type(data).__name__}")
    try:
        scene = Scene.model_validate(data)
    except ValidationError as exc:
        raise SceneError(f"{origin}: invalid scene\n  " + "\n  ".join(_format_errors(exc))) from None
    scene.source_dir = Path(source_dir)
    problems = _semantic_problems(scene)
    if problems:
        raise SceneError(f"{origin}: invalid scene\n  " + "\n  ".join(problems))
    return scene


def load_scene(path: str | Path, overrides: dict | None = None) -> Scene:
    """Read, parse and validate a YAML scene file; ``overrides`` replace top-level keys."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise SceneError(f"{path}: not valid YAML: {exc}") from None
    if isinstance(data, dict) and overrides:
        data = {**data, **overrides}
    return parse_scene(data, path.parent, origin=str(path))
