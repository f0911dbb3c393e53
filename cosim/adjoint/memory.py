"""What a gradient run will hold in memory, estimated before it starts (`cosim gradcheck`, `cosim optimize`).

Two parts: the tape (the MPM checkpoints it keeps, every step's control impulse field, the
running loss terms' gradients) and the engines' Taichi fields with their adjoints (one macro step
of substeps: K + 1 particle slots, K grids). The checkpoints stay on the engine's device as far as
its budget goes (``cosim.engines.mpm_checkpoints``), the rest of the tape is on the host; the
estimate says how many fit. Not counted: the boundary states each record keeps (per substep: a
few floats per rigid body, a cloth's vertices), the one or two state adjoints in flight, and
Taichi's own runtime.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from cosim.engines.arch import CPU_ARCHES, running_arch
from cosim.engines.device_memory import taichi_field_bytes

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
    device_budget: int | None = None  # [bytes] checkpoints the device may hold (None: no bound)
    arch: str = "x64"  # Taichi's arch the engines run on

    @property
    def on_device(self) -> int:
        """How many of the held checkpoints the device keeps (the first ones made; the rest on the host)."""
        if self.device_budget is None:
            return self.held_checkpoints
        return min(self.held_checkpoints, self.device_budget // max(self.checkpoint_bytes, 1))

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
            f"memory estimate: {self.total_bytes / MIB:.0f} MiB = tape {self.tape_bytes / MIB:.1f} MiB "
            f"(at most {self.held_checkpoints} MPM checkpoints of {self.checkpoint_bytes / MIB:.2f} MiB: {kept}; "
            f"{self._where()}) + engine fields {self.field_bytes / MIB:.0f} MiB, plus the interpreter and "
            "Taichi's runtime"
        )

    def _where(self) -> str:
        """Where the checkpoints are, in words."""
        if self.device_budget is None:
            return "in Taichi arrays, the host's memory on a CPU" if self.arch in CPU_ARCHES else f"on the {self.arch}"
        budget = f"{self.device_budget / MIB:.0f} MiB"
        if self.on_device == self.held_checkpoints:
            return f"on the {self.arch}, within its checkpoint budget of {budget}"
        if self.on_device == 0:
            return f"on the host: the {self.arch}'s checkpoint budget of {budget} holds none"
        return f"{self.on_device} on the {self.arch} (its checkpoint budget of {budget}), the rest on the host"


def held_checkpoints(steps: int, every: int) -> int:
    """The most MPM states the tape holds at once: one per k-th step, plus the last step's after the
    forward pass, or the k - 1 states of the segment the backward pass recomputes."""
    kept = math.ceil(steps / every)
    return min(steps, kept + max(every - 1, 1 if (steps - 1) % every else 0))


def estimate_memory(system, steps: int, checkpoint_every: int = 1, running_loss: bool = False) -> MemoryEstimate:
    """The estimate for ``system`` (built with gradients) over ``steps`` macro steps."""
    mpm = system.mpm
    n, d = mpm.n_particles, mpm.dim
    state = (
        mpm.checkpoints.state_bytes * system.exchanges
    )  # a macro step's checkpoints: one before each of its exchanges
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
        mpm.checkpoints.budget(),
        running_arch(),
    )
