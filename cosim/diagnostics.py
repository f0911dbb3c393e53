"""Energies of an MPM state from its host arrays [J]: for states read back or saved, and the reference
the device sums (``cosim.engines.mpm_energy``, what runs read) are tested against."""

from __future__ import annotations

import numpy as np


def kinetic_energy(mass: np.ndarray, v: np.ndarray) -> float:
    """sum 1/2 m |v|^2 (particle velocities; APIC's affine part is not counted)."""
    return float(0.5 * np.sum(mass * np.sum(v * v, axis=1)))


def gravity_potential(mass: np.ndarray, x: np.ndarray, gravity) -> float:
    """-sum m g . x, zero at the domain origin."""
    return float(-np.sum(mass * (x @ np.asarray(gravity))))


def singular_values(F: np.ndarray) -> np.ndarray:
    """(n, d) singular values of (n, d, d) matrices, as ``np.linalg.svd`` gives them (>= 0) to round-off:
    in 2D in closed form, (p +- q) / 2 with p = |(a + d, c - b)|, q = |(a - d, c + b)| (p^2 - q^2 = 4 det F);
    in 3D the square roots of the eigenvalues of F^T F. Faster than the SVD, and exact enough for energies."""
    if F.shape[-1] == 2:
        a, b, c, d = F[:, 0, 0], F[:, 0, 1], F[:, 1, 0], F[:, 1, 1]
        p, q = np.hypot(a + d, c - b), np.hypot(a - d, c + b)
        return np.stack([0.5 * (p + q), 0.5 * np.abs(p - q)], axis=1)
    return np.sqrt(np.maximum(np.linalg.eigvalsh(np.matmul(F.transpose(0, 2, 1), F)), 0.0))


def corotated_energy(F: np.ndarray, volume: float, mu: float, lam: float) -> float:
    """Fixed corotated strain energy sum V0 (mu |F - R|^2 + lam/2 (J - 1)^2), R = U V^T of F's SVD, so
    |F - R|^2 = sum_i (sigma_i - 1)^2 over F's singular values."""
    J = np.linalg.det(F)
    psi = mu * np.sum((singular_values(F) - 1.0) ** 2, axis=1) + 0.5 * lam * (J - 1.0) ** 2
    return float(volume * psi.sum())


def liquid_energy(F: np.ndarray, volume: float, bulk: float) -> float:
    """Volumetric energy sum V0 K/2 (J - 1)^2 of a weakly compressible liquid."""
    J = np.linalg.det(F)
    return float(volume * 0.5 * bulk * np.sum((J - 1.0) ** 2))


def body_energies(engine, state: dict[str, np.ndarray], gravity) -> dict[str, dict[str, float]]:
    """Per body {name: {kinetic, gravity, strain, total}} of the MPM state [J]."""
    out = {}
    for b, (body, (lo, hi)) in enumerate(zip(engine.bodies, engine.ranges)):
        mu, lam = engine.lame(b)  # the current E and nu, after any set_parameters
        F, mass = state["F"][lo:hi], engine.mass[lo:hi]
        if body.material == "liquid":
            strain = liquid_energy(F, body.particle_volume, lam + 2.0 * mu / engine.dim)
        else:
            strain = corotated_energy(F, body.particle_volume, mu, lam)
        kin = kinetic_energy(mass, state["v"][lo:hi])
        pot = gravity_potential(mass, state["x"][lo:hi], gravity)
        out[body.name] = {"kinetic": kin, "gravity": pot, "strain": strain, "total": kin + pot + strain}
    return out


def summed(per_body: dict[str, dict[str, float]]) -> dict[str, float]:
    """Kinetic, gravitational, strain and total energy [J] over all bodies, from per-body energies
    (``body_energies`` or ``MPMEngine.energies``)."""
    return {k: sum(e[k] for e in per_body.values()) for k in ("kinetic", "gravity", "strain", "total")}


def energies(engine, state: dict[str, np.ndarray], gravity) -> dict[str, float]:
    """Kinetic, gravitational and strain energy of the whole MPM state [J]."""
    return summed(body_energies(engine, state, gravity))
