"""The cloth's element derivatives (``cosim.engines.cloth_energy``): the closed-form gradients agree with
central differences of the energies and with JAX's reverse mode, the Hessians (forward mode over those
gradients) with JAX's Hessians of the energies, on random elements from stretched to crumpled."""

import jax
import numpy as np

from cosim.engines import cloth_energy as ce


def _batched(fn):
    """fn over a batch of elements, compiled (eager vmap dispatches op by op: 5x slower here on a cold cache)."""
    return jax.jit(jax.vmap(fn))


def _faces(n: int = 64, seed: int = 0):
    """Random rest triangles and deformed positions: stretched, compressed to 5 %, sheared, and flipped."""
    rng = np.random.default_rng(seed)
    rest = rng.standard_normal((n, 3, 2))
    Dm = np.stack([rest[:, 1] - rest[:, 0], rest[:, 2] - rest[:, 0]], axis=2)
    scale = rng.choice([0.05, 0.7, 1.0, 1.6], size=n)[:, None, None]
    x = rng.standard_normal((n, 3, 3)) * scale
    return x, np.linalg.inv(Dm), 0.5 * np.abs(np.linalg.det(Dm))


def _hinges(n: int = 64, seed: int = 1):
    """Random hinges at every dihedral angle (|theta| < pi), rest angles anywhere in (-1, 1) rad."""
    rng = np.random.default_rng(seed)
    return rng.standard_normal((n, 4, 3)), 0.5 + rng.random(n), rng.uniform(-1.0, 1.0, n)


def _central(energy, x: np.ndarray, *args, eps: float = 1e-6) -> np.ndarray:
    """Central differences of ``energy`` (jitted) at one element's positions x (k, 3)."""
    out = np.zeros(x.size)
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = eps
        plus, minus = (float(energy((x.ravel() + s * d).reshape(x.shape), *args)) for s in (1, -1))
        out[i] = (plus - minus) / (2 * eps)
    return out.reshape(x.shape)


def test_membrane_gradient_and_hessian_match_differences_and_autodiff():
    x, Dm_inv, area = _faces()
    g = np.asarray(_batched(ce.membrane_gradient)(x, Dm_inv, area))
    assert (
        np.abs(g - np.asarray(_batched(jax.grad(ce.membrane_energy))(x, Dm_inv, area))).max() <= 1e-12 * np.abs(g).max()
    )
    for k in range(8):  # central differences: no autodiff involved
        fd = _central(jax.jit(ce.membrane_energy), x[k], Dm_inv[k], area[k])
        assert np.abs(g[k] - fd).max() <= 1e-6 * max(np.abs(fd).max(), 1e-3), k
    H = np.asarray(_batched(jax.jacfwd(ce.membrane_gradient))(x, Dm_inv, area)).reshape(-1, 9, 9)
    H_ref = np.asarray(_batched(jax.hessian(ce.membrane_energy))(x, Dm_inv, area)).reshape(-1, 9, 9)
    assert np.abs(H - H_ref).max() <= 1e-10 * np.abs(H_ref).max()


def test_bending_gradient_and_hessian_match_differences_and_autodiff():
    x, weight, theta0 = _hinges()
    g = np.asarray(_batched(ce.bending_gradient)(x, weight, theta0))
    g_ref = np.asarray(_batched(jax.grad(ce.bending_energy))(x, weight, theta0))
    assert np.abs(g - g_ref).max() <= 1e-12 * np.abs(g_ref).max()
    for k in range(8):
        fd = _central(jax.jit(ce.bending_energy), x[k], weight[k], theta0[k])
        assert np.abs(g[k] - fd).max() <= 1e-6 * max(np.abs(fd).max(), 1e-3), k
    H = np.asarray(_batched(ce.bending_hessian)(x, weight, theta0)).reshape(-1, 12, 12)
    H_ref = np.asarray(_batched(jax.hessian(ce.bending_energy))(x, weight, theta0)).reshape(-1, 12, 12)
    assert np.abs(H - H_ref).max() <= 1e-10 * np.abs(H_ref).max()
    translated = np.asarray(_batched(ce.hinge_angle_gradient)(x)).sum(axis=1)  # theta ignores translations
    assert np.abs(translated).max() <= 1e-12 * np.abs(np.asarray(_batched(ce.hinge_angle_gradient)(x))).max()
