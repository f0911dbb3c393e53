"""Gradients across the MPM-cloth coupling, against central differences (float64, contact active).

One small 3D scene: an elastic block driven by control impulses under a 5 x 5 towel whose four
corners are pulled down into it (grid contact with the towel's band, friction 0.3), 10 macro steps.
Cloth to MPM: a loss on the particles with respect to the cloth's action. MPM to cloth: a loss on
the towel's vertices with respect to the control impulses. Both cross every coupling step.
"""

import numpy as np
import pytest

from cosim.adjoint.gradcheck import check_gradients
from cosim.adjoint.objective import Objective
from cosim.losses import Loss
from cosim.scene import parse_scene
from cosim.scene.build import build_system

CORNERS = [[0.3, 0.45, 0.3], [0.7, 0.45, 0.3], [0.3, 0.45, 0.7], [0.7, 0.45, 0.7]]
SCENE = {
    "name": "cloth_gradients",
    "dim": 3,
    "precision": "float64",
    "steps": 10,
    "time": {"frame_dt": 2e-3, "substeps": 2},
    "mpm": {
        "grid": {"cells": 16},
        "bodies": [
            {
                "name": "jelly",
                "material": {"type": "elastic", "E": 3e3, "nu": 0.3, "density": 500},
                "shape": {"type": "box", "center": [0.5, 0.35, 0.5], "size": [0.25, 0.125, 0.25]},
            }
        ],
    },
    "controls": [{"body": "jelly", "impulse": [0.0, 1e-5, 0.0]}],
    "cloth": [
        {
            "name": "towel",
            "mesh": {"type": "rectangle", "center": [0.5, 0.45, 0.5], "size": [0.4, 0.4], "resolution": [5, 5]},
            "material": {"stretch": 300, "bend": 1e-3, "density": 0.3},
            "controls": [{"name": "corners", "vertices": {"points": CORNERS}}],
            "actions": {"hold": 5, "initial": [0.0, -0.5, 0.0]},
        }
    ],
    "contact": {"model": "grid", "friction": 0.3},
}


@pytest.mark.slow
def test_gradients_cross_the_mpm_cloth_coupling_both_ways():
    """Adjoint vs central differences, rel. 1e-5, two random directions each; the contact must carry
    momentum in every step after the first (the towel's reaction impulse is non-zero)."""
    scene = parse_scene(SCENE)
    system = build_system(scene, requires_grad=True)
    objective = Objective(system)
    params = objective.initial_params()
    touching = []
    system.rollout(
        on_step=lambda n: n and touching.append(np.abs(system.last.outputs["reactions"]["towel"]["impulse"]).sum())
    )
    assert len(touching) == 10 and min(touching[1:]) > 0  # all starts at rest: nothing approaches in step 1
    cases = [("jelly", "towel.action"), ("towel", "impulse")]
    for body, name in cases:
        spec = scene.loss.model_copy(update={"type": "weighted_positions", "body": body})
        objective.loss = Loss(spec, 3, 0, system.slices, system.mpm.mass, cloths=[system.engines["towel"]])
        results = check_gradients(objective.evaluate, params, [name], objective.natural_scales(), 2)
        worst = max(r.relative_error for r in results)
        assert worst < 1e-5, f"{body} loss, d/d{name}: {[(r.adjoint, r.finite_difference) for r in results]}"


@pytest.mark.slow
def test_gradients_through_the_added_mass_of_heavy_material():
    """The same scene under the forecast model with a jelly of 2000 kg/m^3 on the towel (material one
    cell deep weighs 400 times the towel per area): the exchange carries the material's added mass
    (``cosim.couplers.mpm_cloth``), which is active from step 2 on and heavier than the towel's vertices
    it loads; adjoint vs central differences, rel. 1e-5, both ways across the coupling. Step 1e-5 of
    the natural scale: at gradcheck's 1e-6 the jelly loss's difference is round-off bound (1.1e-5 off,
    the same with the added mass's adjoint left out: 1.2e-5), at 1e-5 it is 2.9e-6 off."""
    data = {**SCENE, "contact": {"model": "forecast", "friction": 0.3}}
    data["mpm"] = {**SCENE["mpm"], "bodies": [{**SCENE["mpm"]["bodies"][0]}]}
    data["mpm"]["bodies"][0]["material"] = {"type": "elastic", "E": 3e3, "nu": 0.3, "density": 2000}
    scene = parse_scene(data)
    system = build_system(scene, requires_grad=True)
    objective = Objective(system)
    params = objective.initial_params()
    coupler = next(c for c in system.couplers if c.engine == "towel")
    ratios = []
    system.rollout(
        on_step=lambda n: (
            n and ratios.append(coupler.state()["added_mass"].max() / system.engines["towel"].masses().max())
        )
    )
    assert min(ratios[1:]) > 1.0
    for body, name in [("jelly", "towel.action"), ("towel", "impulse")]:
        spec = scene.loss.model_copy(update={"type": "weighted_positions", "body": body})
        objective.loss = Loss(spec, 3, 0, system.slices, system.mpm.mass, cloths=[system.engines["towel"]])
        results = check_gradients(objective.evaluate, params, [name], objective.natural_scales(), 2, rel_step=1e-5)
        worst = max(r.relative_error for r in results)
        assert worst < 1e-5, f"{body} loss, d/d{name}: {[(r.adjoint, r.finite_difference) for r in results]}"
