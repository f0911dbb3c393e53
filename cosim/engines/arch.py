"""What depends on the processor Taichi runs on, chosen in one place.

A scatter (P2G, the G2P adjoint) on a CPU runs fastest on one thread with plain adds: several
threads contend on atomic adds to the same grid nodes. On a GPU one thread would use one of
thousands of cores, so there the scatter is parallel with atomic adds. Taichi's own start-up
options by arch (threads, cache) are in ``cosim.runtime.init_options``.
"""

from __future__ import annotations

from dataclasses import dataclass

CPU_ARCHES = ("cpu", "x64", "arm64")  # the scene's name and Taichi's names of CPU backends


@dataclass(frozen=True)
class ArchChoices:
    """The settings an engine takes from the arch."""

    serial_scatter: bool  # one thread, non-atomic adds (CPU) instead of parallel atomic adds (GPU)


def choices_for(arch: str) -> ArchChoices:
    """The choices for ``arch``: 'cpu' (or Taichi's 'x64', 'arm64'), 'cuda', 'gpu', 'vulkan', ..."""
    return ArchChoices(serial_scatter=arch in CPU_ARCHES)


def running_arch() -> str:
    """The name of the arch Taichi runs on now (Taichi's name: 'x64', 'cuda', ...)."""
    from taichi.lang import impl

    return impl.current_cfg().arch.name


def current_choices() -> ArchChoices:
    """The choices for the arch Taichi runs on now."""
    return choices_for(running_arch())
