"""Elastic moduli in plain Python (no Taichi): what the scene checks and the substep bound need.

Lame parameters and the P-wave speed from Young's modulus E [Pa], Poisson's ratio nu and
density [kg/m^3], and the explicit viscous time-step bound; ``cosim.engines.materials``
re-exports them beside the Taichi constitutive laws.
"""

from __future__ import annotations

import math


def lame_parameters(E: float, nu: float, dim: int) -> tuple[float, float]:
    """Lame parameters (mu, lambda) [Pa] from Young's modulus E [Pa] and Poisson's ratio."""
    mu = E / (2.0 * (1.0 + nu))
    lam = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


def wave_speed(E: float, nu: float, density: float, dim: int) -> float:
    """P-wave speed sqrt((lam + 2 mu) / rho) [m/s], the explicit time-step bound's speed."""
    mu, lam = lame_parameters(E, nu, dim)
    return ((lam + 2.0 * mu) / density) ** 0.5


def viscous_time_step(density: float, viscosity: float, dx: float, dim: int) -> float:
    """[s] The explicit diffusion bound rho dx^2 / (2 d eta) of a viscosity eta [Pa s] on a grid of
    spacing dx [m] (infinite without viscosity). Measured: water of 30 Pa s at dx = 1/256 m went
    non-finite in its first step at dt = 2.1e-4 s, above this bound's 1.3e-4 s."""
    return math.inf if viscosity <= 0 else density * dx**2 / (2.0 * dim * viscosity)
