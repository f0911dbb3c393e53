"""Newton's method for the cloth's backward-Euler step, a mixin of ``ClothEngine`` (see its module
docstring for the scheme and the tolerance): projected Newton with a round-off aware line search."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.sparse.linalg import splu

from cosim.engines.cloth_contact import ContactSet
from cosim.engines.cloth_linear import SPD_LU
from cosim.errors import SimulationError

LINE_SEARCH_HALVINGS = 30


@dataclass
class StepData:
    """What the incremental potential of one step depends on besides x."""

    x_n: np.ndarray
    x_hat: np.ndarray
    forces: np.ndarray
    material: Any  # ClothMaterial
    contacts: ContactSet | None = None  # the rigid contacts of this step (``attach_rigid_contact``)
    added_mass: np.ndarray | None = None  # (V,) [kg] from the coupling
    mass: np.ndarray = field(init=False)  # (V, 1) [kg] lumped (gravity, damping); inertia: + added mass
    inertia: np.ndarray = field(init=False)


class ClothSolver:
    """``_solve`` and its parts; reads the engine's ``free``, ``free_dofs``, ``_ff``, ``max_iterations``,
    ``_gradient``, ``_potential``, ``_tolerance``, ``_mass_diagonal``, ``_element_hessians`` and ``_factor``
    (a ``ReusedFactorisation``)."""

    def _solve(self, d: StepData, x_pres: np.ndarray) -> tuple[np.ndarray, int, float, float]:
        """Projected Newton from x^ (prescribed vertices at ``x_pres``); (x, iterations, residual, tol)."""
        x = d.x_hat.copy()
        x[~self.free] = x_pres[~self.free]
        tol = self._tolerance(d)
        residual, history, best, alpha, potential = np.inf, [], None, 1.0, None
        for it in range(self.max_iterations + 1):
            g = self._gradient(x, d).reshape(-1)[self.free_dofs]
            residual = float(np.abs(g).max()) if len(g) else 0.0
            if not np.isfinite(residual):
                raise SimulationError(
                    f"cloth '{self.name}': non-finite residual in step {self.steps}, Newton iteration {it}; reduce frame_dt or check the forces"
                )
            if residual <= tol:
                return x, it, residual, tol
            if best is None or residual < best[1]:
                best = (x, residual)
            history.append(residual)
            if _stalled_at_round_off(history, tol):  # the best iterate is as good as float64 allows
                return best[0], it, best[1], tol
            if it == self.max_iterations:
                break
            # after a step the line search had to cut below half, the exact Hessian's model is poor here
            # (cloth_catch, step 963: 52 iterations of steps cut to 1/256..1/2048 with it, 26 so)
            direction = self._direction(x, g, d, exact=alpha >= 0.5)
            x, alpha, potential = self._line_search(x, direction, g, d, potential)
        raise SimulationError(
            f"cloth '{self.name}': Newton did not converge in step {self.steps} within {self.max_iterations} iterations: "
            f"residual ||grad E||_inf = {residual:.3e} N > tolerance {tol:.3e} N; "
            "reduce frame_dt, raise max_iterations or soften the material"
        )

    def _direction(self, x: np.ndarray, g: np.ndarray, d: StepData, exact: bool = True) -> np.ndarray:
        """Newton direction over the free dofs: with the exact Hessian when ``exact`` and it is positive
        definite (then Newton converges quadratically), else with the per-element PSD-projected one
        (always a descent direction, and the stiffer model where elements are compressed or bent; alone
        it converges only linearly once the exact Hessian would do). Solved to float64's floor: a looser
        solve leaves Newton's last iterate noisier (central differences through the step with it)."""
        diagonal = self._mass_diagonal(d.material, d.added_mass)
        for project in (False, True) if exact else (True,):
            H = self._ff.matrix(self._element_hessians(x, d.material, d.contacts, project), diagonal)
            dx = self._factor.solve_spd(H, -g)
            if dx is not None:
                return dx
        return splu(H, **SPD_LU).solve(-g)  # projected, PSD only to round-off: as direct as before

    def _line_search(
        self, x: np.ndarray, dx: np.ndarray, g: np.ndarray, d: StepData, at_x: tuple[float, float] | None = None
    ) -> tuple[np.ndarray, float, tuple[float, float]]:
        """Backtracking on E along the free-dof direction dx: accept a sufficient decrease (Armijo,
        c = 1e-4); once the predicted decrease alpha |g . dx| is below E's round-off (near convergence)
        E cannot rank the points, so accept any step that does not raise E beyond its round-off.
        ``at_x``: ``_potential`` at x where the last line search found it. Returns the new positions, the step
        length alpha taken and ``_potential`` there."""
        E0, noise = self._potential(x, d) if at_x is None else at_x
        slope = float(g @ dx)
        alpha = 1.0
        for _ in range(LINE_SEARCH_HALVINGS):
            trial = x.copy()
            trial.reshape(-1)[self.free_dofs] += alpha * dx
            at_trial = self._potential(trial, d)
            E = at_trial[0]
            if E <= E0 + 1e-4 * alpha * slope or (alpha * abs(slope) <= noise and E <= E0 + noise):
                return trial, alpha, at_trial
            alpha *= 0.5
        return trial, alpha, at_trial


STALL_WINDOW, STALL_FACTOR = 4, 100.0


def _stalled_at_round_off(history: list[float], tol: float) -> bool:
    """Newton has reached float64's floor: its best residual is within ``STALL_FACTOR`` of the
    tolerance (whose round-off floor is an estimate) and the last ``STALL_WINDOW`` iterations did not
    improve on the best before them by 10%. Measured on cloth_catch after 963 steps: quadratic
    convergence to 2.3e-9 N, then 40 iterations between 2.19e-9 and 2.29e-9 (in a later run, iterates
    wandering up to 2.9e-7) against an estimated 1.95e-9; the solver then returns its best iterate."""
    if len(history) <= STALL_WINDOW:
        return False
    best_before = min(history[:-STALL_WINDOW])
    return best_before <= STALL_FACTOR * tol and min(history[-STALL_WINDOW:]) > 0.9 * best_before
