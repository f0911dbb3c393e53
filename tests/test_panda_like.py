"""The shipped Panda-like arm (scenes/assets/panda_like/panda_like.urdf) loaded by dartpy.

The URDF and the reference below are both written from Franka's published modified-DH table, so the
forward-kinematics test checks that the URDF's joint origins and axes transcribe that table consistently
with the modified (Craig) DH convention; the q = 0 flange position is also checked against the
well-known value (0.088, 0, 0.926) m.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import dartpy as dart
import numpy as np
import pytest

URDF = Path(__file__).resolve().parent.parent / "scenes" / "assets" / "panda_like" / "panda_like.urdf"

# Franka Emika Panda, modified DH (Craig): rows (a_{i-1}, d_i, alpha_{i-1}), theta_i = q_i.
DH = [
    (0.0, 0.333, 0.0),
    (0.0, 0.0, -math.pi / 2),
    (0.0, 0.316, math.pi / 2),
    (0.0825, 0.0, math.pi / 2),
    (-0.0825, 0.384, -math.pi / 2),
    (0.0, 0.0, math.pi / 2),
    (0.088, 0.0, math.pi / 2),
]
FLANGE_D = 0.107
HAND_YAW = -math.pi / 4  # the hand is turned -45 deg about the flange axis
BOTTLE_OFFSET = 0.1034  # bottle centre on the hand's z axis

# Published limits (Franka "Robot and interface specifications", Panda).
Q_MIN = [-2.8973, -1.7628, -2.8973, -3.0718, -2.8973, -0.0175, -2.8973]
Q_MAX = [2.8973, 1.7628, 2.8973, -0.0698, 2.8973, 3.7525, 2.8973]
DQ_MAX = [2.1750, 2.1750, 2.1750, 2.1750, 2.6100, 2.6100, 2.6100]
TAU_MAX = [87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0]

# Approximate masses written into the URDF (links 1-7: identified values from the literature).
MASSES = {
    "panda_link0": 0.629769,
    "panda_link1": 4.970684,
    "panda_link2": 0.646926,
    "panda_link3": 3.228604,
    "panda_link4": 3.587895,
    "panda_link5": 1.225946,
    "panda_link6": 1.666555,
    "panda_link7": 0.735522,
    "panda_hand": 0.73,
}
BOTTLE_MASS = 0.3


def _rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _trans(x, y, z):
    t = np.eye(4)
    t[:3, 3] = (x, y, z)
    return t


def dh_flange(q) -> np.ndarray:
    """Base -> flange by the modified DH product RotX(alpha) TransX(a) RotZ(theta) TransZ(d)."""
    t = np.eye(4)
    for (a, d, alpha), theta in zip(DH, q):
        t = t @ _rot_x(alpha) @ _trans(a, 0, 0) @ _rot_z(theta) @ _trans(0, 0, d)
    return t @ _trans(0, 0, FLANGE_D)


@pytest.fixture(scope="module")
def skel():
    loader = dart.utils.DartLoader()
    options = loader.getOptions()
    options.mDefaultRootJointType = dart.utils.DartLoaderRootJointType.FIXED
    loader.setOptions(options)
    s = loader.parseSkeleton(dart.common.Uri(f"file://{URDF}"))
    assert s is not None, f"DART could not parse {URDF}"
    return s


def test_structure_seven_revolute_dofs(skel):
    assert skel.getNumDofs() == 7
    joints = {skel.getJoint(i).getName(): skel.getJoint(i) for i in range(skel.getNumJoints())}
    revolute = sorted(n for n, j in joints.items() if j.getType() == "RevoluteJoint")
    assert revolute == [f"panda_joint{i}" for i in range(1, 8)]
    # everything else (root weld, hand, bottle) is fixed and carries no dof
    others = {n: j for n, j in joints.items() if n not in revolute}
    assert all(j.getType() == "WeldJoint" and j.getNumDofs() == 0 for j in others.values()), others
    assert skel.getRootJoint().getType() == "WeldJoint"
    bodies = [skel.getBodyNode(i).getName() for i in range(skel.getNumBodyNodes())]
    assert bodies == [f"panda_link{i}" for i in range(8)] + ["panda_hand", "bottle"]
    for i in range(1, 8):
        np.testing.assert_array_equal(joints[f"panda_joint{i}"].getAxis(), [0.0, 0.0, 1.0])
        assert skel.getDof(i - 1).getName() == f"panda_joint{i}"


def test_joint_limits_are_the_published_values(skel):
    for i in range(7):
        dof = skel.getDof(i)
        got = (
            dof.getPositionLowerLimit(),
            dof.getPositionUpperLimit(),
            dof.getVelocityLowerLimit(),
            dof.getVelocityUpperLimit(),
            dof.getForceLowerLimit(),
            dof.getForceUpperLimit(),
        )
        want = (Q_MIN[i], Q_MAX[i], -DQ_MAX[i], DQ_MAX[i], -TAU_MAX[i], TAU_MAX[i])
        assert got == pytest.approx(want, abs=1e-12), dof.getName()
        assert 0.0 < dof.getDampingCoefficient() <= 1.0  # "a little" damping


def _configs():
    rng = np.random.default_rng(7)
    qs = [
        np.zeros(7),  # outside joint 4/6 limits, but kinematics does not care
        np.array([0.0, -math.pi / 4, 0.0, -3 * math.pi / 4, 0.0, math.pi / 2, math.pi / 4]),  # "ready"
        np.array(Q_MIN),
        np.array(Q_MAX),
    ]
    qs += [rng.uniform(Q_MIN, Q_MAX) for _ in range(6)]
    return qs


@pytest.mark.parametrize("k", range(10))
def test_forward_kinematics_matches_modified_dh(skel, k):
    q = _configs()[k]
    skel.setPositions(q)
    np.testing.assert_array_equal(skel.getPositions(), q)  # setPositions silently ignores a wrong length
    want_hand = dh_flange(q) @ _rot_z(HAND_YAW)
    hand = skel.getBodyNode("panda_hand").getWorldTransform().matrix()
    assert np.abs(hand[:3, 3] - want_hand[:3, 3]).max() < 1e-9  # metres
    assert np.abs(hand[:3, :3] - want_hand[:3, :3]).max() < 1e-9
    # bottle: centre 0.1034 m along the approach axis, its axis (bottle z) along the hand's x axis
    bottle = skel.getBodyNode("bottle").getWorldTransform().matrix()
    want_centre = want_hand @ np.array([0.0, 0.0, BOTTLE_OFFSET, 1.0])
    assert np.abs(bottle[:3, 3] - want_centre[:3]).max() < 1e-9
    assert np.abs(bottle[:3, 2] - want_hand[:3, 0]).max() < 1e-9


def test_flange_at_zero_is_the_known_position(skel):
    # Independent anchor: with q = 0 the Panda's flange sits at (a7, 0, d1 + d3 + d5 - d_flange).
    skel.setPositions(np.zeros(7))
    hand = skel.getBodyNode("panda_hand").getWorldTransform().matrix()
    np.testing.assert_allclose(hand[:3, 3], [0.088, 0.0, 0.926], atol=1e-12)
    np.testing.assert_allclose(hand[:3, 2], [0.0, 0.0, -1.0], atol=1e-12)  # approach axis points down


def test_masses(skel):
    bodies = {skel.getBodyNode(i).getName(): skel.getBodyNode(i) for i in range(skel.getNumBodyNodes())}
    for name, m in MASSES.items():
        assert bodies[name].getMass() == pytest.approx(m, rel=1e-12), name
    arm = sum(bodies[n].getMass() for n in MASSES)
    assert 17.0 <= arm <= 18.5  # arm + hand; Franka states about 18 kg
    assert arm == pytest.approx(17.421901, abs=1e-9)
    assert bodies["bottle"].getMass() == pytest.approx(BOTTLE_MASS)
    assert skel.getMass() == pytest.approx(arm + BOTTLE_MASS, abs=1e-12)


def _primitive_inertia(geometry, m):
    if geometry.tag == "cylinder":
        r, h = float(geometry.get("radius")), float(geometry.get("length"))
        side = m * (3 * r * r + h * h) / 12
        return np.diag([side, side, m * r * r / 2])
    x, y, z = (float(v) for v in geometry.get("size").split())
    return np.diag([m * (y * y + z * z), m * (x * x + z * z), m * (x * x + y * y)]) / 12


def _rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _rpy(r, p, y):
    """URDF fixed-axis roll-pitch-yaw: R = Rz(y) Ry(p) Rx(r)."""
    return (_rot_z(y) @ _rot_y(p) @ _rot_x(r))[:3, :3]


def test_inertials_are_the_solid_primitives(skel):
    """Each link: one collision primitive; COM at its centre; inertia = solid-primitive formula, as DART read it."""
    root = ET.parse(URDF).getroot()
    geoms = root.findall(".//geometry/*")
    assert geoms and {g.tag for g in geoms} <= {"box", "cylinder", "sphere"}  # primitives only, no meshes
    for link in root.findall("link"):
        name = link.get("name")
        (col,) = link.findall("collision")
        origin = col.find("origin")
        xyz = np.array([float(v) for v in origin.get("xyz").split()])
        rot = _rpy(*(float(v) for v in origin.get("rpy").split()))
        body = skel.getBodyNode(name)
        m = body.getMass()
        want = rot @ _primitive_inertia(col.find("geometry")[0], m) @ rot.T
        np.testing.assert_allclose(body.getInertia().getMoment(), want, rtol=1e-8, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(body.getLocalCOM(), xyz, atol=1e-12, err_msg=name)
    bottle = root.find("link[@name='bottle']/collision/geometry/cylinder")
    assert (float(bottle.get("radius")), float(bottle.get("length"))) == (0.035, 0.2)
