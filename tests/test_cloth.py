"""The in-house cloth engine (``cosim.engines.cloth``): adjoint against central differences, physics
against closed forms, solver behaviour, meshes. Pure NumPy/JAX, float64; each test names its law."""

from __future__ import annotations

import numpy as np
import pytest

from cosim.engines import cloth_mesh
from cosim.engines.cloth import MATERIAL_KEYS, ClothEngine, ClothMaterial
from cosim.errors import SimulationError

G = 9.81


def hanging_sheet(k_stretch=1000.0, res=(5, 5), **kw) -> ClothEngine:
    """A 0.5 x 0.5 m sheet in the xy-plane (normal z) pinned along its top edge, gravity -y."""
    mesh = cloth_mesh.rectangle((0.5, 0.5), res, normal="z")
    top = np.flatnonzero(np.isclose(mesh.vertices[:, 1], mesh.vertices[:, 1].max()))
    return ClothEngine(mesh, ClothMaterial(k_stretch=k_stretch, k_bend=1e-3, density=0.2), fixed=top, **kw)


# ------------------------------------------------------------------------------------ 1. the adjoint


def _rollout(engine, state0, actions, forces, material, steps):
    engine.set_state(state0)
    engine.set_parameters(material)
    records = []
    for n in range(steps):
        records.append(engine.step({"action": actions, "forces": forces})[1])
    return engine.state(), records


def test_vjp_matches_central_differences_for_every_block():
    """Every vjp block (x0, v0, action, forces, each material parameter) of a 2-step rollout against
    central differences along a random direction, L = <wx, x_2> + <wv, v_2>. Newton tolerance 1e-13 of
    the vertex weight (floored at round-off) so the differences resolve the converged map; rel. 1e-6."""
    rng = np.random.default_rng(7)
    mesh = cloth_mesh.rectangle((0.4, 0.4), (5, 5), normal="z")
    material = ClothMaterial(k_stretch=40.0, k_bend=2e-3, c_mass=0.5, density=0.3)
    engine = ClothEngine(mesh, material, fixed=[20], controls=[[24], [0, 1]], frame_dt=1e-2, rtol=1e-13)
    V = mesh.n_vertices
    state0 = {"x": mesh.vertices + 0.02 * rng.standard_normal((V, 3)), "v": 0.3 * rng.standard_normal((V, 3))}
    actions = 0.2 * rng.standard_normal(engine.action_size)
    forces = 0.05 * rng.standard_normal((V, 3))
    mat0 = engine.material()
    wx, wv = rng.standard_normal((V, 3)), rng.standard_normal((V, 3))
    steps = 2

    def loss(s0=state0, a=actions, f=forces, m=mat0):
        final, records = _rollout(engine, s0, a, f, m, steps)
        return float(np.sum(wx * final["x"]) + np.sum(wv * final["v"])), records

    _, records = loss()
    assert np.all(np.abs(engine.energy.angles(records[-1].x_next)) > 1e-4), "bending must be active"
    grad_state = {"x": wx, "v": wv}
    total = {"action": 0.0, "forces": 0.0, **{k: 0.0 for k in MATERIAL_KEYS}}
    for rec in reversed(records):
        out = engine.vjp(rec, {"state": grad_state})
        grad_state = out["state"]
        for key in total:
            total[key] = total[key] + out[key]

    def check(name, adjoint, fd):
        assert abs(adjoint - fd) <= 1e-6 * max(abs(fd), 1e-12), f"{name}: adjoint {adjoint:.10e} vs FD {fd:.10e}"

    for key, scale in (("x", 1e-6), ("v", 1e-5)):
        d = rng.standard_normal((V, 3))
        plus = loss(s0={**state0, key: state0[key] + scale * d})[0]
        minus = loss(s0={**state0, key: state0[key] - scale * d})[0]
        check(f"state {key}", float(np.sum(grad_state[key] * d)), (plus - minus) / (2 * scale))
    d = rng.standard_normal(actions.shape)
    fd = (loss(a=actions + 1e-5 * d)[0] - loss(a=actions - 1e-5 * d)[0]) / 2e-5
    check("action", float(total["action"] @ d), fd)
    d = rng.standard_normal(forces.shape)
    fd = (loss(f=forces + 1e-5 * d)[0] - loss(f=forces - 1e-5 * d)[0]) / 2e-5
    check("forces", float(np.sum(total["forces"] * d)), fd)
    for key in MATERIAL_KEYS:
        eps = 1e-5 * float(mat0[key])
        fd = (loss(m={**mat0, key: mat0[key] + eps})[0] - loss(m={**mat0, key: mat0[key] - eps})[0]) / (2 * eps)
        check(key, float(total[key]), fd)


def test_force_gradient_on_prescribed_vertices_is_zero():
    """A force on a fixed or controlled vertex moves nothing, so its adjoint is exactly zero."""
    engine = hanging_sheet(res=(4, 4), controls=[[0]])
    _, rec = engine.step({"action": np.array([0.0, 0.1, 0.0])})
    out = engine.vjp(rec, {"state": {"x": np.ones((16, 3)), "v": np.ones((16, 3))}})
    assert np.all(out["forces"][~engine.free] == 0.0)
    assert np.all(np.abs(out["forces"][engine.free]) > 0)
