"""The tape: per-macro-step records, replayed in reverse through each engine's vjp.

Forward, the runner pushes one record per macro step: the engine state at the
start of the step (a host-side checkpoint), the step's inputs (control
impulses) and its substep count and dt. Backward, the tape walks the records
from last to first and calls ``engine.vjp(record, dL/dstate_after)``, which
recomputes that step's substeps from its checkpoint and returns dL/dstate_before
plus the gradients of the step's inputs and parameters. Memory is one state per
macro step on the host plus one macro step of substeps in the engine:
O(S N + K N), never O(S K N).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class StepRecord:
    state: dict[str, np.ndarray]  # engine state before the step
    dt: float  # [s] substep length
    substeps: int
    impulse: np.ndarray | None = None  # (N, d) [N s] per-particle control impulse
    token: int = -1  # the engine's id of this forward step (lets it skip a recompute)
    time: float = 0.0  # [s] at the start of the step (moving boundaries are restored from it)

    def as_dict(self) -> dict:
        return {
            "state": self.state,
            "dt": self.dt,
            "substeps": self.substeps,
            "impulse": self.impulse,
            "token": self.token,
        }

    @property
    def nbytes(self) -> int:
        extra = 0 if self.impulse is None else self.impulse.nbytes
        return sum(a.nbytes for a in self.state.values()) + extra


@dataclass
class Gradients:
    """dL/d(inputs) of a whole rollout."""

    state0: dict[str, np.ndarray]  # dL/d(initial state): x, v, C, F
    impulse: list[np.ndarray | None]  # per macro step, (N, d)
    params: dict[str, np.ndarray] = field(default_factory=dict)  # per-body E, nu


class Tape:
    """Records macro steps forward; ``backward`` replays them in reverse."""

    def __init__(self) -> None:
        self.records: list[StepRecord] = []

    def push(self, record: StepRecord) -> None:
        self.records.append(record)

    def clear(self) -> None:
        self.records.clear()

    @property
    def nbytes(self) -> int:
        """Host memory held by the checkpoints [bytes]."""
        return sum(r.nbytes for r in self.records)

    def backward(self, engine, grad_final: dict[str, np.ndarray], before_step=None) -> Gradients:
        """Chain rule over the recorded steps: dL/ds^n = dL/ds^{n+1} ds^{n+1}/ds^n.

        ``before_step(t0, dt, K)`` restores a step's moving-boundary states before
        its vjp recomputes it (the simulation's hook; None without boundaries).
        """
        grad_state = grad_final
        impulses: list[np.ndarray | None] = [None] * len(self.records)
        params: dict[str, np.ndarray] = {}
        for n in reversed(range(len(self.records))):
            rec = self.records[n]
            if before_step is not None:
                before_step(rec.time, rec.dt, rec.substeps)
            out = engine.vjp(rec.as_dict(), grad_state)
            grad_state = out["state"]
            impulses[n] = out.get("impulse")
            for key in ("E", "nu"):
                params[key] = params.get(key, 0.0) + out[key]
        return Gradients(state0=grad_state, impulse=impulses, params=params)
