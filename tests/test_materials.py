"""Constitutive pieces against closed forms: polar decomposition, stresses, return mapping."""

import numpy as np
import pytest
import taichi as ti

from cosim.engines.materials import Liquid, Plastic, corotated_kirchhoff, polar_rotation
from cosim.engines.moduli import lame_parameters


def random_deformations(n, dim, lo, hi, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        U, _ = np.linalg.qr(rng.standard_normal((dim, dim)))
        V, _ = np.linalg.qr(rng.standard_normal((dim, dim)))
        U[:, 0] *= np.sign(np.linalg.det(U))
        V[:, 0] *= np.sign(np.linalg.det(V))
        s = np.exp(rng.uniform(np.log(lo), np.log(hi), dim))
        out.append(U @ np.diag(s) @ V.T)
    return np.array(out)


@ti.kernel
def _polar(F: ti.types.ndarray(), R: ti.types.ndarray(), dim: ti.template()):
    for i in range(F.shape[0]):
        m = ti.Matrix.zero(float, dim, dim)
        for a, b in ti.static(ti.ndrange(dim, dim)):
            m[a, b] = F[i, a, b]
        r = polar_rotation(m)
        for a, b in ti.static(ti.ndrange(dim, dim)):
            R[i, a, b] = r[a, b]


@pytest.mark.parametrize(
    "dim,lo,hi,tol", [(2, 0.05, 20, 1e-13), (3, 0.99, 1.01, 1e-13), (3, 0.5, 2, 1e-13), (3, 0.05, 20, 1e-13)]
)
def test_polar_rotation_matches_svd(dim, lo, hi, tol):
    """R = U V^T of the SVD to round-off (measured 0.9-9e-15) from near rotations to stretches of 0.05-20:
    the Newton iteration stops on its update's size, not after a fixed count (that left 7e-9 at 0.05-20)."""
    F = random_deformations(200, dim, lo, hi)
    R = np.zeros_like(F)
    _polar(F, R, dim)
    U, _, Vt = np.linalg.svd(F)
    assert np.abs(R - U @ Vt).max() < tol


@ti.kernel
def _apply(
    F: ti.types.ndarray(),
    out: ti.types.ndarray(),
    mat: ti.template(),
    mu: float,
    lam: float,
    ys: float,
    which: ti.template(),
):
    for i in range(F.shape[0]):
        m = ti.Matrix.zero(float, 3, 3)
        for a, b in ti.static(ti.ndrange(3, 3)):
            m[a, b] = F[i, a, b]
        r = ti.Matrix.zero(float, 3, 3)
        if ti.static(which == 0):
            r = mat.project(m, mu, lam, ys)
        else:
            r = mat.kirchhoff(m, ti.Matrix.zero(float, 3, 3), mu, lam, 0.0)
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[i, a, b] = r[a, b]


def test_plastic_return_mapping_lands_on_the_yield_surface():
    """Trial states outside are scaled radially onto |dev e| = sqrt(2/3) ys / (2 mu); inside ones stay."""
    mu, lam = lame_parameters(1e4, 0.3, 3)
    ys = 200.0
    limit = np.sqrt(2 / 3) * ys / (2 * mu)
    F = np.concatenate([random_deformations(50, 3, 0.8, 1.25, seed=3), random_deformations(50, 3, 0.99, 1.01, seed=4)])
    out = np.zeros_like(F)
    _apply(F, out, Plastic(), mu, lam, ys, 0)

    def dev_norm(G):
        e = np.linalg.svd(G, compute_uv=False) - 1
        return np.linalg.norm(e - e.mean(axis=1, keepdims=True), axis=1)

    n_in, n_out = dev_norm(F), dev_norm(out)
    outside = n_in > limit
    assert outside.sum() > 10 and (~outside).sum() > 10
    assert np.allclose(n_out[outside], limit, rtol=1e-8)
    assert np.allclose(out[~outside], F[~outside], atol=1e-12)
    # the volumetric (mean) strain is untouched by the deviatoric return
    s_in = np.linalg.svd(F, compute_uv=False)
    s_out = np.linalg.svd(out, compute_uv=False)
    assert np.allclose((s_in - 1).mean(axis=1), (s_out - 1).mean(axis=1), atol=1e-12)


def test_liquid_stress_is_isotropic_pressure_of_the_volume_ratio():
    """tau = K J (J - 1) I whatever the shape of F: a liquid feels volume change only."""
    mu, lam = lame_parameters(1e4, 0.3, 3)
    K = lam + 2 * mu / 3
    F = random_deformations(50, 3, 0.8, 1.2, seed=5)
    out = np.zeros_like(F)
    _apply(F, out, Liquid(), mu, lam, 0.0, 1)
    J = np.linalg.det(F)
    assert np.allclose(out, (K * J * (J - 1))[:, None, None] * np.eye(3), atol=1e-9)


@ti.kernel
def _corotated(F: ti.types.ndarray(), out: ti.types.ndarray(), mu: float, lam: float):
    for i in range(F.shape[0]):
        m = ti.Matrix.zero(float, 3, 3)
        for a, b in ti.static(ti.ndrange(3, 3)):
            m[a, b] = F[i, a, b]
        r = corotated_kirchhoff(m, mu, lam)
        for a, b in ti.static(ti.ndrange(3, 3)):
            out[i, a, b] = r[a, b]


def test_corotated_stress_is_the_energy_derivative():
    """tau = (d psi / d F) F^T with psi = mu |F - R|^2 + lam/2 (J - 1)^2, checked by central differences."""
    mu, lam = lame_parameters(1e4, 0.3, 3)
    F = random_deformations(5, 3, 0.7, 1.4, seed=7)
    out = np.zeros_like(F)
    _corotated(F, out, mu, lam)

    def psi(G):
        U, _, Vt = np.linalg.svd(G)
        return mu * np.sum((G - U @ Vt) ** 2) + 0.5 * lam * (np.linalg.det(G) - 1) ** 2

    for k in range(len(F)):
        P = np.zeros((3, 3))
        for a in range(3):
            for b in range(3):
                E = np.zeros((3, 3))
                E[a, b] = 1e-6
                P[a, b] = (psi(F[k] + E) - psi(F[k] - E)) / 2e-6
        assert np.allclose(out[k], P @ F[k].T, rtol=1e-6, atol=1e-3)
