"""The gradient problem of the accuracy benchmark: the adjoint of the vibrating bar against its closed form.

The free strip of ``BarVibration`` started in its first mode has the modal displacement
q(t) = (v0 / omega) sin(omega t), omega proportional to sqrt(E). The adjoint's d q(t_end) / d ln E
(``Objective`` with q as the loss, the tape through every substep) is compared with
``accuracy_measures.bar_modal_gradient`` at t_end about one period (where the value is least
sensitive to a phase error, so the comparison tests the gradient rather than the period again).
Central differences of the same discretisation are reported beside it (``adjoint_vs_fd``): that
is the consistency of the adjoint, not its accuracy.
"""

from __future__ import annotations

import time

import numpy as np

from cosim.bench import accuracy_measures as am
from cosim.bench.accuracy_problem import Setting
from cosim.bench.accuracy_soft import BarVibration


class BarGradient(BarVibration):
    """d q(t_end) / d ln E of the free bar by the adjoint, t_end about one period."""

    name = "gradient"
    title = "gradient: adjoint d(modal displacement)/d ln E of the bar"
    error_measure = "|g - g_exact| / |g_exact|, g = d q(t_end) / d ln E by the adjoint (forward + backward timed)"
    source = "closed form: dq/dlnE = (v0 / 2) (t cos(omega t) - sin(omega t) / omega), omega of the Rayleigh-Love bar"
    default = Setting(64, 0.3, "float64")  # gradcheck and optimize run in float64
    periods = 1.0

    def loss(self, context: dict):
        """q of the final state, and its gradient (``Objective``'s loss contract)."""
        from cosim.losses import zeros_like

        rest, mass = context["rest"], context["mass"]
        phi = np.cos(np.pi * (rest[:, 0] - self.x0) / self.length)
        weight = mass * phi / np.sum(mass * phi**2)

        def q(state: dict) -> tuple[float, dict]:
            grad = zeros_like(state)
            grad["mpm"]["x"][:, 0] = weight
            return self.modal(state["mpm"]["x"], context), grad

        return q

    def run(self, setting: Setting) -> dict:
        """The adjoint gradient, timed (wall and CPU seconds of forward + backward, after one evaluation
        that compiles), and
        central differences over the same rollout (relative step 1e-4 in float64, 1e-3 in float32)."""
        from cosim.adjoint.objective import Objective

        sim = self.build(setting, requires_grad=True)
        context = self.prepare(sim)  # before the objective, which keeps the initial state
        objective = Objective(sim, loss=self.loss(context))
        E = objective.initial_params()["E"]
        objective.evaluate({"E": E}, grad=True)
        t0, c0 = time.perf_counter(), time.process_time()
        _, grads = objective.evaluate({"E": E}, grad=True)
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        eps = 1e-4 if setting.precision == "float64" else 1e-3
        plus = objective.evaluate({"E": E * (1 + eps)})[0]
        minus = objective.evaluate({"E": E * (1 - eps)})[0]
        gradient = float(np.sum(grads["E"] * E))
        fd = (plus - minus) / (2 * eps)
        t_end = sim.steps * sim.frame_dt
        return {
            "gradient": gradient,
            "finite_difference": float(fd),
            "adjoint_vs_fd": am.relative_error(gradient, fd),
            "t_end": t_end,
            "seconds": seconds,
            "cpu_seconds": cpu_seconds,
            "sim_seconds": t_end,
            "particles": int(sim.mpm.n_particles),
            "substeps": sim.steps * sim.grad_substeps,
        }

    def error(self, observation: dict, reference: dict | None) -> float:
        exact = am.bar_modal_gradient(self.v0, self.omega, observation["t_end"])
        return am.relative_error(observation["gradient"], exact)
