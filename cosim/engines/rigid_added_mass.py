"""DART's step with an added mass: the material a coupling says follows a body enters its inertia.

A coupling (``cosim.couplers.mpm_rigid``) hands the rigid engine, per body b, a 6x6 inertia A_b
[kg, kg m, kg m^2] acting on the body's world twist [omega; v] about its origin: the material that
moves with the body over the frame. In generalised coordinates it adds
A_hat = sum_b J_b^T A_b J_b (J_b the body's world Jacobian at the step's start) to the mass matrix,
so the step's velocity change solves, on the dofs forces drive (F; K: the velocity-commanded dofs,
whose change is prescribed),

    (M + dt D + A_hat)_FF dqd_F = dt f_F - (M + A_hat)_FK dqd_K

(D the joint damping, f every force DART applies), where DART's own step solves it with A_hat = 0.
The engine gets there in two DART steps from the same state: the first gives DART's dqd, from which
dqd' follows by one solve: (M + dt D + A_hat)_FF dqd'_F = (M + dt D)_FF dqd_F - A_hat_FK dqd_K;
the second applies the extra wrench -A_b J_b dqd' / dt to each body, whose generalised force
-A_hat dqd' / dt makes DART's step land on dqd' (exactly when no contact or limit acts; otherwise
DART resolves its constraints under the extra wrench). Why a mass and not a force: see the coupler.
"""

from __future__ import annotations

import numpy as np

from cosim.errors import InputError


def check_added_mass(added, bodies: int) -> np.ndarray | None:
    """``added`` as a (bodies, 6, 6) float array, or None where it is absent or zero; clear errors otherwise."""
    if added is None:
        return None
    added = np.asarray(added, dtype=np.float64)
    if added.shape != (bodies, 6, 6):
        raise InputError(
            f"rigid added_mass must have shape ({bodies}, 6, 6) (bodies, twist x twist), got {added.shape}"
        )
    if not np.all(np.isfinite(added)):
        raise InputError("rigid added_mass contains non-finite values")
    return added if np.any(added) else None


def body_jacobians(engine, added: np.ndarray) -> dict[int, np.ndarray]:
    """{body index: its world Jacobian (6 x its skeleton's dofs)} of the bodies with an added mass, at the
    engine's current state (each a call into DART: asked once per step)."""
    return {i: engine._body_jacobian(k, body) for i, (k, body) in enumerate(engine._bodies) if np.any(added[i])}


def generalised(engine, added: np.ndarray, jacobians: dict[int, np.ndarray]) -> list[np.ndarray]:
    """Per skeleton, A_hat = sum_b J_b^T A_b J_b (dofs x dofs), ``jacobians`` from ``body_jacobians``."""
    out = [np.zeros((s.getNumDofs(), s.getNumDofs())) for s in engine.skeletons]
    for i, J in jacobians.items():
        out[engine._bodies[i][0]] += J.T @ added[i] @ J
    return out


def inertia(engine, k: int) -> np.ndarray:
    """M + dt D of skeleton k at the current state: the matrix of DART's implicit-damping step."""
    skel = engine.skeletons[k]
    D = np.array([skel.getDof(i).getDampingCoefficient() for i in range(skel.getNumDofs())])
    return np.asarray(skel.getMassMatrix()) + engine.dt * np.diag(D)


def corrected_change(engine, added: np.ndarray, dqd: np.ndarray, jacobians: dict[int, np.ndarray]) -> np.ndarray:
    """dqd' (dofs,): the velocity change with the added mass, from DART's own change ``dqd`` over a step
    from the current state (module docstring)."""
    out = np.array(dqd, dtype=np.float64)
    for k, A_hat in enumerate(generalised(engine, added, jacobians)):
        free = ~engine._kinematic[k]
        if not free.any() or not np.any(A_hat[free]):
            continue
        o = slice(engine._offsets[k], engine._offsets[k + 1])
        d = out[o]
        M = inertia(engine, k)
        kin = ~free
        rhs = M[np.ix_(free, free)] @ d[free] - A_hat[np.ix_(free, kin)] @ d[kin]
        d[free] = np.linalg.solve(M[np.ix_(free, free)] + A_hat[np.ix_(free, free)], rhs)
        out[o] = d
    return out


def extra_wrenches(engine, added: np.ndarray, change: np.ndarray, jacobians: dict[int, np.ndarray]) -> np.ndarray:
    """(bodies, 6) [torque; force] -A_b J_b dqd' / dt: the wrenches that make DART's step follow ``change``."""
    out = np.zeros((len(engine._bodies), 6))
    for i, J in jacobians.items():
        k = engine._bodies[i][0]
        out[i] = -added[i] @ (J @ change[engine._offsets[k] : engine._offsets[k + 1]]) / engine.dt
    return out


def added_mass_adjoint(engine, added: np.ndarray, y: list[np.ndarray], change: np.ndarray) -> np.ndarray:
    """dL/dA_b (bodies, 6, 6) from y_k = (M + dt D + A_hat)_FF^-T dL/dqd'_F (zero on velocity-commanded dofs)
    per skeleton and the step's velocity change: dL/dA_hat = -y dqd'^T, dL/dA_b = J_b (dL/dA_hat) J_b^T."""
    out = np.zeros_like(added)
    for i, (k, body) in enumerate(engine._bodies):
        J = engine._body_jacobian(k, body)
        G = -np.outer(y[k], change[engine._offsets[k] : engine._offsets[k + 1]])
        out[i] = J @ G @ J.T
    return out
