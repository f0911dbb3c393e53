"""Health checks of the MPM particles on the device: what the coupled system's NaN, CFL and domain checks read.

- In every substep's G2P (``MPMKernels._g2p_advect``, a forward kernel with a hand-written adjoint) ``flag``
  looks at the new x and F it has just computed, which a NaN or inf in the gathered v or C, or in the x and F
  it started from, reaches (x' = x + dt v, F' = project((I + dt C) F)): a particle whose new x or F is
  non-finite lowers its body's first bad substep to s, or to s - 1 when its x or F (as substep s - 1 left
  them) already was (-1: the step started from it). An atomic min, written only by bad particles; the
  healthy path is one sum and one test (testing x, F, v and C too would slow every G2P for nothing).
- ``survey(slot)``, after a step: one parallel pass over the particles gives per body the largest velocity
  component [m/s], the particles with a non-finite x, v, C and F, those outside [dx, L - dx] on some
  axis (L the grid's extent [m]), and the first bad substep, which it resets. The host reads that small
  table, never the particle state.

Neither is differentiated: the substep's adjoint is the same with and without them.
"""

from dataclasses import dataclass

import numpy as np
import taichi as ti

from cosim.engines import field_pool
from cosim.engines.data_oriented import data_oriented

KEYS = ("x", "v", "C", "F")  # the particle state's keys, as the survey counts them
NONE = 2**30  # the first bad substep of a body with none
# A chunk is one thread's serial loop, its result a row of the table the host reads. Few long chunks
# leave a GPU's threads idle, each waiting on its own loads (1,485 particles were two threads of 1,024
# iterations); many short ones make a long table. So: MIN_CHUNK particles a chunk, longer from
# MIN_CHUNK * MAX_CHUNKS particles on so that there are MAX_CHUNKS chunks, and never more than CHUNK.
MIN_CHUNK = 16
MAX_CHUNKS = 4096
CHUNK = 1024


def chunk_length(particles: int) -> int:
    """Particles per chunk for an engine of ``particles`` (``MIN_CHUNK``, ``MAX_CHUNKS``, ``CHUNK``)."""
    return min(CHUNK, max(MIN_CHUNK, -(-particles // MAX_CHUNKS)))


def body_chunks(ranges: list[tuple[int, int]]) -> np.ndarray:
    """(chunks, 3) int32 rows (start, end, body): each body's particle range [lo, hi) cut into chunks of
    ``chunk_length`` of all the particles, which a per-chunk reduction sums serially and in parallel with
    the others (no atomics: the sums' order is fixed by the particles alone)."""
    size = chunk_length(sum(hi - lo for lo, hi in ranges))
    chunks = [(p, min(p + size, hi), b) for b, (lo, hi) in enumerate(ranges) for p in range(lo, hi, size)]
    return np.array(chunks, dtype=np.int32).reshape(-1, 3)


def chunk_rows(capacity: int, bodies: int) -> int:
    """Rows enough for the chunks of any particle count up to ``capacity`` in ``bodies`` bodies (each body
    may end in a partial chunk): the table's shape, fixed by the engine's bucket (``particle_capacity``)
    so that another count in it compiles no kernel anew."""
    return max(min(-(-capacity // MIN_CHUNK), MAX_CHUNKS), -(-capacity // CHUNK)) + bodies


class ChunkTable:
    """The particle chunks (``body_chunks``) of ``owner``'s per-chunk kernels: ``host`` the rows on the host,
    ``table`` the same in an i32 field of ``chunk_rows`` rows (the unused ones empty), ``count`` a 0-D field
    holding how many are used, which the kernels loop to (a Python count would be a constant compiled into
    them). An array handed to a kernel from the host is, on a GPU, a copy and a wait at every launch; these
    are copied once."""

    def __init__(self, owner, chunks: np.ndarray, capacity: int, bodies: int):
        self.host = chunks  # the rows used, on the host (their bodies group the kernels' results)
        rows = chunk_rows(capacity, bodies)
        if len(chunks) > rows:
            raise ValueError(f"{len(chunks)} particle chunks exceed the {rows} rows of capacity {capacity}")
        self.table = field_pool.scalar(owner, ti.i32, shape=(rows, 3))
        padded = np.zeros((rows, 3), dtype=np.int32)
        padded[: len(chunks)] = chunks
        self.table.from_numpy(padded)
        self.count = field_pool.scalar(owner, ti.i32, shape=())
        self.count[None] = len(chunks)


@dataclass
class BodyHealth:
    """One body's particles at the end of a step."""

    speed: float  # [m/s] the largest velocity component
    non_finite: dict[str, int]  # per state key (x, v, C, F): particles with a NaN or inf in it
    outside: int  # particles outside [dx, L - dx] on some axis
    first_bad: int | None  # the step's first substep that left a NaN or inf (-1: it started with one)


@ti.func
def non_finite(value) -> bool:
    """True when the scalar ``value`` is NaN or +-inf: its exponent bits all set, one integer test on its bits
    (immune to fast-math folding, and branch-free: a branch such as ``isnan(v) or isinf(v)`` slows G2P's loop).
    A sum of a particle's entries is non-finite exactly when one of them is (inf - inf is NaN), barring an
    overflow of the sum itself near the float's largest value."""
    result = False
    if ti.static(ti.lang.impl.get_runtime().default_fp == ti.f64):
        high = ti.cast(ti.bit_cast(ti.cast(value, ti.f64), ti.u64) >> 32, ti.u32)
        result = (high & 0x7FFFFFFF) >= 0x7FF00000
    else:
        result = (ti.bit_cast(ti.cast(value, ti.f32), ti.u32) & 0x7FFFFFFF) >= 0x7F800000
    return result


@data_oriented
class ParticleWatch:
    """The per-substep flags and the survey of one MPM engine (``MPMKernels``: its fields are read)."""

    def __init__(self, engine):
        self.engine = engine
        self.n_bodies = len(engine.bodies)
        self.first = field_pool.scalar(self, ti.i32, shape=self.n_bodies)  # per body: first bad substep, NONE if none
        self.first.fill(NONE)
        self.low = engine.dx  # [m] inside the grid: at least a cell from each face
        self.high = ti.Vector([c * engine.dx - engine.dx for c in engine.cfg.cells])
        self.chunks = ChunkTable(self, body_chunks(engine.ranges), engine.capacity, self.n_bodies)

    @ti.func
    def flag(self, p, s, x, F, new_x, new_F):
        """In substep s's G2P of particle p: x and F from before it, new_x and new_F from after it."""
        if non_finite(new_x.sum() + new_F.sum()):  # one test on the healthy path
            ti.atomic_min(self.first[self.engine.body_id[p]], s - 1 if non_finite(x.sum() + F.sum()) else s)

    @ti.kernel
    def _survey(self, slot: ti.i32, out: ti.types.ndarray(), meters: ti.template()):
        """Per chunk c (parallel), into ``out[c]``: max |v|, particles with a non-finite x, v, C, F, particles
        outside and its body's first bad substep, then (with an energy meter: ``meters`` holds none or one)
        its energy terms; then the first bad substeps are reset."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for c in range(self.chunks.count[None]):
            peak, outside = 0.0, 0
            bad = ti.Vector.zero(ti.i32, 4)
            energy = ti.Vector.zero(ti.f64, 4)
            for p in range(self.chunks.table[c, 0], self.chunks.table[c, 1]):
                for meter in ti.static(meters):
                    energy += meter.particle_terms(slot, self.chunks.table[c, 2], p)
                x, v = e.x[slot, p], e.v[slot, p]
                peak = ti.max(peak, ti.abs(v).max())
                sums = ti.Vector([x.sum(), v.sum(), e.C[slot, p].sum(), e.F[slot, p].sum()])
                for k in ti.static(range(4)):
                    bad[k] += non_finite(sums[k])
                away = 0
                for k in ti.static(range(e.dim)):
                    away |= (x[k] < self.low) | (x[k] > self.high[k])
                outside += away
            out[c, 0] = peak
            for k in ti.static(range(4)):
                out[c, 1 + k] = bad[k]
            out[c, 5] = outside
            out[c, 6] = self.first[self.chunks.table[c, 2]]
            for k in ti.static(range(4 * len(meters))):
                out[c, 7 + k] = energy[k]
        ti.loop_config(serialize=True)  # a few bodies: a thread-pool dispatch would cost more (arch)
        for b in range(self.n_bodies):
            self.first[b] = NONE

    def survey(self, slot: int, meter=None) -> tuple[dict[str, BodyHealth], np.ndarray | None]:
        """({body name: its ``BodyHealth``} for the particles in ``slot``, with the first bad substep of the
        substeps since the last survey (reset by it); with an ``EnergyMeter`` its ``body_sums`` of the slot,
        taken in the same pass (a launch and a host array less a step), else None)."""
        body = self.chunks.host[:, 2]
        out = np.zeros((len(body), 7 if meter is None else 11))
        self._survey(slot, out, () if meter is None else (meter,))
        first = np.full(self.n_bodies, NONE)
        first[body] = out[:, 6]  # each of a body's chunks holds its first bad substep
        peak = np.zeros(self.n_bodies)
        np.maximum.at(peak, body, out[:, 0])
        counts = np.zeros((self.n_bodies, 5))
        np.add.at(counts, body, out[:, 1:6])
        health = {
            body.name: BodyHealth(
                speed=float(peak[b]),
                non_finite={k: int(n) for k, n in zip(KEYS, counts[b, :4])},
                outside=int(counts[b, 4]),
                first_bad=None if first[b] >= NONE else int(first[b]),
            )
            for b, body in enumerate(self.engine.bodies)
        }
        return health, (None if meter is None else meter.by_body(out[:, 7:]))
