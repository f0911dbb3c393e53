"""Two-way coupling of the MPM with a cloth engine: vertex states in, per-vertex forces and added mass out.

One macro step n (frame T = K dt): the cloth's state s_C^n = {x, v} (V, 3) is the
boundary of the MPM's K substeps (frozen during them, ``ClothBoundary``: the
material meets the sheet at x^n moving with v_b^n = v^n); the contact reactions
summed over the step, impulse J^n (V, 3) [N s], push the cloth over its step.

Why not just F = J^n / T (the explicit exchange): the material the contact moves,
mass A per vertex, leaves the step at the sheet's old velocity v^n while the sheet
moves on to v^{n+1}, and the next step's reaction drags the sheet back by
A (v^{n+1} - v^n): on a model problem a perturbation of the sheet's velocity is
multiplied by -A / m per frame (m the vertex mass), however short the frame: a sheet
carrying material heavier than itself flutters, and gradients over long contacts are
noise. So the reaction enters linearised, as a mass: the material that followed v_b follows the sheet to v^{n+1} too, which costs
A (v^{n+1} - v_b) of momentum:

    (m + A^n)(v^{n+1} - v^n) = T f_cloth + J^n + A^{n-1}(v^n - v_b^{n-1})

The last term pays back, one step late, the momentum the previous step's added mass
took from the sheet and the MPM's material delivers only now (its reaction J^n
includes the catch-up -A^{n-1}(v^n - v_b^{n-1})), so the momentum the sheet receives
over a run is exactly the MPM's reactions, delayed by a step. On the model problem
(material of mass A_true in inelastic contact) a perturbation is multiplied by
(A - A_true) / (m + A) per frame: 0 with A = A_true, of modulus below one for any
A > (A_true - m) / 2. So A must be the material's actual response to the sheet's
velocity over a frame, dJ/dv_b, not the mass merely near the sheet (much of which the
contact moves only partly within a frame). A^n is the contact model's engagement
summed per vertex (``ClothBoundary._contact_mass``, ``ForecastContact.engagement``),
which follows how far each substep's contact moves a particle towards the sheet's
velocity. Other contact models give no engagement yet: A = 0, the explicit exchange.
Known defect: the sheet is frozen at x^n over the substeps while its contact velocity
is v_b, so material that follows a moving sheet crosses that frozen position by up to
T |v_b| per frame (and is traced inside until it is back on its side); the fix is to
move the sheet with v_b over the substeps.

The coupler's state carries A^{n-1} (V,) [kg] and v_b^{n-1} (V, 3) [m/s] from step to
step, with the penetration tracing's per-particle state (``state`` / ``set_state``).

Backward (A is a smooth function of the particles and the sheet, so it is differentiated
too): ``forces_vjp`` gives dL/dJ = g / T (g = dL/dF), dL/dA^n = the cloth's dL/d(its
added mass) + dL/d(the carried A^n), both handed to the MPM's vjp as the reaction
adjoint "mass"; this coupler's state before the step gets dL/dv_b^{n-1} = -A^{n-1} g / T
and dL/dA^{n-1} = g . (v_b^n - v_b^{n-1}) / T; the cloth's v^n gets A^{n-1} g / T.
``boundary_vjp`` passes the MPM's dL/d{x, v} of the boundary states to the cloth's
state, plus that carry and dL/d(the carried v_b^n = v^n). Tracing carries no gradient.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.errors import SimulationError


@dataclass
class ClothCouplingRecord:
    dt: float  # [s] MPM substep
    substeps: int
    owed_mass: np.ndarray  # (V,) [kg] A^{n-1}, the added mass whose momentum this step pays back
    catch_up: np.ndarray  # (V, 3) [m/s] v_b^n - v_b^{n-1}, the velocity change it pays for

    @property
    def frame(self) -> float:
        return self.dt * self.substeps


class MPMClothCoupler:
    """Joins the cloth engine ``cloth`` (anything with ``name``, ``state()`` -> {x, v} and ``masses()``) to the
    MPM through the boundary source attached under ``name`` (default: the cloth engine's name).
    ``added_mass=False`` exchanges explicitly (F = J / T, for comparisons)."""

    capabilities = frozenset({"carried_state"})

    def __init__(self, cloth, name: str | None = None, max_travel: float = np.inf, added_mass: bool = True):
        self.cloth = cloth
        self.engine = cloth.name
        self.medium = "mpm"
        self.name = self.source = name or cloth.name
        self.max_travel = float(max_travel)  # [m] per frame: the tracing band (``ClothBoundary.max_step_travel``)
        self.added_mass = bool(added_mass)
        V = len(cloth.state()["v"])
        self._fresh = {"tracking": None, "added_mass": np.zeros(V), "boundary_v": np.zeros((V, 3))}
        self._state = dict(self._fresh)
        self._v_b: np.ndarray | None = None

    def state(self) -> dict:
        """{"tracking": {face, side, inside} (N,) int or None (fresh), "added_mass": (V,) [kg] A^{n-1},
        "boundary_v": (V, 3) [m/s] v_b^{n-1}}: what the next step reads."""
        out = {k: None if v is None else np.array(v) for k, v in self._state.items() if k != "tracking"}
        tracking = self._state["tracking"]
        out["tracking"] = None if tracking is None else {k: v.copy() for k, v in tracking.items()}
        return out

    def set_state(self, state: dict | None) -> None:
        """Restore a state from ``state()`` (None: fresh, as at the start of a run)."""
        state = state or self._fresh
        tracking = state["tracking"]
        self._state = {
            "tracking": None if tracking is None else {k: np.array(v, dtype=np.int32) for k, v in tracking.items()},
            "added_mass": np.array(state["added_mass"], dtype=np.float64),
            "boundary_v": np.array(state["boundary_v"], dtype=np.float64),
        }

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
        states["tracking"] = self._state["tracking"]
        states["substeps"] = substeps
        self._v_b = states["v"]
        catch_up = self._v_b - self._state["boundary_v"]
        return states, ClothCouplingRecord(dt, substeps, self._state["added_mass"], catch_up)

    def forces(self, record: ClothCouplingRecord, reactions: dict) -> dict:
        """{"forces": (V, 3) [N] the reaction impulses over the frame plus the momentum owed from the last
        step, "added_mass": (V,) [kg] A^n}; keeps the tracing state and A^n, v_b^n for the next step."""
        owed = record.owed_mass[:, None] * record.catch_up
        added = reactions["mass"] if self.added_mass else np.zeros_like(reactions["mass"])
        self._state = {"tracking": reactions["tracking"], "added_mass": added, "boundary_v": self._v_b}
        return {"forces": (reactions["impulse"] + owed) / record.frame, "added_mass": added}

    def forces_vjp(
        self, record: ClothCouplingRecord, grad_load: dict, grad_state: dict | None = None
    ) -> tuple[dict | None, dict, dict]:
        """From dL/d{forces, added_mass} of the cloth's step and dL/d(this coupler's state after the step):
        (dL/d{impulse, mass} of the MPM's reactions, the carry to the cloth's v^n, dL/d(this coupler's
        state before the step))."""
        V = len(record.owed_mass)
        grad_state = grad_state or {}
        carry = np.zeros((V, 3))
        if grad_state.get("boundary_v") is not None:
            carry += grad_state["boundary_v"]  # the carried v_b^n is the cloth's v^n
        g_mass = np.zeros(V)
        if self.added_mass:  # A^n is both the step's inertia and the carried A^{n-1} of the next step
            for g in (grad_load.get("added_mass"), grad_state.get("added_mass")):
                if g is not None:
                    g_mass = g_mass + g
        before = {"boundary_v": np.zeros((V, 3)), "added_mass": np.zeros(V)}
        if grad_load.get("forces") is None:
            return {"impulse": np.zeros((V, 3)), "mass": g_mass}, {"v": carry}, before
        g = np.asarray(grad_load["forces"]) / record.frame
        owed = record.owed_mass[:, None] * g
        before = {"boundary_v": -owed, "added_mass": np.sum(g * record.catch_up, axis=1)}
        return {"impulse": g, "mass": g_mass}, {"v": carry + owed}, before

    def budgeted(self) -> bool:
        """The cloth's energy is in the system's budget: its contact work on the material is internal."""
        return True

    def boundary_vjp(self, record: ClothCouplingRecord, grad_boundary: dict, carry: dict) -> dict[str, np.ndarray]:
        return {"x": grad_boundary["x"], "v": grad_boundary["v"] + carry["v"]}
