"""The runner's energy budget (cosim.conservation): work done by a moving rigid body and by control
impulses, accounted exactly, and an energy gain that no work explains stops the run naming the body."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_scene

from cosim.errors import SimulationError
from cosim.scene.build import build_system

WEIGHTLESS = {"grid": {"cells": 32}, "gravity": [0.0, 0.0]}


def block(center, velocity=(0.0, 0.0)) -> dict:
    return {
        "name": "block",
        "material": {"type": "elastic", "E": 2e3, "nu": 0.3, "density": 1000},
        "shape": {"type": "box", "center": list(center), "size": [0.2, 0.2]},
        "velocity": list(velocity),
    }


def momentum(sim) -> np.ndarray:
    return (sim.mpm.mass[:, None] * sim.mpm.state()["v"]).sum(axis=0)


def test_a_pushing_rigid_body_does_work_equal_to_momentum_given_times_its_speed():
    """A plate at constant V pushes a resting block (no gravity): the work W = -sum J . V must equal
    the momentum the block gained times V (MLS-MPM transfers momentum exactly), and the block's energy
    gain is positive and at most W (the grid contact is inelastic)."""
    speed = np.array([0.0, 0.5])
    scene = make_scene(
        steps=60,
        mpm={**WEIGHTLESS, "bodies": [block([0.5, 0.35])]},
        rigid={
            "bodies": [
                {
                    "name": "plate",
                    "shape": {"type": "box", "size": [0.3, 0.05]},
                    "position": [0.5, 0.2],
                    "motion": {"type": "constant", "velocity": speed.tolist()},
                }
            ]
        },
        contact={"model": "grid", "friction": 0.0},
    )
    sim = build_system(scene)
    p0 = momentum(sim)
    sim.rollout()
    cons = sim.conservation
    gained = momentum(sim) - p0
    assert gained[1] > 0.5  # the plate has pushed the block [kg m/s per m of depth]
    assert cons.work == pytest.approx(float(gained @ speed), rel=1e-9)
    energy_gain = sum(e["total"] for e in _energies(sim).values()) - cons.E0
    assert 0 < energy_gain <= cons.work


def _energies(sim):
    from cosim.diagnostics import body_energies

    return body_energies(sim.mpm, sim.mpm.state(), sim.gravity)


@pytest.mark.parametrize("requires_grad", [False, True], ids=["forward", "gradients"])
def test_control_impulses_do_work_equal_to_the_kinetic_energy_they_add(requires_grad):
    """Uniform impulses on a free block (no gravity, no walls reached): its particles keep one velocity,
    so the energy gained is exactly the accounted I . v + |I|^2 / 2m, summed over the steps (on the
    device, from the slot the step started from: a rotating one forward, slot 0 with gradients)."""
    scene = make_scene(
        steps=20,
        mpm={**WEIGHTLESS, "bodies": [block([0.5, 0.5], velocity=(0.1, 0.0))]},
        controls=[{"body": "block", "impulse": [2e-3, 1e-3]}],
    )
    sim = build_system(scene, requires_grad=requires_grad)
    sim.rollout()
    cons = sim.conservation
    energy_gain = sum(e["total"] for e in _energies(sim).values()) - cons.E0
    assert cons.work > 0
    assert energy_gain == pytest.approx(cons.work, rel=1e-6)
    assert abs(cons.excess) < 1e-6


def test_energy_gained_from_nowhere_stops_a_short_run_at_that_step_naming_the_body():
    """Triple every velocity of a sliding block after step 2 of a 6-step run (as an instability would): the
    check after step 3 (every macro step) finds 9x the kinetic energy with no work done and stops there,
    naming the block; steps 0-2 passed it."""
    scene = make_scene(
        steps=6,
        mpm={**WEIGHTLESS, "bodies": [block([0.5, 0.5], velocity=(0.3, 0.0)), block([0.2, 0.2]) | {"name": "still"}]},
    )
    sim = build_system(scene)
    for _ in range(3):
        sim.step()
    assert sim.conservation.excess is not None  # checked already, in a run shorter than 10 steps
    state = dict(sim.mpm.state())
    sl = sim.slices["block"]
    state["v"] = state["v"].copy()
    state["v"][sl] *= 3.0
    sim.mpm.set_state(state)
    with pytest.raises(SimulationError, match=r"^step 3: the energy grew .* body 'block' gained most"):
        sim.step()


def test_a_conservative_short_run_is_checked_every_step_and_not_stopped():
    """A tumbling block falling under gravity for 4 steps: each step is checked (the excess is known after
    the first) and none stops it; the energy only dissipates (symplectic Euler under gravity loses
    m g^2 dt^2 / 2 per substep)."""
    scene = make_scene(steps=4, mpm={"grid": {"cells": 32}, "bodies": [block([0.5, 0.2], velocity=(0.2, -0.5))]})
    sim = build_system(scene)
    sim.step()
    assert sim.conservation.excess is not None
    for _ in range(3):
        sim.step()
    assert sim.conservation.excess <= 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_the_strain_energy_sees_the_singular_values_numpys_svd_gives(dim):
    """The corotated energy's |F - R|^2 = sum (sigma_i - 1)^2 (R = U V^T of the SVD) from the closed-form
    (2D) or eigvalsh (3D) singular values: per matrix it matches numpy's SVD to round-off, for small and
    large strains, reflections (det F < 0) and a nearly flattened F."""
    from cosim.diagnostics import singular_values

    rng = np.random.default_rng(dim)
    F = np.concatenate([np.eye(dim) + s * rng.standard_normal((200, dim, dim)) for s in (1e-4, 0.3, 2.0)])
    F[:20] *= -1.0
    F[20:30, 0] *= 1e-6
    U, _, Vt = np.linalg.svd(F)
    expected = np.sum((F - U @ Vt) ** 2, axis=(1, 2))
    got = np.sum((singular_values(F) - 1.0) ** 2, axis=1)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-14)
    assert abs(got.sum() - expected.sum()) <= 1e-12 * expected.sum()


@pytest.mark.parametrize("dim", [2, 3])
def test_device_energies_match_the_host_reference(dim):
    """``MPMEngine.energies`` (summed on the device, what the check and saved frames read) against the host's
    numpy sums (``cosim.diagnostics``, singular values from eigvalsh / closed form) for an elastic, a plastic
    and a liquid body with their E changed after the build, random velocities and deformations from 1e-4 to
    large strains (det F > 0: for a reflection the 2D stress's R is a rotation, the host's U V^T is not):
    every term of every body to 1e-9, and the volume sum V0 det F."""
    from cosim.diagnostics import body_energies

    materials = [
        {"type": "elastic", "E": 2e3, "nu": 0.3, "density": 1000},
        {"type": "plastic", "E": 3e3, "nu": 0.25, "yield_stress": 20.0},
        {"type": "liquid", "E": 2e3, "nu": 0.3, "viscosity": 0.5},
    ]
    bodies = [
        {
            "name": m["type"],
            "material": m,
            "shape": {"type": "box", "center": [0.3 + 0.2 * i] + [0.5] * (dim - 1), "size": [0.12] * dim},
        }
        for i, m in enumerate(materials)
    ]
    gravity = [0.0, -9.81, 0.0][:dim]
    sim = build_system(make_scene(dim=dim, mpm={"grid": {"cells": 32}, "gravity": gravity, "bodies": bodies}))
    engine = sim.mpm
    engine.set_parameters({"E": np.array([2.5e3, 3.5e3, 1.5e3])})
    rng = np.random.default_rng(dim)
    state = dict(engine.state())
    n = len(state["F"])
    scale = np.choose(np.arange(n) % 3, [1e-4, 0.3, 2.0])[:, None, None]
    F = np.eye(dim) + scale * rng.standard_normal((n, dim, dim))
    F[np.linalg.det(F) < 0, :, 0] *= -1.0
    state["F"] = F
    state["v"] = rng.standard_normal((n, dim))
    engine.set_state(state)
    host = body_energies(engine, engine.state(), gravity)
    device = engine.energies()
    for name, terms in host.items():
        for key, value in terms.items():
            assert device[name][key] == pytest.approx(value, rel=1e-9, abs=1e-12), (name, key)
        sl = sim.slices[name]
        volume = engine.bodies[list(sim.slices).index(name)].particle_volume * np.linalg.det(state["F"][sl]).sum()
        assert device[name]["volume"] == pytest.approx(volume, rel=1e-9)


def test_a_light_door_flung_by_the_explicit_exchange_trips_the_whole_system_budget():
    """pull_door with its door 6x lighter (100 kg/m^3): exchanging the reactions alone once per frame, the
    gripper's impact on the handle gives the door more kinetic energy than the gripper loses (no work is
    done: no gravity, no impulses). The MPM's energy only falls, so the budget of the material alone never
    saw it; the whole system's stops the run at the impact, naming the DART engine. With the added-mass
    exchange (the default) the same door stays within the budget."""
    from pathlib import Path

    from cosim.scene import load_scene

    path = Path(__file__).parent.parent / "scenes" / "pull_door.yaml"
    light = [f"articulated.skeletons[0].links[{i}].density=100" for i in range(3)]
    sim = build_system(load_scene(path, {"precision": "float64"}, light), steps=25)
    for coupler in sim.mpm_couplers:
        coupler.added_mass = False
    with pytest.raises(SimulationError, match=r"^step 1[0-9]: the energy grew .* engine 'dart' gained most"):
        sim.rollout()
    sim = build_system(load_scene(path, {"precision": "float64"}, light), steps=25)
    sim.rollout()
    assert sim.conservation.excess < 0.01


def test_a_towel_lifted_by_its_corners_gains_the_work_its_prescribed_vertices_do():
    """A towel hanging from its four corners, which are raised at 0.5 m/s for 60 frames: the work the
    prescribed corners do (``ClothEngine.external_work``, the force holding them times their displacement)
    is the towel's energy gain plus what backward Euler dissipates, so it is at least the gain and, the
    lift being mostly a rigid translation that BE does not damp, at most 10 % more."""
    from cosim.engines.cloth import ClothEngine, ClothMaterial
    from cosim.engines.cloth_mesh import rectangle

    mesh = rectangle((0.3, 0.3), (9, 9), (0.0, 0.5, 0.0), "y")
    corners = [int(np.argmin(np.linalg.norm(mesh.vertices - c, axis=1))) for c in mesh.vertices[[0, 8, 72, 80]]]
    towel = ClothEngine(mesh, ClothMaterial(k_stretch=500.0, k_bend=1e-3, density=0.3), controls=[corners])
    for _ in range(60):  # hang first
        towel.step({})
    e0, work = towel.energy_and_mass()[0], 0.0
    for _ in range(60):
        _, record = towel.step({"action": [0.0, 0.5, 0.0]})
        work += towel.external_work(record)
    gain = towel.energy_and_mass()[0] - e0
    assert gain > 0.0 and gain <= work <= 1.1 * gain, (gain, work)


def test_the_survey_sums_the_energies_the_meter_does_and_forgets_them_with_the_moduli():
    """The runner's budget reads the energies every step, so the survey sums them in its own pass over the
    particles: the meter's sums from its pass alone, to 1e-12 (the two compiled kernels may contract the
    same arithmetic differently). Changing E changes the strain energy (linear in E at fixed deformation,
    so doubling E doubles it): sums kept from before the change would not."""
    from cosim.engines.mpm_energy import TERMS

    bodies = [block((0.5, 0.5), (0.4, -0.2))]
    bodies[0]["material"]["E"] = 4e3
    sim = build_system(make_scene(mpm={"grid": {"cells": 32}, "gravity": [0.0, -9.81], "bodies": bodies}))
    engine = sim.mpm
    sim.step()
    state = dict(engine.state())
    n = len(state["F"])
    state["F"] = np.eye(2) + 0.1 * np.random.default_rng(0).standard_normal((n, 2, 2))
    engine.set_state(state)
    surveyed = engine.energies()
    alone = engine._energy_meter.body_sums(engine.slot)[0]
    np.testing.assert_allclose([surveyed["block"][k] for k in TERMS], alone, rtol=1e-12, atol=0)
    assert surveyed["block"]["strain"] > 1e-3 * surveyed["block"]["kinetic"]
    engine.set_parameters({"E": np.array([8e3])})
    assert engine.energies()["block"]["strain"] == pytest.approx(2 * surveyed["block"]["strain"], rel=1e-12)
