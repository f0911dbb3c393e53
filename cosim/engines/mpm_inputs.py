"""What an MPM engine is built from: its soft bodies (``ParticleBody``), grid and walls (``MPMConfig``),
and the keys of the particle state it exchanges (``STATE_KEYS``)."""

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class ParticleBody:
    """One soft body: its particles and material. Arrays are (n, dim)."""

    name: str
    material: str  # 'elastic' | 'plastic' | 'liquid'
    E: float  # Young's modulus [Pa]
    nu: float  # Poisson's ratio [-]
    density: float  # [kg/m^3]
    particle_volume: float  # [m^d] volume each particle stands for
    positions: np.ndarray
    velocities: np.ndarray
    yield_stress: float = math.inf  # [Pa], plastic only
    viscosity: float = 0.0  # [Pa s], liquid only
    deformation: np.ndarray | None = None  # (n, d, d) initial F, default identity

    @property
    def n(self) -> int:
        return len(self.positions)

    @property
    def particle_mass(self) -> float:
        return self.density * self.particle_volume


@dataclass
class MPMConfig:
    """Grid, walls and gravity. ``cells`` per axis; dx [m]; gravity [m/s^2]."""

    dim: int
    cells: tuple[int, ...]
    dx: float
    gravity: tuple[float, ...]
    wall: str = "slip"  # 'slip' | 'sticky' | 'none'
    wall_cells: int = 3
    requires_grad: bool = False
    grad_substeps: int = 1  # gradient mode: substeps per macro step (slots = this + 1)
    has_controls: bool = False
    scatter: str | None = None  # "serial" | "coloured" | "atomic" (``cosim.engines.arch``); None: by the arch
    checkpoints: str = "auto"  # gradients: "auto" | "device" | "host" (``cosim.engines.mpm_checkpoints``)


STATE_KEYS = ("x", "v", "C", "F")

MIN_CAPACITY = 256  # the smallest particle capacity
CAPACITY_BUCKETS = 4  # capacities per doubling of the particle count


def particle_capacity(n: int) -> int:
    """How many particles an engine's particle fields hold for ``n`` particles: ``n`` rounded up to
    ``MIN_CAPACITY`` or to one of ``CAPACITY_BUCKETS`` sizes per doubling (2^k times 1, 1.25, 1.5,
    1.75), at most 25% spare. Taichi's kernel cache keys include field shapes, so scenes whose
    particle counts share a bucket (and that match otherwise) reuse each other's compiled kernels;
    kernels loop over the count (``MPMKernels.count``), or (a GPU's substep, ``arch.constant_loop_bounds``) over
    the capacity with the count checked inside, never past the count's particles."""
    if n <= MIN_CAPACITY:
        return MIN_CAPACITY
    step = (1 << ((n - 1).bit_length() - 1)) // CAPACITY_BUCKETS
    return -(-n // step) * step
