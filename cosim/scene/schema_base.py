"""The scene format's building blocks shared by its sections: strict models, vectors and body shapes."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

Vec = list[float]
Positive = Annotated[float, Field(gt=0)]


class Strict(BaseModel):
    """Unknown keys are errors, not silently ignored."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


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


Shape = Annotated[BoxShape | SphereShape | CylinderShape | MeshShape, Field(discriminator="type")]
