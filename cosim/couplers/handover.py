"""The hand-over of the added-mass coupling: material that followed a body gets the body's velocity change.

An added-mass coupling (``cosim.couplers.mpm_cloth``, ``cosim.couplers.mpm_rigid``) steps a light
body with the material that follows it as part of its inertia, (m + A)(v^{n+1} - v^n) = T f + J:
the body's velocity change already carries that material along, but the MPM's material ended the
step at the body's old velocity. So, before the next step's first P2G, each particle p the
contact model engages (share e_p, ``engagement``) gets the velocity change of the body point
under it, e_p dv(p) (dv the body's change over its last step: a twist for a rigid body, vertex
velocities interpolated by the contact frame for a cloth), as momentum m_p e_p dv(p) in P2G.
The material and the body then move on together, and the total momentum is the reactions'
(the body gave up A dv, the material receives sum_p m_p e_p dv(p), the same sum A is made of).

Why not give the body that momentum back instead (the first form of this coupling, pay-back
of A (v^{n+1} - v^n) in the next step's force): it is right while the material stays pressed
against the body (its next reaction then drags the body back by as much), but after an impact
the material, stopped at the body's old velocity, separates and never drags: the pay-back then
hands the body all the material's momentum, as the explicit exchange does, and a light plate
hit by a block, or a tortilla by its filling, was flung with more energy than it was hit with.

A source that declares ``added_mass`` provides ``@ti.func handover(s, x, p)`` -> the velocity
change [m/s] for particle p at x in substep s (0) and reads its "handover" boundary state (the
body's velocity change); this
particle hook (``attach_particle_hook``) scatters m_p times it at substep 0 and nothing after.
"""

import taichi as ti

from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented


@data_oriented
class Handover:
    """Particle hook of the ``sources`` (those declaring ``added_mass``) on ``engine``."""

    def __init__(self, engine, sources: list):
        self.engine = engine
        self.sources = list(sources)
        grad = engine.cfg.requires_grad
        self.output = field_pool.vector(self, engine.dim, float, shape=engine.per_particle, needs_grad=grad)
        self._held = -1  # the grid copy whose output holds substep 0's momenta (-1: none)
        engine.attach_particle_hook(self)

    @ti.kernel
    def _apply(self, src: ti.i32, g: ti.i32):
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            x = e.x[src, p]
            dv = ti.Vector.zero(float, e.dim)
            for source in ti.static(self.sources):
                dv += source.handover(0, x, p)
            self.output[g, p] = e.mass_of(p) * dv

    @ti.kernel
    def _clear(self, g: ti.i32):
        for p in range(self.engine.count[None]):
            self.output[g, p] = ti.Vector.zero(float, self.engine.dim)

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        """Substep 0: the momenta; later substeps: none. Without gradients every substep shares grid copy 0,
        cleared once at substep 1; with them each substep has its own, and substep 0's stays for its adjoint."""
        if s == 0:
            self._apply(src, g)
            self._held = g
        elif g == self._held:
            self._clear(g)
            self._held = -1

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        if s == 0:
            self._apply.grad(src, g)

    def zero_grad(self) -> None:
        self.output.grad.fill(0)
