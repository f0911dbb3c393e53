"""Boundary sources: what the MPM contact models see of a manipulator.

A boundary source holds, for each of its ``n`` bodies and each substep s of the
current macro step, what a contact model needs at a point x (world frame):

    @ti.func distance(s, b, x, p)          signed distance [m], negative inside
    @ti.func distance_normal(s, b, x, p)   (distance, outward unit normal in the world)
    @ti.func contact_velocity(s, b, x, p)  velocity [m/s] of the body's surface point at x
    @ti.func add_reaction(s, b, x, dp, p)  the contact gave the material momentum dp [N s] at x

p is the particle asking (its index in the MPM engine; the forecast model's look-ahead
point x + dt v asks for its particle) or ``NODE`` for a grid node at x. Rigid bodies ignore it;
a cloth needs it, since which side of a sheet is legal is a per-particle state that
penetration tracing carries across steps. ``NODE`` is a Python int and particle indices are
Taichi expressions, so a source that takes p as a ``ti.template()`` tells the two apart when the
kernel compiles (``at_node``) and compiles only the path its caller takes. A source may define
``before_substep(src, s)`` (host): the MPM engine calls it before the particle hooks of substep s
(particles in slot ``src``), to run discrete per-particle work such as nearest-face queries and
tracing; if it also computes something differentiable there, it defines
``before_substep_grad(src, s)``, which the engine calls at the end of substep s's adjoint.

and on the host, the MPM engine's side of the contract (``cosim.engines.contract``):
``write(states)`` (BoundaryStates of substeps 0..K-1; clears their reactions),
``reactions(K)``, ``zero_grad()``, ``seed_reaction_grads(grads)`` and
``state_grads(K)``. The contact models (``cosim.couplers.contact``) are written once
against this interface and take any number of sources; rigid SDF bodies are one
source (``RigidBoundaries``), the cloth's traced distance (``ClothBoundary``) is another.
"""

import numpy as np
import taichi as ti

from cosim.couplers.sdf_field import SDFField
from cosim.couplers.sdf_grid import SDFGrid
from cosim.engines import field_pool
from cosim.engines.contract import BOUNDARY_KEYS, REACTION_KEYS
from cosim.engines.data_oriented import data_oriented

BOTH_KEYS = BOUNDARY_KEYS + REACTION_KEYS  # a write sets the states and clears the reactions
NODE = -1  # the p of a grid node (the grid model's queries)


def at_node(p) -> bool:
    """Whether a source's query comes from a grid node: decided as the kernel compiles (``NODE`` is a
    Python int, a particle index an expression). A cloth's node and particle paths compiled into one
    function both went through the forecast model's adjoint: its compile took 29 s where 5 s do."""
    return isinstance(p, int) and p == NODE


@data_oriented
class RigidBoundaries:
    """Rigid bodies described by body-frame SDFs, moving with per-substep poses and twists.

    Body b at substep s: origin ``pos[s, b]``, rotation ``rot[s, b]`` (body to world),
    origin velocity ``vel[s, b]``, angular velocity ``omega[s, b]`` (world frame, one
    component in 2D). The reaction on body b: ``impulse[s, b]`` [N s] = minus the
    momentum the contact gave the material, ``angular_impulse[s, b]`` [N m s] its
    moment about ``pos[s, b]``.

    With ``added_mass`` (the MPM-DART coupler's strong coupling, ``cosim.couplers.mpm_rigid``) its
    reactions also carry "mass" (n, k, k) [kg, kg m, kg m^2], k = 3 in 2D, 6 in 3D: per body, the
    material that follows the body's twist [omega; v] (about ``pos``) over the frame, as a
    rigid-body inertia (``cosim.couplers.rigid_engagement``), and its boundary states take
    "handover" (n, k): each body's twist change over its last step, which the material it engages
    gets at the next step's start (``cosim.couplers.handover``).
    """

    def __init__(
        self, sdfs: list[SDFGrid], dim: int, max_substeps: int, requires_grad: bool = False, added_mass: bool = False
    ):
        self.dim = dim
        self.n = len(sdfs)
        self.wdim = 1 if dim == 2 else 3
        self.sdfs = [SDFField(g) for g in sdfs]
        shape = (max_substeps, self.n)
        grad = requires_grad
        self.pos = field_pool.vector(self, dim, float, shape=shape, needs_grad=grad)
        self.rot = field_pool.matrix(self, dim, dim, float, shape=shape, needs_grad=grad)
        self.vel = field_pool.vector(self, dim, float, shape=shape, needs_grad=grad)
        self.omega = field_pool.vector(self, self.wdim, float, shape=shape, needs_grad=grad)
        self.impulse = field_pool.vector(self, dim, float, shape=shape, needs_grad=grad)
        self.angular_impulse = field_pool.vector(self, self.wdim, float, shape=shape, needs_grad=grad)
        self.real = np.float64 if self.pos.dtype == ti.f64 else np.float32
        self.capabilities = frozenset({"added_mass"}) if added_mass else frozenset()
        self.engagement = None  # the contact model that says how much material follows a body (forecast)
        self.added = None
        if added_mass:
            from cosim.couplers.rigid_engagement import RigidEngagement

            self.added = RigidEngagement(self, grad)
        self._substeps = 1

    # ------------------------------------------------------------------ what a contact model asks
    @ti.func
    def distance(self, s, b: ti.template(), x, p):
        return self.sdfs[b].distance(self.rot[s, b].transpose() @ (x - self.pos[s, b]))

    @ti.func
    def distance_normal(self, s, b: ti.template(), x, p):
        R = self.rot[s, b]
        d, n_body = self.sdfs[b].distance_normal(R.transpose() @ (x - self.pos[s, b]))
        return d, R @ n_body

    @ti.func
    def contact_velocity(self, s, b: ti.template(), x, p):
        return self.vel[s, b] + self.spin(self.omega[s, b], x - self.pos[s, b])

    @ti.func
    def add_reaction(self, s, b: ti.template(), x, dp, p):
        self.impulse[s, b] -= dp
        self.angular_impulse[s, b] -= self.moment(x - self.pos[s, b], dp)

    @ti.func
    def spin(self, w, r):
        """omega x r in the world frame (2D: w has one component)."""
        out = ti.Vector.zero(float, self.dim)
        if ti.static(self.dim == 2):
            out = w[0] * ti.Vector([-r[1], r[0]])
        else:
            out = w.cross(r)
        return out

    @ti.func
    def moment(self, r, f):
        """r x f, as a 1-vector in 2D."""
        out = ti.Vector.zero(float, self.wdim)
        if ti.static(self.dim == 2):
            out[0] = r[0] * f[1] - r[1] * f[0]
        else:
            out = r.cross(f)
        return out

    # ------------------------------------------------------------------ the MPM engine's side
    def write(self, states: dict[str, np.ndarray]) -> None:
        """Body states of substeps 0..K-1 (BoundaryStates, ``cosim.engines.contract``); clears their reactions.
        Only the K slots are written (the fields hold max_substeps)."""
        self._substeps = K = len(states["pos"])
        zeros = {key: np.zeros((K, self.n, self.width(key))) for key in REACTION_KEYS}
        self._exchange(self._pack({**states, **zeros}, BOTH_KEYS), K, BOTH_KEYS, False, False)
        if self.added is not None:
            self.added.write(states, self._substeps)

    # Each direction of a step's exchange is one host array (``_pack``, ``_unpack``) and one launch
    # (``_exchange``): on a GPU every host array a kernel takes is a device allocation, a copy each way and a wait.
    def width(self, key: str) -> int:
        """Entries of field ``key``'s element: d (pos, vel, impulse), d^2 (rot), 1 or 3 (omega, angular_impulse)."""
        fld = getattr(self, key)
        return fld.n * fld.m

    def _layout(self, keys: tuple[str, ...]) -> list[tuple[str, int]]:
        """(key, its first column) of each key side by side in a packed array."""
        starts = np.cumsum([0] + [self.width(key) for key in keys])
        return [(key, int(start)) for key, start in zip(keys, starts)]

    def _fields(self, keys: tuple[str, ...], adjoints: bool) -> list:
        """(field, or its adjoint, its first column) of each key in a packed array (``_exchange``)."""
        return [
            (getattr(self, key).grad if adjoints else getattr(self, key), start) for key, start in self._layout(keys)
        ]

    def _pack(self, values: dict[str, np.ndarray], keys: tuple[str, ...]) -> np.ndarray:
        """(K, n, sum of the keys' widths): values[key] (K, n, ...) flattened row-major, side by side."""
        K = len(values[keys[0]])
        parts = [np.reshape(values[key], (K, self.n, -1)) for key in keys]
        return np.ascontiguousarray(np.concatenate(parts, axis=-1), dtype=self.real)

    def _unpack(self, packed: np.ndarray, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
        """``_pack``'s inverse, in float64: {key: (K, n, d) for vectors, (K, n, d, d) for rot}."""
        packed = packed.astype(np.float64)
        out = {}
        for key, start in self._layout(keys):
            fld = getattr(self, key)
            shape = (fld.n,) if fld.ndim == 1 else (fld.n, fld.m)
            out[key] = packed[..., start : start + self.width(key)].reshape(packed.shape[:2] + shape)
        return out

    def _read(self, keys: tuple[str, ...], K: int, adjoints: bool) -> dict[str, np.ndarray]:
        """Substeps 0..K-1 of the fields ``keys`` (their adjoints if ``adjoints``), unpacked."""
        packed = np.zeros((K, self.n, sum(self.width(key) for key in keys)), dtype=self.real)
        self._exchange(packed, K, keys, adjoints, True)
        return self._unpack(packed, keys)

    @ti.kernel
    def _exchange(
        self, packed: ti.types.ndarray(), K: ti.i32, keys: ti.template(), adjoints: ti.template(), out: ti.template()
    ):
        """Substeps 0..K-1 of the fields ``keys`` (their adjoints if ``adjoints``) and ``packed`` in ``_pack``'s
        layout: out of the fields into it if ``out``, else into the fields."""
        ti.loop_config(serialize=True)  # substeps x bodies: far less work than a thread-pool dispatch (arch)
        for s, b in ti.ndrange(K, self.n):
            for fld, start in ti.static(self._fields(keys, adjoints)):
                for k in ti.static(range(fld.n * fld.m)):
                    if ti.static(fld.ndim == 1 and out):
                        packed[s, b, start + k] = fld[s, b][k]
                    elif ti.static(fld.ndim == 1):
                        fld[s, b][k] = packed[s, b, start + k]
                    elif ti.static(out):
                        packed[s, b, start + k] = fld[s, b][k // fld.m, k % fld.m]
                    else:
                        fld[s, b][k // fld.m, k % fld.m] = packed[s, b, start + k]

    @staticmethod
    def work(states: dict[str, np.ndarray], reactions: dict[str, np.ndarray]) -> np.ndarray:
        """(m,) [J] Work each body did on the material over a macro step: -sum_k (J_k . v_k + L_k . w_k),
        exact for a rigid body's velocity field (twists at each substep's start)."""
        K = len(reactions["impulse"])
        return -(
            np.sum(reactions["impulse"] * states["vel"][:K], axis=(0, 2))
            + np.sum(reactions["angular_impulse"] * states["omega"][:K], axis=(0, 2))
        )

    def reactions(self, K: int) -> dict[str, np.ndarray]:
        """Reactions of substeps 0..K-1: impulse (K, n, d) [N s], angular_impulse (K, n, 1|3) about pos;
        with an engagement, "mass" (n, k, k) (the class docstring)."""
        out = self._read(REACTION_KEYS, K, adjoints=False)
        if self.added is not None and self.engagement is not None:
            out["mass"] = self.added.mass(self.engagement.engine._slot, K)
        return out

    @ti.kernel
    def _zero_adjoints(self):
        """Zero the adjoints of the boundary states and reactions: one launch, not a fill per field."""
        for fld in ti.static((self.pos, self.rot, self.vel, self.omega, self.impulse, self.angular_impulse)):
            for I in ti.grouped(fld.grad):
                fld.grad[I] = ti.zero(fld.grad[I])

    @ti.func
    def handover(self, s, x, p):
        """[m/s] The velocity change the material at x (particle p) gets from the bodies at substep s
        (``cosim.couplers.rigid_engagement``)."""
        return self.added.handover(s, x, p)

    def zero_grad(self) -> None:
        self._zero_adjoints()
        if self.added is not None:
            self.added.zero_grad()

    def seed_reaction_grads(self, grads: dict[str, np.ndarray]) -> None:
        """dL/d(reactions) of substeps 0..K-1 (Reactions layout, and "mass" with an engagement), after
        ``zero_grad`` and after the state's adjoint is seeded (the mass reads the particles at the end)."""
        K = len(grads[REACTION_KEYS[0]])  # the later substeps' adjoints stay as ``zero_grad`` left them
        self._exchange(self._pack(grads, REACTION_KEYS), K, REACTION_KEYS, True, False)
        g_mass = grads.get("mass")
        if g_mass is not None and self.added is not None and self.engagement is not None and np.any(g_mass):
            self.added.seed(g_mass, self.engagement.engine._slot, self._substeps)

    def state_grads(self, K: int) -> dict[str, np.ndarray]:
        """dL/d(body states) of substeps 0..K-1 (BoundaryStates layout; and of "handover") after a vjp."""
        out = self._read(BOUNDARY_KEYS, K, adjoints=True)
        if self.added is not None:
            out.update(self.added.state_grads())
        return out
