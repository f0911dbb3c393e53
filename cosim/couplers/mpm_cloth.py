"""Two-way coupling of the MPM with a cloth engine: vertex states in, per-vertex forces out.

One macro step n (frame T = K dt): the cloth's state s_C^n = {x, v} (V, 3) is the
boundary of the MPM's K substeps (frozen during them, ``ClothBoundary``); the
contact reactions summed over the step, impulse (V, 3) [N s], become the cloth's
external forces F^n = impulse / T [N], constant over its step. Penetration tracing
carries a per-particle state from step to step; this coupler holds it between steps
(``state`` / ``set_state``: reset or replay it with the MPM's state), hands it to the
MPM as part of the boundary input and takes the updated one from the reactions.

Backward: ``forces_vjp`` is dL/d impulse = dL/dF / T; ``boundary_vjp`` passes the
MPM's dL/d{x, v} of the boundary states straight to the cloth's state (they are the
state itself). Tracing is discrete and carries no gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import SimulationError


@dataclass
class ClothCouplingRecord:
    dt: float  # [s] MPM substep
    substeps: int

    @property
    def frame(self) -> float:
        return self.dt * self.substeps


class MPMClothCoupler:
    """Joins the cloth engine ``cloth`` (anything with ``name`` and ``state()`` -> {x, v}) to the MPM through
    the boundary source attached under ``name`` (default: the cloth engine's name)."""

    capabilities = frozenset({"carried_state"})

    def __init__(self, cloth, name: str | None = None, max_travel: float = np.inf):
        self.cloth = cloth
        self.engine = cloth.name
        self.name = self.source = name or cloth.name
        self.max_travel = float(max_travel)  # [m] per frame: the tracing band (``ClothBoundary.max_step_travel``)
        self._tracking: dict | None = None

    def state(self) -> dict | None:
        """The tracing state {face, side, inside} (N,) int before the next step (None: fresh)."""
        return None if self._tracking is None else {k: v.copy() for k, v in self._tracking.items()}

    def set_state(self, tracking: dict | None) -> None:
        """Restore a tracing state from ``state()`` (None: fresh, as at the start of a run)."""
        self._tracking = None if tracking is None else {k: np.array(v, dtype=np.int32) for k, v in tracking.items()}

    def boundary(self, dt: float, substeps: int) -> tuple[dict, ClothCouplingRecord]:
        """The cloth's current vertex positions and velocities and the tracing state, for the MPM step."""
        s = self.cloth.state()
        travel = float(np.linalg.norm(s["v"], axis=1).max()) * dt * substeps
        if travel > self.max_travel:
            raise SimulationError(
                f"cloth '{self.engine}' moves up to {travel:.3g} m in one frame, more than the tracing band "
                f"{self.max_travel:.3g} m: particles near it could cross it unseen; lower time.frame_dt or slow "
                "the cloth's controls"
            )
        states = {"x": np.array(s["x"], dtype=np.float64), "v": np.array(s["v"], dtype=np.float64)}
        states["tracking"] = self._tracking
        return states, ClothCouplingRecord(dt, substeps)

    def forces(self, record: ClothCouplingRecord, reactions: dict) -> np.ndarray:
        """(V, 3) [N]: the step's reaction impulses over the frame; keeps the updated tracing state."""
        self._tracking = reactions["tracking"]
        return reactions["impulse"] / record.frame

    def forces_vjp(self, record: ClothCouplingRecord, grad_forces: np.ndarray | None) -> tuple[dict | None, None]:
        if grad_forces is None:
            return None, None
        return {"impulse": np.asarray(grad_forces) / record.frame}, None

    def boundary_vjp(self, record: ClothCouplingRecord, grad_boundary: dict, carry: None) -> dict[str, np.ndarray]:
        return {"x": grad_boundary["x"], "v": grad_boundary["v"]}
