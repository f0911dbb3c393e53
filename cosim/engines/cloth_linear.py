"""The cloth's symmetric linear solves (Newton directions and adjoints): conjugate gradients preconditioned by
an earlier step's sparse factorisation, a fresh factorisation only when that stops working.

Why: a sparse LU of the cloth Hessian costs far more than its solves and grows faster than the mesh (a
2,025-vertex sheet: 51 ms to factorise, 1.4 ms to solve; 10,000 vertices: 850 ms and 16 ms), while the Hessian
changes little from one Newton iteration or step to the next. Preconditioned by the factor of a Hessian a few
steps old, conjugate gradients reach float64's floor in 5-7 iterations on the falling sheet of `cosim bench
cloth` (measured at 2,025 and 10,000 vertices over 6-8 steps). As the factor ages the iterations grow (the
default scene's 169-vertex towel, pressed by the MPM: 4 at first, 15 after 100 solves), so a solve that took
more than ``STALE_AFTER`` makes the next one factorise afresh (an LU costs 35-50 solves with it; refreshed at
8 iterations, a solve averages about 7). Where a solve does not converge within ``REFACTOR_AFTER`` iterations
the matrix at hand is factorised and kept; the result is always checked against the true residual, so a
solve is as accurate as a direct one or it is direct.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu

SPD_LU = {"permc_spec": "MMD_AT_PLUS_A", "diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}
REFACTOR_AFTER = 25  # conjugate-gradient iterations before the matrix at hand is factorised instead
STALE_AFTER = 8  # iterations of a solve beyond which the next solve factorises afresh
ROUND_OFF = 64 * np.finfo(np.float64).eps  # residual / (||A||_inf ||x||_inf) of the order a direct LU leaves


def positive_definite(lu) -> bool:
    """A symmetric matrix factorised without row pivoting (P_r = P_c) is positive definite iff every
    pivot (diagonal of U) is positive."""
    return bool(np.array_equal(lu.perm_r, lu.perm_c) and np.all(lu.U.diagonal() > 0))


class CGResult(NamedTuple):
    x: np.ndarray | None  # None: not converged within the iterations allowed, or A not positive definite
    indefinite: bool  # a search direction p had p^T A p <= 0: A is not positive definite
    iterations: int


def preconditioned_cg(A: sp.spmatrix, b: np.ndarray, precondition, max_iterations: int) -> CGResult:
    """Conjugate gradients for A x = b (A symmetric) preconditioned by the SPD operator ``precondition``, to
    float64's floor: x with ||b - A x||_inf <= ROUND_OFF ||A||_inf ||x||_inf, checked on the true residual."""
    x, r = np.zeros_like(b), b.copy()
    if not np.any(r):
        return CGResult(x, False, 0)
    floor = ROUND_OFF * float(abs(A).sum(axis=1).max())
    z = precondition(r)
    p, rz = z.copy(), float(r @ z)
    for iteration in range(1, max_iterations + 1):
        Ap = A @ p
        curvature = float(p @ Ap)
        if not curvature > 0:
            return CGResult(None, True, iteration)
        alpha = rz / curvature
        x += alpha * p
        r -= alpha * Ap
        enough = floor * np.abs(x).max()
        if np.abs(r).max() <= enough:  # the recurrence's residual: confirm with the true one
            return CGResult(x if np.abs(b - A @ x).max() <= enough else None, False, iteration)
        z = precondition(r)
        rz, rz_old = float(r @ z), rz
        p = z + (rz / rz_old) * p
    return CGResult(None, False, max_iterations)


class ReusedFactorisation:
    """Solves symmetric systems by conjugate gradients preconditioned with the last positive definite matrix
    it factorised, afresh once a solve took more than ``STALE_AFTER`` iterations (see the module docstring);
    ``forget`` drops that factor, so that what follows depends on its own inputs only (a rollout from a
    restored state repeats bit for bit)."""

    def __init__(self, cg_iterations: int = REFACTOR_AFTER) -> None:
        self.cg_iterations = cg_iterations  # before it factorises the matrix at hand (0: every solve is direct)
        self.lu = None
        self.stale = False  # the last solve took more than STALE_AFTER iterations
        self.factorisations = 0  # fresh factorisations so far (for the benchmarks' split)

    def forget(self) -> None:
        self.lu, self.stale = None, False

    def solve_spd(self, A: sp.spmatrix, b: np.ndarray) -> np.ndarray | None:
        """A^-1 b to float64's floor (``preconditioned_cg``) or by a direct solve, or None where A is not
        positive definite."""
        if self.lu is not None and self.cg_iterations > 0 and not self.stale:
            result = preconditioned_cg(A, b, self.lu.solve, self.cg_iterations)
            self.stale = result.iterations > STALE_AFTER
            if result.x is not None or result.indefinite:
                return result.x
        lu = splu(sp.csc_matrix(A), **SPD_LU)
        self.factorisations += 1
        if not positive_definite(lu):
            return None
        self.lu, self.stale = lu, False
        return lu.solve(b)
