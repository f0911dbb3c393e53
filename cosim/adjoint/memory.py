"""What a gradient run will hold in memory, estimated before it starts (`cosim gradcheck`, `cosim optimize`).

Two parts: the tape on the host (the MPM checkpoints it keeps, every step's control impulse
field, the running loss terms' gradients) and the engines' Taichi fields with their adjoints
(one macro step of substeps: K + 1 particle slots, K grids). Not counted: the boundary states
each record keeps (per substep: a few floats per rigid body, a cloth's vertices) and Taichi's
own runtime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

MIB = 2**20


@dataclass
class MemoryEstimate:
    """Bytes a gradient rollout of ``steps`` macro steps holds at its peak."""

    steps: int
    checkpoint_every: int
    checkpoint_bytes: int  # a macro step's MPM states (one per exchange) in the engine's precision
    held_checkpoints: int  # the most the tape holds at once (forward end or backward segment)
    per_step_bytes: int  # what every record holds whatever k: the control impulse field
    running_bytes: int  # the running loss terms' gradients, one per state
    field_bytes: int  # the engines' Taichi fields, adjoints included

    @property
    def tape_bytes(self) -> int:
        return self.held_checkpoints * self.checkpoint_bytes + self.steps * self.per_step_bytes + self.running_bytes

    @property
    def total_bytes(self) -> int:
        return self.tape_bytes + self.field_bytes

    def describe(self) -> str:
        k = self.checkpoint_every
        kept = "one per step" if k == 1 else f"every {k}th of {self.steps} kept, one segment recomputed"
        return (
            f"memory estimate: {self.total_bytes / MIB:.0f} MiB = tape {self.tape_bytes / MIB:.1f} MiB on the host "
            f"(at most {self.held_checkpoints} MPM checkpoints of {self.checkpoint_bytes / MIB:.2f} MiB: {kept}) "
            f"+ engine fields {self.field_bytes / MIB:.0f} MiB, plus the interpreter and Taichi's runtime"
        )


def held_checkpoints(steps: int, every: int) -> int:
    """The most MPM states the tape holds at once: one per k-th step, plus the last step's after the
    forward pass, or the k - 1 states of the segment the backward pass recomputes."""
    kept = math.ceil(steps / every)
    return min(steps, kept + max(every - 1, 1 if (steps - 1) % every else 0))


def estimate_memory(system, steps: int, checkpoint_every: int = 1, running_loss: bool = False) -> MemoryEstimate:
    """The estimate for ``system`` (built with gradients) over ``steps`` macro steps."""
    mpm = system.mpm
    n, d = mpm.n_particles, mpm.dim
    itemsize = np.dtype(mpm.real).itemsize
    per_exchange = n * (2 * d + 2 * d * d) * itemsize  # x, v, C, F
    state = per_exchange * system.exchanges  # a macro step's checkpoints: one before each of its exchanges
    impulse = n * d * 8 * system.exchanges if mpm.control is not None else 0  # the (N, d) field per exchange, float64
    running = (steps + 1) * n * 2 * d * 8 if running_loss else 0  # dL/dx and dL/dv per state, at most
    objects = [mpm, *mpm.grid_hooks, *mpm.particle_hooks, *mpm.boundaries.values(), *system.engines.values()]
    return MemoryEstimate(
        steps,
        checkpoint_every,
        state,
        held_checkpoints(steps, checkpoint_every),
        impulse,
        running,
        taichi_field_bytes(objects),
    )


def taichi_field_bytes(objects: list) -> int:
    """Bytes of the Taichi fields reachable from the objects through cosim objects' attributes, lists
    and dicts (each field counted once), with their adjoints."""
    import taichi as ti
    from taichi.lang.util import to_numpy_type

    seen: set[int] = set()
    total = 0
    pending = list(objects)
    while pending:
        value = pending.pop()
        if id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, ti.Field):
            entries = getattr(value, "n", 1) * getattr(value, "m", 1)
            size = math.prod(value.shape) * entries * np.dtype(to_numpy_type(value.dtype)).itemsize
            total += size * (2 if getattr(value, "grad", None) is not None else 1)
        elif isinstance(value, (list, tuple)):
            pending.extend(value)
        elif isinstance(value, dict):
            pending.extend(value.values())
        elif type(value).__module__.startswith("cosim") and hasattr(value, "__dict__"):
            pending.extend(vars(value).values())
    return total
