"""The MLS-MPM kernels and substep phases (Taichi, 2D and 3D); ``cosim.engines.mpm`` adds the contract.

Moving least squares MPM (Hu et al. 2018) with quadratic B-splines and APIC
affine momentum. Units are SI: positions [m], velocities [m/s], masses [kg],
stresses [Pa], impulses [N s]. The domain is the box [0, cells * dx]^d.

Particle state lives in *slots*: ``x[slot, p]`` etc. A forward-only engine
uses four slots and one grid: a step alternates between the two slots that
neither it nor the last step started from (``cosim.engines.mpm``). An engine
built with ``requires_grad`` keeps ``substeps + 1`` slots and one grid (and
stress scratch) per substep, so one macro step is all resident for the adjoint
(``cosim.engines.mpm_adjoint``), which never re-runs P2G.

One substep, split into the phases a coupler drives (docs/architecture.md):

- pre-coupling  ``p2g``: stress from F (per material), scatter of mass,
  APIC momentum, stress momentum and external impulses (controls; particle
  hooks such as particle-penalty contact) onto the grid;
- coupling      ``grid_update``: momentum to velocity, gravity, domain walls,
  then the grid hooks (grid / forecast contact) in the order attached;
- post-coupling ``g2p``: gather velocity and affine field (through the last grid
  hook's ``velocity(g, I)``); ``advect`` (per material): move particles, update
  F, apply the material's return mapping.
"""

import numpy as np
import taichi as ti

from cosim.engines import field_pool
from cosim.engines.arch import SCATTERS, current_choices
from cosim.engines.data_oriented import data_oriented
from cosim.engines.materials import MATERIALS
from cosim.engines.mpm_bins import ParticleBins
from cosim.engines.mpm_g2p import G2PKernels
from cosim.engines.mpm_inputs import MPMConfig, ParticleBody, particle_capacity
from cosim.engines.mpm_p2g import P2GKernels
from cosim.engines.mpm_slot_io import SlotIO
from cosim.engines.mpm_stencil import StencilFunctions, stencil_rows
from cosim.engines.mpm_watch import ParticleWatch
from cosim.engines.smooth import soft_ramp

WALL_SOFT = 1e-4  # [m/s] the domain walls' removal of an approach is rounded over this speed (``_grid_update``)


@data_oriented
class MPMKernels(StencilFunctions, SlotIO, ParticleBins, P2GKernels, G2PKernels):
    """Fields, kernels and substep phases of the MPM; hooks and the contract live in ``MPMEngine``."""

    def __init__(self, config: MPMConfig, bodies: list[ParticleBody]):
        if not bodies:
            raise ValueError("MPMEngine needs at least one body")
        self.cfg = config
        self.dim = d = config.dim
        self.bodies = bodies
        self.n_particles = sum(b.n for b in bodies)
        # particle fields hold ``capacity`` particles, kernels loop over ``count``: kernels compiled for
        # one particle count serve every count of its bucket (``particle_capacity``)
        self.capacity = n = particle_capacity(self.n_particles)
        self.count = field_pool.scalar(self, ti.i32, shape=())
        self.dx = float(config.dx)
        self.inv_dx = 1.0 / self.dx
        starts = np.cumsum([0] + [b.n for b in bodies])
        self.ranges = [(int(starts[i]), int(starts[i + 1])) for i in range(len(bodies))]
        self.materials = [MATERIALS[b.material]() for b in bodies]
        grad = config.requires_grad
        _check_gradient_build(grad)
        self.n_slots = config.grad_substeps + 1 if grad else 4

        self.x = field_pool.vector(self, d, float, shape=(self.n_slots, n), needs_grad=grad)
        self.v = field_pool.vector(self, d, float, shape=(self.n_slots, n), needs_grad=grad)
        self.C = field_pool.matrix(self, d, d, float, shape=(self.n_slots, n), needs_grad=grad)
        self.F = field_pool.matrix(self, d, d, float, shape=(self.n_slots, n), needs_grad=grad)
        nb = len(bodies)
        self.E = field_pool.scalar(self, float, shape=nb, needs_grad=grad)
        self.nu = field_pool.scalar(self, float, shape=nb, needs_grad=grad)
        self.yield_stress = field_pool.scalar(self, float, shape=nb)
        self.viscosity = field_pool.scalar(self, float, shape=nb)
        self.p_mass = field_pool.scalar(self, float, shape=nb)
        self.p_vol = field_pool.scalar(self, float, shape=nb)
        self.p_radius = field_pool.scalar(self, float, shape=nb)  # [m] half the lattice spacing
        self.p_liquid = field_pool.scalar(self, ti.i32, shape=nb)  # 1 for a liquid body
        self.body_range = field_pool.vector(self, 2, ti.i32, shape=nb)  # its particles' [start, end)
        self.body_id = field_pool.scalar(self, ti.i32, shape=n)  # which body each particle belongs to
        # Grid and per-particle stress scratch: one copy per substep with
        # gradients (the adjoint reads them back instead of recomputing P2G),
        # one copy otherwise. g below is that copy's index.
        self.nodes = tuple(int(c) + 1 for c in config.cells)  # nodes at 0, dx, ..., cells * dx
        self.rows = stencil_rows(d)  # the stencil's rows (``mpm_stencil``)
        self.n_grids = config.grad_substeps if grad else 1
        # per node: momentum [kg m/s] in components 0..d-1, mass [kg] in component d, side by side
        # so that P2G adds both with one vector add to one place (``node_momentum``, ``node_mass``)
        self.grid_mm = field_pool.vector(self, d + 1, float, shape=(self.n_grids, *self.nodes), needs_grad=grad)
        self.grid_v = field_pool.vector(self, d, float, shape=(self.n_grids, *self.nodes), needs_grad=grad)
        self.gravity = ti.Vector([float(g) for g in config.gravity])
        self.per_particle = (self.n_grids, n)  # the shape of per-substep particle scratch (hooks' momenta)
        # the nodes the P2G of each grid copy's substep touched: [active_lo, active_hi) per axis (``_p2g``)
        self.active_lo = field_pool.vector(self, d, ti.i32, shape=self.n_grids)
        self.active_hi = field_pool.vector(self, d, ti.i32, shape=self.n_grids)
        # the adjoint of the grid velocities one G2P read (gradients only; see ``mpm_adjoint``)
        self.gathered_grad = field_pool.vector(self, d, float, shape=self.nodes) if grad else None
        # one adjoint kernel's sum of dL/dmu, dL/dlam over a body's particles (``mpm_adjoint._lame_grad``)
        self.lame_bar = field_pool.vector(self, 2, float, shape=()) if grad else None
        self.control = None
        if config.has_controls:
            self.control = field_pool.vector(self, d, float, shape=n, needs_grad=grad)

        self.real = np.float64 if self.x.dtype == ti.f64 else np.float32
        constants = [
            [b.E, b.nu, min(b.yield_stress, 1e30), b.viscosity, b.particle_mass, b.particle_volume]
            + [0.5 * b.particle_volume ** (1.0 / d)]
            for b in bodies
        ]
        flags = [[b.material == "liquid", *r] for b, r in zip(bodies, self.ranges)]
        self._write_bodies(self._real(constants), np.array(flags, dtype=np.int32))
        self.count[None] = self.n_particles
        self.fuse_substeps = True  # a substep in one launch where it can be (``_fused``)
        self.mass = np.concatenate([np.full(b.n, b.particle_mass) for b in bodies])
        self.body_id.from_numpy(
            self.padded(np.concatenate([np.full(b.n, i, dtype=np.int32) for i, b in enumerate(bodies)]))
        )
        choices = current_choices()
        # loops too short to repay a CPU thread-pool dispatch run on the launching thread (``arch``); hooks
        # looping over this engine's particles or nodes follow the same two flags
        self.serial_particle_loops = choices.serial_particles(self.n_particles)
        # P2G's and the G2P adjoint's (``arch.SCATTERS``): by the arch, serial where the particle loops are
        self.scatter = config.scatter or ("serial" if self.serial_particle_loops else choices.scatter)
        if self.scatter not in SCATTERS:
            raise ValueError(f"MPMConfig.scatter: {self.scatter!r} is none of {', '.join(SCATTERS)}")
        if self.scatter == "coloured":
            self._init_bins()
        # a parallel scatter computes each particle's affine momentum as it scatters; the serial one reads
        # it from ``affine``, which a parallel loop filled. The adjoint reads it back (``mpm_adjoint``), but its
        # own adjoint never leaves a particle's registers (``_particle_adjoint``): no field for that
        self.stress_in_scatter = self.scatter != "serial"
        self.affine = None
        if grad or not self.stress_in_scatter:
            self.affine = field_pool.matrix(self, d, d, float, shape=self.per_particle)
        self.bounded_grid = choices.bounded_grid_passes  # else every grid pass covers the whole grid (GPU)
        self.constant_loop_bounds = choices.constant_loop_bounds  # P2G's and G2P's particle loops (GPU)
        if not self.bounded_grid:
            self.active_hi.from_numpy(np.tile(np.array(self.nodes, dtype=np.int32), (self.n_grids, 1)))
        # the grid passes cover the particles' box (``_clear_box``), which few particles keep small: a
        # small engine's grid loops are serial on any grid (a thread-pool dispatch per pass would cost more than
        # the pass). Few particles spread over a large grid would make them slower than parallel.
        self.serial_grid_loops = choices.serial_nodes(int(np.prod(self.nodes))) or self.serial_particle_loops
        # whether the adjoint computes dL/dE and dL/dnu: an objective optimising neither turns it off
        # (``Objective.evaluate``), which saves a good part of the 3D stress adjoint
        self.material_grads = True
        self.grid_hooks: list = []  # contact models rewriting grid velocities, in order
        self.box_margin = 0  # nodes added around the box P2G bounds: the largest any grid hook asks for
        self.particle_hooks: list = []  # contact models adding momentum in P2G
        self.substep_preparers: list = []  # boundary sources' before_substep(src, s), run on the host
        self.substep_preparer_grads: list = []  # their before_substep_grad(src, s), if differentiable
        # what G2P gathers velocities from (``velocity(g, I)``, adjoint ``velocity_grad``): the last grid hook
        self._grid_out = self
        self._slot = 0
        self._token = 0
        self._resident = -1  # token of the step whose substeps fill the slots
        self.watch = ParticleWatch(self)  # NaN / speed / domain checks on the device
        eye = np.eye(d)
        self.set_state(
            {
                "x": np.concatenate([b.positions for b in bodies]),
                "v": np.concatenate([b.velocities for b in bodies]),
                "C": np.zeros((self.n_particles, d, d)),
                "F": np.concatenate(
                    [np.broadcast_to(eye, (b.n, d, d)) if b.deformation is None else b.deformation for b in bodies]
                ),
            }
        )

    def _real(self, values) -> np.ndarray:
        """Host array in the engine's precision (float32 or float64)."""
        return np.asarray(values, dtype=self.real)

    def padded(self, per_particle: np.ndarray) -> np.ndarray:
        """A per-particle host array (n_particles, ...) padded with zeros to the capacity, for ``from_numpy``."""
        out = np.zeros((self.capacity, *per_particle.shape[1:]), dtype=per_particle.dtype)
        out[: self.n_particles] = per_particle
        return out

    # ------------------------------------------------------------------ kernels
    @ti.func
    def mass_of(self, p):
        """Mass [kg] of particle p."""
        return self.p_mass[self.body_id[p]]

    @ti.func
    def radius_of(self, p):
        """Half the lattice spacing [m] of particle p (its volume's side / 2): how far its material
        reaches beyond its centre."""
        return self.p_radius[self.body_id[p]]

    @ti.func
    def is_liquid(self, p):
        """1 if particle p belongs to a liquid body, else 0."""
        return self.p_liquid[self.body_id[p]]

    @ti.func
    def _lame(self, b):
        E, nu = self.E[b], self.nu[b]
        return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @ti.func
    def idle(self, p):
        """Whether particle slot p has no particle, in a loop over every slot (``constant_loop_bounds``: a GPU's
        loops, whose bounds are constants; elsewhere loops end at the count and this is False)."""
        out = False
        if ti.static(self.constant_loop_bounds):
            out = p >= self.count[None]
        return out

    @ti.func
    def off_body(self, b, p):
        """Whether particle slot p is not body b's, in a loop over every slot (as ``idle``)."""
        out = False
        if ti.static(self.constant_loop_bounds):
            out = p < self.body_range[b][0] or p >= self.body_range[b][1]
        return out

    @ti.func
    def node_mass(self, g, I):
        """Mass [kg] P2G scattered to node I of grid copy g."""
        return self.grid_mm[g, I][self.dim]

    @ti.func
    def node_momentum(self, g, I):
        """Momentum [kg m/s] P2G scattered to node I of grid copy g."""
        mm = self.grid_mm[g, I]
        return ti.Vector([mm[k] for k in ti.static(range(self.dim))])

    @ti.func
    def velocity(self, g, I):
        """Grid velocity G2P gathers at node I of grid copy g (a grid hook may supply its own)."""
        return self.grid_v[g, I]

    @ti.kernel
    def _write_bodies(self, constants: ti.types.ndarray(), flags: ti.types.ndarray()):
        """Each body's constants in one launch (a ``from_numpy`` per field compiled a kernel per field):
        ``constants[b]`` E, nu, yield stress, viscosity, particle mass, volume and radius in the engine's
        precision; ``flags[b]`` the liquid flag and the particle range [start, end)."""
        ti.loop_config(serialize=True)
        for b in range(constants.shape[0]):
            self.E[b], self.nu[b], self.yield_stress[b] = constants[b, 0], constants[b, 1], constants[b, 2]
            self.viscosity[b], self.p_mass[b], self.p_vol[b] = constants[b, 3], constants[b, 4], constants[b, 5]
            self.p_radius[b], self.p_liquid[b] = constants[b, 6], flags[b, 0]
            self.body_range[b] = ti.Vector([flags[b, 1], flags[b, 2]])

    @ti.kernel
    def _grid_update(self, g: ti.i32, dt: float, mass_floor: float):
        """Momentum to velocity, gravity and domain walls over the active nodes (``_p2g``); nodes
        outside keep stale velocities, which no gather reads. Its loop is written here, not inlined from a
        ``ti.func``: Taichi differentiates this kernel (``_grid_update.grad``) and refuses such a loop."""
        ti.loop_config(serialize=self.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (self.active_lo[g][k], self.active_hi[g][k]) if ti.static(self.bounded_grid) else (0, self.nodes[k])
                    for k in ti.static(range(self.dim))
                ]
            )
        ):
            self._grid_node_update(g, I, dt, mass_floor)

    @ti.func
    def _grid_update_pass(self, g: ti.template(), dt: ti.template(), mass_floor: ti.template()):
        """``_grid_update``'s loop, for the fused substep (``_substep_fused``)."""
        ti.loop_config(serialize=self.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (self.active_lo[g][k], self.active_hi[g][k]) if ti.static(self.bounded_grid) else (0, self.nodes[k])
                    for k in ti.static(range(self.dim))
                ]
            )
        ):
            self._grid_node_update(g, I, dt, mass_floor)

    @ti.func
    def _grid_node_update(self, g, I, dt, mass_floor):
        """Node I of grid copy g: its velocity from its momentum, gravity and the walls."""
        m = self.node_mass(g, I)
        vel = ti.Vector.zero(float, self.dim)
        if m > mass_floor:
            vel = self.node_momentum(g, I) / m + dt * self.gravity
            if ti.static(self.cfg.wall != "none"):
                for k in ti.static(range(self.dim)):
                    # in a wall's band, the speed towards the wall is taken away (slip) or the whole
                    # velocity (sticky), rounded over WALL_SOFT (``soft_ramp``: C2 where a node at rest
                    # against a wall starts to approach it, never more than the exact projection)
                    toward = 0.0
                    if I[k] < self.cfg.wall_cells:
                        toward = -1.0
                    elif I[k] > self.nodes[k] - 1 - self.cfg.wall_cells:
                        toward = 1.0
                    approach = toward * vel[k]
                    if approach > 0:
                        removed = soft_ramp(approach, WALL_SOFT)
                        if ti.static(self.cfg.wall == "sticky"):
                            vel *= 1.0 - removed / approach
                        else:
                            vel[k] -= toward * removed
        self.grid_v[g, I] = vel
        if ti.static(self._fused_clear()):
            # forward-only: leave the grid cleared for the next P2G (saves a pass);
            # with gradients the backward pass reads these values back, and
            # a contact hook reads the masses after this kernel
            self.grid_mm[g, I] = ti.Vector.zero(float, self.dim + 1)

    # ------------------------------------------------------------ substep phases
    def _mass_floor(self) -> float:
        # float32 only: nodes lighter than 1e-8 particle masses count as empty,
        # since the adjoint of p/m needs 1/m^2, which overflows float32 at nodes
        # touched only by a far weight tail. The momentum so dropped is below
        # float32 round-off; float64 needs no floor and keeps momentum exact.
        if self.real == np.float64:
            return 0.0
        return 1e-8 * float(min(b.particle_mass for b in self.bodies))

    def _hook_fields(self, kind: str) -> list:
        """The grid hooks' grid-shaped fields listed under ``kind``: "scratch" (zeroed by the grid clear each
        substep) or "grid_adjoints" (their adjoints zeroed at the start of each substep's adjoint)."""
        return [fld for hook in self.grid_hooks for fld in getattr(hook, kind, ())]

    def _fused_clear(self) -> bool:
        """Forward-only engines without a grid hook clear the grid inside grid_update."""
        return not self.cfg.requires_grad and not self.grid_hooks

    def _grid_index(self, src: int) -> int:
        """The grid copy substep ``src`` uses: its own with gradients, the only one otherwise."""
        return src if self.cfg.requires_grad else 0

    def pre_coupling(self, src: int, s: int, dt: float, control_share: float = 0.0) -> None:
        """Let boundary sources prepare substep s (``before_substep``), let the particle hooks compute their
        momenta, clear the grid and scatter every body (P2G)."""
        for prepare in self.substep_preparers:
            prepare(src, s)
        g = self._grid_index(src)
        for hook in self.particle_hooks:  # per-particle momenta (``output``): no grid written before the clear
            hook.apply(src, g, s, dt)
        clear = not self._fused_clear()  # else grid_update cleared it
        for b, (mat, (lo, hi)) in enumerate(zip(self.materials, self.ranges)):
            if self.scatter == "coloured":
                self.bin_particles(src, lo, hi)
            for colour in range(self.colours if self.scatter == "coloured" else 1):  # a launch per colour, in turn
                first = colour == 0
                self._p2g(self.scatter, mat, b, lo, hi, src, g, dt, control_share, b == 0 and first, colour,
                          clear and b == 0 and first, first)  # fmt: skip

    def coupling(self, src: int, s: int, dt: float) -> None:
        """Grid update (velocities, gravity, walls), then the grid hooks in the order attached."""
        g = self._grid_index(src)
        self._grid_update(g, dt, self._mass_floor())
        for hook in self.grid_hooks:
            hook.apply(src, g, s, dt)

    def post_coupling(self, src: int, dst: int, dt: float, s: int) -> None:
        """Gather from the grid (G2P) for substep s, advect and update deformation, per body."""
        g = self._grid_index(src)
        for b, (mat, (lo, hi)) in enumerate(zip(self.materials, self.ranges)):
            self._g2p_advect(mat, b, lo, hi, src, dst, g, self._grid_out, s, dt)

    def _substep(self, src: int, dst: int, dt: float, control_share: float, s: int) -> None:
        if self._fused():
            self._substep_fused(src, dst, self._grid_index(src), s, dt, control_share, self._mass_floor())
            return
        self.pre_coupling(src, s, dt, control_share)
        self.coupling(src, s, dt)
        self.post_coupling(src, dst, dt, s)

    def _fused(self) -> bool:
        """Whether a substep is one launch (``_substep_fused``; forward, recorded or recomputed: the adjoints
        read what it wrote, as they read the separate kernels'): allowed (``fuse_substeps``), a scatter of one pass (not the coloured one's pass per colour), no boundary source preparing substeps,
        and every particle and grid hook with a ``forward_pass`` that it lets run fused (``fuses``, default
        true: the forecast model's bench diagnostic reads a sum back every substep)."""
        return (
            self.fuse_substeps
            and self.scatter != "coloured"
            and not self.substep_preparers
            and all(
                hasattr(hook, "forward_pass") and getattr(hook, "fuses", True)
                for hook in self.particle_hooks + self.grid_hooks
            )
        )

    @ti.kernel
    def _substep_fused(
        self, src: ti.i32, dst: ti.i32, g: ti.i32, s: ti.i32, dt: float, control_share: float, floor: float
    ):
        """A substep in one launch (grid copy g): each particle hook's ``forward_pass``, each body's P2G, the
        grid update, each grid hook's ``forward_pass`` and each body's G2P, the passes' loops run in this
        order as the kernel's parallel tasks, on the same functions as the substep's separate kernels
        (the same numbers; to round-off under fast math, which may contract a larger kernel differently).
        A launch costs tens of microseconds of Python and Taichi, as much as a small scene's loops."""
        for hook in ti.static(self.particle_hooks):
            hook.forward_pass(src, g, s, dt)
        clear = ti.static(not self._fused_clear())  # else the grid update cleared the grid
        for b in ti.static(range(len(self.bodies))):
            # the loops' bounds (unused where they are constant: read there, a GPU would run a serial task for them)
            lo, hi = (0, 0) if ti.static(self.constant_loop_bounds) else (self.body_range[b][0], self.body_range[b][1])
            self._p2g_pass(self.scatter, self.materials[b], b, lo, hi, src, g, dt, control_share,
                           b == 0, 0, clear and b == 0, 1)  # fmt: skip
        self._grid_update_pass(g, dt, floor)
        for hook in ti.static(self.grid_hooks):
            hook.forward_pass(src, g, s, dt)
        for b in ti.static(range(len(self.bodies))):
            # the loops' bounds (unused where they are constant: read there, a GPU would run a serial task for them)
            lo, hi = (0, 0) if ti.static(self.constant_loop_bounds) else (self.body_range[b][0], self.body_range[b][1])
            self._g2p_pass(self.materials[b], b, lo, hi, src, dst, g, self._grid_out, s, dt)


def _check_gradient_build(requires_grad: bool) -> None:
    """Taichi 1.7.4's float32 reverse mode is wrong without advanced optimisation (zero or NaN
    adjoints through max, min, select and branches; ``cosim.runtime``): refuse to build on it."""
    cfg = ti.lang.impl.current_cfg()
    if requires_grad and cfg.default_fp == ti.f32 and not cfg.advanced_optimization:
        raise RuntimeError(
            "float32 gradients need Taichi started with advanced_optimization=True (without it Taichi 1.7.4 "
            "returns wrong float32 adjoints): build with cosim.build_system, or call "
            "cosim.runtime.ensure_taichi(arch, 'float32', gradients=True) first, or use float64"
        )
