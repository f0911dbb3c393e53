"""What depends on the processor Taichi runs on, chosen in one place.

A scatter (P2G, the G2P adjoint) on a CPU runs fastest on one thread with plain adds: several
threads contend on atomic adds to the same grid nodes. On a GPU one thread would use one of
thousands of cores, so there the scatter is parallel with atomic adds.

A parallel loop on a CPU costs a dispatch to Taichi's thread pool and back, tens of microseconds
per loop; a loop with less work than that runs faster on the launching thread. So
on a CPU, loops over fewer than ``PARALLEL_MIN_PARTICLES`` particles or ``PARALLEL_MIN_NODES``
grid nodes are serial (a small scene such as pull_door's 78 particles paid the dispatch in every
one of its ~29 loops a step), and so are a small engine's grid loops, which cover only its
particles' box (``MPMKernels``). On a GPU every loop is parallel. Taichi's own start-up options by
arch (threads, cache) are in ``cosim.runtime.init_options``.
"""

from __future__ import annotations

from dataclasses import dataclass

CPU_ARCHES = ("cpu", "x64", "arm64")  # the scene's name and Taichi's names of CPU backends
PARALLEL_MIN_PARTICLES = 2048  # CPU: shorter particle loops run on one thread
PARALLEL_MIN_NODES = 32768  # CPU: grid loops over fewer nodes run on one thread


@dataclass(frozen=True)
class ArchChoices:
    """The settings an engine takes from the arch."""

    serial_scatter: bool  # one thread, non-atomic adds (CPU) instead of parallel atomic adds (GPU)
    parallel_min_particles: int = 0  # particle loops over fewer particles run on one thread
    parallel_min_nodes: int = 0  # grid loops over fewer nodes run on one thread
    # grid passes over the box of nodes the particles reach, which the scatter bounds with a min / max
    # per particle (plain on one CPU thread); a GPU passes over the whole grid in a few microseconds,
    # where every thread's atomic min / max on the same two entries would contend
    bounded_grid_passes: bool = False

    def serial_particles(self, n: int) -> bool:
        """Whether loops over ``n`` particles should run on one thread."""
        return n < self.parallel_min_particles

    def serial_nodes(self, n: int) -> bool:
        """Whether loops over a grid of ``n`` nodes should run on one thread."""
        return n < self.parallel_min_nodes


def choices_for(arch: str) -> ArchChoices:
    """The choices for ``arch``: 'cpu' (or Taichi's 'x64', 'arm64'), 'cuda', 'gpu', 'vulkan', ..."""
    if arch in CPU_ARCHES:
        return ArchChoices(True, PARALLEL_MIN_PARTICLES, PARALLEL_MIN_NODES, bounded_grid_passes=True)
    return ArchChoices(False)


def running_arch() -> str:
    """The name of the arch Taichi runs on now (Taichi's name: 'x64', 'cuda', ...)."""
    from taichi.lang import impl

    return impl.current_cfg().arch.name


def current_choices() -> ArchChoices:
    """The choices for the arch Taichi runs on now."""
    return choices_for(running_arch())
