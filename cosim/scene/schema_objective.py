"""The scene format's objective sections: the loss (terms, Chamfer targets), gradcheck and optimize."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field

from cosim.scene.schema_base import Positive, Shape, Strict, Vec


class TargetPointsSpec(Strict):
    """A target point set (chamfer): exactly one of ``file`` (.npy (M, dim), or .npz with an array
    ``x_<body>`` or a single array), ``shape`` (filled with points like a body, at ``spacing``,
    default dx / 2) or ``rollout`` (the ``target.npz`` of ``cosim run --save-target``: its
    ``x_<body>``, the body's final positions in that run)."""

    file: str | None = None
    shape: Shape | None = None
    rollout: str | None = None
    spacing: Positive | None = None  # [m] shape: point spacing


class LossTermSpec(Strict):
    """One term of the loss, on the final state or (``running``) summed over every macro step's state.

    - weighted_positions: mean over particles of w_p . x_p with fixed seeded
      normal weights w_p: a generic probe of every particle's final position;
    - com_target: squared distance [m^2] of a body's centre of mass to ``target``;
    - joint_target: squared distance of a DART joint's positions (``velocity``: velocities), or of
      their ``components``, to ``target``; on a free joint, the rigid body's pose (rotation vector,
      position) or twist;
    - pose_target: mean squared distance [m^2] of a body's points (particles or cloth vertices)
      to their start positions rotated by ``rotation`` about ``pivot`` and shifted by ``target``;
    - chamfer: the symmetric Chamfer distance [m^2] between a body's points and the point set
      ``points``: the mean squared distance from each point to the nearest target point plus the
      mean from each target point to the nearest body point (KD-trees).

    ``body`` names an MPM body or a cloth (its vertices are the points). The term adds
    ``weight`` times its value (running: times the sum of its values at steps 0..S).
    """

    type: Literal["weighted_positions", "com_target", "joint_target", "pose_target", "chamfer"] = "weighted_positions"
    body: str | None = None  # restrict to one body (required for com_target, pose_target, chamfer)
    target: Vec | None = None  # com_target: a point; joint_target: the joint's positions; pose_target: shift
    rotation: Vec | None = None  # pose_target: rotation vector [rad] (3D)
    pivot: Vec | None = None  # pose_target: the rotation's centre [m]
    points: TargetPointsSpec | None = None  # chamfer: the target point set
    rest_positions: Any = Field(default=None, exclude=True)  # set by the loss for MPM bodies, not in files
    skeleton: str | None = None  # joint_target: the articulated skeleton
    joint: str | None = None  # joint_target: its joint
    velocity: bool = False  # joint_target: on the joint's velocities instead of its positions
    # joint_target: which of the joint's coordinates (indices; default all): a free joint's height is [4]
    components: Annotated[list[Annotated[int, Field(ge=0)]], Field(min_length=1)] | None = None
    weight: float = 1.0
    running: bool = False  # summed over the states after every macro step (and the initial one)


class LossSpec(LossTermSpec):
    """The scalar loss: this term alone, or the sum of ``terms`` when given (the top-level term
    keys are then not used)."""

    terms: Annotated[list[LossTermSpec], Field(min_length=1)] | None = None

    def all_terms(self) -> list[LossTermSpec]:
        return list(self.terms) if self.terms else [self]


ParamName = Literal["x0", "v0", "impulse", "E", "nu", "action", "k_stretch", "k_bend", "c_mass", "density"]


class GradientSpec(Strict):
    params: list[ParamName] = ["v0", "impulse", "E"]
    tolerance: Positive = 1e-4  # relative error allowed by `cosim gradcheck`
    directions: Annotated[int, Field(ge=1, le=64)] = 3
    # macro steps of the check (default: min(steps, 5)); a scene whose contact starts late sets it so
    # that the check crosses contact
    steps: Annotated[int, Field(ge=1)] | None = None
    # every gradient run (gradcheck, optimize): the tape keeps the MPM state of every k-th macro step
    # and recomputes the others in the backward pass: S/k states instead of S, about one more forward
    checkpoint_every: Annotated[int, Field(ge=1)] = 1
    # where the tape keeps the MPM checkpoints and state adjoints: on the engine's device while they fit its
    # budget (auto), always there (device), or as host arrays (host; frees the device's memory)
    checkpoints: Literal["auto", "device", "host"] = "auto"


class OptimizeSpec(Strict):
    """`cosim optimize`: Adam, SGD (momentum 0.9) or L-BFGS-B on the loss's adjoint gradient."""

    params: list[ParamName] = ["impulse"]
    iterations: Annotated[int, Field(ge=1, le=100000)] = 30
    learning_rate: Positive = 0.05  # a fraction of each parameter's natural scale per step
    method: Literal["adam", "sgd", "lbfgs"] = "adam"
