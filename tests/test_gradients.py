"""Adjoint gradients of the MPM rollout against central finite differences (float64).

Tolerance: 1e-5 relative along random directions. Central differences with a
step of 1e-6 of each parameter's scale have truncation error ~1e-12 and
round-off ~1e-16 |L| / (eps |g.d|) ~ 1e-8 here, so a larger error means a
wrong adjoint, not noise.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from cosim.adjoint.gradcheck import check_gradients
from cosim.adjoint.objective import Objective
from cosim.scene.build import build_system

TOL = 1e-5


def three_material_scene(steps=3, substeps=4, frame_dt=4e-3, loss=None):
    """Elastic, plastic (yielding) and liquid bodies, the elastic one hitting the floor, with controls."""
    dx = 1 / 32
    bodies = [
        {
            "name": "jelly",
            "material": {"type": "elastic", "E": 2e3, "nu": 0.3},
            "shape": {"type": "box", "center": [0.3, 3 * dx + 0.07], "size": [0.12, 0.12]},
            "velocity": [0.3, -1.5],
            "jitter": 0.3,
        },
        {
            "name": "dough",
            "material": {"type": "plastic", "E": 3e3, "nu": 0.25, "yield_stress": 20.0},
            "shape": {"type": "sphere", "center": [0.6, 3 * dx + 0.075], "radius": 0.07},
            "velocity": [-1.0, -2.0],
            "jitter": 0.3,
        },
        {
            "name": "water",
            "material": {"type": "liquid", "E": 2e3, "nu": 0.3, "viscosity": 0.5},
            "shape": {"type": "box", "center": [0.7, 0.3], "size": [0.1, 0.1]},
            "velocity": [0.0, -0.5],
        },
    ]
    return make_scene(
        steps=steps,
        time={"frame_dt": frame_dt, "substeps": substeps},
        mpm={"grid": {"cells": 32}, "boundary": {"type": "slip"}, "bodies": bodies},
        controls=[{"body": "jelly", "region": {"min": [0.0, 0.15], "max": [1.0, 1.0]}, "impulse": [0.002, -0.001]}],
        loss=loss or {"type": "weighted_positions"},
    )


@pytest.fixture(scope="module")
def objective():
    return Objective(build_system(three_material_scene(), requires_grad=True))


@pytest.mark.parametrize("param", ["v0", "impulse", "E", "x0", "nu"])
def test_adjoint_matches_finite_differences_2d(objective, param):
    params = objective.initial_params()
    scales = {"x0": 1 / 32, "v0": 1.0, "impulse": 1e-3, "E": 3e3, "nu": 0.1}
    results = check_gradients(objective.evaluate, params, [param], scales, directions=2, seed=1)
    for r in results:
        assert abs(r.finite_difference) > 0, "the loss must depend on the parameter for the test to mean anything"
        assert r.relative_error < TOL, r


def test_material_gradients_are_skipped_only_when_not_asked_for(objective):
    """Without material parameters the adjoint skips dL/dE and dL/dnu (the costliest part of the stress
    adjoint); the gradients asked for are the same as when they are computed, to round-off (the two
    compiled adjoint kernels differ, and fast math may contract their arithmetic differently)."""
    params = objective.initial_params()
    asked = {"v0": params["v0"], "impulse": params["impulse"]}
    _, without = objective.evaluate(asked, grad=True)
    assert not objective.system.mpm.material_grads
    _, with_material = objective.evaluate({**asked, "E": params["E"]}, grad=True)
    assert objective.system.mpm.material_grads and np.abs(with_material["E"]).max() > 0
    for key in asked:
        np.testing.assert_allclose(
            without[key], with_material[key], rtol=0, atol=1e-12 * np.abs(with_material[key]).max()
        )


def test_plastic_body_yields_during_the_gradient_rollout(objective):
    """The return mapping is on the differentiated path: some dough particles sit on the yield surface.

    The deviatoric Biot strain |dev(S - I)| (F = R S) is capped at
    sqrt(2/3) yield / (2 mu): particles at the cap have yielded.
    """
    objective.rollout(objective.initial_params())
    F = objective.system.mpm.state()["F"][objective.system.slices["dough"]]
    _U, sig, Vt = np.linalg.svd(F)
    S = np.einsum("nji,nj,njk->nik", Vt, sig, Vt)
    strain = S - np.eye(2)
    dev = strain - np.trace(strain, axis1=1, axis2=2)[:, None, None] / 2 * np.eye(2)
    norm = np.sqrt((dev**2).sum(axis=(1, 2)))
    mu, _ = objective.system.mpm.lame(1)
    limit = np.sqrt(2 / 3) * 20.0 / (2 * mu)
    assert norm.max() <= limit * (1 + 1e-6)
    assert (norm > limit * (1 - 1e-6)).sum() >= 5


def test_com_loss_gradient(objective):
    """The centre-of-mass loss's own gradient against finite differences in x (no simulation)."""
    from cosim.losses import Loss

    scene = three_material_scene(loss={"type": "com_target", "body": "dough", "target": [0.5, 0.5]})
    sim = objective.system
    loss = Loss(scene.loss, scene.dim, scene.seed, sim.slices, sim.mpm.mass)
    state = sim.mpm.state()
    _value, grad = loss({"mpm": state})
    d = np.random.default_rng(0).standard_normal(state["x"].shape)
    eps = 1e-6

    def shifted(step):
        return loss({"mpm": dict(state, x=state["x"] + step * d)})[0]

    fd = (shifted(eps) - shifted(-eps)) / (2 * eps)
    assert abs(fd - np.sum(grad["mpm"]["x"] * d)) < 1e-8 * max(abs(fd), 1e-12)


def test_checkpointed_gradients_equal_full_storage():
    """Recomputing substeps from macro-step checkpoints gives the gradients of keeping every substep.

    4 macro steps x 3 substeps (checkpoints, recompute) against 1 macro step of
    12 substeps (all states resident, no recompute), same dt: equal to round-off.
    """
    dt = 1e-3
    checkpointed = Objective(
        build_system(three_material_scene(steps=4, substeps=3, frame_dt=3 * dt), requires_grad=True)
    )
    full = Objective(build_system(three_material_scene(steps=1, substeps=12, frame_dt=12 * dt), requires_grad=True))
    assert checkpointed.system.mpm.n_slots == 4 and full.system.mpm.n_slots == 13
    pc, pf = checkpointed.initial_params(), full.initial_params()
    pc["impulse"] = np.zeros_like(pc["impulse"])  # impulses are per macro step: switch them off
    pf["impulse"] = np.zeros_like(pf["impulse"])
    lc, gc = checkpointed.evaluate(pc, grad=True)
    lf, gf = full.evaluate(pf, grad=True)
    assert abs(lc - lf) < 1e-13 * abs(lf)
    for key in ("x0", "v0", "E", "nu"):
        scale = np.abs(gf[key]).max()
        assert np.abs(gc[key] - gf[key]).max() < 1e-9 * scale, key
    # memory: the tape holds one state (x, v, C, F) and one impulse field per
    # macro step, whatever the substep count; the engine one macro step of substeps
    n = checkpointed.system.mpm.n_particles
    assert checkpointed.tape.nbytes == 4 * n * (2 + 2 + 4 + 4 + 2) * 8
    assert checkpointed.memory_estimate().tape_bytes == checkpointed.tape.nbytes  # what gradcheck prints


@pytest.mark.slow
def test_adjoint_matches_finite_differences_3d():
    """The same check in 3D (Newton polar decomposition on the adjoint path): one elastic body on the floor."""
    dx = 1 / 16
    scene = make_scene(
        dim=3,
        steps=2,
        time={"frame_dt": 4e-3, "substeps": 3},
        mpm={
            "grid": {"cells": 16},
            "bodies": [
                {
                    "name": "cube",
                    "material": {"type": "elastic", "E": 2e3, "nu": 0.3},
                    "shape": {"type": "box", "center": [0.5, 3 * dx + 0.1, 0.5], "size": [0.2, 0.2, 0.2]},
                    "velocity": [0.2, -1.0, 0.1],
                    "jitter": 0.3,
                }
            ],
        },
        controls=[{"body": "cube", "impulse": [0.0, 1e-4, 0.0]}],
    )
    obj = Objective(build_system(scene, requires_grad=True))
    params = obj.initial_params()
    scales = {"v0": 1.0, "impulse": 1e-4, "E": 2e3}
    results = check_gradients(obj.evaluate, params, ["v0", "impulse", "E"], scales, directions=1, seed=2)
    assert {r.param for r in results} == {"v0", "impulse", "E"}
    for r in results:
        assert abs(r.finite_difference) > 0, "the loss must depend on the parameter for the test to mean anything"
        assert r.relative_error < TOL, r
