"""The cloth as an MPM boundary: nearest faces, penetration tracing, momentum balance, no pass-through, adjoints.

The cloth is given as plain arrays (a static sheet, a Möbius strip); the MPM engines are
small 3D ones (16^3 cells) built directly, float64 on the CPU (conftest)."""

from types import SimpleNamespace

import numpy as np
import pytest
import taichi as ti

from cosim.bench.kernel_profile import counting_launches
from cosim.couplers.cloth_boundary import ClothBoundary
from cosim.couplers.cloth_mesh_query import MeshQuery
from cosim.couplers.cloth_tracing import ClothTracingError
from cosim.couplers.contact import ForecastContact, GridContact, ParticlePenalty
from cosim.couplers.mpm_cloth import MPMClothCoupler
from cosim.engines.mpm import MPMConfig, MPMEngine, ParticleBody

DX = 1 / 16
SHEET_Y = 0.45


# ---------------------------------------------------------------------------- meshes and engines
def quad_grid(points: np.ndarray, wrap_twisted: bool = False) -> np.ndarray:
    """Triangles of a (nu, nv) grid of vertex indices; ``wrap_twisted`` closes u with a half twist (Möbius)."""
    nu, nv = points.shape
    faces = []
    for i in range(nu if wrap_twisted else nu - 1):
        for j in range(nv - 1):
            a, d = points[i, j], points[i, j + 1]
            if i + 1 < nu:
                b, c = points[i + 1, j], points[i + 1, j + 1]
            else:  # the seam: row 0 seen upside down
                b, c = points[0, nv - 1 - j], points[0, nv - 2 - j]
            faces += [[a, b, c], [a, c, d]]
    return np.array(faces, dtype=np.int32)


def flat_sheet(n: int, lo: float, hi: float, y: float = SHEET_Y, jitter: float = 0.0, seed: int = 0):
    """An n x n quad sheet over [lo, hi]^2 in x, z at height y (optionally jittered in y)."""
    s = np.linspace(lo, hi, n + 1)
    X, Z = np.meshgrid(s, s, indexing="ij")
    Y = y + jitter * np.random.default_rng(seed).standard_normal(X.shape)
    verts = np.stack([X, Y, Z], axis=-1).reshape(-1, 3)
    return verts, quad_grid(np.arange(len(verts)).reshape(n + 1, n + 1))


def mobius(nu: int = 40, nv: int = 4, radius: float = 0.3, half_width: float = 0.05):
    """A Möbius strip around (0.5, 0.5, 0.5): X(u, v) = ((R + v cos(u/2)) cos u, (R + v cos(u/2)) sin u,
    v sin(u/2)); nu x nv quads, the last column joined to the first with the twist."""
    u = 2 * np.pi * np.arange(nu) / nu
    v = np.linspace(-half_width, half_width, nv + 1)
    U, V = np.meshgrid(u, v, indexing="ij")
    verts = np.stack(mobius_point(U, V, radius), axis=-1).reshape(-1, 3)
    return verts, quad_grid(np.arange(len(verts)).reshape(nu, nv + 1), wrap_twisted=True)


def mobius_point(u, v, radius=0.3):
    r = radius + v * np.cos(u / 2)
    return 0.5 + r * np.cos(u), 0.5 + r * np.sin(u), 0.5 + v * np.sin(u / 2)


def mobius_normal(u, radius=0.3):
    """Unit normal of the strip's centre line, continuous in u (N(u + 2 pi) = -N(u))."""
    du = np.array([-radius * np.sin(u), radius * np.cos(u), 0.0])
    dv = np.array([np.cos(u / 2) * np.cos(u), np.cos(u / 2) * np.sin(u), np.sin(u / 2)])
    n = np.cross(du, dv)
    return n / np.linalg.norm(n)


def mpm(positions, velocity=(0.0, 0.0, 0.0), gravity=(0.0, -9.81, 0.0), E=1e4):
    """A forward-only 3D MPM engine (16^3 cells, no walls) with one elastic body at ``positions``."""
    cfg = MPMConfig(dim=3, cells=(16, 16, 16), dx=DX, gravity=gravity, wall="none")
    vel = np.broadcast_to(np.asarray(velocity, dtype=float), positions.shape).copy()
    body = ParticleBody("block", "elastic", E, 0.3, 1000.0, (DX / 2) ** 3, positions, vel)
    return MPMEngine(cfg, [body])


def block(lo_y: float, height: float = 0.1, width: float = 0.2) -> np.ndarray:
    s = DX / 2
    xs = 0.5 - width / 2 + s * (np.arange(round(width / s)) + 0.5)
    ys = lo_y + s * (np.arange(round(height / s)) + 0.5)
    return np.stack(np.meshgrid(xs, ys, xs, indexing="ij"), axis=-1).reshape(-1, 3)


def reference_distance(x, a, b, c):
    """Point-triangle distance by another construction than Ericson's: the plane distance when the
    projection falls inside the triangle (edge sign tests), else the nearest of the three clamped
    segment points. Broadcasts over leading axes."""
    n = np.cross(b - a, c - a)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    q = x - ((x - a) * n).sum(-1, keepdims=True) * n
    inside = np.ones(np.broadcast_shapes(x.shape, a.shape)[:-1], dtype=bool)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        inside &= (np.cross(p1 - p0, q - p0) * n).sum(-1) >= 0
    segs = []
    for p0, p1 in ((a, b), (b, c), (c, a)):
        d = p1 - p0
        t = np.clip(((x - p0) * d).sum(-1) / (d * d).sum(-1), 0.0, 1.0)
        segs.append(np.linalg.norm(x - (p0 + t[..., None] * d), axis=-1))
    return np.where(inside, np.linalg.norm(x - q, axis=-1), np.min(segs, axis=0))


# ---------------------------------------------------------------------------- a probe of the ti.funcs
@ti.kernel
def _probe(
    src: ti.template(), s: ti.i32, pts: ti.template(), pid: ti.template(), dps: ti.template(), out: ti.template()
):
    """L = sum_i 0.7 d_i + n_i . (0.3, -0.2, 0.5) + v_c,i . (0.4, 0.1, -0.6); each point also hands back
    the reaction dp_i (1 + d_i) (so the impulses depend on the geometry)."""
    for i in range(pts.shape[0]):
        x, p = pts[i], pid[i]
        d, n = src.distance_normal(s, 0, x, p)
        vc = src.contact_velocity(s, 0, x, p)
        src.add_reaction(s, 0, x, dps[i] * (1.0 + d), p)
        out[None] += 0.7 * d + n.dot(ti.Vector([0.3, -0.2, 0.5])) + vc.dot(ti.Vector([0.4, 0.1, -0.6]))


@ti.kernel
def _distances(src: ti.template(), s: ti.i32, pts: ti.template(), pid: ti.template(), out: ti.template()):
    for i in range(pts.shape[0]):
        out[i] = src.distance(s, 0, pts[i], pid[i])


_PROBE_FIELDS: dict = {}  # one set of fields per particle count (new fields would recompile the kernel)


def particle_distances(src, engine, s: int = 0) -> np.ndarray:
    """The signed distance every particle of ``engine`` (slot 0) sees at substep s."""
    n = engine.n_particles
    if n not in _PROBE_FIELDS:
        _PROBE_FIELDS[n] = ti.Vector.field(3, float, n), ti.field(ti.i32, n), ti.field(float, n)
    pts, pid, out = _PROBE_FIELDS[n]
    pts.from_numpy(engine.x.to_numpy()[0])
    pid.from_numpy(np.arange(n, dtype=np.int32))
    _distances(src, s, pts, pid, out)
    return out.to_numpy()


@ti.kernel
def _frames(src: ti.template(), pts: ti.template(), pid: ti.template(), out: ti.template()):
    """(distance, normal, contact velocity) of each point, as a contact model reads them at substep 0."""
    for i in range(pts.shape[0]):
        d, n = src.distance_normal(0, 0, pts[i], pid[i])
        vc = src.contact_velocity(0, 0, pts[i], pid[i])
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = d, n[0], n[1], n[2]
        out[i, 4], out[i, 5], out[i, 6] = vc[0], vc[1], vc[2]


def cloth_states(verts, v=None, tracking=None) -> dict:
    return {"x": verts, "v": np.zeros_like(verts) if v is None else v, "tracking": tracking}


# ---------------------------------------------------------------------------- nearest face
def curved_mesh(n=14, seed=0):
    """A wavy sheet, jittered, with every third face's winding reversed."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.1, 0.9, n)
    U, W = np.meshgrid(s, s, indexing="ij")
    verts = np.stack([U, 0.5 + 0.2 * np.sin(5 * U) * np.cos(4 * W), W], -1).reshape(-1, 3)
    verts += rng.normal(0.0, 0.01, verts.shape)
    faces = quad_grid(np.arange(n * n).reshape(n, n))
    faces[::3] = faces[::3, ::-1]
    return verts, faces


def test_nearest_face_matches_brute_force():
    """The hash query against a brute force over every face with an independent point-triangle
    distance, on 4000 random points around a wavy, jittered mesh of mixed windings: the same face
    up to ties (equal distances), distances to 1e-12 (float64), and no face beyond the band."""
    verts, faces = curved_mesh()
    band = 0.08
    query = MeshQuery(faces, len(verts), band)
    query.update(verts)
    pts = np.random.default_rng(1).uniform([0.05, 0.2, 0.05], [0.95, 0.8, 0.95], (4000, 3))
    face, dist, bary = query.query(pts)
    tri = verts[faces]
    D = reference_distance(pts[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    near = D.min(axis=1) < band
    assert 1000 < near.sum() < len(pts)  # both cases occur
    assert np.all(face[~near] == -1)
    i = np.flatnonzero(near)
    assert np.abs(dist[i] - D[i].min(axis=1)).max() < 1e-12
    assert np.abs(D[i, face[i]] - D[i].min(axis=1)).max() < 1e-12  # the chosen face is a nearest one
    ties = (D[i] <= D[i].min(axis=1, keepdims=True) + 1e-12).sum(axis=1) > 1
    assert np.all(face[i][~ties] == D[i][~ties].argmin(axis=1))  # identical where unique
    closest = np.einsum("nk,nkd->nd", bary[i], tri[face[i]])
    assert np.abs(np.linalg.norm(pts[i] - closest, axis=1) - dist[i]).max() < 1e-12
    assert np.abs(bary[i].sum(axis=1) - 1).max() < 1e-14 and bary[i].min() >= 0


# ---------------------------------------------------------------------------- tracing
def trace_path(src, engine, verts, path, tracking=None):
    """Move the engine's single particle along ``path`` (n, 3), tracing after each move; returns the
    inside flags and the signed distances seen at each point."""
    src.write(cloth_states(verts, tracking=tracking))
    inside, dist = [], []
    for k, x in enumerate(path):
        state = engine.state()
        state["x"] = x[None]
        engine.set_state(state)
        src.before_substep(0, 0 if k == 0 else 1)
        s = 0 if k == 0 else 1
        inside.append(int(src.tracer.inside_s.to_numpy()[s % src.slots, 0]))
        dist.append(particle_distances(src, engine, s)[0])
    src.tracer.check()  # what the traces met (a macro step's reactions check it)
    return np.array(inside), np.array(dist)


@pytest.fixture(scope="module")
def one_particle_sheet():
    engine = mpm(np.array([[0.5, 0.6, 0.5]]))
    verts, faces = flat_sheet(10, 0.25, 0.75)
    return engine, ClothBoundary(engine, verts, faces), verts


def test_crossing_in_small_steps_flips_inside_once(one_particle_sheet):
    """A particle moved down through the sheet in steps of a tenth of the band: inside flips exactly
    once, where it crosses, and the signed distance changes sign there (it is y - y_sheet above, and
    stays negative below: the particle is inside)."""
    engine, src, verts = one_particle_sheet
    ys = SHEET_Y + src.band * np.linspace(0.5, -0.5, 11) + 1e-4
    path = np.stack([np.full_like(ys, 0.52), ys, np.full_like(ys, 0.47)], axis=1)
    inside, dist = trace_path(src, engine, verts, path)
    assert list(inside) == [0] * 6 + [1] * 5
    assert np.allclose(dist, np.where(ys > SHEET_Y, 1, -1) * np.abs(ys - SHEET_Y), atol=1e-14)
    back, dist_back = trace_path(src, engine, verts, path[::-1], tracking=src.tracer.state())
    assert list(back) == [1] * 5 + [0] * 6  # and back out
    assert np.allclose(dist_back, dist[::-1], atol=1e-14)


def test_a_step_longer_than_the_band_stops_the_run(one_particle_sheet):
    """Crossing by more than the band in one move cannot be traced: a clear error naming the fix."""
    engine, src, verts = one_particle_sheet
    path = np.array([[0.5, SHEET_Y + 0.3 * src.band, 0.5], [0.5, SHEET_Y - 0.8 * src.band, 0.5]])
    with pytest.raises(ClothTracingError, match=r"particle 0 .*before substep 1;.*smaller substeps"):
        trace_path(src, engine, verts, path)


def test_a_jump_out_of_the_neighbourhood_stops_the_run():
    """With a tiny search radius a lateral move within the band reaches a face outside the
    neighbourhood of the last one: the error names the particle and the fix."""
    engine = mpm(np.array([[0.5, 0.6, 0.5]]))
    verts, faces = flat_sheet(25, 0.25, 0.75)  # faces 2 cm across, band 6.25 cm
    src = ClothBoundary(engine, verts, faces, radius=1e-3)
    path = np.array([[0.4, SHEET_Y + 0.01, 0.5], [0.4 + 0.9 * src.band, SHEET_Y + 0.01, 0.5]])
    lost = r"particle 0 .*outside the neighbourhood.* at substep 1:.*search radius"
    with pytest.raises(ClothTracingError, match=lost):
        trace_path(src, engine, verts, path)


def test_moebius_strip_keeps_its_side_across_the_seam_and_flips_once_through_it():
    """A particle slides along the strip's centre line (on vertices and edges of the mesh) across
    the twisted seam at a fixed offset on one side: no flip and a positive distance all the way.
    Then it is pushed through the sheet at the seam: exactly one flip."""
    verts, faces = mobius()
    engine = mpm(np.array([[0.5, 0.5, 0.5]]))
    band = 0.03
    src = ClothBoundary(engine, verts, faces, band=band)
    offset = 0.3 * band
    us = np.linspace(2 * np.pi * 0.75, 2 * np.pi * 1.25, 200)  # steps of 5 mm, across u = 2 pi
    path = np.array([np.array(mobius_point(u, 0.0)) + offset * mobius_normal(u) for u in us])
    inside, dist = trace_path(src, engine, verts, path)
    assert not inside.any()
    assert dist.min() > 0.5 * offset and dist.max() < 1.5 * offset
    u = 2 * np.pi + 0.05  # just past the seam
    heights = np.linspace(offset, -offset, 12)
    through = np.array([np.array(mobius_point(u, 0.01)) + h * mobius_normal(u) for h in heights])
    inside, dist = trace_path(src, engine, verts, through)
    flip = int(np.argmax(inside))
    assert inside[0] == 0 and list(inside) == [0] * flip + [1] * (len(inside) - flip)  # exactly one flip
    assert np.all(dist[:flip] > 0) and np.all(dist[flip:] < 0)
    assert src.max_neighbours < 200


# ---------------------------------------------------------------------------- with the MPM
MODELS = ["grid", "particle", "forecast"]
# a coupled step's host arrays: the cloth's states in (2), reactions and tracing errors out (2), the survey (1)
ARRAYS_PER_STEP = 5


def cloth_scene(model, positions, velocity, gravity=(0.0, -9.81, 0.0), stiffness=400.0):
    """A block over a static 10 x 10 sheet (5 cm quads) under a contact model; the coupler and a
    stand-in cloth engine that never moves."""
    engine = mpm(positions, velocity, gravity)
    verts, faces = flat_sheet(10, 0.25, 0.75)
    src = ClothBoundary(engine, verts, faces)
    cloth = SimpleNamespace(
        name="cloth", state=lambda: {"x": verts, "v": np.zeros_like(verts)}, free=np.ones(len(verts), dtype=bool)
    )
    coupler = MPMClothCoupler(cloth)
    engine.attach_boundary(coupler.source, src)
    if model == "grid":  # band one cell: the sheet lies 0.8 cells below the nodes above it
        GridContact(engine, [src], friction=0.3, band=DX)
    elif model == "forecast":
        ForecastContact(engine, [src], friction=0.3)
    else:
        ParticlePenalty(engine, [src], stiffness, friction=0.3)
    return engine, src, coupler


_SCENES: dict = {}


def scene(model, positions, velocity, trace=True):
    """One engine per contact model for the whole module (each new engine compiles its kernels anew,
    ~10 s), reset to a block at ``positions`` and a fresh tracing state."""
    if model not in _SCENES:
        _SCENES[model] = cloth_scene(model, positions, velocity)
    engine, src, coupler = _SCENES[model]
    n = len(positions)
    eye = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    vel = np.broadcast_to(np.asarray(velocity, dtype=float), positions.shape).copy()
    engine.set_state({"x": positions, "v": vel, "C": np.zeros((n, 3, 3)), "F": eye})
    coupler.set_state(None)
    src.set_tracing(trace)
    return engine, src, coupler


def run(engine, coupler, steps, K, dt):
    """``steps`` macro steps of K substeps; returns the summed reaction impulse (V, 3) and forces."""
    total = 0.0
    for _ in range(steps):
        states, record = coupler.boundary(dt, K)
        out, _ = engine.step({"dt": dt, "substeps": K, "impulse": None, "boundaries": {coupler.source: states}})
        reactions = out["reactions"][coupler.source]
        assert np.allclose(coupler.forces(record, reactions)["forces"] * K * dt, reactions["impulse"])
        total = total + reactions["impulse"]
    return total


@pytest.mark.parametrize("model", MODELS)
def test_momentum_lost_by_the_block_is_the_cloth_impulse(model):
    """Third law: over 8 x 4 substeps (the penalty model acts once particles have crossed), the particles' momentum change minus gravity's M g t equals
    minus the summed per-vertex impulses on the cloth, to round-off (float64, no walls)."""
    x0 = block(SHEET_Y - 0.005)  # the lowest particles 1.1 cm above the sheet, 2.4 cm of fall
    engine, _src, coupler = scene(model, x0, (0.0, -1.5, 0.0))
    m = engine.mass[:, None]
    p0 = (m * engine.state()["v"]).sum(axis=0)
    K, dt, steps = 4, 5e-4, 8
    impulse = run(engine, coupler, steps, K, dt)
    p1 = (m * engine.state()["v"]).sum(axis=0)
    gravity = m.sum() * np.array([0.0, -9.81, 0.0]) * steps * K * dt
    assert np.linalg.norm(impulse.sum(axis=0)) > 0.1 * np.linalg.norm(p0)  # a real collision
    assert np.abs(p1 - p0 - gravity + impulse.sum(axis=0)).max() < 1e-12 * np.abs(p0).max()


def test_a_step_replays_bit_for_bit_from_its_boundary_input():
    """The tracking state is part of a step's boundary input (the MPM's vjp recomputes a step from its
    record): restoring the MPM state and writing the recorded input again gives the same particles and
    the same tracking state after the step, bit for bit, while particles are crossing the sheet."""
    engine, _src, coupler = scene("particle", block(SHEET_Y - 0.005), (0.0, -1.5, 0.0))
    K, dt = 4, 5e-4
    run(engine, coupler, 6, K, dt)
    before, (states, _record) = engine.state(), coupler.boundary(dt, K)
    inputs = {"dt": dt, "substeps": K, "impulse": None, "boundaries": {coupler.source: states}}
    first, record = engine.step(inputs)
    assert record.nbytes > sum(a.nbytes for a in first["reactions"][coupler.source]["tracking"].values())
    engine.set_state(before)
    again, _ = engine.step(inputs)
    tracked = first["reactions"][coupler.source]["tracking"]
    assert tracked["inside"].sum() > 0 and (tracked["face"] >= 0).sum() > 50  # tracing is at work
    assert np.array_equal(first["state"]["x"], again["state"]["x"])
    for key in tracked:
        assert np.array_equal(tracked[key], again["reactions"][coupler.source]["tracking"][key])


def test_a_coupled_step_hands_the_device_the_same_host_arrays_whatever_its_substeps():
    """What the traces meet stays on the device until the macro step's end (on a GPU every read between
    substeps is a wait): a coupled step of 2 and of 6 substeps takes and returns the same host arrays
    (the cloth's states in, reactions and tracing errors out in one launch each), and a substep more only
    launches kernels."""
    per_step = {}
    for K in (2, 6):
        engine, _src, coupler = scene("forecast", block(SHEET_Y - 0.005), (0.0, -1.5, 0.0))
        run(engine, coupler, 1, K, 5e-4)  # compiles
        with counting_launches() as tally:
            run(engine, coupler, 2, K, 5e-4)
        per_step[K] = {key: count / 2 for key, count in tally.items()}
    assert per_step[6]["arrays"] == per_step[2]["arrays"] <= ARRAYS_PER_STEP, per_step
    assert per_step[6]["launches"] > per_step[2]["launches"], per_step


def test_a_particle_too_fast_for_tracing_stops_the_macro_step():
    """A block thrown at the sheet faster than tracing can follow (|v| dt above the band): the coupled
    step raises at its end, naming the substep where it began."""
    engine, src, coupler = scene("forecast", block(SHEET_Y + 0.01), (0.0, -40.0, 0.0))
    assert 40.0 * 2e-3 > src.band
    with pytest.raises(ClothTracingError, match=r"particle \d+ .*before substep 1;.*smaller substeps"):
        run(engine, coupler, 1, 2, 2e-3)


def wrong_side(x: np.ndarray, depth: float) -> int:
    """Particles over the sheet's footprint more than ``depth`` below it."""
    over = (np.abs(x[:, 0] - 0.5) < 0.25) & (np.abs(x[:, 2] - 0.5) < 0.25)
    return int((over & (x[:, 1] < SHEET_Y - depth)).sum())


@pytest.mark.parametrize("model,trace", [("forecast", True), ("particle", True), ("particle", False)])
def test_the_sheet_stops_a_falling_block_only_with_tracing(model, trace):
    """A block dropped at 1.5 m/s onto the sheet under gravity for 0.16 s: with tracing no particle
    ends more than a quarter cell below it (the penalty model lets particles in that deep at most:
    its spring stops 1.5 m/s within v / sqrt(k g / dx) ~ 0.1 dx per particle layer). Without tracing
    the penalty model sees every crossed particle as legal on its new side and the block falls through."""
    engine, _src, coupler = scene(model, block(SHEET_Y + 0.01), (0.0, -1.5, 0.0), trace=trace)
    run(engine, coupler, 40, 10, 4e-4)
    x = engine.state()["x"]
    if trace:
        assert wrong_side(x, 0.25 * DX) == 0
        assert x[:, 1].min() > SHEET_Y - 0.25 * DX
    else:
        assert wrong_side(x, 0.25 * DX) > 0.9 * len(x)


# ---------------------------------------------------------------------------- adjoints of the ti.funcs
def test_source_gradients_match_central_differences():
    """dL/d(vertex positions), dL/d(vertex velocities) and dL/d(query points) of the probe loss (the
    distance, normal and contact velocity every contact model reads, the reactions they hand back and
    the added mass the forecast model's engagement gives each vertex, ``_contact_mass``) against central
    differences (float64, eps 1e-7: the engagement's exponential blend makes eps 1e-6 truncation-bound at
    2.8e-6, random directions): relative error below 1e-6.
    Points: particles above and (traced) below the face interior, beyond a free edge and a free
    corner (edge and vertex regions), look-ahead points of particles, and grid nodes near the sheet."""
    verts, faces = flat_sheet(4, 0.3, 0.7, jitter=0.01, seed=3)
    particles = np.array(
        [[0.46, SHEET_Y + 0.02, 0.52], [0.55, SHEET_Y - 0.015, 0.43], [0.73, SHEET_Y + 0.01, 0.5], [0.72, 0.47, 0.72]]
    )
    engine = mpm(particles)
    src = ClothBoundary(engine, verts, faces, band=0.06, requires_grad=True)
    ForecastContact(engine, [src], friction=0.3)  # the engagement behind the added mass
    src.write(cloth_states(verts))
    src.before_substep(0, 0)
    tracking = src.tracer.state()
    tracking["inside"][1] = 1  # particle 1 is below the sheet but belongs above it
    nodes = np.array([[8, 7, 8], [9, 7, 6]]) * DX  # 0.4375: about a cell below the sheet
    pts_np = np.concatenate([particles, particles[:2] + [[0.003, -0.03, 0.002], [0.001, 0.02, -0.004]], nodes])
    pid_np = np.array([0, 1, 2, 3, 0, 1, -1, -1], dtype=np.int32)
    n = len(pts_np)
    rng = np.random.default_rng(5)
    vel = rng.standard_normal(verts.shape)
    dps_np, W = rng.standard_normal((n, 3)) * 0.1, rng.standard_normal(verts.shape)
    W_mass = rng.standard_normal(len(verts)) * 10.0
    pts, pid, dps = ti.Vector.field(3, float, n, needs_grad=True), ti.field(ti.i32, n), ti.Vector.field(3, float, n)
    out = ti.field(float, (), needs_grad=True)
    pid.from_numpy(pid_np)
    dps.from_numpy(dps_np)

    def loss(v_pos, v_vel, x):
        src.write(cloth_states(v_pos, v_vel, tracking))
        src.before_substep(0, 0)
        pts.from_numpy(x)
        out[None] = 0.0
        _probe(src, 0, pts, pid, dps, out)
        src.contact_mass.fill(0)
        src._contact_mass(0, 0, 1)  # substep 0 of a one-substep frame
        mass = src.contact_mass.to_numpy()
        return out[None] + float((src.impulse.to_numpy() * W).sum()) + float((mass * W_mass).sum())

    loss(verts, vel, pts_np)
    d = particle_distances(src, engine)
    assert d[0] > 0 and d[1] < 0 and np.all(d < 0.06)  # above, traced inside, near the edge and corner
    assert np.count_nonzero(src.contact_mass.to_numpy()) >= 6  # the added mass reaches several vertices
    src.zero_grad()
    pts.grad.fill(0)
    out.grad[None] = 1.0
    src.seed_reaction_grads({"impulse": W, "mass": W_mass})
    _probe.grad(src, 0, pts, pid, dps, out)
    src.before_substep_grad(0, 0)  # through each particle's blended frame
    grads = src.state_grads(1)
    g_pts = pts.grad.to_numpy()
    eps = 1e-7
    for which, g in (("x", grads["x"]), ("v", grads["v"]), ("pts", g_pts)):
        inputs = {"x": verts, "v": vel, "pts": pts_np}
        step = {which: rng.standard_normal(inputs[which].shape)}
        plus = [inputs[k] + eps * step.get(k, 0.0) for k in ("x", "v", "pts")]
        minus = [inputs[k] - eps * step.get(k, 0.0) for k in ("x", "v", "pts")]
        fd = (loss(*plus) - loss(*minus)) / (2 * eps)
        direction = step[which]
        assert abs(fd) > 1e-3, which
        assert abs(fd - (g * direction).sum()) < 1e-6 * abs(fd), (which, fd, (g * direction).sum())


def test_contact_frame_is_continuous_where_the_nearest_face_changes():
    """Two faces folded into a valley (dihedral angle ~53 degrees), particles 2 cm above the crease, a
    hair (1e-7 m) either side of the plane where their nearest face switches. With one face the normal
    turned by the fold angle there and the contact velocity jumped between the two faces' vertices;
    the blended frame moves by O(1e-7 / tau) only (tau = 1e-3 band): distance, normal and velocity
    agree to 1e-3 on both sides. Away from the switch (2 mm off) the frame is the nearest face's."""
    y0, h = SHEET_Y, 0.1
    verts = np.array([[0.3, y0, 0.5], [0.7, y0, 0.5], [0.5, y0 + h, 0.3], [0.5, y0 + h, 0.7]])
    faces = np.array([[0, 1, 2], [1, 0, 3]])
    vel = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.5], [0.0, -1.0, -0.5]])
    hair, off = 1e-7, 2e-3
    pts_np = np.array([[0.5, y0 + 0.02, 0.5 + z] for z in (-hair, hair, -off, off)])
    engine = mpm(pts_np, gravity=(0.0, 0.0, 0.0))
    src = ClothBoundary(engine, verts, faces, band=0.06)
    src.write(cloth_states(verts, vel))
    src.before_substep(0, 0)
    pts, pid, out = ti.Vector.field(3, float, 4), ti.field(ti.i32, 4), ti.field(float, (4, 7))
    pts.from_numpy(pts_np)
    pid.from_numpy(np.arange(4, dtype=np.int32))
    _frames(src, pts, pid, out)
    frame = out.to_numpy()
    assert np.abs(frame[0] - frame[1]).max() < 1e-3, frame[:2]
    # 2 mm off the switch each side has its own face: normal and velocity of that face alone
    for k, face in ((2, 0), (3, 1)):
        a, b, c = verts[faces[face]]
        normal = np.cross(b - a, c - a)
        normal *= np.sign(normal[1]) / np.linalg.norm(normal)
        assert np.abs(frame[k, 1:4] - normal).max() < 1e-6, (k, frame[k, 1:4], normal)
    assert np.abs(frame[2, 1:4] - frame[3, 1:4]).max() > 0.5  # the fold: the faces' normals differ
