"""G2P, the gather from the grid to the particles, with the advection: ``G2PKernels``, a base of ``MPMKernels``.

One launch per body (``_g2p_advect``), or the last pass of the fused forward substep
(``MPMKernels._substep_fused``). Its functions read the engine's fields (``x``, ``v``, ``C``, ``F``,
``yield_stress``, ``body_range``), settings (``dim``, ``inv_dx``, ``capacity``, the loop flags), the stencil
(``StencilFunctions``) and the NaN watch (``watch``); the adjoint is in ``mpm_adjoint``.
"""

import taichi as ti

from cosim.engines.data_oriented import data_oriented


@data_oriented
class G2PKernels:
    """The gather, the advection and the deformation update of one substep (``_g2p_advect``)."""

    @ti.kernel
    def _g2p_advect(
        self,
        mat: ti.template(),
        b: ti.i32,
        start: ti.i32,
        end: ti.i32,
        src: ti.i32,
        dst: ti.i32,
        g: ti.i32,
        source: ti.template(),
        s: ti.i32,
        dt: float,
    ):
        """G2P and advection of one body (parallel unless the engine is small): gather velocity and affine
        field from the grid (``source.velocity``) into slot ``dst``, flag NaN / inf for substep s
        (``mpm_watch``), move the particles and update F with the material's return mapping. One kernel,
        not two: a launch and a pass over v and C fewer per substep. Its adjoint is split (``mpm_adjoint``)."""
        self._g2p_pass(mat, b, start, end, src, dst, g, source, s, dt)

    @ti.func
    def _g2p_pass(
        self,
        mat: ti.template(),
        b: ti.template(),
        start: ti.template(),
        end: ti.template(),
        src: ti.template(),
        dst: ti.template(),
        g: ti.template(),
        source: ti.template(),
        s: ti.template(),
        dt: ti.template(),
    ):
        """``_g2p_advect``'s loop (inlined in it, and in the fused substep)."""
        ti.loop_config(serialize=self.serial_particle_loops)
        for p in range(
            0 if ti.static(self.constant_loop_bounds) else start,
            self.capacity if ti.static(self.constant_loop_bounds) else end,
        ):
            if self.off_body(b, p):  # a thread per particle slot (``constant_loop_bounds``)
                continue
            xp = self.x[src, p]
            base, fx, w = self.stencil(xp)
            new_v, first = self.gather_moments(source, g, base, w)
            new_C = (4.0 * self.inv_dx) * (first - new_v.outer_product(fx))
            self.v[dst, p] = new_v
            self.C[dst, p] = new_C
            F = self.F[src, p]
            mu, lam = self._lame(b)
            new_x = xp + dt * new_v
            self.x[dst, p] = new_x
            F_trial = (ti.Matrix.identity(float, self.dim) + dt * new_C) @ F
            new_F = mat.project(F_trial, mu, lam, self.yield_stress[b])
            self.F[dst, p] = new_F
            self.watch.flag(p, s, xp, F, new_x, new_F)  # last: a branch earlier slows the loop
