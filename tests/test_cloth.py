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


def _rollout(engine, state0, actions, forces, material, steps, added=None):
    engine.set_state(state0)
    engine.set_parameters(material)
    records = []
    for n in range(steps):
        records.append(engine.step({"action": actions, "forces": forces, "added_mass": added})[1])
    return engine.state(), records


def test_vjp_matches_central_differences_for_every_block():
    """Every vjp block (x0, v0, action, forces, a coupling's added mass, each material parameter) of a
    2-step rollout with an added mass on some vertices against central differences along a random
    direction, L = <wx, x_2> + <wv, v_2>. Newton tolerance 1e-13 of the vertex weight (floored at
    round-off) so the differences resolve the converged map; rel. 1e-6."""
    rng = np.random.default_rng(7)
    mesh = cloth_mesh.rectangle((0.4, 0.4), (5, 5), normal="z")
    material = ClothMaterial(k_stretch=40.0, k_bend=2e-3, c_mass=0.5, density=0.3)
    engine = ClothEngine(mesh, material, fixed=[20], controls=[[24], [0, 1]], frame_dt=1e-2, rtol=1e-13)
    V = mesh.n_vertices
    state0 = {"x": mesh.vertices + 0.02 * rng.standard_normal((V, 3)), "v": 0.3 * rng.standard_normal((V, 3))}
    actions = 0.2 * rng.standard_normal(engine.action_size)
    forces = 0.05 * rng.standard_normal((V, 3))
    added = np.where(rng.random(V) < 0.5, 0.0, 3.0 * engine.masses().max() * rng.random(V))  # heavier than the cloth
    mat0 = engine.material()
    wx, wv = rng.standard_normal((V, 3)), rng.standard_normal((V, 3))
    steps = 2

    def loss(s0=state0, a=actions, f=forces, m=mat0, A=added):
        final, records = _rollout(engine, s0, a, f, m, steps, A)
        return float(np.sum(wx * final["x"]) + np.sum(wv * final["v"])), records

    _, records = loss()
    assert np.all(np.abs(engine.energy.angles(records[-1].x_next)) > 1e-4), "bending must be active"
    grad_state = {"x": wx, "v": wv}
    total = {"action": 0.0, "forces": 0.0, "added_mass": 0.0, **{k: 0.0 for k in MATERIAL_KEYS}}
    for rec in reversed(records):
        out = engine.vjp(rec, {"state": grad_state})
        grad_state = out["state"]
        flat = {**out, **out["material"]}
        total = {key: value + flat[key] for key, value in total.items()}

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
    d = rng.random(V) * (added > 0)  # the added mass stays >= 0; a step of 1e-4 of its size (~1e-3 kg)
    fd = (loss(A=added + 1e-7 * d)[0] - loss(A=added - 1e-7 * d)[0]) / 2e-7
    check("added mass", float(np.sum(total["added_mass"] * d)), fd)
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


# ------------------------------------------------------------------------------------- 2.-5. physics


def test_hanging_strip_stretches_as_a_membrane_under_its_own_weight():
    """A strip L = 1 m long hanging from its top edge, in static equilibrium (backward Euler with
    h = 100 s is a static solve). In uniaxial stretch the ARAP membrane has tension T = 2 k (stretch - 1)
    and no lateral contraction, so at depth s the strain is rho g (L - s) / (2 k) and the elongation
    at depth s is u(s) = rho g (L s - s^2 / 2) / (2 k), at the bottom rho g L^2 / (4 k) (the linear
    membrane's rho g L^2 / (2 k_lin) with k_lin = 2 k). Linear elements with these row loads are nodally
    exact for the 1-D bar; what remains is the uneven lumped mass along a row (end vertices carry 1 or
    2 triangles), which tilts rows by ~1e-3 m and moves the bottom's mean by 5e-5 (refinement: 1.4e-4,
    4.6e-5, 6e-6 at 11, 21, 41 rows): tolerance 1e-3 on the bottom, 1 % of it along the strip."""
    L, W, rho, k = 1.0, 0.2, 0.2, 10.0
    mesh = cloth_mesh.rectangle((W, L), (3, 21), normal="z")
    y0 = mesh.vertices[:, 1]
    top = np.flatnonzero(np.isclose(y0, y0.max()))
    engine = ClothEngine(mesh, ClothMaterial(k_stretch=k, k_bend=1e-6, density=rho), fixed=top, frame_dt=100.0)
    for _ in range(3):
        engine.step({})
    s = y0.max() - y0
    u = y0 - engine.x[:, 1]
    exact = rho * G * (L * s - s**2 / 2) / (2 * k)
    bottom = np.isclose(s, L)
    assert u[bottom].mean() == pytest.approx(rho * G * L**2 / (4 * k), rel=1e-3)
    assert np.abs(u - exact).max() <= 1e-2 * exact.max()


def test_damped_dilation_mode_decays_at_the_backward_euler_rate():
    """A free equilateral triangle (side a, lumped masses rho A / 3) dilating homogeneously: by symmetry
    the mode x = c + lam (X - c) is invariant, with kinetic energy I lam'^2 / 2 (I = rho A a^2 / 3) and
    ARAP energy 2 k A (lam - 1)^2, so w^2 = 12 k / (rho a^2), and with mass damping c_m backward Euler
    gives u_{n+1} (1 + c_m h + w^2 h^2) = (2 + c_m h) u_n - u_{n-1} for u = lam - 1. The discrete mode
    energy Q_n = u_{n+1}^2 - (b/a) u_{n+1} u_n + u_n^2 / a (a = 1 + c_m h + w^2 h^2, b = 2 + c_m h) is
    exactly |u_{n+1} - z u_n|^2 for the root z, so it shrinks by 1/a every step (checked to 1e-7), and
    the physical energy decays at the mean rate ln(1/a) per step, not the continuous -c_m h: backward
    Euler's numerical damping w^2 h^2 is half the decay here (checked over 5 periods, 3 %)."""
    a_side, rho, c_m, h, w = 0.1, 0.2, 1.0, 1e-2, 10.0
    k = w**2 * rho * a_side**2 / 12
    X = a_side * np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, np.sqrt(3) / 2, 0.0]])
    mesh = cloth_mesh.build(X, [[0, 1, 2]], "triangle")
    engine = ClothEngine(
        mesh, ClothMaterial(k_stretch=k, k_bend=0.0, c_mass=c_m, density=rho), gravity=(0, 0, 0), frame_dt=h
    )
    centre = X.mean(axis=0)
    engine.set_state({"x": X.copy(), "v": 0.5 * (X - centre)})
    m = engine.masses()[:, None]
    u, energy = [0.0], []
    for _ in range(320):
        engine.step({})
        lengths = np.linalg.norm(engine.x - np.roll(engine.x, 1, axis=0), axis=1)
        assert np.ptp(lengths) <= 1e-12 * a_side, "the dilation mode must stay homogeneous"
        u.append(lengths.mean() / a_side - 1)
        energy.append(0.5 * np.sum(m * engine.v**2) + engine.elastic_energy(engine.x))
    u = np.array(u)
    amp = 1 + c_m * h + w**2 * h**2
    b = 2 + c_m * h
    assert np.allclose(u[2:] * amp - b * u[1:-1] + u[:-2], 0.0, atol=1e-9 * np.abs(u).max())
    Q = u[1:] ** 2 - (b / amp) * u[1:] * u[:-1] + u[:-1] ** 2 / amp
    assert np.allclose(Q[1:] / Q[:-1], 1 / amp, rtol=1e-7)
    rate = np.polyfit(np.arange(len(energy)), np.log(energy), 1)[0]
    assert rate == pytest.approx(-np.log(amp), rel=0.03)
    assert abs(rate + c_m * h) > 0.4 * c_m * h, "the test must tell numerical damping from c_m"


def test_linear_momentum_is_conserved_without_gravity_pins_or_damping():
    """Psi is translation invariant, so internal forces sum to zero and backward Euler keeps
    sum m v exactly up to the Newton residual: |dP| <= h * sum_steps sum_vertices |residual| <=
    steps h V tol per component. (Angular momentum changes by O(h^2) per step under backward Euler.)"""
    rng = np.random.default_rng(3)
    mesh = cloth_mesh.rectangle((0.5, 0.5), (5, 5), normal="y")
    engine = ClothEngine(
        mesh, ClothMaterial(k_stretch=200.0, k_bend=5e-3, c_mass=0.0), gravity=(0, 0, 0), frame_dt=1e-2
    )
    V = mesh.n_vertices
    engine.set_state({"x": mesh.vertices + 0.03 * rng.standard_normal((V, 3)), "v": rng.standard_normal((V, 3))})
    m = engine.masses()[:, None]
    p0 = np.sum(m * engine.v, axis=0)
    bound = 0.0
    for _ in range(20):
        engine.step({})
        bound += engine.frame_dt * V * engine.last_solve["tolerance"]
    drift = np.abs(np.sum(m * engine.v, axis=0) - p0).max()
    assert drift <= bound
    assert drift <= 1e-9 * np.sum(m * np.abs(engine.v))
    assert np.abs(engine.v - rng.standard_normal((V, 3))).max() > 0  # it moved and deformed


@pytest.mark.parametrize("k_stretch", [1e2, 1e3, 1e4, 1e5])
def test_stiffness_sweep_converges_and_stays_physical(k_stretch):
    """The hanging sheet at frame dt = 2e-3 s over 4 decades of stiffness: every step converges (few
    Newton iterations), the total energy (kinetic + elastic + gravity) never increases (backward
    Euler dissipates), nothing falls faster than free fall (drop <= g t^2 / 2) and the largest
    edge strain stays below twice the static top strain rho g H / (2 k) (a suddenly applied load
    overshoots at most 2x) plus 1e-9. Energy increases up to 1e-10 of m g H are allowed: the residual
    tolerance (its round-off floor grows with k) leaves that much noise in a converged step."""
    engine = hanging_sheet(k_stretch=k_stretch, res=(7, 7), frame_dt=2e-3)
    mesh, m, h = engine.mesh, engine.masses(), engine.frame_dt
    rest = np.linalg.norm(mesh.vertices[mesh.edges[:, 1]] - mesh.vertices[mesh.edges[:, 0]], axis=1)

    def total_energy():
        return 0.5 * np.sum(m[:, None] * engine.v**2) + engine.elastic_energy(engine.x) + G * np.sum(m * engine.x[:, 1])

    energies, iterations = [total_energy()], []
    for _ in range(40):
        engine.step({})
        iterations.append(engine.last_solve["iterations"])
        energies.append(total_energy())
    assert max(iterations) <= 8, f"k = {k_stretch:g} N/m: Newton iterations {iterations}"
    weight_scale = G * m.sum() * 0.5  # [J] the sheet's weight times its height; converged-step noise ~1e-11 of it
    assert np.all(np.diff(energies) <= 1e-10 * weight_scale)
    drop = (mesh.vertices[:, 1] - engine.x[:, 1]).max()
    assert drop <= 0.5 * G * (40 * h) ** 2
    strain = np.abs(np.linalg.norm(engine.x[mesh.edges[:, 1]] - engine.x[mesh.edges[:, 0]], axis=1) / rest - 1)
    assert strain.max() <= 2 * 0.2 * G * 0.5 / (2 * k_stretch) + 1e-9
    print(
        f"k_stretch {k_stretch:g} N/m: Newton iterations per step {min(iterations)}-{max(iterations)}, max strain {strain.max():.2e}"
    )


# ------------------------------------------------------------------------------------- 6. the solver


def test_non_converged_step_raises_and_is_not_accepted():
    """With one Newton iteration a nonlinear step cannot reach the tolerance: SimulationError naming the
    step and the residual, and the engine keeps the state it had."""
    engine = hanging_sheet(k_stretch=1e4, frame_dt=2e-2)
    engine.step({})
    before = engine.state()
    engine.max_iterations = 1
    with pytest.raises(SimulationError, match=r"step 1 .*residual \|\|grad E\|\|_inf = [0-9.e+-]+ N > tolerance"):
        engine.step({})
    assert np.array_equal(engine.x, before["x"]) and np.array_equal(engine.v, before["v"])


def test_set_state_replays_bitwise():
    engine = hanging_sheet(res=(4, 4))
    engine.step({})
    s = engine.state()
    first = engine.step({})[0]["state"]
    engine.set_state(s)
    again = engine.step({})[0]["state"]
    assert np.array_equal(first["x"], again["x"]) and np.array_equal(first["v"], again["v"])


# ------------------------------------------------------------------------------------- 7. meshes


def test_rectangle_and_disc_counts_and_areas():
    rect = cloth_mesh.rectangle((0.6, 0.4), (7, 5), center=(1.0, 2.0, 3.0), normal="y")
    assert (rect.n_vertices, len(rect.faces)) == (35, 2 * 6 * 4)
    assert len(rect.edges) == 6 * 5 + 7 * 4 + 6 * 4 and len(rect.hinges) == len(rect.edges) - 2 * (6 + 4)
    assert rect.rest_area.sum() == pytest.approx(0.24, rel=1e-14)
    assert rect.vertex_areas().sum() == pytest.approx(0.24, rel=1e-14)
    assert np.allclose(rect.vertices.mean(axis=0), [1.0, 2.0, 3.0]) and np.ptp(rect.vertices[:, 1]) == 0
    n, r = 5, 0.7
    disc = cloth_mesh.disc(r, rings=n)
    assert (disc.n_vertices, len(disc.faces), len(disc.boundary)) == (1 + 3 * n * (n + 1), 6 * n**2, 6 * n)
    assert disc.rest_area.sum() == pytest.approx(0.5 * 6 * n * r**2 * np.sin(2 * np.pi / (6 * n)), rel=1e-13)
    normals = np.cross(*(disc.vertices[disc.faces[:, k]] - disc.vertices[disc.faces[:, 0]] for k in (1, 2)))
    assert np.all(normals[:, 1] > 0), "disc faces wind consistently"


def _moebius_obj(path, n=24, radius=0.3, half_width=0.06):
    """A Moebius strip (n segments, 2 vertices across) written as OBJ; the seam joins vertex j of the
    last column to vertex 1 - j of the first, so the faces cannot all wind the same way."""
    u = 2 * np.pi * np.arange(n) / n
    verts = []
    for ui in u:
        for v in (-half_width, half_width):
            verts.append(
                [
                    (radius + v * np.cos(ui / 2)) * np.cos(ui),
                    (radius + v * np.cos(ui / 2)) * np.sin(ui),
                    v * np.sin(ui / 2),
                ]
            )
    faces = []
    for i in range(n):
        a, b = 2 * i, 2 * i + 1
        c, d = (2 * (i + 1), 2 * (i + 1) + 1) if i < n - 1 else (1, 0)
        faces += [[a, c, d], [a, d, b]]
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in verts] + [f"f {i + 1} {j + 1} {k + 1}" for i, j, k in faces]
    path.write_text("\n".join(lines) + "\n")
    return np.array(verts), np.array(faces)


def test_moebius_strip_loads_rests_as_is_and_steps(tmp_path):
    """Non-orientable mesh from a file: faces kept as given (windings disagree across some hinge), the
    curved rest shape is an equilibrium (rest angles from the mesh, angle independent of windings:
    zero elastic gradient, energy quadratic in a small perturbation) and it hangs from pinned vertices."""
    verts, faces = _moebius_obj(tmp_path / "moebius.obj")
    mesh = cloth_mesh.from_file(tmp_path / "moebius.obj")
    assert np.array_equal(mesh.faces, faces) and np.allclose(mesh.vertices, verts, rtol=0, atol=1e-15)

    def runs_forward(face, a, b):
        i = list(face).index(a)
        return face[(i + 1) % 3] == b

    disagree = [
        runs_forward(mesh.faces[f1], a, b) == runs_forward(mesh.faces[f2], a, b)
        for (a, b, _, _), (f1, f2) in zip(mesh.hinges, mesh.hinge_faces)
    ]
    assert any(disagree), "the Moebius strip must have a hinge whose faces wind inconsistently"
    engine = ClothEngine(
        mesh,
        ClothMaterial(k_stretch=500.0, k_bend=1e-2, density=0.2),
        fixed=[0, 1, 2, 3],
        gravity=(0, 0, -G),
        frame_dt=5e-3,
    )
    assert np.abs(engine.energy.rest_angle).max() > 0.1, "the rest shape is curved"
    g_mem, g_bend = engine.energy.gradients(mesh.vertices)
    assert np.abs(g_mem).max() < 1e-12 and np.abs(g_bend).max() < 1e-12
    delta = np.random.default_rng(1).standard_normal(mesh.vertices.shape)
    e1, e2 = (engine.elastic_energy(mesh.vertices + s * 1e-4 * delta) for s in (1, 2))
    assert e2 / e1 == pytest.approx(4.0, rel=1e-3)
    for _ in range(5):
        engine.step({})
    assert engine.x[4:, 2].mean() < verts[4:, 2].mean() - 1e-4  # it sags
    assert engine.last_solve["residual"] <= engine.last_solve["tolerance"]


def test_bad_meshes_raise_clear_errors(tmp_path):
    bad = tmp_path / "bad.obj"
    bad.write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match=r"bad\.obj"):
        cloth_mesh.from_file(bad)
    with pytest.raises(ValueError, match=r"missing\.obj' does not exist"):
        cloth_mesh.from_file(tmp_path / "missing.obj")
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=float)
    with pytest.raises(ValueError, match=r"non-manifold edge \[0, 1\] is shared by 3 faces"):
        cloth_mesh.build(x, [[0, 1, 2], [1, 0, 3], [0, 1, 4]], "fan")
    with pytest.raises(ValueError, match=r"degenerate \(zero-area\) faces, first face 1"):
        cloth_mesh.build(x, [[0, 1, 2], [0, 1, 1]], "sliver")


def test_engine_conforms_to_the_contract():
    """Same names and types as the other engines: the Objective can take the cloth's parameters as they are."""
    from cosim.engines.contract import Engine

    engine = hanging_sheet(res=(3, 3), controls=[[0]])
    assert isinstance(engine, Engine)
    params = {p.name: p for p in engine.parameters()}
    assert {(p.kind, p.key) for p in params.values()} == {
        ("state", "x"),
        ("state", "v"),
        ("input", "action"),
        *(("material", k) for k in MATERIAL_KEYS),
    }
    assert all(p.engine == "cloth" and p.scale > 0 for p in params.values())
    assert set(engine.material()) == set(MATERIAL_KEYS)
    _, record = engine.step({})
    out = engine.vjp(record, {"state": engine.state()})
    assert set(out) == {"state", "action", "forces", "added_mass", "boundaries", "material"}
    assert set(out["material"]) == set(MATERIAL_KEYS)
    assert all(np.shape(out["material"][k]) == np.shape(engine.material()[k]) for k in MATERIAL_KEYS)


def test_newton_accepts_a_residual_stalled_at_round_off_only_near_the_tolerance():
    from cosim.engines.cloth_solve import _stalled_at_round_off

    quadratic = [1e2, 1e-2, 4e-7]
    flat = quadratic + [2.3e-9, 2.2e-9, 2.29e-9, 2.19e-9, 2.29e-9]  # cloth_catch, step 963
    assert not _stalled_at_round_off(quadratic, 1.95e-9)
    assert _stalled_at_round_off(flat, 1.95e-9)
    assert not _stalled_at_round_off(flat, 1e-12)  # 2000x the tolerance: not converged
    still_improving = quadratic + [2e-8, 1e-8, 5e-9, 2.5e-9, 2.2e-9]
    assert not _stalled_at_round_off(still_improving, 1.95e-9)
    wandering = quadratic + [2.3e-9, 2.9e-7, 4e-8, 1e-7, 2.9e-7]  # round-off steps that raise the residual
    assert _stalled_at_round_off(wandering, 1.95e-9)
    assert not _stalled_at_round_off(quadratic + [3e-7, 2.9e-7, 4e-8, 1e-7, 2.9e-7], 1.95e-9)  # best 150x tol
