"""Hand-written adjoints of the MPM's particle kernels (P2G scatter, G2P gather, stress, advection).

Taichi's reverse-mode autodiff of the transfer kernels unrolls the 3^d stencil
into a large reverse program that is slow to compile in 3D. The adjoints here are
written out instead. Their gathers
sum the stencil row by row like the forward G2P (``row_weight``, ``row_gradient``:
a row's sums along the last axis, then its weight and the weight's gradient once),
about half the arithmetic of a node-by-node sum, and a short compile. The G2P adjoint
is a parallel gather into the particle position, in one pass with the advection's adjoint
(``_g2p_adjoint``), and a scatter onto the grid (with no grid hook, straight onto the grid
velocity's adjoint): in the same pass with the atomic scatter, else its own serial or coloured
launches, like the forward P2G. The per-particle stress
and the advection with its return mapping are written out too (``_stress_adjoint_particle``,
``_advect_adjoint_particle``, with the materials' ``kirchhoff_vjp`` and ``project_vjp``): the
3D polar decomposition's derivative is one 3x3 solve, where Taichi's reverse mode
replayed its Newton iterations. Only the grid update (and the contact hooks' own
rules) keep Taichi's autodiff.

Notation for one particle at x with stencil nodes i: weights w_i(x) (products of
per-axis quadratic B-splines), offsets dpos_i = (i - x / dx) dx. Both depend on x:
grad w_i = (1 / dx) d w_i / d fx (``row_gradient``), d dpos_i / dx = -I. The base node is
piecewise constant in x and carries no gradient.
"""

import taichi as ti

from cosim.engines.data_oriented import data_oriented
from cosim.engines.mpm_kernels import MPMKernels


@data_oriented
class MPMAdjointKernels(MPMKernels):
    """The MPM kernels plus the adjoint of one substep (``_substep_grad``)."""

    @ti.kernel
    def _particle_adjoint(
        self,
        mat: ti.template(),
        b: ti.i32,
        start: ti.i32,
        end: ti.i32,
        src: ti.i32,
        g: ti.i32,
        dt: float,
        control_share: float,
        material_grads: ti.template(),
    ):
        """Adjoint of body b's P2G (``_p2g``) and then of its stress (``_stress``), particle by particle in
        one parallel pass: the affine momentum's adjoint the first gives the second stays in registers (a
        field of d^2 entries per particle and grid copy, written and read back, before)."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(
            0 if ti.static(self.constant_loop_bounds) else start,
            self.capacity if ti.static(self.constant_loop_bounds) else end,
        ):  # each particle owns its adjoint entries: plain adds, not atomics
            if self.off_body(b, p):  # a thread per particle slot (``constant_loop_bounds``)
                continue
            g_affine = self._p2g_adjoint_particle(b, p, src, g, control_share)
            self._stress_adjoint_particle(mat, b, p, src, dt, g_affine, material_grads)
        if ti.static(material_grads):
            self._lame_grad(b)

    @ti.func
    def _p2g_adjoint_particle(self, b, p, src, g, control_share):
        """Adjoint of particle p's scatter in ``_p2g``: a gather of the grid momentum and mass adjoints into
        its velocity, position, control and particle-hook momenta; returns its affine momentum's adjoint."""
        m_p = self.p_mass[b]
        base, fx, w = self.stencil(self.x[src, p])
        slopes = self.stencil_slopes(fx)
        affine = self.affine[g, p]
        # what node o received: mom + affine (o - fx) dx = at_base + steps o (``_p2g``)
        steps = affine * self.dx
        at_base = self.particle_momentum(src, g, p, m_p, control_share) - steps @ fx
        d = ti.static(self.dim)
        g_mom = ti.Vector.zero(float, d)
        columns = [ti.Vector.zero(float, d) for _ in ti.static(range(d))]  # column k: sum_o W g_o o_k
        g_fx = ti.Vector.zero(float, d)  # d/d fx of sum_o W_o h_o, h_o = g_o . (what o received) + m g_m,o
        for row in ti.static(self.rows):  # row by row (``row_weight``)
            row_base = self.plus_steps(at_base, steps, row, 0)
            along_g = ti.Vector.zero(float, d)
            moment_g = ti.Vector.zero(float, d)
            along_h, slope_h = 0.0, 0.0
            for c in ti.static(range(3)):
                node = base + self.row_node(row, c)
                g_mm = self.grid_mm.grad[g, node]
                g_node = ti.Vector([g_mm[k] for k in ti.static(range(d))])
                h = g_node.dot(self.plus_steps(row_base, steps, [c], d - 1)) + m_p * g_mm[d]
                weighted = w[c][d - 1] * g_node
                along_g += weighted
                if ti.static(c > 0):
                    moment_g += c * weighted
                along_h += w[c][d - 1] * h
                slope_h += slopes[c][d - 1] * h
            w_row = self.row_weight(w, row)
            g_mom += w_row * along_g
            columns[d - 1] += w_row * moment_g
            for k in ti.static(range(d - 1)):
                if ti.static(row[k] > 0):
                    columns[k] += (row[k] * w_row) * along_g
            g_fx += self.row_gradient(w, slopes, row, along_h, slope_h)
        # sum_o W g_o (o - fx)^T dx, and d dpos / dx = -I: sum_o W affine^T g_o, both out of the loop
        g_affine = self.dx * (ti.Matrix.cols(columns) - g_mom.outer_product(fx))
        g_x = self.inv_dx * g_fx - affine.transpose() @ g_mom
        # each particle owns these adjoint entries: plain adds, not atomics
        self.v.grad[src, p] = self.v.grad[src, p] + m_p * g_mom
        if ti.static(self.cfg.has_controls):
            self.control.grad[p] = self.control.grad[p] + control_share * g_mom
        for hook in ti.static(self.particle_hooks):
            hook.output.grad[g, p] = hook.output.grad[g, p] + g_mom
        self.x.grad[src, p] = self.x.grad[src, p] + g_x
        return g_affine

    @ti.func
    def velocity_grad(self, g, I, g_v):
        """Adjoint of ``velocity(g, I)``: add g_v to the adjoint of the grid velocity it read."""
        self.grid_v.grad[g, I] += g_v

    @ti.func
    def _g2p_adjoint_particle(self, p, src, dst, g, out: ti.template()):
        """Scatter particle p's new velocity and affine adjoints onto ``out`` over its stencil, with plain adds
        (the serial and coloured scatters: ``_g2p_adjoint_scatter``)."""
        base, fx, w = self.stencil(self.x[src, p])
        self._g2p_adjoint_spread(base, fx, w, self.v.grad[dst, p], self.C.grad[dst, p], g, out, False)

    @ti.func
    def _g2p_adjoint_spread(self, base, fx, w, v_bar, C_bar, g, out: ti.template(), atomic: ti.template()):
        """Add a particle's new velocity and affine adjoints (``v_bar``, ``C_bar``) to ``out`` (grid copy g)
        over its stencil (base node, fractional position, weights)."""
        g_C = (4.0 * self.inv_dx) * C_bar
        at_base = v_bar - g_C @ fx  # node o's adjoint / weight: g_v + g_C (o - fx)
        for offset in ti.static(ti.grouped(ti.ndrange(*([3] * self.dim)))):
            g_node = self.stencil_weight(w, offset) * self.plus_steps(at_base, g_C, offset, 0)
            self.add_at(out, g, base + offset, g_node, atomic)

    @ti.kernel
    def _g2p_adjoint_scatter(
        self,
        scatter: ti.template(),
        src: ti.i32,
        dst: ti.i32,
        g: ti.i32,
        out: ti.template(),
        colour: ti.i32,
        source: ti.template(),
        hand_over: ti.template(),
    ):
        """Adjoint of G2P (``_g2p_advect``) with respect to the velocities it gathered, where the scatter is not
        atomic (``_g2p_adjoint`` scatters then): scatter the new velocity's and affine field's adjoints onto
        ``out``: the grid velocity's adjoint (copy g) when G2P read the engine's own grid, else
        ``gathered_grad``, which the last launch (``hand_over``) hands to the last grid hook (``source``,
        ``_hand_over``). ``scatter`` as in ``_p2g``: "serial", one thread; "coloured", colour ``colour``'s
        blocks (``bin_particles``' lists of slot src)."""
        if ti.static(scatter == "coloured"):
            for j in range(self.colour_count[colour] * self.spread):  # a block per task (``mpm_bins.SPREAD``)
                if j % self.spread == 0:
                    blk = self.colour_blocks[colour, j // self.spread]
                    first = self.block_start[blk]
                    for k in range(first, first + self.block_count[blk]):
                        self._g2p_adjoint_particle(self.bin_order[k], src, dst, g, out)
        else:
            ti.loop_config(serialize=True)
            for p in range(self.count[None]):
                self._g2p_adjoint_particle(p, src, dst, g, out)
        if ti.static(hand_over):
            self._hand_over(g, source)

    @ti.func
    def _g2p_position_adjoint(self, base, fx, w, v_bar, C_bar, g, source: ti.template()):
        """Adjoint of a particle's G2P with respect to its position (weights and offsets move with it), from
        its new velocity's and affine field's adjoints: a gather of the grid velocities (``source``)."""
        slopes = self.stencil_slopes(fx)
        g_C = (4.0 * self.inv_dx) * C_bar
        at_base = v_bar - g_C @ fx  # at node o: g_v + g_C (o - fx)
        d = ti.static(self.dim)
        g_fx = ti.Vector.zero(float, d)  # d/d fx of sum_o W_o h_o, h_o = v_o . (g_v + g_C (o - fx))
        new_v = ti.Vector.zero(float, d)
        for row in ti.static(self.rows):  # row by row (``row_weight``)
            row_base = self.plus_steps(at_base, g_C, row, 0)
            along_v = ti.Vector.zero(float, d)
            along_h, slope_h = 0.0, 0.0
            for c in ti.static(range(3)):
                node_v = source.velocity(g, base + self.row_node(row, c))
                h = node_v.dot(self.plus_steps(row_base, g_C, [c], d - 1))
                along_v += w[c][d - 1] * node_v
                along_h += w[c][d - 1] * h
                slope_h += slopes[c][d - 1] * h
            new_v += self.row_weight(w, row) * along_v
            g_fx += self.row_gradient(w, slopes, row, along_h, slope_h)
        # d dpos / dx = -I / dx: sum_i w_i g_C^T v_i / dx, taken out of the loop
        return self.inv_dx * g_fx - self.inv_dx * (g_C.transpose() @ new_v)

    @ti.func
    def _hand_over(self, g: ti.template(), source: ti.template()):
        """Hand the adjoint of the gathered velocities to their source (``velocity_grad``: the
        engine's grid velocity or the last grid hook, which passes it upstream) and clear it.
        A grid pass of its own after the scatter (the last loop of its last launch): inside the G2P
        adjoint's stencil loop, the hooks' adjoint chain compiles far longer in 3D than this pass
        does. Over grid copy g's box: the G2P adjoint wrote nothing outside it."""
        ti.loop_config(serialize=self.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (self.active_lo[g][k], self.active_hi[g][k]) if ti.static(self.bounded_grid) else (0, self.nodes[k])
                    for k in ti.static(range(self.dim))
                ]
            )
        ):
            source.velocity_grad(g, I, self.gathered_grad[I])
            self.gathered_grad[I] = ti.Vector.zero(float, self.dim)

    @ti.func
    def _stress_adjoint_particle(self, mat: ti.template(), b, p, src, dt, affine_bar, material_grads: ti.template()):
        """Adjoint of particle p's stress in ``_stress`` (affine = s tau(F, C, mu, lam) + m_p C, s = -dt V0 4 /
        dx^2): from dL/d(affine) to dL/dF, dL/dC and, summed in ``lame_bar``, dL/dmu, dL/dlam."""
        mu, lam = self._lame(b)
        m_p, vol = self.p_mass[b], self.p_vol[b]
        tau_bar = (-dt * vol * 4.0 * self.inv_dx * self.inv_dx) * affine_bar
        F_bar, C_bar, mu_bar, lam_bar = mat.kirchhoff_vjp(
            self.F[src, p], self.C[src, p], mu, lam, self.viscosity[b], tau_bar
        )
        self.F.grad[src, p] = self.F.grad[src, p] + F_bar
        self.C.grad[src, p] = self.C.grad[src, p] + C_bar + m_p * affine_bar
        if ti.static(material_grads):
            self.lame_bar[None] += ti.Vector([mu_bar, lam_bar])

    @ti.kernel
    def _g2p_adjoint(
        self,
        scatter: ti.template(),
        mat: ti.template(),
        b: ti.i32,
        start: ti.i32,
        end: ti.i32,
        src: ti.i32,
        dst: ti.i32,
        g: ti.i32,
        source: ti.template(),
        out: ti.template(),
        dt: float,
        material_grads: ti.template(),
        first: ti.template(),
        hand_over: ti.template(),
    ):
        """Adjoint of body b's G2P and advection (``_g2p_advect``), particle by particle in one parallel pass:
        the advection's (``_advect_adjoint_particle``), then the gather's with respect to the position
        (``_g2p_position_adjoint``), and with the atomic scatter also the gather's with respect to the grid
        velocities, a scatter onto ``out`` (``_g2p_adjoint_scatter``), all from the particle's registers.
        The first kernel of substep src's adjoint, it starts slot src's particle adjoints (x, F assigned, v
        and C zeroed; the later kernels add to them), so no fill of every slot precedes the backward. The
        substep's ``first`` launch begins with zeroing its grid copy's adjoints (``_zero_grid_grad``); with the
        atomic scatter and a grid hook, its last ends with handing the scatter's sums to the hook
        (``hand_over``, ``_hand_over``)."""
        if ti.static(first):
            self._zero_grid_grad(g)
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(
            0 if ti.static(self.constant_loop_bounds) else start,
            self.capacity if ti.static(self.constant_loop_bounds) else end,
        ):  # each particle owns its adjoint entries: plain adds, not atomics
            if self.off_body(b, p):  # a thread per particle slot (``constant_loop_bounds``)
                continue
            x_bar, v_bar, C_bar = self._advect_adjoint_particle(mat, b, p, src, dst, dt, material_grads)
            base, fx, w = self.stencil(self.x[src, p])
            self.x.grad[src, p] = x_bar + self._g2p_position_adjoint(base, fx, w, v_bar, C_bar, g, source)
            if ti.static(scatter == "atomic"):
                self._g2p_adjoint_spread(base, fx, w, v_bar, C_bar, g, out, True)
            else:  # for the scatter's own launches (serial: one thread; coloured: a launch per colour)
                self.v.grad[dst, p] = v_bar
                self.C.grad[dst, p] = C_bar
        if ti.static(mat.project_uses_lame):  # noqa: SIM102 (compile-time tests)
            if ti.static(material_grads):
                self._lame_grad(b)
        if ti.static(hand_over):
            self._hand_over(g, source)

    @ti.func
    def _advect_adjoint_particle(self, mat: ti.template(), b, p, src, dst, dt, material_grads: ti.template()):
        """Adjoint of particle p's advection (x' = x + dt v', F' = project((I + dt C') F)): from dL/dx', dL/dF'
        to dL/dF (stored) and the body's dL/dmu, dL/dlam (``lame_bar``; a plastic body's yield limit depends
        on mu); returns dL/dx and the complete dL/dv', dL/dC'. Zeroes slot src's v and C adjoints."""
        mu, lam = self._lame(b)
        x_bar = self.x.grad[dst, p]
        self.v.grad[src, p] = ti.zero(self.v.grad[src, p])
        self.C.grad[src, p] = ti.zero(self.C.grad[src, p])
        F = self.F[src, p]
        step = ti.Matrix.identity(float, self.dim) + dt * self.C[dst, p]
        trial_bar, mu_bar, lam_bar = mat.project_vjp(step @ F, mu, lam, self.yield_stress[b], self.F.grad[dst, p])
        self.F.grad[src, p] = step.transpose() @ trial_bar
        if ti.static(mat.project_uses_lame):  # noqa: SIM102 (compile-time; else a zero added to E and nu by every particle)
            if ti.static(material_grads):
                self.lame_bar[None] += ti.Vector([mu_bar, lam_bar])
        v_bar = self.v.grad[dst, p] + dt * x_bar
        C_bar = self.C.grad[dst, p] + dt * trial_bar @ F.transpose()
        return x_bar, v_bar, C_bar

    @ti.func
    def _lame_grad(self, b: ti.template()):
        """Add dL/dE and dL/dnu of body b from the dL/dmu and dL/dlam its particles summed into ``lame_bar``
        (mu = E / (2 (1 + nu)), lam = E nu / q, q = (1 + nu)(1 - 2 nu)), and reset the sum. Called after
        the particle loop: as its own one-iteration loop it runs once the sums are complete. Summing into
        a 0-D field lets Taichi keep one sum per thread (its thread-local reduction); adds to E.grad[b]
        (b known at run time) would be atomic adds to one address from every particle, contended by
        every thread."""
        for _ in range(1):
            mu_bar, lam_bar = self.lame_bar[None]
            E, nu = self.E[b], self.nu[b]
            q = (1.0 + nu) * (1.0 - 2.0 * nu)
            self.E.grad[b] += mu_bar / (2.0 * (1.0 + nu)) + lam_bar * nu / q
            self.nu.grad[b] += -mu_bar * E / (2.0 * (1.0 + nu) ** 2) + lam_bar * E * (1.0 + 2.0 * nu * nu) / (q * q)
            self.lame_bar[None] = ti.Vector.zero(float, 2)

    @ti.kernel
    def _read_moduli_grads(self, out: ti.types.ndarray()):
        """dL/dE and dL/dnu of every body into ``out`` (bodies, 2): one launch and one copy, not two."""
        ti.loop_config(serialize=True)  # a few bodies (``arch``)
        for b in range(ti.static(len(self.bodies))):
            out[b, 0] = self.E.grad[b]
            out[b, 1] = self.nu.grad[b]

    @ti.kernel
    def _zero_moduli_grads(self):
        """Zero dL/dE and dL/dnu, which every substep's adjoint adds to, before a macro step's adjoint."""
        ti.loop_config(serialize=True)
        for b in range(ti.static(len(self.bodies))):
            self.E.grad[b] = 0.0
            self.nu.grad[b] = 0.0

    @ti.func
    def _zero_grid_grad(self, g: ti.template()):
        """Zero grid copy g's adjoints, and its grid hooks' (``grid_adjoints``), over its box (``_clear_box``):
        only its nodes are read and written by its substep's adjoint, so no fill of all K grids. The first loop
        of its substep's first adjoint launch (``_g2p_adjoint``)."""
        ti.loop_config(serialize=self.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (self.active_lo[g][k], self.active_hi[g][k]) if ti.static(self.bounded_grid) else (0, self.nodes[k])
                    for k in ti.static(range(self.dim))
                ]
            )
        ):
            self.grid_mm.grad[g, I] = ti.Vector.zero(float, self.dim + 1)
            self.grid_v.grad[g, I] = ti.Vector.zero(float, self.dim)
            for fld in ti.static(self._hook_fields("grid_adjoints")):  # a fill of all K grid copies cost more
                fld.grad[g, I] = ti.zero(fld.grad[g, I])

    def _substep_grad(self, s: int, dt: float, control_share: float) -> None:
        """Adjoint of substep s (slots s -> s + 1); its grid and stress copies are still held."""
        hooked = self._grid_out is not self
        out = self.gathered_grad if hooked else self.grid_v.grad  # no grid hook: straight on
        atomic = self.scatter == "atomic"  # then ``_g2p_adjoint`` scatters, and its last launch hands over
        last = len(self.bodies) - 1
        for b in reversed(range(len(self.bodies))):
            lo, hi = self.ranges[b]
            self._g2p_adjoint(self.scatter, self.materials[b], b, lo, hi, s, s + 1, s, self._grid_out, out, dt,
                              self.material_grads, b == last, atomic and hooked and b == 0)  # fmt: skip
        if not atomic:
            if self.scatter == "coloured":
                self.bin_particles(s, 0, self.n_particles)
            colours = self.colours if self.scatter == "coloured" else 1
            for colour in range(colours):
                self._g2p_adjoint_scatter(self.scatter, s, s + 1, s, out, colour, self._grid_out,
                                          hooked and colour == colours - 1)  # fmt: skip
        for hook in reversed(self.grid_hooks):
            hook.apply_grad(s, s, s, dt)
        self._grid_update.grad(s, dt, self._mass_floor())
        for b in reversed(range(len(self.bodies))):
            lo, hi = self.ranges[b]
            self._particle_adjoint(self.materials[b], b, lo, hi, s, s, dt, control_share, self.material_grads)
        for hook in reversed(self.particle_hooks):
            hook.apply_grad(s, s, s, dt)
        for prepare_grad in reversed(self.substep_preparer_grads):
            prepare_grad(s, s)
