"""cosim.engines.so3 against SciPy's rotations and against central differences.

Tolerances: the closed forms are exact up to float64 round-off (entries are O(1), so a few ulps,
1e-14 absolute); central differences of exp with step h = 1e-6 have truncation error ~h^2 |d^3 exp|
~ 1e-12 and round-off ~eps / h ~ 1e-10, hence 1e-8. Just above the series threshold (1e-6 rad) the
closed form's (1 - cos t) / t^2 loses ~4 digits to cancellation (1 - cos t ~ 5e-13 against an ulp of
1e-16) and multiplies [phi]x ~ 1e-6, so J_l is good to ~1e-10 there: products with J_l get 1e-9.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cosim.engines import so3

RNG = np.random.default_rng(7)
# random vectors, angles up to just below pi, and angles on both sides of the series threshold
ANGLES = np.concatenate([RNG.uniform(0, 3.1, 6), [0.0, 1e-12, 1e-8, 0.999e-6, 1.001e-6, 1e-4]])
AXES = RNG.normal(size=(len(ANGLES), 3))
PHIS = ANGLES[:, None] * AXES / np.linalg.norm(AXES, axis=1, keepdims=True)


def test_hat_is_the_cross_product_and_axial_its_adjoint():
    a, b = RNG.normal(size=(4, 5, 3)), RNG.normal(size=(4, 5, 3))
    assert so3.hat(a).shape == (4, 5, 3, 3)
    assert np.allclose((so3.hat(a) @ b[..., None])[..., 0], np.cross(a, b), rtol=0, atol=1e-14)
    assert np.allclose(so3.hat(a[0, 0]) @ b[0, 0], np.cross(a[0, 0], b[0, 0]), rtol=0, atol=1e-14)  # single vector
    M = RNG.normal(size=(4, 5, 3, 3))
    assert np.allclose(np.sum(M * so3.hat(a), axis=(-2, -1)), np.sum(a * so3.axial(M), axis=-1), rtol=0, atol=1e-13)


def test_exp_matches_scipy_batched_and_single():
    R = so3.exp(PHIS)
    assert R.shape == (len(PHIS), 3, 3)
    assert np.allclose(R, Rotation.from_rotvec(PHIS).as_matrix(), rtol=0, atol=1e-14)
    assert np.allclose(so3.exp(PHIS[0]), R[0], rtol=0, atol=0)  # a (3,) vector gives the same (3, 3)
    assert np.array_equal(so3.exp(np.zeros(3)), np.eye(3))


@pytest.mark.parametrize("t", [1e-12, 1e-8, 0.999e-6, 1.001e-6])
def test_exp_keeps_tiny_rotations(t):
    """Near 0, R - I is lost to round-off next to I, so check the skew part directly:
    axial(R) / 2 = sin(t) / t phi, relative to |phi| (the Taylor branch must not drop it)."""
    phi = t * np.array([0.6, -0.8, 0.0])
    assert np.allclose(so3.axial(so3.exp(phi)) / 2, np.sin(t) / t * phi, rtol=1e-14, atol=0)


def _fd_left_jacobian(phi: np.ndarray, h: float = 1e-6) -> np.ndarray:
    """Column k: vee of d/de exp(phi + e e_k) exp(phi)^T at e = 0, by central differences."""
    cols = []
    for e in np.eye(3):
        dR = (so3.exp(phi + h * e) - so3.exp(phi - h * e)) / (2 * h)
        cols.append(so3.axial(dR @ so3.exp(phi).T) / 2)
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("k", range(len(ANGLES)))
def test_left_jacobian_matches_central_differences(k):
    phi = PHIS[k]
    assert np.allclose(so3.left_jacobian(phi), _fd_left_jacobian(phi), rtol=0, atol=1e-8)


def test_left_jacobian_batched_and_its_inverse():
    J = so3.left_jacobian(PHIS)
    assert np.allclose(J, np.stack([so3.left_jacobian(p) for p in PHIS]), rtol=0, atol=0)
    assert np.allclose(so3.left_jacobian_inv(PHIS) @ J, np.eye(3), rtol=0, atol=1e-9)  # see the docstring
    # the right Jacobian J_r(phi) = J_l(-phi) = exp(phi)^T J_l(phi)
    assert np.allclose(so3.left_jacobian(-PHIS), np.swapaxes(so3.exp(PHIS), -1, -2) @ J, rtol=0, atol=1e-9)


def test_planar_axis_and_euler_rotations_match_scipy():
    angles = RNG.uniform(-np.pi, np.pi, size=(5, 3))
    assert np.allclose(so3.euler_xyz(angles), Rotation.from_euler("xyz", angles).as_matrix(), rtol=0, atol=1e-14)
    for axis in range(3):
        expected = Rotation.from_rotvec(angles[:, :1] * np.eye(3)[axis]).as_matrix()
        assert np.allclose(so3.about_axis(angles[:, 0], axis), expected, rtol=0, atol=1e-14)
    assert np.allclose(so3.rotation_2d(angles[:, 0]), so3.about_axis(angles[:, 0], 2)[:, :2, :2], rtol=0, atol=0)
    assert so3.rotation_2d(0.5).shape == (2, 2)
