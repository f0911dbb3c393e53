"""P2G, the scatter from particles to the grid: ``P2GKernels``, a base of ``MPMKernels``.

One launch per body (per colour with the coloured scatter, ``cosim.engines.mpm_bins``), or a pass of
the fused forward substep (``MPMKernels._substep_fused``), holds up to three loops: the clear of the grid
box the last substep wrote, the body's stress (its affine momentum: its own parallel loop beside the serial
scatter, else computed by the scatter particle by particle, ``stress_in_scatter``), and the scatter, which
also bounds the box the next grid passes cover. Its functions read the engine's
fields (``x``, ``v``, ``C``, ``F``, ``affine``, ``grid_mm``, ``grid_v``, ``active_lo`` / ``active_hi``),
settings (``dim``, ``dx``, ``nodes``, ``box_margin``, ``bounded_grid``, the loop flags) and hooks.
"""

import taichi as ti

from cosim.engines.data_oriented import data_oriented


@data_oriented
class P2GKernels:
    """The grid clear, the stress and the scatter of one substep (``_p2g``)."""

    @ti.func
    def _clear_box(self, g: ti.template(), clear: ti.template()):
        """Zero grid copy g where its last substep wrote (if ``clear``, else nothing): its box, which this
        substep's P2G then bounds anew. Every write to a grid copy stays inside its box, so the whole copy is
        zero afterwards. Every pass over a grid copy (this clear, the grid update, the grid hooks, their
        adjoints) loops over its box, ``ti.grouped(ti.ndrange(*[(active_lo[g][k], active_hi[g][k]) ...]))``:
        the nodes outside hold no material and no gather reads them. (Written out in each kernel: Taichi
        cannot return a range from a ``ti.func``, and a ``ti.func`` computing the bounds before the loop
        breaks Taichi's autodiff of the grid update.) Inlined at a kernel's top level, its loop is one of
        the kernel's parallel loops (``_p2g``)."""
        ti.loop_config(serialize=self.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (self.active_lo[g][k], self.active_lo[g][k] + clear * (self.active_hi[g][k] - self.active_lo[g][k]))
                    if ti.static(self.bounded_grid)
                    else (0, clear * self.nodes[k])  # the whole grid, constant bounds when ``clear`` is (``arch``)
                    for k in ti.static(range(self.dim))
                ]
            )
        ):
            self.grid_mm[g, I] = ti.Vector.zero(float, self.dim + 1)
            self.grid_v[g, I] = ti.Vector.zero(float, self.dim)
            for fld in ti.static(self._hook_fields("scratch")):
                fld[g, I] = ti.zero(fld[g, I])

    @ti.func
    def _affine_momentum(self, mat: ti.template(), b, p, src, dt):
        """Particle p's affine momentum (body b, slot src): its stress term -dt V0 4 / dx^2 tau(F, C) plus
        APIC's m_p C [kg/s]; node o receives it times (o - fx) dx in P2G."""
        mu, lam = self._lame(b)
        m_p, vol = self.p_mass[b], self.p_vol[b]
        tau = mat.kirchhoff(self.F[src, p], self.C[src, p], mu, lam, self.viscosity[b])
        return (-dt * vol * 4.0 * self.inv_dx * self.inv_dx) * tau + m_p * self.C[src, p]

    @ti.func
    def _stress(self, mat: ti.template(), b, start, end, src, g, dt):
        """Affine momenta of particles [start, end) into ``affine`` (parallel unless the engine is small:
        ``arch``; its own loop of ``_p2g``'s kernel) when the scatter does not compute them itself
        (``stress_in_scatter``). With ``constant_loop_bounds``: of every slot of body b if end > start."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(
            0 if ti.static(self.constant_loop_bounds) else start,
            self.capacity * (end > start) if ti.static(self.constant_loop_bounds) else end,
        ):
            if self.off_body(b, p):  # a thread per particle slot (``constant_loop_bounds``)
                continue
            self.affine[g, p] = self._affine_momentum(mat, b, p, src, dt)

    @ti.func
    def _scattered_affine(self, mat: ti.template(), b, p, src, g, dt):
        """The affine momentum P2G scatters for particle p: computed here when the scatter is parallel
        (``stress_in_scatter``; stored for the adjoint only with gradients), else what ``_stress`` stored."""
        affine = ti.Matrix.zero(float, self.dim, self.dim)
        if ti.static(self.stress_in_scatter):
            affine = self._affine_momentum(mat, b, p, src, dt)
            if ti.static(self.cfg.requires_grad):
                self.affine[g, p] = affine
        else:
            affine = self.affine[g, p]
        return affine

    @ti.func
    def particle_momentum(self, src, g, p, m_p, control_share):
        """Momentum [N s] particle p scatters in P2G besides its affine part: m_p v, its share of the
        control impulse and the particle hooks' momenta."""
        mom = m_p * self.v[src, p]
        if ti.static(self.cfg.has_controls):
            mom += control_share * self.control[p]
        for hook in ti.static(self.particle_hooks):
            mom += hook.output[g, p]
        return mom

    @ti.func
    def _p2g_particle(self, mat: ti.template(), b, p, src, g, dt, control_share, atomic: ti.template()):
        """Scatter particle p's mass and momentum onto its stencil (of body b); returns its base node."""
        m_p = self.p_mass[b]
        base, fx, w = self.stencil(self.x[src, p])
        # node o receives weight * (mom + affine @ (o - fx) dx) = weight * (at_base + sum_k o_k steps[:, k])
        steps = self._scattered_affine(mat, b, p, src, g, dt) * self.dx
        at_base = self.particle_momentum(src, g, p, m_p, control_share) - steps @ fx
        for offset in ti.static(ti.grouped(ti.ndrange(*([3] * self.dim)))):
            mom = self.plus_steps(at_base, steps, offset, 0)
            share = self.stencil_weight(w, offset) * ti.Vector([mom[k] for k in ti.static(range(self.dim))] + [m_p])
            self.add_at(self.grid_mm, g, base + offset, share, atomic)
        return base

    @ti.kernel
    def _p2g(
        self,
        scatter: ti.template(),
        mat: ti.template(),
        b: ti.i32,
        start: ti.i32,
        end: ti.i32,
        src: ti.i32,
        g: ti.i32,
        dt: float,
        control_share: float,
        first_body: ti.i32,
        colour: ti.i32,
        clear: ti.i32,
        stress: ti.i32,
    ):
        """One body's (one colour's) P2G: ``_p2g_pass``."""
        self._p2g_pass(scatter, mat, b, start, end, src, g, dt, control_share, first_body, colour, clear, stress)

    @ti.func
    def _p2g_pass(
        self,
        scatter: ti.template(),
        mat: ti.template(),
        b: ti.template(),
        start: ti.template(),
        end: ti.template(),
        src: ti.template(),
        g: ti.template(),
        dt: ti.template(),
        control_share: ti.template(),
        first_body: ti.template(),
        colour: ti.template(),
        clear: ti.template(),
        stress: ti.template(),
    ):
        """Scatter mass and momentum, and bound the nodes written: the box [active_lo, active_hi) of grid
        copy g, which the grid passes loop over (a body usually covers a small part of the domain), started
        afresh by the first body's scatter, widened by ``box_margin`` nodes on every side (a grid hook
        reading a node's neighbours asks for it) within the grid. ``scatter`` (``arch.SCATTERS``): "serial", one
        thread with plain adds and min / max; "coloured", colour ``colour``'s blocks (``bin_particles``), each
        block's particles in index order on one thread with plain adds (a launch per colour: one compiled
        copy, not 2^d); "atomic", every particle in parallel with atomic adds. The adjoint is a gather.
        One launch a body (a colour) for what were three: first the clear of the last box (``clear``: the
        first body's first launch) and, beside the serial scatter, the body's stress (``stress``: its first
        launch), each its own loop; inlined in a kernel (``_p2g``, the fused substep), each loop is one of its
        parallel tasks. A parallel scatter computes each particle's stress itself (``stress_in_scatter``):
        no affine field written and read back, 2 d^2 floats a particle less memory traffic."""
        self._clear_box(g, clear)
        if ti.static(not self.stress_in_scatter):
            if ti.static(self.constant_loop_bounds):
                self._stress(mat, b, 0, stress, src, g, dt)  # every slot of body b if ``stress``
            else:
                self._stress(mat, b, start, start + stress * (end - start), src, g, dt)
        margin = ti.static(self.box_margin)
        bounded = ti.static(self.bounded_grid)  # else the box stays the whole grid (``arch``)
        if ti.static(bounded):  # noqa: SIM102 (a compile-time test: Taichi cannot join it with a run-time one)
            if first_body:
                self.active_lo[g] = ti.Vector(self.nodes)
                self.active_hi[g] = ti.Vector.zero(ti.i32, self.dim)
        if ti.static(scatter == "coloured"):
            if ti.static(bounded):  # noqa: SIM102 (a compile-time test)
                if colour == 0:
                    ti.atomic_min(self.active_lo[g], self.reach_lo[None] - margin)
                    ti.atomic_max(self.active_hi[g], self.reach_hi[None] + 2 + margin)
            for j in range(self.colour_count[colour] * self.spread):  # a block per task (``mpm_bins.SPREAD``)
                if j % self.spread == 0:
                    blk = self.colour_blocks[colour, j // self.spread]
                    first = self.block_start[blk]
                    for k in range(first, first + self.block_count[blk]):
                        self._p2g_particle(mat, b, self.bin_order[k], src, g, dt, control_share, False)
        else:
            ti.loop_config(serialize=scatter == "serial")
            for p in range(
                0 if ti.static(self.constant_loop_bounds) else start,
                self.capacity if ti.static(self.constant_loop_bounds) else end,
            ):
                if self.off_body(b, p):  # a thread per particle slot (``constant_loop_bounds``)
                    continue
                base = self._p2g_particle(mat, b, p, src, g, dt, control_share, scatter == "atomic")
                if ti.static(bounded):
                    ti.atomic_min(self.active_lo[g], base - margin)
                    ti.atomic_max(self.active_hi[g], base + 3 + margin)
        if ti.static(bounded):  # noqa: SIM102 (compile-time tests)
            if ti.static(margin > 0):  # the widened box kept inside the grid
                self.active_lo[g] = ti.max(self.active_lo[g], 0)
                self.active_hi[g] = ti.min(self.active_hi[g], ti.Vector(self.nodes))
