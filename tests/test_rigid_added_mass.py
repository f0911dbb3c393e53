"""DART's step with a coupling's added mass: the velocity change against the closed form (M + A) dv = dt F,
and every vjp block, the added mass's included, against central differences over the two-pass step."""

from __future__ import annotations

import numpy as np
import pytest
from test_rigid import DT, SYSTEMS, VJP_RTOL, central, free_body, rel_err

from cosim.engines.rigid import RigidEngine


def _random_added(rng, bodies: int) -> np.ndarray:
    """Symmetric positive definite 6x6 added masses [kg, kg m, kg m^2], one per body, about the body's weight."""
    B = rng.normal(size=(bodies, 6, 6)) * 0.3
    return B @ np.swapaxes(B, 1, 2) + 0.5 * np.eye(6)


def test_a_free_body_under_a_force_accelerates_as_its_mass_plus_the_added_mass():
    """A free box (no gravity) pushed by a world force F through its centre of mass with an added mass a I on
    its linear dofs: dv = dt F / (m + a), to round-off; the added mass's rotational block spins it
    as a rotational inertia I_body + A_ww would."""
    eng = RigidEngine([free_body("passive", q0=(0, 0, 0, 0, 0, 0), qd0=(0, 0, 0, 0, 0, 0))], DT, (0, 0, 0), False)
    m = eng.skeletons[0].getMass()
    added = np.zeros((1, 6, 6))
    added[0, 3:, 3:] = 2.0 * m * np.eye(3)
    added[0, :3, :3] = np.diag([1e-3, 2e-3, 3e-3])
    wrench = np.array([[0.01, 0.02, 0.03, 1.0, -2.0, 0.5]])
    eng.advance(None, wrench, added)
    qd = eng.state()["qd"]
    assert rel_err(qd[3:], DT * wrench[0, 3:] / (3.0 * m)) < 1e-9
    inertia = eng.skeletons[0].getBodyNode(0).getInertia().getMoment() + added[0, :3, :3]
    assert rel_err(qd[:3], DT * np.linalg.solve(inertia, wrench[0, :3])) < 1e-6  # gyroscopic term O(dt w^2)


@pytest.mark.parametrize("name", ["free_torque", "chain_torque", "chain_velocity", "planar_tree"])
def test_step_vjp_with_added_mass_matches_finite_differences(name):
    eng = RigidEngine(SYSTEMS[name](), DT, collision=False)
    rng = np.random.default_rng(5)
    nb = len(eng.body_names)
    s0 = eng.flat_state()
    a = rng.normal(size=eng.action_size)
    w = rng.normal(size=(nb, 6))
    added = _random_added(rng, nb)
    record = eng.advance(a, w, added)
    g = rng.normal(size=2 * eng.dofs)
    grad_s, grad_a, grad_w, grad_added = eng.vjp_flat(record, g)

    def loss(s, a_, w_, added_):
        return g @ eng._advance(s, a_, w_, added_)

    # h = 1e-4 for the inputs: the round-off of two DART steps and a solve, divided by 2h, is what limits
    # these differences (their error falls as h grows, 1/h, down to h = 1e-3)
    assert rel_err(grad_a, central(lambda x: loss(s0, x, w, added), a, 1e-4)) < VJP_RTOL
    assert rel_err(grad_w, central(lambda x: loss(s0, a, x, added), w, 1e-4)) < VJP_RTOL
    assert rel_err(grad_added, central(lambda x: loss(s0, a, w, x), added, 1e-4)) < VJP_RTOL
    assert rel_err(grad_s, central(lambda x: loss(x, a, w, added), s0)) < VJP_RTOL
