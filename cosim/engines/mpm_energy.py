"""Energies of the MPM particles, summed on the device: what the conservation check and saved frames read.

Per body [J]: kinetic sum 1/2 m |v|^2 (APIC's affine part not counted), gravitational -sum m g . x (zero at
the domain origin), and strain: fixed corotated sum V0 (mu |F - R|^2 + lam/2 (J - 1)^2) for elastic and
plastic bodies (R the polar rotation of F, so |F - R|^2 = sum (sigma_i - 1)^2 over F's singular values),
sum V0 K/2 (J - 1)^2 for liquids (K = lam + 2 mu / d); and the volume sum V0 det F [m^3, 2D: m^2]. The
Lame parameters are the bodies' current ones (``set_parameters``).

One parallel pass over chunks of particles, each summed serially in float64 (no atomics), then a small
table to the host, instead of reading every particle back and taking its SVD on the host.
"""

import numpy as np
import taichi as ti

from cosim.engines.data_oriented import data_oriented
from cosim.engines.materials import polar_rotation

TERMS = ("kinetic", "gravity", "strain", "volume")


@data_oriented
class EnergyMeter:
    """``body_sums(slot)`` of one MPM engine (``MPMKernels``: its fields are read)."""

    def __init__(self, engine):
        self.engine = engine
        self.chunks = engine.watch.chunks  # the same particle chunks as the survey's, on the device once

    @ti.func
    def strain_density(self, b, F):
        """Strain energy per reference volume [J/m^3] of body b at deformation gradient F."""
        e = self.engine
        mu, lam = e._lame(b)
        J = F.determinant()
        psi = 0.0
        if e.p_liquid[b]:
            psi = 0.5 * (lam + 2.0 * mu / e.dim) * (J - 1.0) ** 2
        else:
            psi = mu * (F - polar_rotation(F)).norm_sqr() + 0.5 * lam * (J - 1.0) ** 2
        return psi

    @ti.kernel
    def _chunk_sums(self, slot: ti.i32, out: ti.types.ndarray()):
        """Per chunk c (parallel; serial within a chunk), into ``out[c]``: the ``TERMS`` of its particles."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for c in range(self.chunks.count[None]):
            b = self.chunks.table[c, 2]
            sums = ti.Vector.zero(ti.f64, 4)
            for p in range(self.chunks.table[c, 0], self.chunks.table[c, 1]):
                sums += self.particle_terms(slot, b, p)
            for k in ti.static(range(4)):
                out[c, k] = sums[k]

    @ti.func
    def particle_terms(self, slot, b, p):
        """The ``TERMS`` of particle p of body b in ``slot``, float64 (summed per chunk here and, when the
        engine surveys its energies, in the survey's pass: ``cosim.engines.mpm_watch``)."""
        e = self.engine
        m, vol = e.p_mass[b], e.p_vol[b]
        F = e.F[slot, p]
        terms = ti.Vector(
            [
                0.5 * m * e.v[slot, p].norm_sqr(),
                -m * e.gravity.dot(e.x[slot, p]),
                vol * self.strain_density(b, F),
                vol * F.determinant(),
            ]
        )
        return ti.cast(terms, ti.f64)

    @ti.kernel
    def _chunk_control_work(self, slot: ti.i32, out: ti.types.ndarray()):
        """Per chunk c, into ``out[c]``: sum I . v + |I|^2 / 2m of its particles, I the control impulse."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for c in range(self.chunks.count[None]):
            m = e.p_mass[self.chunks.table[c, 2]]
            work = ti.cast(0.0, ti.f64)
            for p in range(self.chunks.table[c, 0], self.chunks.table[c, 1]):
                impulse = e.control[p]
                work += ti.cast(impulse.dot(e.v[slot, p]) + impulse.norm_sqr() / (2.0 * m), ti.f64)
            out[c] = work

    def control_work(self, slot: int) -> float:
        """[J] Kinetic energy the control impulses (``engine.control``) add to the particles in ``slot``
        (their velocities before the impulses): sum I . v + |I|^2 / 2m."""
        out = np.zeros(len(self.chunks.host))
        self._chunk_control_work(slot, out)
        return float(out.sum())

    def body_sums(self, slot: int) -> np.ndarray:
        """(bodies, 4) float64: per body the ``TERMS`` of the particles in ``slot``."""
        out = np.zeros((len(self.chunks.host), len(TERMS)))
        self._chunk_sums(slot, out)
        return self.by_body(out)

    def by_body(self, chunk_sums: np.ndarray) -> np.ndarray:
        """(bodies, 4): the per-chunk ``TERMS`` (chunks, 4) summed per body."""
        sums = np.zeros((len(self.engine.bodies), len(TERMS)))
        np.add.at(sums, self.chunks.host[:, 2], chunk_sums)
        return sums
