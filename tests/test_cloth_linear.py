"""The cloth's linear solves (``cosim.engines.cloth_linear``): conjugate gradients preconditioned by an
earlier factorisation solve as accurately as a direct LU, detect an indefinite matrix, and let a sheet
factorise a few times a run instead of at every Newton iteration and adjoint step."""

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu, spsolve

from cosim.engines import cloth_linear, cloth_mesh
from cosim.engines.cloth import ClothEngine, ClothMaterial
from cosim.engines.cloth_linear import SPD_LU, preconditioned_cg


def _stiff_grid(n: int = 30, seed: int = 0) -> tuple[sp.csc_matrix, sp.csc_matrix]:
    """A 2D Laplacian on an n x n grid plus a small diagonal (condition ~1e4, SPD), and the same with every
    off-diagonal spring 0-10 % stiffer: a Hessian and the next step's."""
    rng = np.random.default_rng(seed)
    lap1 = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.eye(n)
    A = (sp.kron(lap1, eye) + sp.kron(eye, lap1) + 1e-3 * sp.eye(n * n)).tocoo()
    off = A.row != A.col
    bump = sp.coo_matrix((A.data * off * 0.1 * rng.random(A.nnz), (A.row, A.col)), shape=A.shape)
    bump = 0.5 * (bump + bump.T)
    stiffer = A + bump - sp.diags(np.asarray(bump.sum(axis=1)).ravel())  # rows still sum as before: SPD
    return A.tocsc(), stiffer.tocsc()


def test_cg_with_an_older_factor_solves_as_accurately_as_a_direct_lu():
    """Preconditioned by the LU of the older matrix, the new one is solved to float64's floor in a few
    iterations (without a preconditioner 40 iterations do not reach it), and agrees with a direct solve."""
    old, new = _stiff_grid()
    b = np.random.default_rng(1).standard_normal(new.shape[0])
    lu = splu(old, **SPD_LU)
    calls = []

    def precondition(r):
        calls.append(1)
        return lu.solve(r)

    x, indefinite, _ = preconditioned_cg(new, b, precondition, 25)
    exact = spsolve(new, b)
    assert x is not None and not indefinite
    assert np.abs(x - exact).max() <= 1e-10 * np.abs(exact).max()
    assert len(calls) <= 12, len(calls)  # 8 measured
    assert preconditioned_cg(new, b, lambda r: r, 40).x is None


def test_cg_meets_the_negative_curvature_of_an_indefinite_matrix():
    """Shifted below its smallest eigenvalues the matrix is indefinite: CG reports it (the Newton direction
    then falls back to the projected Hessian, the adjoint to a pivoting LU) instead of returning a solution."""
    old, new = _stiff_grid()
    lowest = np.sort(np.linalg.eigvalsh(new.toarray()))[:5]
    indefinite_matrix = (new - sp.eye(new.shape[0]) * float(lowest[3])).tocsc()  # three negative eigenvalues
    b = np.random.default_rng(2).standard_normal(new.shape[0])
    x, indefinite, _ = preconditioned_cg(indefinite_matrix, b, splu(old, **SPD_LU).solve, 25)
    assert x is None and indefinite


def _sheet(cg_iterations: int) -> ClothEngine:
    mesh = cloth_mesh.rectangle((0.5, 0.5), (12, 12), normal="z")
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
    material = ClothMaterial(k_stretch=1000.0, k_bend=1e-3, density=0.2)
    return ClothEngine(mesh, material, fixed=top, cg_iterations=cg_iterations)


def test_a_falling_sheet_factorises_rarely_and_matches_direct_solves_forward_and_backward():
    """A pinned sheet falling for 12 steps: with the engine's solves it factorises at most twice forward and
    once in the backward pass (a fresh LU for every solve: one a Newton iteration, 1-2 a step, and one an
    adjoint step), ends within the Newton tolerance of the direct run's positions and gets the same gradient of a
    random linear loss to 1e-9."""
    runs = {}
    for cg_iterations in (25, 0):
        engine = _sheet(cg_iterations)
        records = [engine.step({})[1] for _ in range(12)]
        rng = np.random.default_rng(3)
        grad = {"x": rng.standard_normal(engine.x.shape), "v": rng.standard_normal(engine.x.shape)}
        for record in reversed(records):
            grad = engine.vjp(record, {"state": grad})["state"]
        lu = engine.factorisations
        solves = sum(r.iterations for r in records) + len(records)  # Newton directions and adjoint solves
        runs[cg_iterations] = (engine.x.copy(), grad, lu, solves, engine)
    (x, grad, lu, _, engine), (x_direct, grad_direct, lu_direct, solves, _) = runs[25], runs[0]
    assert lu <= 3 and lu_direct == solves >= 30, (lu, lu_direct, solves)
    inertia_stiffness = engine.masses().max() / engine.frame_dt**2  # [N/m]: tolerance [N] / it is a length
    assert np.abs(x - x_direct).max() <= 10 * engine.last_solve["tolerance"] / inertia_stiffness
    for key in ("x", "v"):
        assert np.abs(grad[key] - grad_direct[key]).max() <= 1e-9 * np.abs(grad_direct[key]).max()


def test_an_aged_factor_is_refreshed_where_the_hessian_keeps_changing(monkeypatch):
    """A heavy band of added mass (20x the sheet's own, as material pressing on it) sweeps across the sheet:
    each step's Hessian differs from the last one's along the band, and solves with an old factor take 15-25
    iterations. A solve that took more than STALE_AFTER makes the next factorise afresh, which keeps the
    preconditioned solves at 7.3 iterations on average (12.7 without the refresh) for 20 factorisations in
    40 steps (both asserted with room for another CPU's round-off); the positions end within the Newton
    tolerance of direct solves."""
    iterations = []
    solve = cloth_linear.preconditioned_cg

    def counting(*args):
        result = solve(*args)
        iterations.append(result.iterations)
        return result

    monkeypatch.setattr(cloth_linear, "preconditioned_cg", counting)
    ends = []
    for cg_iterations in (25, 0):
        engine = _sheet(cg_iterations)
        m = engine.masses()
        for k in range(40):
            band = np.abs(engine.mesh.vertices[:, 0] - (-0.25 + 0.5 * k / 40)) < 0.08
            engine.step({"added_mass": np.where(band, 20 * m, 0.0)})
        ends.append(engine.x.copy())
        if cg_iterations:
            factorisations = engine.factorisations
    assert np.mean(iterations) <= 10 and factorisations <= 30, (np.mean(iterations), factorisations)
    inertia_stiffness = engine.masses().max() / engine.frame_dt**2
    assert np.abs(ends[0] - ends[1]).max() <= 10 * engine.last_solve["tolerance"] / inertia_stiffness
