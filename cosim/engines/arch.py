"""What depends on the processor Taichi runs on, chosen in one place.

A scatter (P2G, the G2P adjoint) adds each particle's share to the grid nodes around it (``SCATTERS``).
On a CPU with few threads it runs fastest on one thread with plain adds: several threads contend on
atomic adds to the same nodes. With more threads the coloured scatter (``cosim.engines.mpm_bins``)
spreads it over them, its sums still in an order the particles alone fix. On a GPU one thread would use
one of thousands of cores, so there the scatter is parallel with atomic adds.

A parallel loop on a CPU costs a dispatch to Taichi's thread pool and back, tens of microseconds
per loop; a loop with less work than that runs faster on the launching thread. So
on a CPU, loops over fewer than ``PARALLEL_MIN_PARTICLES`` particles or ``PARALLEL_MIN_NODES``
grid nodes are serial (a small scene such as pull_door's 78 particles paid the dispatch in every
one of its ~29 loops a step), and so are a small engine's grid loops, which cover only its
particles' box (``MPMKernels``). On a GPU every loop is parallel, and the substep's loops have bounds known
when they compile (``constant_loop_bounds``). Taichi's own start-up options by
arch (threads, cache) are in ``cosim.runtime.init_options``.
"""

from __future__ import annotations

from dataclasses import dataclass

CPU_ARCHES = ("cpu", "x64", "arm64")
# how the scatters (P2G, the G2P adjoint) add to the grid: one thread with plain adds; blocks of one colour
# in parallel with plain adds (``cosim.engines.mpm_bins``); every particle in parallel with atomic adds.
# The first two sum in an order fixed by the particles alone (bit-reproducible on any thread count), the
# atomic one in the threads' order (reproducible to round-off).
SCATTERS = ("serial", "coloured", "atomic")  # the scene's name and Taichi's names of CPU backends
COLOURED_MIN_THREADS = 4  # CPU: from this many threads the coloured scatter, below it the serial one
PARALLEL_MIN_PARTICLES = 2048  # CPU: shorter particle loops run on one thread
PARALLEL_MIN_NODES = 32768  # CPU: grid loops over fewer nodes run on one thread


@dataclass(frozen=True)
class ArchChoices:
    """The settings an engine takes from the arch."""

    scatter: str  # of ``SCATTERS``
    parallel_min_particles: int = 0  # particle loops over fewer particles run on one thread
    parallel_min_nodes: int = 0  # grid loops over fewer nodes run on one thread
    # grid passes over the box of nodes the particles reach, which the scatter bounds with a min / max
    # per particle (plain on one CPU thread); a GPU passes over the whole grid in a few microseconds,
    # where every thread's atomic min / max on the same two entries would contend
    bounded_grid_passes: bool = False
    # loops whose bounds Taichi would read from a field or an argument run over the whole grid or every particle
    # slot instead, with constant bounds (the threads of other bodies idle): a GPU runs each of a kernel's tasks
    # as a launch of its own, and a loop's bounds not known when it compiles cost a serial task before it
    constant_loop_bounds: bool = False

    def serial_particles(self, n: int) -> bool:
        """Whether loops over ``n`` particles should run on one thread."""
        return n < self.parallel_min_particles

    def serial_nodes(self, n: int) -> bool:
        """Whether loops over a grid of ``n`` nodes should run on one thread."""
        return n < self.parallel_min_nodes


def choices_for(arch: str, threads: int = 1) -> ArchChoices:
    """The choices for ``arch`` ('cpu' or Taichi's 'x64', 'arm64'; 'cuda', 'gpu', 'vulkan', ...), on a CPU
    with Taichi's ``threads``: the coloured scatter costs one thread more than the serial one (its
    binning, its colours' passes) and gains with every thread, so it is the default from
    ``COLOURED_MIN_THREADS`` on (``cosim bench mpm --threads ... --scatter serial,coloured``)."""
    if arch in CPU_ARCHES:
        scatter = "coloured" if threads >= COLOURED_MIN_THREADS else "serial"
        return ArchChoices(scatter, PARALLEL_MIN_PARTICLES, PARALLEL_MIN_NODES, bounded_grid_passes=True)
    return ArchChoices("atomic", constant_loop_bounds=True)


def running_arch() -> str:
    """The name of the arch Taichi runs on now (Taichi's name: 'x64', 'cuda', ...)."""
    from taichi.lang import impl

    return impl.current_cfg().arch.name


def running_threads() -> int:
    """The CPU threads Taichi runs its parallel loops on now."""
    from taichi.lang import impl

    return int(impl.current_cfg().cpu_max_num_threads)


def gpu_choices_asked() -> bool:
    """Whether ``COSIM_ARCH_CHOICES=gpu`` asks for a GPU's choices on any arch (the kernels a GPU runs, on the
    CPU: to check them, and count their tasks, without a GPU); an ``InputError`` for another value."""
    import os

    from cosim.errors import InputError

    asked = os.environ.get("COSIM_ARCH_CHOICES", "")
    if asked not in ("", "gpu"):
        raise InputError(f"COSIM_ARCH_CHOICES={asked!r}: set it to gpu (a GPU's loop choices on any arch) or unset it")
    return asked == "gpu"


def current_choices() -> ArchChoices:
    """The choices for the arch Taichi runs on now, or a GPU's (``gpu_choices_asked``)."""
    return choices_for("cuda" if gpu_choices_asked() else running_arch(), running_threads())
