"""Error measures of the accuracy benchmark: closed forms and what is read off a run (NumPy only).

Every function here is a plain computation on arrays, so the tests check each one against a
case whose answer is known (a synthetic signal, an exact floating box) without Taichi.
Lengths in [m], times in [s], densities in [kg/m^3], moduli in [Pa].
"""

from __future__ import annotations

import math

import numpy as np


# ---------------------------------------------------------------- closed forms
def bar_angular_frequency(length: float, width: float, E: float, nu: float, density: float) -> float:
    """[rad/s] Fundamental longitudinal mode of a free-free 2D strip in plane strain.

    The 2D MPM's stress, 2 mu eps + lam tr(eps) I with the 3D Lame parameters, is plane strain; a
    strip free on its long sides then has the uniaxial modulus E' = E / (1 - nu^2), bar speed
    c = sqrt(E' / rho) and, free at both ends, k = pi / L. Lateral inertia (Rayleigh 1877, Love 1927:
    rho u_tt - rho nu_e^2 r^2 u_xxtt = E' u_xx, radius of gyration r^2 = width^2 / 12, in-plane
    contraction ratio nu_e = nu / (1 - nu)) lowers it to omega = c k / sqrt(1 + nu_e^2 r^2 k^2).
    """
    c = math.sqrt(E / (1.0 - nu**2) / density)
    k = math.pi / length
    nu_e = nu / (1.0 - nu)
    return c * k / math.sqrt(1.0 + nu_e**2 * width**2 / 12.0 * k**2)


def bar_modal_gradient(v0: float, omega: float, t: float) -> float:
    """[m] d q(t) / d ln E of the bar's modal displacement q(t) = (v0 / omega) sin(omega t).

    omega grows as sqrt(E) (``bar_angular_frequency``), so d omega / d ln E = omega / 2 and
    dq/dlnE = (v0 / 2) (t cos(omega t) - sin(omega t) / omega); v0 [m/s] is the mode's initial velocity.
    """
    return 0.5 * v0 * (t * math.cos(omega * t) - math.sin(omega * t) / omega)


def resting_com_height(surface: float, height: float, E: float, nu: float, density: float, g: float) -> float:
    """[m] Centre-of-mass height of a 2D elastic block of ``height`` resting under its own weight on
    a frictionless ``surface`` (plane strain, free sides): the strain at depth z is rho g z / E' with
    E' = E / (1 - nu^2), which lowers the centre of mass by rho g H^2 / (3 E') from H / 2."""
    return surface + 0.5 * height - density * g * height**2 / (3.0 * E / (1.0 - nu**2))


# ---------------------------------------------------------------- read off a run
def zero_crossings(t: np.ndarray, s: np.ndarray) -> np.ndarray:
    """[s] Times where the sampled signal ``s(t)`` changes sign, linearly interpolated; a sample
    exactly at zero counts once (the start of a signal that begins at zero is not a crossing)."""
    t, s = np.asarray(t, dtype=np.float64), np.asarray(s, dtype=np.float64)
    nz = np.flatnonzero(s != 0.0)
    t, s = t[nz], s[nz]
    i = np.flatnonzero(np.sign(s[:-1]) != np.sign(s[1:]))
    return t[i] - s[i] * (t[i + 1] - t[i]) / (s[i + 1] - s[i])


def oscillation_period(t: np.ndarray, s: np.ndarray) -> float:
    """[s] Period of an oscillation about zero: twice the least-squares spacing of its zero crossings
    (at least two needed). A sum of odd harmonics of one period crosses zero exactly every half period."""
    crossings = zero_crossings(t, s)
    if len(crossings) < 2:
        return math.nan
    slope = np.polyfit(np.arange(len(crossings)), crossings, 1)[0]
    return 2.0 * float(slope)


def modal_coordinate(x: np.ndarray, x_rest: np.ndarray, mass: np.ndarray, x0: float, length: float) -> float:
    """[m] Displacement along x projected on the free-free mode phi = cos(pi (X - x0) / L):
    sum m u phi / sum m phi^2, with rest positions X (``x_rest``, (N, d)) and positions ``x``."""
    phi = np.cos(np.pi * (x_rest[:, 0] - x0) / length)
    return float(np.sum(mass * (x[:, 0] - x_rest[:, 0]) * phi) / np.sum(mass * phi**2))


def front_position(x: np.ndarray, spacing: float) -> float:
    """[m] The liquid's leading edge along +x: the farthest particle plus half a lattice spacing
    (each particle stands for a square of side ``spacing``)."""
    return float(x[:, 0].max() + 0.5 * spacing)


def surface_level(x: np.ndarray, spacing: float, exclude_center: float, exclude_half_width: float) -> float:
    """[m] Free-surface height of a liquid: the median over particle columns (width ``spacing``) of
    the highest particle plus half a spacing, leaving out columns within ``exclude_half_width`` of
    ``exclude_center`` in x (where a floating body sits)."""
    far = x[np.abs(x[:, 0] - exclude_center) > exclude_half_width]
    columns = np.floor(far[:, 0] / spacing).astype(np.int64)
    order = np.lexsort((far[:, 1], columns))
    cols, ys = columns[order], far[order, 1]
    last = np.r_[np.flatnonzero(cols[1:] != cols[:-1]), len(cols) - 1]
    return float(np.median(ys[last]) + 0.5 * spacing)


def submerged_fraction(surface: float, body_center_y: float, body_height: float) -> float:
    """Share of an upright floating box's height below the free ``surface`` [m]."""
    return (surface - (body_center_y - 0.5 * body_height)) / body_height


def effective_height(y: np.ndarray, spacing: float) -> float:
    """[m] The height of the uniform slab with the same vertical spread: sqrt(12 Var(y) + spacing^2),
    exact for a lattice block of any number of layers (its Var is spacing^2 (n^2 - 1) / 12)."""
    return float(math.sqrt(12.0 * np.var(y) + spacing**2))


def hann_mean(values) -> np.ndarray | float:
    """Mean over the first axis of a sampled signal, weighted by a Hann window: an oscillation left
    in the window biases it far less than a plain mean does (the window's leakage falls as 1/f^3)."""
    values = np.asarray(values, dtype=np.float64)
    w = np.hanning(len(values) + 2)[1:-1]
    mean = np.tensordot(w, values, axes=(0, 0)) / np.sum(w)
    return float(mean) if np.ndim(mean) == 0 else mean


# ---------------------------------------------------------------- comparing
def relative_error(value: float, reference: float) -> float:
    """|value - reference| / |reference|."""
    return abs(value - reference) / abs(reference)


def rms_difference(a: np.ndarray, b: np.ndarray) -> float:
    """Root mean square of a - b over common samples (the shorter length)."""
    n = min(len(a), len(b))
    return float(np.sqrt(np.mean((np.asarray(a[:n]) - np.asarray(b[:n])) ** 2)))


def convergence_order(spacings: list[float], errors: list[float]) -> float:
    """Observed order p of error ~ dx^p: the least-squares slope of log(error) against log(dx)
    (nan with fewer than two positive errors)."""
    pairs = [(h, e) for h, e in zip(spacings, errors) if e > 0 and math.isfinite(e)]
    if len(pairs) < 2:
        return math.nan
    h, e = np.log([p[0] for p in pairs]), np.log([p[1] for p in pairs])
    return float(np.polyfit(h, e, 1)[0])
