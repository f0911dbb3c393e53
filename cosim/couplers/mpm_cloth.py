"""Two-way coupling of the MPM with a cloth engine: vertex states in, per-vertex forces and added mass out.

One exchange n (T = K dt: a macro step, or its share where it makes several, ``Stepping.exchanges``; beyond
``exchange_substeps`` substeps per exchange a sheet frozen over them jitters on the material): the cloth's state s_C^n = {x, v} (V, 3) is the
boundary of the MPM's K substeps (frozen during them, ``ClothBoundary``: the
material meets the sheet at x^n moving with v_b^n = v^n); the contact reactions
summed over the step, impulse J^n (V, 3) [N s], push the cloth over its step.

Why not just F = J^n / T (the explicit exchange): the material the contact moves,
mass A per vertex, leaves the step at the sheet's old velocity v^n while the sheet
moves on to v^{n+1}, and the next step's reaction drags the sheet back by
A (v^{n+1} - v^n): on a model problem a perturbation of the sheet's velocity is
multiplied by -A / m per frame (m the vertex mass), however short the frame: a sheet
carrying material heavier than itself flutters, and gradients over long contacts are
noise. So the reaction enters linearised, as a mass: the material that followed v_b follows
the sheet to v^{n+1} too:

    (m + A^n)(v^{n+1} - v^n) = T f_cloth + J^n

and that material is handed the sheet's velocity change v^{n+1} - v^n (on the vertices that
are not prescribed: a fixed or controlled vertex moves as told, its inertia unused) at the start
of the next step (``cosim.couplers.handover``: each engaged particle gets its share of the change of
the vertices under it), so it does not drag the sheet back. The momentum the sheet gave up to
carry it, A^n (v^{n+1} - v^n), is the momentum the material receives. On the model problem
(material of mass A_true in inelastic contact) a perturbation dies when A = A_true. So A must
be the material's actual response to the sheet's velocity over a frame, dJ/dv_b, not the
mass merely near the sheet (much of which the contact moves only partly within a frame).
A^n is the contact model's engagement summed per vertex (``ClothBoundary._contact_mass``,
``ForecastContact.engagement``), which follows how far each substep's contact moves a
particle towards the sheet's velocity. Other contact models give no engagement yet: A = 0,
the explicit exchange. Known defect: the sheet is frozen at x^n over the substeps while its
contact velocity is v_b, so material that follows a moving sheet crosses that frozen position
by up to T |v_b| per frame (and is traced inside until it is back on its side); the fix is
to move the sheet with v_b over the substeps.

The coupler's state carries v_b^{n-1} (V, 3) [m/s] (None at the start: nothing to hand over)
from step to step, with the penetration tracing's per-particle state (``state`` / ``set_state``).

Backward (A is a smooth function of the particles and the sheet, so it is differentiated
too): ``forces_vjp`` gives dL/dJ = g / T (g = dL/dF) and dL/dA^n = the cloth's dL/d(its
added mass), both handed to the MPM's vjp as the reaction adjoints; ``boundary_vjp`` passes
the MPM's dL/d{x, v} of the boundary states to the cloth's state, the hand-over's adjoint
dL/d(v^n - v_b^{n-1}) to the cloth's v^n and, negated, to this coupler's state before the
step, and dL/d(the carried v_b^n = v^n) to v^n. Tracing carries no gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import SimulationError


@dataclass
class ClothCouplingRecord:
    dt: float  # [s] MPM substep
    substeps: int
    handover: bool  # whether this step's MPM hands over a velocity change (not at the start)

    @property
    def frame(self) -> float:
        return self.dt * self.substeps


class MPMClothCoupler:
    """Joins the cloth engine ``cloth`` (anything with ``name``, ``state()`` -> {x, v}, ``free`` (V,) bool and
    ``masses()``) to the MPM through the boundary source attached under ``name`` (default: the cloth engine's
    name). ``added_mass=False`` exchanges explicitly (F = J / T, for comparisons)."""

    capabilities = frozenset({"carried_state", "exchange_limit"})
    exchange_substeps = 8  # a sheet at r = 5 on an elastic block grows a perturbation at 20 per exchange (docs/bench)

    def __init__(self, cloth, name: str | None = None, max_travel: float = np.inf, added_mass: bool = True):
        self.cloth = cloth
        self.engine = cloth.name
        self.medium = "mpm"
        self.name = self.source = name or cloth.name
        self.max_travel = float(max_travel)  # [m] per frame: the tracing band (``ClothBoundary.max_step_travel``)
        self.added_mass = bool(added_mass)
        self._free = np.asarray(cloth.free, dtype=np.float64)[:, None]  # the vertices no action prescribes
        self._fresh = {"tracking": None, "boundary_v": None}
        self._state = dict(self._fresh)
        self._v_b: np.ndarray | None = None

    def state(self) -> dict:
        """{"tracking": {face, side, inside} (N,) int or None (fresh), "boundary_v": (V, 3) [m/s] v_b^{n-1} or
        None (fresh)}: what the next step reads."""
        v_b = self._state["boundary_v"]
        tracking = self._state["tracking"]
        return {
            "tracking": None if tracking is None else {k: v.copy() for k, v in tracking.items()},
            "boundary_v": None if v_b is None else np.array(v_b),
        }

    def set_state(self, state: dict | None) -> None:
        """Restore a state from ``state()`` (None: fresh, as at the start of a run)."""
        state = state or self._fresh
        tracking, v_b = state["tracking"], state.get("boundary_v")
        self._state = {
            "tracking": None if tracking is None else {k: np.array(v, dtype=np.int32) for k, v in tracking.items()},
            "boundary_v": None if v_b is None else np.array(v_b, dtype=np.float64),
        }

    def boundary(self, dt: float, substeps: int) -> tuple[dict, ClothCouplingRecord]:
        """The cloth's current vertex positions and velocities, the tracing state and the velocity change to
        hand over (``cosim.couplers.handover``), for the MPM step."""
        s = self.cloth.state()
        travel = float(np.linalg.norm(s["v"], axis=1).max()) * dt * substeps
        if travel > self.max_travel:
            raise SimulationError(
                f"cloth '{self.engine}' moves up to {travel:.3g} m in one frame, more than the tracing band "
                f"{self.max_travel:.3g} m: particles near it could cross it unseen; lower time.frame_dt or slow "
                "the cloth's controls"
            )
        states = {"x": np.array(s["x"], dtype=np.float64), "v": np.array(s["v"], dtype=np.float64)}
        states["tracking"] = self._state["tracking"]
        states["substeps"] = substeps
        self._v_b = states["v"]
        handover = self.added_mass and self._state["boundary_v"] is not None
        if handover:  # the free vertices' change: a prescribed vertex's motion carries no added mass
            states["handover"] = (self._v_b - self._state["boundary_v"]) * self._free
        return states, ClothCouplingRecord(dt, substeps, handover)

    def forces(self, record: ClothCouplingRecord, reactions: dict) -> dict:
        """{"forces": (V, 3) [N] the reaction impulses over the frame, "added_mass": (V,) [kg] A^n}; keeps the
        tracing state and v_b^n for the next step."""
        added = reactions["mass"] if self.added_mass else np.zeros_like(reactions["mass"])
        self._state = {"tracking": reactions["tracking"], "boundary_v": self._v_b}
        return {"forces": reactions["impulse"] / record.frame, "added_mass": added}

    def forces_vjp(
        self, record: ClothCouplingRecord, grad_load: dict, grad_state: dict | None = None
    ) -> tuple[dict | None, dict, dict]:
        """From dL/d{forces, added_mass} of the cloth's step and dL/d(this coupler's state after the step):
        (dL/d{impulse, mass} of the MPM's reactions, the carry to ``boundary_vjp``, dL/d(this coupler's
        state before the step), which ``boundary_vjp`` completes)."""
        V = len(self._free)
        grad_state = grad_state or {}
        carry_v = np.zeros((V, 3))
        if grad_state.get("boundary_v") is not None:
            carry_v += grad_state["boundary_v"]  # the carried v_b^n is the cloth's v^n
        g_mass = np.zeros(V)
        if self.added_mass and grad_load.get("added_mass") is not None:
            g_mass = g_mass + grad_load["added_mass"]
        before = {"boundary_v": np.zeros((V, 3))}
        g = np.zeros((V, 3)) if grad_load.get("forces") is None else np.asarray(grad_load["forces"]) / record.frame
        return {"impulse": g, "mass": g_mass}, {"v": carry_v, "before": before}, before

    def budgeted(self) -> bool:
        """The cloth's energy is in the system's budget: its contact work on the material is internal."""
        return True

    def boundary_vjp(self, record: ClothCouplingRecord, grad_boundary: dict, carry: dict) -> dict[str, np.ndarray]:
        """dL/d{x, v} of the cloth's state before the step; the hand-over's adjoint also completes dL/d(this
        coupler's state before the step) in ``carry["before"]``."""
        g_v = grad_boundary["v"] + carry["v"]
        if record.handover:
            g_change = grad_boundary["handover"] * self._free
            g_v = g_v + g_change
            carry["before"]["boundary_v"] = -g_change
        return {"x": grad_boundary["x"], "v": g_v}
