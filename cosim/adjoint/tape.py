"""The tape: per-macro-step records, replayed in reverse through each engine's vjp.

Forward, the runner pushes one record per macro step: the MPM state at the
start of the step (a host-side checkpoint), the step's inputs (control
impulses), its substep count and dt, and for coupled scenes the rigid engine's
record and the boundary states (``coupled``). Backward, the tape walks the
records from last to first and calls ``step_vjp(record, dL/dstate_after)`` (the
simulation's: the MPM vjp, which recomputes that step's substeps from its
checkpoint, chained with DART's for coupled scenes), which returns
dL/dstate_before plus the gradients of the step's inputs and parameters. Memory is one state per
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
    coupled: object = None  # cosim.couplers.mpm_rigid.CoupledRecord of a coupled step

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

    state0: dict[str, np.ndarray]  # dL/d(initial state): x, v, C, F (and "rigid" when coupled)
    impulse: list[np.ndarray | None]  # per macro step, (N, d)
    params: dict[str, np.ndarray] = field(default_factory=dict)  # per-body E, nu
    action: list[np.ndarray | None] = field(default_factory=list)  # per macro step, rigid actions


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

    def backward(self, step_vjp, grad_final: dict[str, np.ndarray]) -> Gradients:
        """Chain rule over the recorded steps: dL/ds^n = dL/ds^{n+1} ds^{n+1}/ds^n.

        ``step_vjp(record, dL/dstate_after)`` differentiates one step (``Simulation.step_vjp``)
        and returns a dict with "state" and the step's input and parameter gradients.
        """
        grad_state = grad_final
        n_steps = len(self.records)
        impulses: list[np.ndarray | None] = [None] * n_steps
        actions: list[np.ndarray | None] = [None] * n_steps
        params: dict[str, np.ndarray] = {}
        for n in reversed(range(n_steps)):
            out = step_vjp(self.records[n], grad_state)
            grad_state = out["state"]
            impulses[n] = out.get("impulse")
            actions[n] = out.get("action")
            for key in ("E", "nu"):
                params[key] = params.get(key, 0.0) + out[key]
        return Gradients(state0=grad_state, impulse=impulses, params=params, action=actions)
