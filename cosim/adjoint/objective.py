"""Loss of a whole rollout as a function of its differentiable inputs.

The inputs (``PARAMS``): initial positions ``x0`` (N, d) [m], initial
velocities ``v0`` (N, d) [m/s], control impulses ``impulse`` (S, n_ctrl, d)
[N s] (all controls' particles, concatenated), per-body Young's moduli
``E`` [Pa] and Poisson's ratios ``nu``, and the rigid action sequence
``action`` (segments, action size) of a scene with DART skeletons (each
segment held ``articulated.actions.hold`` macro steps). ``Objective.evaluate`` runs the
rollout and, when asked, the adjoint through the tape.
"""

from __future__ import annotations

import numpy as np

from cosim.adjoint.tape import StepRecord, Tape
from cosim.losses import Loss
from cosim.simulation import Simulation

PARAMS = ("x0", "v0", "impulse", "E", "nu", "action")


class Objective:
    """L(params) for one simulation; the simulation must be built with ``requires_grad``."""

    def __init__(self, sim: Simulation):
        self.sim = sim
        self.initial_state = sim.mpm.state()
        self.initial_material = sim.mpm.params()  # evaluations overwrite the engine's copy
        rigid = sim.articulated.engine if sim.articulated is not None else None
        self.loss = Loss(sim.scene, sim.slices, sim.mpm.mass, rigid)
        self.tape = Tape()
        self.ctrl_index = np.concatenate([c.indices for c in sim.controls]) if sim.controls else np.zeros(0, dtype=int)

    def initial_params(self) -> dict[str, np.ndarray]:
        s = self.initial_state
        out = {"x0": s["x"].copy(), "v0": s["v"].copy(), **{k: v.copy() for k, v in self.initial_material.items()}}
        if self.sim.controls:
            out["impulse"] = np.concatenate(self.sim.default_actions(), axis=1)
        if self.sim.articulated is not None and self.sim.articulated.engine.action_size:
            out["action"] = self.sim.rigid_actions.copy()
        return out

    def _impulse_field(self, impulse: np.ndarray | None, n: int) -> np.ndarray | None:
        if impulse is None:
            return None
        full = np.zeros((self.sim.mpm.n_particles, self.sim.scene.dim))
        np.add.at(full, self.ctrl_index, impulse[n])
        return full

    def natural_scales(self) -> dict[str, float]:
        """Each parameter's natural size: finite-difference steps and optimizer steps are fractions of it."""
        p = self.initial_params()
        impulse = float(max(np.abs(p["impulse"]).max(), self.sim.mpm.mass.max() * 0.1)) if "impulse" in p else 1.0
        action = float(max(np.abs(p["action"]).max(), 1e-3)) if "action" in p else 1.0
        return {"x0": self.sim.dx, "v0": 1.0, "impulse": impulse, "E": float(p["E"].max()), "nu": 0.1, "action": action}

    def rollout(self, params: dict[str, np.ndarray], record: bool = False, on_step=None) -> dict[str, np.ndarray]:
        """Run all macro steps from ``params``; returns the final state.

        ``record`` fills the tape; ``on_step(n)`` is called with the state of
        macro step n in the engine (n = 0: the initial state).
        """
        sim = self.sim
        s0 = dict(self.initial_state, x=params["x0"], v=params["v0"])
        sim.mpm.set_state(s0)
        sim.mpm.set_params(
            E=params.get("E", self.initial_material["E"]), nu=params.get("nu", self.initial_material["nu"])
        )
        sim.step_index = 0
        if sim.articulated is not None:
            sim.articulated.engine.set_state(sim.rigid_state0)
        self.tape.clear()
        if on_step is not None:
            on_step(0)
        for n in range(sim.steps):
            imp = self._impulse_field(params.get("impulse"), n)
            before = sim.mpm.state() if record else None
            t0 = sim.step_index * sim.frame_dt
            action = sim.action(n, params.get("action"))
            info = sim.step(imp, action)
            if record:
                self.tape.push(StepRecord(before, info.dt, info.substeps, imp, info.token, t0, sim.last_coupled))
            if on_step is not None:
                on_step(n + 1)
        return self.final_state()

    def final_state(self) -> dict[str, np.ndarray]:
        """The MPM state, plus the rigid state under "rigid" when the scene has skeletons."""
        state = self.sim.mpm.state()
        if self.sim.articulated is not None:
            state["rigid"] = self.sim.articulated.engine.state()
        return state

    def evaluate(self, params: dict[str, np.ndarray], grad: bool = False):
        """Loss value, and with ``grad`` its gradient per parameter (same shapes)."""
        final = self.rollout(params, record=grad)
        value, dstate = self.loss(final)
        if not grad:
            return value, None
        g = self.tape.backward(self.sim.step_vjp, dstate)
        grads = {"x0": g.state0["x"], "v0": g.state0["v"], **g.params}
        if "impulse" in params:
            grads["impulse"] = np.stack([gi[self.ctrl_index] for gi in g.impulse])
        if "action" in params:
            grads["action"] = np.zeros_like(params["action"])
            for n, ga in enumerate(g.action):
                grads["action"][self.sim.action_segment(n, len(params["action"]))] += ga
        return value, grads
