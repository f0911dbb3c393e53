"""Loss of a whole rollout as a function of the differentiable parameters the engines declare.

Each engine lists its parameters (``parameters()``, ``cosim.engines.contract.Parameter``):
the MPM's initial positions ``x0`` (N, d) [m] and velocities ``v0`` (N, d) [m/s], per-body
Young's moduli ``E`` [Pa] and Poisson's ratios ``nu``, control impulses ``impulse``
(S, n_ctrl, d) [N s] (all controls' particles, concatenated); a DART engine's action
sequence ``action`` (segments, action size), each segment held ``hold`` macro steps.
``Objective.evaluate`` runs the rollout and, when asked, the adjoint through the tape.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cosim.adjoint.tape import Tape
from cosim.engines.contract import Parameter, declares


class Objective:
    """L(params) for one coupled system built with ``requires_grad``.

    ``loss(final_state) -> (value, dL/dstate)`` reads any engine's state by name
    (default: the scene's loss, ``cosim.losses.Loss``). ``checkpoint_every``: the tape keeps
    the MPM state of every k-th macro step and recomputes the rest (default: the scene's
    ``gradient.checkpoint_every``, else 1).
    """

    def __init__(self, system, loss: Callable | None = None, checkpoint_every: int | None = None):
        self.system = system
        self.initial_state = system.state()
        engines = {"mpm": system.mpm, **system.engines}
        self.engines = engines
        self.initial_material = {name: e.material() for name, e in engines.items() if declares(e, "material")}
        self.parameters: dict[str, Parameter] = {}
        for e in engines.values():
            for p in e.parameters():
                if p.name in self.parameters:
                    raise ValueError(
                        f"engines '{self.parameters[p.name].engine}' and '{p.engine}' both declare '{p.name}'"
                    )
                self.parameters[p.name] = p
        if loss is None:
            from cosim.losses import Loss

            loss = Loss.for_system(system)
        self.loss = loss
        if checkpoint_every is None:
            scene = system.scene
            checkpoint_every = scene.gradient.checkpoint_every if scene is not None else 1
        self.tape = Tape(checkpoint_every)

    def memory_estimate(self):
        """What a gradient rollout will hold (``cosim.adjoint.memory.MemoryEstimate``)."""
        from cosim.adjoint.memory import estimate_memory

        running = getattr(self.loss, "has_running", False)
        return estimate_memory(self.system, self.system.steps, self.tape.checkpoint_every, running)

    def select(self, names: list[str]) -> list[str]:
        """The declared parameters a scene's ``params`` list asks for: named ``p`` or "<engine>.p"."""
        wanted = set(names)
        return [n for n in self.parameters if n in wanted or n.split(".", 1)[-1] in wanted]

    def initial_params(self) -> dict[str, np.ndarray]:
        """Every declared parameter's value in the scene as built."""
        out = {}
        for name, p in self.parameters.items():
            if p.kind == "state":
                out[name] = self.initial_state[p.engine][p.key].copy()
            elif p.kind == "material":
                out[name] = self.initial_material[p.engine][p.key].copy()
            elif p.key == "impulse":
                out[name] = self.system.default_impulses()
            else:
                out[name] = self.system.plans[p.engine].sequence.copy()
        return out

    def _action_plans(self) -> dict:
        """The action parameters' plans (``ActionPlan``: sequence, bounds, scale, projection), by name."""
        plans = {name: self.system.plans.get(p.engine) for name, p in self.parameters.items() if p.key == "action"}
        return {name: plan for name, plan in plans.items() if plan is not None}

    def bounds(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Per-entry (lower, upper) limits of the action parameters whose scene declares ``bounds``."""
        return {name: plan.bounds for name, plan in self._action_plans().items() if plan.bounds is not None}

    def projections(self) -> dict[str, Callable[[np.ndarray], np.ndarray]]:
        """The action parameters whose scene constrains them (e.g. a cloth's ``reach``): value -> allowed value."""
        return {name: plan.project for name, plan in self._action_plans().items() if plan.project is not None}

    def natural_scales(self) -> dict[str, float | np.ndarray]:
        """Each parameter's natural size: finite-difference and optimiser steps are fractions of it
        (inputs: their largest magnitude, at least the declared scale; actions whose scene declares
        ``scale``: that, per entry)."""
        values, plans = self.initial_params(), self._action_plans()
        out: dict[str, float | np.ndarray] = {}
        for name, p in self.parameters.items():
            plan = plans.get(name)
            if plan is not None and plan.scale is not None:
                out[name] = plan.scale
            else:
                out[name] = max(float(np.abs(values[name]).max()), p.scale) if p.kind == "input" else p.scale
        return out

    def rollout(self, params: dict[str, np.ndarray], record: bool = False, on_step=None) -> dict:
        """Run all macro steps from ``params``; returns the final state of every engine.

        ``record`` fills the tape; ``on_step(n)`` is called with the state of macro step n
        in the engines (n = 0: the initial state).
        """
        state = {name: dict(s) for name, s in self.initial_state.items()}
        material = {name: dict(m) for name, m in self.initial_material.items()}
        impulses, actions = None, {}
        for name, value in params.items():
            p = self.parameters[name]
            if p.kind == "state":
                state[p.engine][p.key] = value
            elif p.kind == "material":
                material[p.engine][p.key] = value
            elif p.key == "impulse":
                impulses = value
            else:
                actions[p.engine] = value
        self.system.set_state(state)
        for name, values in material.items():
            self.engines[name].set_parameters(values)
        self.tape.clear()
        self.system.rollout(impulses, actions, self.tape if record else None, on_step)
        return self.system.state()

    def _want_material_grads(self, params: dict[str, np.ndarray]) -> None:
        """Let each engine that can skip them (``material_grads``) compute material gradients only when
        ``params`` holds one of its material parameters (the others' vjp then reports zeros)."""
        wanted = {self.parameters[name].engine for name in params if self.parameters[name].kind == "material"}
        for name, engine in self.engines.items():
            if declares(engine, "material_grads"):
                engine.material_grads = name in wanted

    def evaluate(self, params: dict[str, np.ndarray], grad: bool = False):
        """Loss value, and with ``grad`` its gradient per parameter (same shapes). Running loss
        terms are evaluated at every macro step's state, their gradients fed into the tape's
        backward pass at their step."""
        running: list[tuple[float, dict | None]] = []  # per state: (value, gradient) of the running terms
        on_step = None
        if getattr(self.loss, "has_running", False):
            self.loss.reset_running()

            def on_step(n: int) -> None:
                value, g = self.loss.running(self.system.state())
                running.append((value, g if grad else None))

        final = self.rollout(params, record=grad, on_step=on_step)
        value, dstate = self.loss(final)
        value += sum(v for v, _g in running)
        if not grad:
            return value, None
        self._want_material_grads(params)
        g = self.tape.backward(
            self.system.vjp, dstate, [g for _v, g in running] or None, self.system.restore_checkpoints
        )
        grads = {}
        for name, param_value in params.items():
            p = self.parameters[name]
            if p.kind == "state":
                grads[name] = g.state0[p.engine][p.key]
            elif p.kind == "material":
                grads[name] = g.material[p.engine][p.key]
            elif p.key == "impulse":
                grads[name] = np.stack([gi[self.system.ctrl_index] for gi in g.impulse])
            else:
                plan = self.system.plans[p.engine]
                grads[name] = np.zeros_like(param_value)
                for n, ga in enumerate(g.action[p.engine]):
                    grads[name][plan.segment(n, len(param_value))] += ga
        return value, grads
