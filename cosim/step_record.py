"""The coupled system's record of one macro step, as the tape keeps it (``cosim.adjoint.tape``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class StepRecord:
    """One macro step on the tape: one record per engine and coupler, keyed by name."""

    time: float  # [s] at the start of the step
    mpm: Any
    engines: dict[str, Any]
    couplers: dict[str, Any]
    outputs: dict[str, Any] = field(default_factory=dict)  # non-differentiable per-step data (reactions)

    @property
    def substeps(self) -> int:
        return self.mpm.substeps

    @property
    def dt(self) -> float:
        return self.mpm.dt

    @property
    def nbytes(self) -> int:
        """Host memory the record holds [bytes]: the MPM's checkpoint, impulses and boundaries, and the
        manipulator engines' records."""
        return self.mpm.nbytes + sum(getattr(r, "nbytes", 0) for r in self.engines.values())

    @property
    def checkpoint(self) -> dict[str, np.ndarray] | None:
        """The MPM state before the step, or None when released (the engines' own states are always held)."""
        return self.mpm.state

    def keep_checkpoint(self, state: dict[str, np.ndarray] | None) -> None:
        """Hold the MPM state before the step (in the engine's precision), or release it (None)."""
        self.mpm.keep_checkpoint(state)

    @property
    def exchanges(self) -> list[StepRecord]:
        """The exchanges of the macro step: this one."""
        return [self]


@dataclass
class FrameRecord:
    """A macro step of several exchanges (``Stepping.exchanges``): their records in order. Reads as its
    exchanges together: the checkpoint before the first, the substeps of all, the outputs of the last."""

    exchanges: list[StepRecord]

    @property
    def time(self) -> float:
        return self.exchanges[0].time

    @property
    def substeps(self) -> int:
        return sum(s.substeps for s in self.exchanges)

    @property
    def outputs(self) -> dict[str, Any]:
        return self.exchanges[-1].outputs

    @property
    def nbytes(self) -> int:
        return sum(s.nbytes for s in self.exchanges)

    @property
    def checkpoint(self) -> dict[str, np.ndarray] | None:
        return self.exchanges[0].checkpoint

    def keep_checkpoint(self, state: dict[str, np.ndarray] | None) -> None:
        """Hold the MPM state before the first exchange (and each later one's own), or release them all (None)."""
        for i, s in enumerate(self.exchanges):
            s.keep_checkpoint(None if state is None else state if i == 0 else s.checkpoint)
