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


def _turns(phi: np.ndarray) -> np.ndarray:
    """Rotations by rotation vectors phi (T, 1) in 2D (angles), (T, 3) in 3D: (T, d, d)."""
    return so3.rotation_2d(phi[:, 0]) if phi.shape[-1] == 1 else so3.exp(phi)


@dataclass(frozen=True)
class _SegmentTable:
    """A piecewise motion's segments as arrays, row i segment i, the last row the rest after them: start
    time ``begins`` [s] (``ends``: the segments' end times), ``velocity`` [m/s], ``spin`` [rad/s] (1 or 3
    components), and the pose at the start as a displacement ``start_p`` [m] and rotation ``start_R`` from
    the cycle's start pose (p, R): (p + start_p, start_R R)."""

    begins: np.ndarray
    ends: np.ndarray
    velocity: np.ndarray
    spin: np.ndarray
    start_p: np.ndarray
    start_R: np.ndarray


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

    # -------------------------------------------------------------- segments
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
    def _table(self) -> _SegmentTable:
        """Each segment's start time, twist and start pose (from the cycle's start), then the last one's end
        (at rest there)."""
        dp, dR, starts = np.zeros(self.dim), np.eye(self.dim), []
        for seg in self.segments:
            starts.append((dp, dR))
            if seg.duration < math.inf:
                dp, dR = self._advance_one(dp, dR, seg, seg.duration)
        starts.append((dp, dR))
        ends = np.cumsum([seg.duration for seg in self.segments])
        spins = [self._spin(seg.angular_velocity) for seg in self.segments] + [self._spin(0.0)]
        return _SegmentTable(
            begins=np.concatenate([[0.0], ends]),
            ends=ends,
            velocity=np.array([np.asarray(seg.velocity, float) for seg in self.segments] + [np.zeros(self.dim)]),
            spin=np.array(spins),
            start_p=np.array([p for p, _ in starts]),
            start_R=np.array([R for _, R in starts]),
        )

    def _spin(self, w) -> np.ndarray:
        """An angular velocity as a (1,) array in 2D, (3,) in 3D (where a scalar 0 stands for no spin)."""
        return np.array([float(w)]) if self.dim == 2 else np.broadcast_to(np.asarray(w, float), (3,)).copy()

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

    def _segment_states(self, t: np.ndarray):
        """``states`` of a constant or piecewise motion: find each time's segment (after whole cycles of
        ``repeat``), start from its start pose and move with its twist for the time spent in it."""
        period, shift, turn = self._cycle
        table = self._table
        whole = self.repeat and 0 < period < math.inf
        cycles = np.floor(t / period) if whole else None
        if whole:
            t = t - cycles * period
        i = np.searchsorted(table.ends, t, side="right")  # the segment holding t (len(segments): after the last)
        velocity, spin = table.velocity[i], table.spin[i]
        p = self.p0 + table.start_p[i] + velocity * (t - table.begins[i])[:, None]
        R = self.R0
        if whole:
            p += cycles[:, None] * shift
            if turn is not None:  # every whole cycle turns the start pose once more
                R = np.array([np.linalg.matrix_power(turn, int(c)) for c in cycles]) @ R
        R = table.start_R[i] @ R
        if spin.any():  # a turn within the segment
            R = _turns(spin * (t - table.begins[i])[:, None]) @ R
        return p, R, velocity, spin

    # -------------------------------------------------------------- public
    def states(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pose and twist at each of ``times`` (T,) [s], in one pass: position (T, d), rotation (T, d, d),
        velocity (T, d) of the body origin and angular velocity (T, 1) in 2D, (T, 3) in 3D."""
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        n, d = len(t), self.dim
        if self.kind in ("constant", "piecewise"):
            return self._segment_states(t)
        R = np.broadcast_to(self.R0.astype(np.float64), (n, d, d)).copy()
        spin = np.zeros((n, 1 if d == 2 else 3))
        if self.kind == "shake":  # starts at p0 whatever the phase
            w = 2 * math.pi * self.frequency
            angle = (w * t + self.phase)[:, None]
            p = self.p0 + self.amplitude * (np.sin(angle) - math.sin(self.phase))
            return p, R, self.amplitude * w * np.cos(angle), spin
        # waypoints: piecewise linear, at rest after the last
        p = np.stack([np.interp(t, self.times, self.positions[:, k]) for k in range(d)], axis=-1)
        k = np.searchsorted(self.times, t, side="right") - 1
        moving = k < len(self.times) - 1
        k = np.minimum(k, len(self.times) - 2)
        v = (self.positions[k + 1] - self.positions[k]) / (self.times[k + 1] - self.times[k])[:, None]
        return p, R, np.where(moving[:, None], v, 0.0), spin

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Position (d,) and rotation (d, d) of the body frame at time t."""
        p, R, _, _ = self.states([t])
        return p[0], R[0]

    def twist(self, t: float) -> tuple[np.ndarray, np.ndarray | float]:
        """Linear velocity (d,) of the body origin and angular velocity (world frame) at time t (a float in 2D)."""
        _, _, v, w = self.states([t])
        return v[0], float(w[0, 0]) if self.dim == 2 else w[0]

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
    times = t0 + np.arange(K) * dt
    for b, motion in enumerate(motions):
        out["pos"][:, b], out["rot"][:, b], out["vel"][:, b], out["omega"][:, b] = motion.states(times)
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
