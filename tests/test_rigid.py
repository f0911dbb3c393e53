"""DART rigid engine: physics against closed forms, every vjp block against central differences over DART's
own step, input errors, and URDF loading."""

from __future__ import annotations

import numpy as np
import pytest

from cosim.engines.rigid import RigidEngine
from cosim.engines.rigid_build import LinkSpec, ShapeSpec, SkeletonSpec, link_mass_properties, shape_mass_properties
from cosim.errors import InputError, SimulationError

DT = 1e-3
G = 9.81
BOX = ShapeSpec("box", size=(0.1, 0.2, 0.3))
VJP_RTOL = 1e-6  # measured 1e-10..3e-7: the differences' own truncation/round-off error


def free_body(
    control="passive", q0=(0.3, -0.2, 0.5, 1.0, 2.0, 3.0), qd0=(1, 2, 3, 0.4, 0.5, 0.6), **link
) -> SkeletonSpec:
    link = {"density": 500.0, **link}
    return SkeletonSpec(
        "puck", links=[LinkSpec("b", [BOX], q0=list(q0), qd0=list(qd0), **link)], default_control=control
    )


def chain(mode="torque") -> SkeletonSpec:
    """Revolute -> prismatic -> ball, with damping and offsets, so M, C and J are all non-trivial."""
    capsule = ShapeSpec("capsule", radius=0.05, height=0.2, position=(0, 0, -0.15), rotation=(10, 0, 20))
    return SkeletonSpec(
        "arm",
        links=[
            LinkSpec("l1", [BOX], density=1000, joint="revolute", axis=(0, 1, 0), damping=0.3, q0=0.4, qd0=0.7),
            LinkSpec(
                "l2",
                [capsule],
                density=800,
                joint="prismatic",
                parent="l1",
                origin_position=(0, 0, -0.3),
                axis=(0, 0.6, 0.8),
                damping=0.1,
                q0=0.05,
                qd0=-0.2,
            ),
            LinkSpec(
                "l3",
                [ShapeSpec("sphere", radius=0.05)],
                mass=0.3,
                joint="ball",
                parent="l2",
                origin_position=(0.1, 0, -0.2),
                q0=[0.2, -0.3, 0.4],
                qd0=[1, -2, 0.5],
                damping=0.05,
            ),
        ],
        controls={"l1": mode, "l2": "torque", "l3": mode},
    )


def ground() -> SkeletonSpec:
    return SkeletonSpec(
        "ground",
        links=[
            LinkSpec("g", [ShapeSpec("box", size=(2, 2, 0.2))], mass=1.0, joint="weld", origin_position=(0, 0, -0.1))
        ],
    )


def rel_err(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-12))


# ------------------------------------------------------------------------------------------------ replay


def test_set_state_replay_is_bitwise():
    falling = free_body(q0=(0.1, 0.2, 0.0, 0.0, 0.0, 0.12), qd0=(0, 0, 0, 0.2, 0, -0.5))
    eng = RigidEngine([ground(), falling, chain()], DT)
    rng = np.random.default_rng(1)
    actions = rng.normal(size=(60, eng.action_size))
    for a in actions[:20]:
        eng.advance(a)
    s = eng.flat_state()
    first = [eng.advance(a).next_state for a in actions[20:]]
    eng.set_flat_state(s)
    second = [eng.advance(a).next_state for a in actions[20:]]
    assert np.array_equal(np.array(first), np.array(second))
    assert np.ptp(np.array(first)[:, eng.dofs + 5]) > 0  # the puck's vertical velocity changed: contact happened


# ----------------------------------------------------------------------------------------------- physics


def test_free_fall_matches_semi_implicit_euler():
    eng = RigidEngine([free_body(q0=(0, 0, 0, 0, 0, 1.0), qd0=(0,) * 6)], DT, collision=False)
    n = 300
    for _ in range(n):
        eng.advance()
    z, vz = eng.flat_state()[5], eng.flat_state()[11]
    assert vz == pytest.approx(-G * n * DT, rel=1e-12)
    assert z == pytest.approx(1.0 - G * DT**2 * n * (n + 1) / 2, rel=1e-12)  # v first, then x += dt v
    t = n * DT
    assert abs(z - (1.0 - G * t**2 / 2)) <= G * DT * t / 2 + 1e-12


def pendulum_energy(damping: float, steps: int = 1000) -> tuple[float, float]:
    bob = ShapeSpec("sphere", radius=0.05, position=(0, 0, -0.5))
    spec = SkeletonSpec(
        "pend", links=[LinkSpec("p", [bob], mass=1.0, joint="revolute", axis=(1, 0, 0), damping=damping, q0=1.0)]
    )
    eng = RigidEngine([spec], DT, collision=False)
    skel = eng.skeletons[0]
    e0 = skel.computeKineticEnergy() + skel.computePotentialEnergy()
    for _ in range(steps):
        eng.advance()
    return e0, skel.computeKineticEnergy() + skel.computePotentialEnergy()


def test_pendulum_energy_with_and_without_damping():
    swing = 1.0 * G * 0.5 * (1 - np.cos(1.0))  # m g l (1 - cos q0): the energy exchanged per half swing [J]
    e0, e1 = pendulum_energy(0.0)
    assert abs(e1 - e0) < 5e-3 * swing  # semi-implicit Euler: bounded O(dt omega) oscillation, no drift
    e0, e1 = pendulum_energy(0.2)
    assert e0 - e1 > 0.1 * swing


def test_wrench_gives_impulse_response():
    inertia = np.array([0.02, 0.05, 0.07])
    spec = free_body("passive", q0=(0.4, -0.3, 0.2, 0, 0, 0), qd0=(0,) * 6, mass=2.0, inertia=list(inertia))
    eng = RigidEngine([spec], DT, gravity=(0, 0, 0), collision=False)
    R = eng.body_states()["rotation"][0]
    assert np.allclose(link_mass_properties(spec.links[0])[1], 0)  # COM at the origin: torque about either
    w = np.array([[0.3, -0.2, 0.5, 1.0, -2.0, 3.0]])
    eng.advance(None, w)
    b = eng.body_states()
    assert np.allclose(b["linear_velocity"][0], w[0, 3:] * DT / 2.0, rtol=1e-12, atol=0)
    I_world = R @ np.diag(inertia) @ R.T
    assert np.allclose(b["angular_velocity"][0], np.linalg.solve(I_world, w[0, :3]) * DT, rtol=1e-10, atol=0)


def test_joint_limits_are_enforced():
    spec = SkeletonSpec(
        "j",
        links=[LinkSpec("l", [BOX], density=1000, joint="revolute", axis=(1, 0, 0), lower=-0.1, upper=0.1)],
        default_control="torque",
    )
    eng = RigidEngine([spec], DT, gravity=(0, 0, 0), collision=False)
    for _ in range(500):
        eng.advance(np.array([1.0]))
    q = eng.flat_state()[0]
    assert 0.09 < q < 0.1 + 1e-3  # unlimited it would reach ~ 0.5 a t^2 >> 1 rad


def test_rigid_collision_can_be_switched_off():
    def final_z(collision: bool) -> float:
        eng = RigidEngine([ground(), free_body(q0=(0, 0, 0, 0, 0, 0.2), qd0=(0,) * 6)], DT, collision=collision)
        for _ in range(400):
            eng.advance()
        return eng.flat_state()[5]

    assert final_z(True) == pytest.approx(0.15, abs=0.01)  # box half-height 0.15 on the ground top z = 0
    assert final_z(False) < -0.5


def test_non_finite_state_names_skeleton_and_step():
    eng = RigidEngine([free_body(), chain()], DT, collision=False)
    eng.advance()
    s = eng.flat_state()
    s[eng.dofs + 6] = np.nan  # stands in for a blow-up (DART zeroes non-finite accelerations, never raises)
    eng.set_flat_state(s)
    with pytest.raises(SimulationError, match=r"'arm'.*after step 2"):
        eng.advance()
    with pytest.raises(InputError, match="non-finite"):
        eng.advance(np.full(eng.action_size, np.nan))


# -------------------------------------------------------------------------------------------------- vjp

SYSTEMS = {
    "free_wrench": lambda: [free_body("wrench")],
    "free_twist": lambda: [free_body("twist")],
    "free_torque": lambda: [free_body("torque")],
    "chain_torque": lambda: [chain("torque")],
    "chain_velocity": lambda: [chain("velocity")],
    "two_skeletons": lambda: [free_body("wrench"), chain("velocity")],
    "free_rotated_origin": lambda: [free_body("twist", origin_position=(1, 2, 3), origin_rotation=(30, -40, 70))],
    "planar_tree": lambda: [planar_tree()],
}


def planar_tree() -> SkeletonSpec:
    """A planar root carrying a free child body: both non-additive and additive integration in one tree."""
    return SkeletonSpec(
        "tree",
        links=[
            LinkSpec("base", [BOX], density=300, joint="planar", q0=[0.1, 0.2, 0.3], qd0=[1, 2, 3]),
            LinkSpec(
                "top",
                [BOX],
                density=300,
                joint="free",
                parent="base",
                origin_position=(0.1, 0, 0),
                q0=[0.3, -0.2, 0.5, 1, 2, 3],
                qd0=[1, 2, 3, 0.4, 0.5, 0.6],
            ),
        ],
        default_control="torque",
    )


def central(f, x, h=1e-5):
    """Central differences of a scalar f at x (any shape)."""
    out = np.zeros(x.size)
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = h
        out[i] = (f(x + e.reshape(x.shape)) - f(x - e.reshape(x.shape))) / (2 * h)
    return out.reshape(x.shape)


@pytest.mark.parametrize("name", SYSTEMS)
def test_step_vjp_matches_finite_differences(name):
    eng = RigidEngine(SYSTEMS[name](), DT, collision=False)
    rng = np.random.default_rng(3)
    s0 = eng.flat_state()
    a = rng.normal(size=eng.action_size)
    w = rng.normal(size=(len(eng.body_names), 6))
    record = eng.advance(a, w)
    g = rng.normal(size=2 * eng.dofs)
    grad_s, grad_a, grad_w, _ = eng.vjp_flat(record, g)
    assert np.array_equal(eng.flat_state(), record.next_state)  # vjp leaves the engine where it was

    def loss(s, a_, w_):
        return g @ eng._advance(s, a_, w_)

    assert rel_err(grad_a, central(lambda x: loss(s0, x, w), a)) < VJP_RTOL
    assert rel_err(grad_w, central(lambda x: loss(s0, a, x), w)) < VJP_RTOL
    assert rel_err(grad_s, central(lambda x: loss(x, a, w), s0)) < VJP_RTOL


@pytest.mark.parametrize("name", ["free_torque", "chain_torque"])
def test_body_states_vjp_matches_finite_differences(name):
    eng = RigidEngine(SYSTEMS[name](), DT, collision=False)
    rng = np.random.default_rng(4)
    nb = len(eng.body_names)
    grads = [rng.normal(size=shape) for shape in ((nb, 3), (nb, 3, 3), (nb, 3), (nb, 3))]
    s0 = eng.flat_state()
    keys = ("position", "rotation", "linear_velocity", "angular_velocity")

    def loss(s):
        eng.set_flat_state(s)
        b = eng.body_states()
        return sum(np.sum(gr * b[k]) for gr, k in zip(grads, keys))

    expected = central(loss, s0)
    got = eng.body_states_vjp(*grads, state=s0)
    assert rel_err(got, expected) < VJP_RTOL


def test_body_velocity_is_origin_velocity():
    eng = RigidEngine([chain()], DT, collision=False)
    b0 = eng.body_states()
    eng.advance()
    b1 = eng.body_states()
    fd = (b1["position"] - b0["position"]) / DT
    assert np.allclose(fd, b1["linear_velocity"], atol=2e-3)  # origin, not COM (differs by ~0.1 m/s here)


# ------------------------------------------------------------------------------------------ mass props


@pytest.mark.parametrize("kind", ["box", "cylinder", "capsule", "sphere"])
def test_primitive_inertia_matches_trimesh(kind):
    import trimesh

    shape = ShapeSpec(kind, size=(0.1, 0.2, 0.3), radius=0.07, height=0.2)
    mesh = {
        "box": lambda: trimesh.creation.box(extents=shape.size),
        "cylinder": lambda: trimesh.creation.cylinder(radius=0.07, height=0.2, sections=256),
        "capsule": lambda: trimesh.creation.capsule(radius=0.07, height=0.2, count=[128, 128]),
        "sphere": lambda: trimesh.creation.icosphere(subdivisions=5, radius=0.07),
    }[kind]()
    m, _, inertia = shape_mass_properties(shape, 1000.0)
    assert m == pytest.approx(1000.0 * mesh.volume, rel=2e-3)
    assert np.allclose(inertia, 1000.0 * mesh.moment_inertia, rtol=5e-3, atol=1e-12)


# ----------------------------------------------------------------------------------------- input errors


def test_bad_inputs_raise_input_error(tmp_path):
    with pytest.raises(InputError, match="URDF file not found"):
        RigidEngine([SkeletonSpec("r", urdf=str(tmp_path / "nope.urdf"))], DT)
    with pytest.raises(InputError, match="unknown joint type 'hinge'"):
        RigidEngine([SkeletonSpec("s", links=[LinkSpec("l", [BOX], density=1.0, joint="hinge")])], DT)
    eng = RigidEngine([chain()], DT)
    with pytest.raises(InputError, match="length 2, expected 5"):
        eng.advance(np.zeros(2))
    with pytest.raises(InputError, match="wrenches"):
        eng.advance(None, np.zeros((1, 6)))
    with pytest.raises(InputError, match="unknown control mode"):
        RigidEngine([SkeletonSpec("s", links=[LinkSpec("l", [BOX], density=1.0)], default_control="force")], DT)
    with pytest.raises(InputError, match="needs a free joint"):
        RigidEngine([chain("wrench")], DT)
    with pytest.raises(InputError, match="mesh file not found"):
        RigidEngine(
            [SkeletonSpec("s", links=[LinkSpec("l", [ShapeSpec("mesh", mesh=str(tmp_path / "x.obj"))], density=1.0)])],
            DT,
        )
    with pytest.raises(InputError, match="'mass' or 'density'"):
        RigidEngine([SkeletonSpec("s", links=[LinkSpec("l", [BOX])])], DT)


def test_open_mesh_needs_explicit_mass(tmp_path):
    import trimesh

    open_mesh = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    open_mesh.update_faces(np.arange(len(open_mesh.faces)) > 1)  # drop one side: not watertight
    path = tmp_path / "open.obj"
    open_mesh.export(path)
    link = LinkSpec("l", [ShapeSpec("mesh", mesh=str(path))], density=1000.0)
    with pytest.raises(InputError, match="not watertight.*mass and inertia"):
        RigidEngine([SkeletonSpec("s", links=[link])], DT)
    link = LinkSpec("l", [ShapeSpec("mesh", mesh=str(path))], mass=1.0, inertia=[1e-3, 1e-3, 1e-3])
    assert RigidEngine([SkeletonSpec("s", links=[link])], DT).dofs == 6


# -------------------------------------------------------------------------------------------------- URDF

URDF = """<?xml version="1.0"?>
<robot name="two">
  <link name="base">
    <inertial><mass value="2.0"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.05" rpy="0 0 0"/><geometry><box size="0.2 0.2 0.1"/></geometry></collision>
  </link>
  <link name="arm">
    <inertial><origin xyz="0 0 0.2"/><mass value="0.5"/>
      <inertia ixx="0.003" iyy="0.003" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.2" rpy="0 1.5707963 0"/>
      <geometry><mesh filename="package://parts/meshes/cube.obj" scale="0.5 0.5 2"/></geometry></collision>
  </link>
  <joint name="hinge" type="revolute">
    <parent link="base"/><child link="arm"/><origin xyz="0 0 0.1"/><axis xyz="1 0 0"/>
    <limit lower="-1.0" upper="1.0" effort="10" velocity="5"/><dynamics damping="0.05"/>
  </joint>
</robot>
"""


def write_urdf(tmp_path, text=URDF):
    import trimesh

    (tmp_path / "parts" / "meshes").mkdir(parents=True)
    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "parts" / "meshes" / "cube.obj")
    path = tmp_path / "two.urdf"
    path.write_text(text)
    return path, {"parts": str(tmp_path / "parts")}


def test_urdf_loads_with_fixed_base_and_mesh_geometry(tmp_path):
    path, packages = write_urdf(tmp_path)
    spec = SkeletonSpec(
        "two",
        urdf=str(path),
        fixed_base=True,
        package_dirs=packages,
        initial_positions={"hinge": 0.5},
        controls={"hinge": "torque"},
    )
    eng = RigidEngine([spec], DT)
    assert eng.dofs == 1 and eng.action_size == 1 and eng.body_names == ["two/base", "two/arm"]
    p0 = eng.body_states()["position"][0].copy()
    for _ in range(400):
        eng.advance(np.array([0.0]))
    assert np.array_equal(eng.body_states()["position"][0], p0)  # welded base holds under gravity
    assert 0.95 < eng.flat_state()[0] < 1.0 + 2e-3  # the arm (COM above the hinge) topples onto its upper limit
    ((box, T_box),) = eng.link_geometry("two/base")
    assert box.kind == "box" and np.allclose(box.size, (0.2, 0.2, 0.1)) and np.allclose(T_box[:3, 3], (0, 0, 0.05))
    ((mesh, T_mesh),) = eng.link_geometry("arm")
    assert mesh.kind == "mesh" and mesh.mesh == str((tmp_path / "parts/meshes/cube.obj").resolve())
    assert np.allclose(mesh.scale, (0.5, 0.5, 2)) and np.allclose(T_mesh[:3, :3] @ [0, 0, 1], [1, 0, 0], atol=1e-6)


def test_urdf_floating_base_and_missing_mesh(tmp_path):
    path, packages = write_urdf(tmp_path)
    eng = RigidEngine([SkeletonSpec("two", urdf=str(path), fixed_base=False, package_dirs=packages)], DT)
    assert eng.dofs == 7
    with pytest.raises(InputError, match="add it to package_dirs"):
        RigidEngine([SkeletonSpec("two", urdf=str(path))], DT)
    (tmp_path / "parts" / "meshes" / "cube.obj").unlink()
    with pytest.raises(InputError, match="mesh file not found.*cube.obj"):
        RigidEngine([SkeletonSpec("two", urdf=str(path), package_dirs=packages)], DT)


def hinge(control: str) -> SkeletonSpec:
    return SkeletonSpec(
        "j",
        links=[LinkSpec("l", [BOX], density=1000, joint="revolute", axis=(1, 0, 0), lower=-0.1, upper=0.1)],
        default_control=control,
    )


def test_velocity_control_stays_inside_the_joint_limits_with_an_exact_gradient():
    """DART ignores position limits on velocity-actuated joints (measured: a hinge commanded at 1 rad/s
    passed its 0.05 rad limit). The engine clips the command instead: at 2 rad/s for 80 steps the
    hinge stops at its 0.1 rad limit after 50, and the gradient of the final state through the
    clipped steps (zero for a clipped command, the limit's dependence on q by the state block)
    matches central differences over the whole sequence."""
    eng = RigidEngine([hinge("velocity")], DT, gravity=(0, 0, 0), collision=False)
    s0 = eng.flat_state()
    actions = np.full((80, 1), 2.0)
    actions[60:] = -0.5  # back off the limit: later steps depend on where it stopped
    records = [eng.advance(a) for a in actions]
    qs = np.array([r.next_state[0] for r in records])
    assert qs.max() <= 0.1 + 1e-12 and qs[55] == pytest.approx(0.1, abs=1e-12)
    assert sum(r.clamped.any() for r in records) >= 5 and not records[0].clamped.any()

    g = np.array([1.0, 0.3])  # loss = g . (q, qd) after the last step

    def final(a: np.ndarray) -> float:
        eng.set_flat_state(s0)
        for row in a:
            eng.advance(row)
        return g @ eng.flat_state()

    grad = np.zeros_like(actions)
    adj = g
    for i in reversed(range(len(records))):
        adj, grad[i], _, _ = eng.vjp_flat(records[i], adj)
    fd = central(final, actions, h=1e-6)
    assert rel_err(grad, fd) < 1e-6
    assert np.all(grad[20:60] == 0)  # commands clipped at the limit do not matter


def test_a_joint_limit_acting_on_a_torque_driven_joint_stops_the_gradient():
    """Torque into a limit: the steps before it differentiate, the first step with a constraint force
    raises, naming the step and the joint's dof."""
    eng = RigidEngine([hinge("torque")], DT, gravity=(0, 0, 0), collision=False)
    records = [eng.advance(np.array([1.0])) for _ in range(500)]
    first = next(i for i, r in enumerate(records) if r.constraint is not None)
    assert 0 < first < 499
    eng.vjp_flat(records[first - 1], np.array([1.0, 0.0]))
    with pytest.raises(SimulationError, match=rf"rigid step {first + 1}: a joint limit .* on 'j/"):
        eng.vjp_flat(records[first], np.array([1.0, 0.0]))
