"""Kinematic rigid bodies: bodies that follow a prescribed motion.

They are the moving boundaries of the contact models (a shaken container, a
pouring glass) and stay useful next to DART for scripted obstacles.

Frame convention (shared with the contact models):
- pose: position ``p`` [m] of the body frame's origin in the world, and the
  rotation ``R`` (d x d) taking body-frame vectors to world vectors, so a body
  point r_b sits at x = p + R r_b;
- twist: linear velocity ``v`` [m/s] of the body origin and angular velocity
  ``w`` [rad/s] in the world frame (a scalar in 2D, a 3-vector in 3D); a point
  x of the body moves with v_c = v + w x (x - p).

Motions (all start from the initial pose ``p0``, ``R0``):
- ``constant``: constant ``velocity`` and ``angular_velocity``;
- ``piecewise``: consecutive segments, each a duration with its own constant
  velocity and angular velocity; ``repeat`` cycles them (e.g. a left-right shake
  at constant speed), else the body rests after the last;
- ``shake``: sinusoidal translation p0 + amplitude sin(2 pi frequency t + phase),
  no rotation;
- ``waypoints``: piecewise-linear positions through ``positions`` at ``times``
  (the first time is 0 and the first position p0), then at rest.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from cosim.engines import so3


def constant(p0, R0, velocity, angular_velocity) -> Motion:
    """A body moving with a constant twist forever."""
    return Motion(
        "constant",
        np.asarray(p0, float),
        np.asarray(R0, float),
        [Segment(math.inf, np.asarray(velocity, float), angular_velocity)],
    )


def rotation_about(w: np.ndarray | float, angle_scale: float, dim: int) -> np.ndarray:
    """exp([w]x * angle_scale): rotation by |w| * angle_scale [rad] about w (2D: w is the angle rate).

    With w an angular velocity [rad/s] and angle_scale a duration [s], the turn of a constant spin.
    """
    if dim == 2:
        return so3.rotation_2d(float(w) * angle_scale)
    w = np.asarray(w, dtype=np.float64)
    if angle_scale == 0 or not np.any(w):  # no turn; also the scalar 0 that stands for "no spin" in 3D
        return np.eye(3)
    return so3.exp(w * angle_scale)


@dataclass
class Segment:
    duration: float  # [s]
    velocity: np.ndarray  # (d,) [m/s]
    angular_velocity: np.ndarray | float  # [rad/s], world frame


@dataclass
class Motion:
    """A prescribed motion: ``pose(t)`` and ``twist(t)`` for t >= 0 [s]."""

    kind: str
    p0: np.ndarray
    R0: np.ndarray
    segments: list[Segment] = field(default_factory=list)  # constant / piecewise
    repeat: bool = False
    amplitude: np.ndarray | None = None  # shake [m]
    frequency: float = 0.0  # shake [Hz]
    phase: float = 0.0  # shake [rad]
    times: np.ndarray | None = None  # waypoints [s]
    positions: np.ndarray | None = None  # waypoints (n, d) [m]

    @property
    def dim(self) -> int:
        return len(self.p0)

    def _zero_w(self):
        return 0.0 if self.dim == 2 else np.zeros(3)

    # -------------------------------------------------------------- segments
    def _segment_index(self, t: float) -> tuple[int, float, int]:
        """Index of the segment holding t (``len(segments)``: after the last, at rest), the time into it
        and the whole cycles of ``repeat`` before it."""
        period, cycles = self._cycle[0], 0
        if self.repeat and 0 < period < math.inf:
            cycles = math.floor(t / period)
            t -= cycles * period
        for i, seg in enumerate(self.segments):
            if t < seg.duration:
                return i, t, cycles
            t -= seg.duration
        return len(self.segments), t, cycles

    def _segment_at(self, t: float) -> tuple[int, float, np.ndarray, np.ndarray]:
        """Index of the segment holding t, time into it, and the pose at its start.

        Index ``len(segments)`` means after the last segment (at rest). Velocities
        are world-frame, so a whole cycle of ``repeat`` shifts by the same
        translation and left-multiplies by the same rotation every time.
        """
        i, tau, cycles = self._segment_index(t)
        _, shift, turn = self._cycle
        p = self.p0.astype(np.float64) + cycles * shift
        R = self.R0.astype(np.float64)
        if cycles and turn is not None:
            R = np.linalg.matrix_power(turn, cycles) @ R
        start_p, start_R = self._starts[i]
        return i, tau, p + start_p, start_R @ R

    @functools.cached_property
    def _cycle(self) -> tuple[float, np.ndarray, np.ndarray | None]:
        """The segments' total duration [s], and the translation and rotation (None: none) one whole
        cycle of them makes (world-frame twists: every cycle shifts and turns alike). Computed once: a
        shaken container asks for its pose at every substep."""
        period = sum(seg.duration for seg in self.segments)
        shift, turn = self._advance(np.zeros(self.dim), np.eye(self.dim), period) if period < math.inf else (0, 0)
        no_turn = period == math.inf or np.array_equal(turn, np.eye(self.dim))
        return period, shift, None if no_turn else turn

    @functools.cached_property
    def _starts(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each segment's start, then the last one's end (where the body rests after it), as a displacement
        and rotation from the cycle's start: the pose there is (p + dp, dR R) for the cycle's start pose (p, R)."""
        dp, dR, out = np.zeros(self.dim), np.eye(self.dim), []
        for seg in self.segments:
            out.append((dp, dR))
            if seg.duration < math.inf:
                dp, dR = self._advance_one(dp, dR, seg, seg.duration)
        return [*out, (dp, dR)]

    @staticmethod
    def _advance_one(p, R, seg: Segment, dt: float):
        """Pose after moving ``dt`` within one constant-twist segment (rotation about the body origin)."""
        return p + seg.velocity * dt, rotation_about(seg.angular_velocity, dt, len(p)) @ R

    def _advance(self, p, R, duration: float):
        for seg in self.segments:
            step = min(seg.duration, duration)
            p, R = self._advance_one(p, R, seg, step)
            duration -= step
        return p, R

    # -------------------------------------------------------------- public
    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (d,) and rotation (d, d) of the body frame at time t."""
        if self.kind in ("constant", "piecewise"):
            i, tau, p, R = self._segment_at(t)
            if i < len(self.segments):
                return self._advance_one(p, R, self.segments[i], tau)
            return p, R
        if self.kind == "shake":  # starts at p0 whatever the phase
            w = 2 * math.pi * self.frequency
            return self.p0 + self.amplitude * (math.sin(w * t + self.phase) - math.sin(self.phase)), self.R0.copy()
        # waypoints
        return np.array([np.interp(t, self.times, self.positions[:, k]) for k in range(self.dim)]), self.R0.copy()

    def twist(self, t: float) -> tuple[np.ndarray, np.ndarray | float]:
        """Linear velocity (d,) of the body origin and angular velocity (world frame) at time t."""
        if self.kind in ("constant", "piecewise"):
            i, _, _ = self._segment_index(t)
            if i < len(self.segments):
                seg = self.segments[i]
                return np.asarray(seg.velocity, dtype=np.float64), seg.angular_velocity
            return np.zeros(self.dim), self._zero_w()
        if self.kind == "shake":
            w = 2 * math.pi * self.frequency
            return self.amplitude * w * math.cos(w * t + self.phase), self._zero_w()
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        if k >= len(self.times) - 1:
            return np.zeros(self.dim), self._zero_w()
        return (self.positions[k + 1] - self.positions[k]) / (self.times[k + 1] - self.times[k]), self._zero_w()

    def point_velocity(self, t: float, x: np.ndarray) -> np.ndarray:
        """Velocity [m/s] of the body's material point at world position(s) x: v + w x (x - p)."""
        p, _ = self.pose(t)
        v, w = self.twist(t)
        r = np.atleast_2d(x) - p
        if self.dim == 2:
            spin = float(w) * np.stack([-r[:, 1], r[:, 0]], axis=1)
        else:
            spin = np.cross(np.asarray(w), r)
        out = v + spin
        return out[0] if np.ndim(x) == 1 else out


def kinematic_states(motions: list[Motion], t0: float, dt: float, K: int) -> dict[str, np.ndarray]:
    """BoundaryStates (``cosim.engines.contract``) of bodies following ``motions``, sampled at the
    start of each substep t0 + s dt, s = 0..K-1: pos (K, m, d), rot (K, m, d, d), vel (K, m, d),
    omega (K, m, 1|3)."""
    dim = motions[0].dim
    m = len(motions)
    out = {
        "pos": np.zeros((K, m, dim)),
        "rot": np.zeros((K, m, dim, dim)),
        "vel": np.zeros((K, m, dim)),
        "omega": np.zeros((K, m, 1 if dim == 2 else 3)),
    }
    for s in range(K):
        for b, motion in enumerate(motions):
            out["pos"][s, b], out["rot"][s, b] = motion.pose(t0 + s * dt)
            out["vel"][s, b], w = motion.twist(t0 + s * dt)
            out["omega"][s, b] = w
    return out


class KinematicEngine:
    """Bodies following prescribed motions, as an engine ("kinematic") of the coupled loop.

    State: ``steps`` (1,), the macro steps taken; the time is steps x ``frame_dt`` [s].
    No actions; external forces are ignored (the motion is prescribed), so the step's
    vjp is zero: a kinematic body passes no gradient back (its motion is not a parameter).
    """

    name = "kinematic"

    def __init__(self, motions: list[Motion], names: list[str], frame_dt: float):
        self.motions = list(motions)
        self.names = list(names)
        self.frame_dt = float(frame_dt)
        self._steps = 0

    @property
    def time(self) -> float:
        """The current time [s]."""
        return self._steps * self.frame_dt

    def state(self) -> dict[str, np.ndarray]:
        return {"steps": np.array([float(self._steps)])}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        self._steps = round(float(state["steps"][0]))

    def step(self, inputs: dict) -> tuple[dict, None]:
        """Advance one frame; ``inputs`` (action, forces) have no effect on a prescribed motion."""
        if inputs.get("action") is not None and np.size(inputs["action"]):
            raise ValueError("kinematic bodies take no action (their motion is prescribed in the scene)")
        self._steps += 1
        return {"state": self.state()}, None

    def vjp(self, record: None, grad_outputs: dict) -> dict:
        return {"state": {"steps": np.zeros(1)}, "action": None, "forces": None}

    def parameters(self) -> list:
        return []

    def poses(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(position, rotation) of every body now."""
        return [m.pose(self.time) for m in self.motions]
