"""Adjoint gradients against central finite differences along random directions.

Each direction is judged on the disagreement |adjoint - difference| against a stated scale:
the larger of |adjoint|, |difference| and the difference's noise floor, an estimate of its own
error measured on it (``check_gradients``). A disagreement within that floor cannot be resolved
by finite differences: such a direction passes and says so (``DirectionCheck.verdict``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

ULP = float(np.finfo(np.float64).eps)  # the losses are float64 numbers
NOISE_FACTOR = 2.0  # the floor: this times |difference at h - difference at h/2|


@dataclass
class DirectionCheck:
    param: str
    direction: int
    adjoint: float  # g . d
    finite_difference: float  # (L(p + h d) - L(p - h d)) / (2 h)
    relative_error: float  # |adjoint - finite_difference| / max(|adjoint|, |finite_difference|, noise_floor)
    noise_floor: float = 0.0  # the finite difference's own error estimate (round-off and truncation)
    step: float = 0.0  # h, a fraction of the parameter's scale

    def verdict(self, tolerance: float) -> str:
        """'ok': relative error within ``tolerance``; 'noise': above it, but the adjoint and the difference
        differ by no more than the difference's noise floor (finite differences cannot tell them apart
        there: it passes, reported as such); 'fail': a disagreement the difference resolves."""
        if self.relative_error <= tolerance:
            return "ok"
        return "noise" if abs(self.adjoint - self.finite_difference) <= self.noise_floor else "fail"

    def passed(self, tolerance: float) -> bool:
        return self.verdict(tolerance) != "fail"


def relative_error(adjoint: float, difference: float, noise_floor: float) -> float:
    """|adjoint - difference| / max(|adjoint|, |difference|, noise_floor); 0 only when they are equal.
    An adjoint of 0 against a difference above the floor is 1; below it, the difference over the floor."""
    gap = abs(adjoint - difference)
    return 0.0 if gap == 0 else gap / max(abs(adjoint), abs(difference), noise_floor)


def central_difference(evaluate, params: dict, name: str, d: np.ndarray, h: float) -> tuple[float, float, float]:
    """(L(p + h d) - L(p - h d), the central difference at step h, the larger |L| of the two) along d
    in parameter ``name``."""
    plus = evaluate(dict(params, **{name: params[name] + h * d}), False)[0]
    minus = evaluate(dict(params, **{name: params[name] - h * d}), False)[0]
    return plus - minus, (plus - minus) / (2 * h), max(abs(plus), abs(minus))


def check_gradients(
    evaluate: Callable[[dict[str, np.ndarray], bool], tuple[float, dict | None]],
    params: dict[str, np.ndarray],
    names: list[str],
    scales: dict[str, float | np.ndarray],
    directions: int = 3,
    rel_step: float = 1e-6,
    seed: int = 0,
    tolerance: float = 1e-5,
) -> list[DirectionCheck]:
    """Compare g . d with central differences along random directions d.

    ``scales[name]`` is the parameter's natural size (dx for positions, E for
    E, ...; a number, or an array per entry that broadcasts to the parameter);
    the direction is a random one of unit RMS per entry times the scale, the
    step ``rel_step`` along it, so every entry is perturbed by a comparable
    relative amount. A parameter of one entry (one body's E) has one direction up to sign, which
    would only repeat the same rollouts: it is checked along one. Run in float64: the truncation
    error is O(eps^2) and the round-off O(1e-16 |L| / eps); when the loss changes by less than 1e-10 |L| (a weak
    parameter such as E) the step grows tenfold, at most three times, so the
    round-off stays below ~1e-6 relative. Growing further is not safe: contact
    models switch at distance thresholds, and a large step straddles such a
    switch (measured: a rigid action's difference was 6% off at 1000x the step,
    1e-7 at 10x). With 1e-9 |L| make_taco's 10-step check (its controls move the
    Chamfer loss by 6e-11 of itself at the first step) grew to 100x and was 3.2e-4
    off, through the loss's curvature; at 10x, 5e-6.

    The noise floor of a difference is measured, not assumed: the difference is taken again at
    h / 2, which doubles its round-off and quarters its truncation error, so the two disagree by
    about the larger of the two errors; the floor is ``NOISE_FACTOR`` (2) times that disagreement
    (two noisy values can disagree by less than either one's noise), and never less than one ulp
    of the loss over h (the rounding of L(p + h d) and L(p - h d) alone). A model such as
    eps_machine |L| / h would undercount what a rollout accumulates over thousands of operations
    and what a cloth's Newton solve leaves at its tolerance, and would pass noise as a gradient
    (or fail a right adjoint against noise). The floor costs two more rollouts, so it is measured
    only for a direction that the ulp floor alone would judge above ``tolerance``: where the adjoint
    and the difference agree, a larger floor could only lower the error further.
    """
    rng = np.random.default_rng(seed)
    value, grads = evaluate(params, True)
    results = []
    for name in names:
        for k in range(directions if params[name].size > 1 else 1):
            d = rng.standard_normal(params[name].shape)
            d *= scales[name] / np.sqrt(np.mean(d * d))
            eps = rel_step
            for attempt in range(4):
                if attempt:
                    eps *= 10.0
                change, fd, size = central_difference(evaluate, params, name, d, eps)
                if abs(change) >= 1e-10 * abs(value):
                    break
            fd, ad = float(fd), float(np.sum(grads[name] * d))
            noise = ULP * size / eps
            if relative_error(ad, fd, noise) > tolerance:
                half = central_difference(evaluate, params, name, d, eps / 2)[1]
                noise = max(NOISE_FACTOR * abs(fd - half), noise)
            results.append(DirectionCheck(name, k, ad, fd, relative_error(ad, fd, noise), noise, eps))
    return results


def report_gradcheck(results: list, tol: float, steps: int) -> int:
    """Print each direction (adjoint, difference, the difference's noise floor, relative error, and a
    note where the disagreement is within that floor) and the verdict; a ``GradientCheckError`` on a
    disagreement beyond ``tol`` that the difference resolves."""
    from cosim.errors import GradientCheckError

    print(f"{'param':>8} {'dir':>4} {'adjoint':>16} {'finite diff':>16} {'noise floor':>11} {'rel error':>10}")
    for r in results:
        note = "  within the noise floor: unresolved, passes" if r.verdict(tol) == "noise" else ""
        print(
            f"{r.param:>8} {r.direction:>4} {r.adjoint:>16.9e} {r.finite_difference:>16.9e} {r.noise_floor:>11.2e} "
            f"{r.relative_error:>10.2e}{note}"
        )
    print(
        "rel error = |adjoint - finite diff| / max(|adjoint|, |finite diff|, noise floor); noise floor = "
        "one ulp of the loss over h, or where that fails the tolerance 2 |finite diff at h - at h/2|"
    )
    if all(r.adjoint == 0 and r.finite_difference == 0 for r in results):
        print(
            f"warning: every gradient is zero over {steps} steps: the parameters do not reach the loss yet; use --steps"
        )
    resolved = [r for r in results if r.verdict(tol) != "noise"]
    unresolved = len(results) - len(resolved)
    worst = max((r.relative_error for r in resolved), default=0.0)
    within = f"; {unresolved} of {len(results)} directions within their noise floor" if unresolved else ""
    print(f"max relative error: {worst:.3e} (tolerance {tol:g}){within}")
    if unresolved == len(results):
        print("warning: no direction rises above the finite differences' noise: the check resolves nothing")
    failed = [r for r in results if not r.passed(tol)]
    if failed:
        raise GradientCheckError(
            f"adjoint and finite differences disagree: {worst:.3e} > {tol:g} "
            f"({len(failed)} of {len(results)} directions, above their noise floor)"
        )
    return 0
