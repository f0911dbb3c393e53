"""Rotations: SO(3) exponential, its Jacobians and the hat/vee maps, batched over leading axes.

Every function takes rotation vectors phi as a (..., 3) array (a single (3,) vector works too) and
returns (..., 3, 3) matrices; angles are in radians, phi = angle * unit axis. Conventions (shared by
the rigid engine, the kinematic bodies and the MPM-rigid coupler):

- ``hat(a) @ b = a x b`` (the cross-product matrix [a]x);
- ``exp(phi)`` rotates by |phi| about phi (Rodrigues);
- ``left_jacobian(phi)`` is J_l with exp(phi + d) = exp(J_l(phi) d) exp(phi) to first order in d;
  the right Jacobian is J_r(phi) = J_l(-phi);
- ``axial(M)`` is the vee of M's skew part, doubled: <M, [a]x> = a . axial(M) (the adjoint of ``hat``).

Near phi = 0 the closed forms divide by |phi|, so below ``SMALL_ANGLE`` they are replaced by their
Taylor series to second order in |phi|: with |phi| < 1e-6 the first dropped term is ~|phi|^4 < 1e-24,
far below float64 round-off.
"""

from __future__ import annotations

import numpy as np

SMALL_ANGLE = 1e-6  # [rad] below this, Taylor series replace the closed forms


def hat(phi: np.ndarray) -> np.ndarray:
    """[phi]x, the cross-product matrix: (..., 3) -> (..., 3, 3)."""
    phi = np.asarray(phi)
    z = np.zeros(phi.shape[:-1])
    x, y, w = phi[..., 0], phi[..., 1], phi[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def _series(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """|phi| (..., 1, 1), [phi]x, [phi]x^2 and a safe |phi| (1 where it is below SMALL_ANGLE)."""
    phi = np.asarray(phi)
    t = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = hat(phi)
    return t, K, K @ K, np.where(t < SMALL_ANGLE, 1.0, t)


def exp(phi: np.ndarray) -> np.ndarray:
    """exp([phi]x) = I + sin t / t [phi]x + (1 - cos t) / t^2 [phi]x^2, t = |phi| (Rodrigues)."""
    t, K, K2, ts = _series(phi)
    a = np.where(t < SMALL_ANGLE, 1.0 - t**2 / 6, np.sin(ts) / ts)
    b = np.where(t < SMALL_ANGLE, 0.5 - t**2 / 24, (1 - np.cos(ts)) / ts**2)
    return np.eye(3) + a * K + b * K2


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """J_l(phi) = I + (1 - cos t) / t^2 [phi]x + (t - sin t) / t^3 [phi]x^2, t = |phi|."""
    t, K, K2, ts = _series(phi)
    a = np.where(t < SMALL_ANGLE, 0.5 - t**2 / 24, (1 - np.cos(ts)) / ts**2)
    b = np.where(t < SMALL_ANGLE, 1 / 6 - t**2 / 120, (ts - np.sin(ts)) / ts**3)
    return np.eye(3) + a * K + b * K2


def left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """J_l(phi)^-1 = I - [phi]x / 2 + (1 / t^2 - (1 + cos t) / (2 t sin t)) [phi]x^2, t = |phi|.

    Defined for t < 2 pi (J_l is singular at t = 2 pi); rotation vectors from a log have t <= pi.
    """
    t, K, K2, ts = _series(phi)
    b = np.where(t < SMALL_ANGLE, 1 / 12 + t**2 / 720, 1 / ts**2 - (1 + np.cos(ts)) / (2 * ts * np.sin(ts)))
    return np.eye(3) - 0.5 * K + b * K2


def axial(M: np.ndarray) -> np.ndarray:
    """(M32 - M23, M13 - M31, M21 - M12), so that <M, [a]x> = a . axial(M): (..., 3, 3) -> (..., 3)."""
    M = np.asarray(M)
    return np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)


def rotation_2d(angle: np.ndarray | float) -> np.ndarray:
    """The planar rotation by ``angle`` [rad] (counter-clockwise): (...) -> (..., 2, 2)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def about_axis(angle: np.ndarray | float, axis: int) -> np.ndarray:
    """The rotation by ``angle`` [rad] about coordinate axis ``axis`` (0 = x, 1 = y, 2 = z): (...) -> (..., 3, 3)."""
    angle = np.asarray(angle, dtype=np.float64)
    R = np.broadcast_to(np.eye(3), (*angle.shape, 3, 3)).copy()
    i, j = (axis + 1) % 3, (axis + 2) % 3  # the plane turned, in right-handed order
    c, s = np.cos(angle), np.sin(angle)
    R[..., i, i], R[..., i, j], R[..., j, i], R[..., j, j] = c, -s, s, c
    return R


def euler_xyz(angles: np.ndarray) -> np.ndarray:
    """R = Rz(c) Ry(b) Rx(a) from fixed-axis xyz Euler angles (a, b, c) [rad] (URDF roll-pitch-yaw):
    (..., 3) -> (..., 3, 3)."""
    angles = np.asarray(angles, dtype=np.float64)
    return about_axis(angles[..., 2], 2) @ about_axis(angles[..., 1], 1) @ about_axis(angles[..., 0], 0)


def scene_rotation(value, dim: int) -> np.ndarray:
    """A scene's rotation as a matrix: an angle [rad] in 2D, a rotation vector [rad] in 3D (a plain
    number in 3D means no rotation, the schema's default)."""
    if dim == 2:
        return rotation_2d(float(value))
    vec = np.zeros(3) if isinstance(value, (int, float)) else np.asarray(value, dtype=np.float64)
    return exp(vec)
