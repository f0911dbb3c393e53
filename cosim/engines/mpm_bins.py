"""Particles binned by grid block, for a parallel scatter whose sums do not depend on the threads.

A scatter (P2G, the G2P adjoint) adds every particle's share to the 3^d nodes of its stencil. On a
CPU it ran on one thread (contended atomic adds cost more than they gain on a few cores), which caps
the MPM on a many-core machine. The *coloured* scatter splits the grid into blocks of ``BLOCK`` cells
per axis and the blocks into 2^d colours by the parity of their coordinates: the stencils of two
particles in different blocks of one colour never share a node (a block's particles reach
``BLOCK + 2`` nodes along an axis, less than the two blocks between same-coloured ones), so the blocks
of one colour scatter in parallel with plain adds, one thread per block, and the colours in turn.

``bin_particles`` lists each block's particles in ascending index: a counting sort whose counts are
kept per chunk of ``CHUNKS`` equal runs of particles (a chunk is one thread's), so the order, and with
it every node's sum, is the same on 1 thread or 64, run after run. The lists stand while every particle
stays within ``DRIFT`` cells of its block (one check pass a substep); the engine has them made afresh
where a macro step or its backward begins, so what a step sums follows from its start state alone.
"""

import numpy as np
import taichi as ti

from cosim.engines import field_pool
from cosim.engines.arch import CPU_ARCHES, running_arch
from cosim.engines.data_oriented import data_oriented

BLOCK = 4  # grid cells per block and axis (at least 2 keeps same-coloured blocks' stencils apart)
CHUNKS = 64  # runs of particles counted apart: at most this many threads count and place at once
DRIFT = (BLOCK - 2) // 2  # [cells] how far a particle's stencil base may leave its listed block
# Taichi 1.7's CPU backend hands a parallel loop out in tasks of 512 to 1024 iterations (its adaptive
# block size, whatever ``loop_config`` says), so a loop over a few hundred blocks or 64 chunks ran on one
# thread. The loops over blocks and chunks therefore run over SPREAD times as many iterations, of which
# every SPREAD-th does one block's (chunk's) work: each task holds at most one. (A GPU: 1.)
SPREAD = 1024


@data_oriented
class ParticleBins:
    """Block lists of the particles (``bin_particles``), read by the coloured scatters of ``MPMKernels``, and
    the scatters' add (``add_at``)."""

    def _init_bins(self) -> None:
        """Fields of the block lists, for the engine's ``nodes`` and ``capacity`` (a ``MPMKernels`` base)."""
        d = self.dim
        self.bin_blocks = tuple(-(-n // BLOCK) for n in self.nodes)  # blocks per axis
        n_blocks = int(np.prod(self.bin_blocks))
        self.colours = 2**d
        self.spread = SPREAD if running_arch() in CPU_ARCHES else 1  # iterations per block or chunk
        per_colour = int(np.prod([-(-b // 2) for b in self.bin_blocks]))
        self.block_of = field_pool.scalar(self, ti.i32, shape=self.capacity)  # each particle's block
        self.bin_order = field_pool.scalar(self, ti.i32, shape=self.capacity)  # particles by block, index order
        # per chunk and block: the count, then the chunk's place within the block; zero between calls
        self.chunk_cursor = field_pool.scalar(self, ti.i32, shape=(CHUNKS, n_blocks))
        self.block_start = field_pool.scalar(self, ti.i32, shape=n_blocks)  # first entry in bin_order
        self.block_count = field_pool.scalar(self, ti.i32, shape=n_blocks)
        self.colour_blocks = field_pool.scalar(self, ti.i32, shape=(self.colours, per_colour))  # non-empty ones
        self.colour_count = field_pool.scalar(self, ti.i32, shape=self.colours)
        self.reach_lo = field_pool.vector(self, d, ti.i32, shape=())  # the stencils' base nodes: [lo, hi)
        self.reach_hi = field_pool.vector(self, d, ti.i32, shape=())
        self.bin_lo = field_pool.vector(self, d, ti.i32, shape=())  # the blocks reached: [bin_lo, bin_hi)
        self.bin_hi = field_pool.vector(self, d, ti.i32, shape=())
        self.bin_fill = field_pool.scalar(self, ti.i32, shape=())  # entries of bin_order placed so far
        self.bin_moved = field_pool.scalar(self, ti.i32, shape=())  # chunks with a particle out of its block
        self._binned = None  # the particle range the lists hold (None: none, make them afresh)

    @ti.func
    def add_at(self, fld: ti.template(), g, I, value, atomic: ti.template()):
        """fld[g, I] += value (fld[I] for a field without grid copies): an atomic add, or a plain load and
        store where no other thread writes the node (one thread, or a colour's blocks: ``mpm_bins``)."""
        if ti.static(len(fld.shape) == self.dim):
            if ti.static(atomic):
                fld[I] += value
            else:
                fld[I] = fld[I] + value
        elif ti.static(atomic):
            fld[g, I] += value
        else:
            fld[g, I] = fld[g, I] + value

    @ti.func
    def block_index(self, J):
        """Linear index of block J (row-major over ``bin_blocks``)."""
        index = 0
        for k in ti.static(range(self.dim)):
            index = index * self.bin_blocks[k] + J[k]
        return index

    @ti.func
    def colour_of(self, J):
        """Colour 0 .. 2^d - 1 of block J: the parities of its coordinates as bits."""
        colour = 0
        for k in ti.static(range(self.dim)):
            colour = colour * 2 + J[k] % 2
        return colour

    @ti.func
    def chunk_range(self, c, start, end):
        """Particles [lo, hi) of chunk c of the range [start, end)."""
        length = (end - start + CHUNKS - 1) // CHUNKS
        lo = ti.min(start + c * length, end)
        return lo, ti.min(lo + length, end)

    @ti.func
    def block_coords(self, blk):
        """Block coordinates J of linear block index blk (``block_index``'s inverse)."""
        J = ti.Vector.zero(ti.i32, self.dim)
        rest = blk
        for k in ti.static(range(self.dim - 1, -1, -1)):
            J[k] = rest % self.bin_blocks[k]
            rest //= self.bin_blocks[k]
        return J

    def bin_particles(self, src: int, start: int, end: int) -> None:
        """Block lists of the particles [start, end) in slot src, and the base nodes they reach
        (``reach_lo``, ``reach_hi``). The lists of the last call stand while they hold the same range and
        every particle's stencil base is still within ``DRIFT`` cells of its listed block: blocks of one
        colour are ``BLOCK`` cells apart, so stencils that far out still never share a node. The engine
        forgets the lists (``_binned = None``) where a macro step or its backward begins, so that what a
        step sums, and in which order, follows from its start state alone (a recompute repeats it)."""
        moved = self._bin_check(src, start, end, int(self._binned != (start, end)))
        if moved:
            self._bin_count(src, start, end)
            self._bin_place(start, end)
            self._binned = (start, end)

    @ti.kernel
    def _bin_check(self, src: ti.i32, start: ti.i32, end: ti.i32, fresh: ti.i32) -> ti.i32:
        """The base nodes the particles reach and the blocks those lie in (``bin_lo``, ``bin_hi``); returns
        how many particles have drifted more than ``DRIFT`` cells out of their listed block (``fresh``: the
        lists are not of this range, every particle counts as moved)."""
        d = ti.static(self.dim)
        self.reach_lo[None] = ti.Vector(self.nodes)
        self.reach_hi[None] = ti.Vector.zero(ti.i32, d)
        self.bin_moved[None] = 0
        for j in range(CHUNKS * self.spread):  # a chunk per task (``SPREAD``)
            if j % self.spread == 0:
                lo, hi = self.chunk_range(j // self.spread, start, end)
                reached_lo = ti.Vector(self.nodes)
                reached_hi = ti.Vector.zero(ti.i32, d)
                moved = 0
                for p in range(lo, hi):
                    base = self.stencil_base(self.x[src, p])
                    reached_lo = ti.min(reached_lo, base)
                    reached_hi = ti.max(reached_hi, base + 1)
                    corner = self.block_coords(self.block_of[p]) * BLOCK
                    for k in ti.static(range(d)):
                        if base[k] < corner[k] - DRIFT or base[k] >= corner[k] + BLOCK + DRIFT:
                            moved = 1
                if hi > lo:
                    ti.atomic_min(self.reach_lo[None], reached_lo)
                    ti.atomic_max(self.reach_hi[None], reached_hi)
                    self.bin_moved[None] += moved + fresh
        self.bin_lo[None] = self.reach_lo[None] // BLOCK
        self.bin_hi[None] = (self.reach_hi[None] - 1) // BLOCK + 1
        return self.bin_moved[None]

    @ti.kernel
    def _bin_count(self, src: ti.i32, start: ti.i32, end: ti.i32):
        """Count the particles of [start, end) in slot src per chunk and block."""
        for j in range(CHUNKS * self.spread):  # a chunk per task (``SPREAD``)
            if j % self.spread == 0:
                c = j // self.spread
                lo, hi = self.chunk_range(c, start, end)
                for p in range(lo, hi):
                    blk = self.block_index(self.stencil_base(self.x[src, p]) // BLOCK)
                    self.block_of[p] = blk
                    self.chunk_cursor[c, blk] = self.chunk_cursor[c, blk] + 1  # this chunk's own column

    @ti.kernel
    def _bin_place(self, start: ti.i32, end: ti.i32):
        """From the counts, list the blocks' particles: ``colour_blocks`` (the non-empty blocks of each
        colour, ``colour_count`` of them), each block's entries [``block_start``, ``block_start`` +
        ``block_count``) of ``bin_order`` (its particles in ascending index)."""
        d = ti.static(self.dim)
        for J in ti.grouped(ti.ndrange(*[(self.bin_lo[None][k], self.bin_hi[None][k]) for k in ti.static(range(d))])):
            blk = self.block_index(J)  # counts -> each chunk's first place within the block
            total = 0
            for c in range(CHUNKS):
                count = self.chunk_cursor[c, blk]
                if count > 0:  # (a chunk with none here keeps its zero: the last loop resets only its own)
                    self.chunk_cursor[c, blk] = total
                    total += count
            self.block_count[blk] = total
        for colour in range(self.colours):
            self.colour_count[colour] = 0
        ti.loop_config(serialize=True)  # the blocks' places in bin_order, in block order
        for J in ti.grouped(ti.ndrange(*[(self.bin_lo[None][k], self.bin_hi[None][k]) for k in ti.static(range(d))])):
            blk = self.block_index(J)
            self.block_start[blk] = self.bin_fill[None]
            self.bin_fill[None] += self.block_count[blk]
            if self.block_count[blk] > 0:
                colour = self.colour_of(J)
                self.colour_blocks[colour, self.colour_count[colour]] = blk
                self.colour_count[colour] += 1
        for j in range(CHUNKS * self.spread):  # place, in index order within each chunk: chunks in order
            if j % self.spread == 0:  # within a block
                c = j // self.spread
                lo, hi = self.chunk_range(c, start, end)
                for p in range(lo, hi):
                    blk = self.block_of[p]
                    place = self.chunk_cursor[c, blk]
                    self.bin_order[self.block_start[blk] + place] = p
                    self.chunk_cursor[c, blk] = place + 1
        for j in range(CHUNKS * self.spread):  # leave the cursors zero for the next call
            if j % self.spread == 0:
                c = j // self.spread
                lo, hi = self.chunk_range(c, start, end)
                for p in range(lo, hi):
                    self.chunk_cursor[c, self.block_of[p]] = 0
        self.bin_fill[None] = 0
