"""Scalar losses of a coupled system's rollout, with their gradients (NumPy).

A loss is a weighted sum of terms (``cosim.losses.terms``); a term reads the final state
{engine name: state} (``CoupledSystem.state``) or, when ``running``, every macro step's
state (summed). Each returns ``(value, dL/dstate)`` of the same structure; entries a
term does not depend on get zeros. The tape (``Objective``) feeds a running term's
gradient in at its step during the backward pass.
"""

from __future__ import annotations

import numpy as np

from cosim.losses.terms import make_term, pose_goal, zeros_like

__all__ = ["Loss", "pose_goal", "zeros_like"]


class Loss:
    """The scene's loss (``loss:`` section), bound to the points or joints its terms read.

    ``values`` holds each term's last value by name (``"<type>"``, or ``"<type>:<body>"``,
    numbered when repeated): the optimiser logs them.
    """

    def __init__(
        self, spec, dim: int, seed: int, slices, mass, rigid=None, cloths=None, dx: float = 0.0, source_dir=None
    ):
        self.terms = []
        names: list[str] = []
        for i, term in enumerate(spec.all_terms()):
            name = term.type if term.body is None else f"{term.type}:{term.body}"
            name = name if name not in names else f"{name}#{i}"
            names.append(name)
            key = "loss" if not spec.terms else f"loss.terms[{i}]"
            fn = make_term(term, dim, seed, slices, mass, rigid, cloths, dx, source_dir, key)
            self.terms.append((name, float(term.weight), bool(term.running), fn))
        self.values: dict[str, float] = {name: 0.0 for name in names}

    @classmethod
    def for_system(cls, system) -> Loss:
        """The loss of the scene ``system`` was built from."""
        from cosim.trajectory import cloth_engines

        cloths = cloth_engines(system)
        x0 = system.initial["mpm"]["x"]
        return cls.for_scene(system.scene, system.slices, x0, system.mpm.mass, system.engines.get("dart"), cloths)

    @classmethod
    def for_scene(cls, scene, slices: dict, x0: np.ndarray, mass: np.ndarray, rigid=None, cloths=()) -> Loss:
        """The loss of ``scene`` bound to its MPM particles (``slices`` per body into the initial positions
        ``x0`` (N, d) [m] and masses ``mass`` (N,) [kg]), its DART engine ``rigid`` and cloth engines."""
        cloth_names = {c.name for c in cloths}
        spec = scene.loss

        def bind(term):  # pose targets of MPM bodies start from the body's initial positions
            if term.type == "pose_target" and term.body not in cloth_names:
                return term.model_copy(update={"rest_positions": x0[slices[term.body]]})
            return term

        spec = spec.model_copy(update={"terms": [bind(t) for t in spec.terms]}) if spec.terms else bind(spec)
        return cls(spec, scene.dim, scene.seed, slices, mass, rigid, list(cloths), scene.dx, scene.source_dir)

    @property
    def has_running(self) -> bool:
        return any(running for _n, _w, running, _f in self.terms)

    def _sum(self, state, running: bool) -> tuple[float, dict]:
        grad = zeros_like(state)
        total = 0.0
        for name, weight, is_running, fn in self.terms:
            if is_running == running:
                value = fn(state, grad, weight)
                self.values[name] = self.values[name] + value if running else value
                total += weight * value
        return total, grad

    def __call__(self, state: dict[str, dict[str, np.ndarray]]) -> tuple[float, dict]:
        """The final-state terms: (value, dL/dstate)."""
        return self._sum(state, running=False)

    def running(self, state: dict[str, dict[str, np.ndarray]]) -> tuple[float, dict]:
        """The running terms at one step's state: (their share of the value, its gradient)."""
        return self._sum(state, running=True)

    def reset_running(self) -> None:
        """Start a new rollout's sums of the running terms."""
        for name, _w, running, _f in self.terms:
            if running:
                self.values[name] = 0.0
