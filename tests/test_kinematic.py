"""Prescribed rigid motions: the pose integrates the twist, segments join, cycles repeat."""

import math

import numpy as np
import pytest

from cosim.engines.kinematic import Motion, Segment, constant, rotation_about


def check_twist_is_pose_derivative(motion: Motion, times, eps=1e-6):
    """Central differences of the pose equal the twist: dp/dt = v, dR/dt R^T = [w]x."""
    for t in times:
        (p_plus, R_plus), (p_minus, R_minus) = motion.pose(t + eps), motion.pose(t - eps)
        v, w = motion.twist(t)
        assert np.allclose((p_plus - p_minus) / (2 * eps), v, atol=1e-6), t
        spin = (R_plus - R_minus) / (2 * eps) @ motion.pose(t)[1].T
        if motion.dim == 2:
            assert np.allclose(spin, [[0, -w], [w, 0]], atol=1e-6), t
        else:
            assert np.allclose(spin, [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], atol=1e-6), t


def test_constant_twist_3d():
    m = constant([0.5, 0.5, 0.5], np.eye(3), [0.1, 0.0, -0.2], np.array([0.0, 2.0, 0.5]))
    p, R = m.pose(1.5)
    assert np.allclose(p, [0.65, 0.5, 0.2])
    assert np.allclose(R, rotation_about(np.array([0.0, 2.0, 0.5]), 1.5, 3)) and np.allclose(R @ R.T, np.eye(3))
    check_twist_is_pose_derivative(m, [0.1, 0.7, 2.3])


def test_a_3d_body_without_spin_may_give_a_scalar_zero():
    """Scenes and tests write angular_velocity 0.0 for a body that does not turn, in 3D too."""
    R0 = rotation_about(np.array([0.3, -0.2, 0.1]), 1.0, 3)
    m = constant([0.2, 0.0, 0.0], R0, [0.0, 0.0, 0.0], 0.0)
    assert np.array_equal(m.pose(2.0)[1], R0)
    assert np.array_equal(rotation_about(np.array([0.0, 2.0, 0.5]), 0.0, 3), np.eye(3))


def test_piecewise_shake_at_constant_speed_repeats():
    """Left 0.25 s, right 0.5 s, left 0.25 s at 0.4 m/s: a closed cycle, so the body returns every period."""
    segs = [
        Segment(0.25, np.array([-0.4, 0.0]), 0.0),
        Segment(0.5, np.array([0.4, 0.0]), 0.0),
        Segment(0.25, np.array([-0.4, 0.0]), 0.0),
    ]
    m = Motion("piecewise", np.array([0.5, 0.5]), np.eye(2), segs, repeat=True)
    for t in (0.0, 1.0, 2.0, 7.0):
        assert np.allclose(m.pose(t)[0], [0.5, 0.5])
    assert np.allclose(m.pose(3.25)[0], [0.4, 0.5])
    assert np.allclose(m.twist(3.3)[0], [0.4, 0.0])
    check_twist_is_pose_derivative(m, [0.1, 0.4, 1.9, 5.6])


def test_piecewise_rotation_then_rest():
    segs = [Segment(0.5, np.array([0.0, 0.2]), math.pi), Segment(0.5, np.array([0.1, 0.0]), 0.0)]
    m = Motion("piecewise", np.array([0.3, 0.3]), np.eye(2), segs)
    p, R = m.pose(2.0)
    assert np.allclose(p, [0.35, 0.4]) and np.allclose(R, rotation_about(math.pi, 0.5, 2))
    assert np.allclose(m.twist(2.0)[0], 0.0) and m.twist(2.0)[1] == 0.0
    check_twist_is_pose_derivative(m, [0.2, 0.7])


def test_sinusoidal_shake():
    m = Motion("shake", np.array([0.5, 0.4]), np.eye(2), amplitude=np.array([0.05, 0.0]), frequency=2.0, phase=0.3)
    assert np.allclose(m.pose(0.0)[0], [0.5, 0.4])
    assert np.allclose(m.pose(0.5)[0], [0.5, 0.4])  # whole periods
    check_twist_is_pose_derivative(m, [0.05, 0.31, 0.77])


def test_waypoints_pass_through_their_points_then_rest():
    pts = np.array([[0.2, 0.2, 0.2], [0.4, 0.2, 0.2], [0.4, 0.5, 0.3]])
    m = Motion("waypoints", pts[0], np.eye(3), times=np.array([0.0, 1.0, 3.0]), positions=pts)
    for t, q in zip((0.0, 1.0, 3.0, 9.0), (pts[0], pts[1], pts[2], pts[2])):
        assert np.allclose(m.pose(t)[0], q)
    check_twist_is_pose_derivative(m, [0.5, 2.0])
    assert np.allclose(m.twist(5.0)[0], 0.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_point_velocity_is_the_rigid_motion_of_a_body_point(dim):
    """v_c = v + w x (x - p): follow a body point through the pose and difference it."""
    w = 1.3 if dim == 2 else np.array([0.4, -1.1, 0.7])
    m = constant(np.full(dim, 0.5), np.eye(dim), np.linspace(0.1, 0.3, dim), w)
    r_body = np.linspace(0.05, -0.08, dim)
    t, eps = 0.8, 1e-6
    x = lambda tt: m.pose(tt)[0] + m.pose(tt)[1] @ r_body
    assert np.allclose(m.point_velocity(t, x(t)), (x(t + eps) - x(t - eps)) / (2 * eps), atol=1e-7)


@pytest.mark.parametrize("dim", [2, 3])
def test_a_repeated_spinning_cycle_poses_as_its_summed_twists(dim):
    """A cycle of three segments with spin about one axis (so turns add as angles), repeated: the pose
    after many cycles is p0 + sum v_j tau_j and the rotation by sum w_j tau_j, tau_j the time spent in
    segment j so far, whatever the cycle's shift and turn are cached as (``Motion._cycle``)."""
    rng = np.random.default_rng(4)
    durations = [0.13, 0.31, 0.07]
    velocities = rng.normal(size=(3, dim))
    spins = rng.normal(size=3)
    axis = np.array([0.0, 0.0, 1.0])
    segments = [Segment(d, v, float(w) if dim == 2 else w * axis) for d, v, w in zip(durations, velocities, spins)]
    p0 = rng.normal(size=dim)
    motion = Motion("piecewise", p0, np.eye(dim), segments, repeat=True)
    period = sum(durations)
    for t in [0.0, 0.2, 3.7, 41.05, 123.456]:
        cycles, rest = divmod(t, period)
        spent = np.array([cycles * d + min(max(rest - sum(durations[:j]), 0.0), d) for j, d in enumerate(durations)])
        p, R = motion.pose(t)
        np.testing.assert_allclose(p, p0 + spent @ velocities, rtol=0, atol=1e-9)
        angle = spent @ spins
        want = rotation_about(angle if dim == 2 else angle * axis, 1.0, dim)
        np.testing.assert_allclose(R, want, rtol=0, atol=1e-9)
        check_twist_is_pose_derivative(motion, [t + 1e-3])
