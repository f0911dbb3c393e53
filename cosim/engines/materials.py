"""Constitutive models of the MPM engine, as small objects with Taichi functions.

Each material offers two ``@ti.func`` methods that the P2G / G2P kernels call
through a compile-time template argument, so the hot kernels hold no
``if material == ...`` chains:

- ``kirchhoff(F, C, mu, lam, eta)``: Kirchhoff stress tau = P F^T [Pa], from
  the deformation gradient F, the APIC affine velocity C (~ grad v, for
  viscosity), the Lame parameters and the viscosity eta [Pa s].
- ``project(F, mu, lam, yield_stress)``: the return mapping applied to the
  trial deformation gradient after G2P (plasticity, liquid reset).

Everything is plain arithmetic (no ``ti.svd``). Gradients go through the
hand-written ``kirchhoff_vjp`` and ``project_vjp`` (``cosim.engines.mpm_adjoint``),
never through Taichi's autodiff, so the 3D polar decomposition may iterate until
it has converged (``polar_rotation``).
"""

import taichi as ti

from cosim.engines.data_oriented import data_oriented

MAX_NEWTON_ITERATIONS = 20  # Frobenius-scaled Newton needs at most ~9 up to condition numbers of 1e16
# Scaling helps only far from a rotation: it is dropped once an iteration moves R less than this
# (squared Frobenius norm), as Higham recommends.
UNSCALED_BELOW = 1e-4
# Squared Frobenius norm of R^T R - I below which Newton-Schulz steps replace Newton's: every singular
# value s then has |s^2 - 1| < 0.3, where Newton-Schulz converges (it needs s < sqrt(3)) about as fast.
NEAR_ORTHOGONAL = 0.09


def newton_stop() -> float:
    """Squared Frobenius norm of a Newton update below which the polar iteration stops: Newton
    converges quadratically (next error ~ update^2 / 2), so an update of sqrt(2 eps) leaves an error
    near the precision's round-off eps (float32 6e-8, float64 1.1e-16). Read when a kernel compiles."""
    return 1e-7 if ti.lang.impl.current_cfg().default_fp == ti.f32 else 2e-16


@ti.func
def inverse_transpose_3(R):
    """R^-T of a 3x3 matrix: its cofactor matrix over its determinant.

    Written out because it is about twice as fast as ``R.inverse().transpose()``
    on the CPU, and it sits in the innermost loop of the 3D stress.
    """
    c00 = R[1, 1] * R[2, 2] - R[1, 2] * R[2, 1]
    c01 = R[1, 2] * R[2, 0] - R[1, 0] * R[2, 2]
    c02 = R[1, 0] * R[2, 1] - R[1, 1] * R[2, 0]
    inv_det = 1.0 / (R[0, 0] * c00 + R[0, 1] * c01 + R[0, 2] * c02)
    cof = ti.Matrix(
        [
            [c00, c01, c02],
            [
                R[0, 2] * R[2, 1] - R[0, 1] * R[2, 2],
                R[0, 0] * R[2, 2] - R[0, 2] * R[2, 0],
                R[0, 1] * R[2, 0] - R[0, 0] * R[2, 1],
            ],
            [
                R[0, 1] * R[1, 2] - R[0, 2] * R[1, 1],
                R[0, 2] * R[1, 0] - R[0, 0] * R[1, 2],
                R[0, 0] * R[1, 1] - R[0, 1] * R[1, 0],
            ],
        ]
    )
    return inv_det * cof


@ti.func
def cofactor(F):
    """det(F) F^-T (2D or 3D): the derivative of det(F) with respect to F."""
    out = F
    if ti.static(F.n == 2):
        out = ti.Matrix([[F[1, 1], -F[1, 0]], [-F[0, 1], F[0, 0]]])
    else:
        out = F.determinant() * inverse_transpose_3(F)
    return out


@ti.func
def polar_rotation(F):
    """Rotation R of the polar decomposition F = R S (S symmetric).

    2D: closed form. 3D: Newton iterations R <- (g R + (g R)^-T) / 2 with
    Frobenius scaling g = (|R^-T| / |R|)^(1/2) (Higham) while R is far from
    orthogonal; once |R^T R - I|^2 < ``NEAR_ORTHOGONAL``, Newton-Schulz steps
    R <- R (3 I - R^T R) / 2, which converge as fast there (defect -> 3/4
    defect^2) with no division or square root (the 3D stress spent ~2/3 of its
    time in the polar decomposition). Both stop when an update is below
    ``newton_stop()``: round-off for stretches between 0.05 and 20
    (tests/test_materials.py); a deformation near a rotation, the common case,
    takes 2 steps. Not for Taichi's autodiff (the loop count depends on F);
    ``polar_rotation_vjp`` is its derivative.
    """
    R = F
    if ti.static(F.n == 2):
        a = F[0, 0] + F[1, 1]
        b = F[1, 0] - F[0, 1]
        inv_norm = 1.0 / ti.sqrt(a * a + b * b)
        c, s = a * inv_norm, b * inv_norm
        R = ti.Matrix([[c, -s], [s, c]])
    else:
        scaled = True
        eye = ti.Matrix.identity(float, 3)
        for _ in range(MAX_NEWTON_ITERATIONS):
            gram = R.transpose() @ R
            defect = (gram - eye).norm_sqr()
            update = 0.0
            if defect < NEAR_ORTHOGONAL:
                R = R @ (1.5 * eye - 0.5 * gram)
                update = defect  # 4x the step's |R (I - R^T R) / 2|^2: it stops where Newton's would
            else:
                R_inv_t = inverse_transpose_3(R)
                g = 1.0
                if scaled:
                    g = ti.sqrt(ti.sqrt(R_inv_t.norm_sqr() / R.norm_sqr()))
                R_next = 0.5 * (g * R + (1.0 / g) * R_inv_t)
                update = (R_next - R).norm_sqr()
                R = R_next
                scaled = update > UNSCALED_BELOW
            if update < ti.static(newton_stop()):
                break
    return R


@ti.func
def polar_rotation_vjp(F, R, R_bar):
    """dL/dF through R = polar_rotation(F), given dL/dR: the derivative of the exact polar
    decomposition (the Newton iterate equals it to round-off), one small solve instead of the
    reverse of the iterations. With F = R S, dR = R [w]x where (tr(S) I - S) w = vee(R^T dF - dF^T R)
    (in 2D, tr(S) w = (R^T dF - dF^T R)_10); hence dL/dF = R [c]x, (tr(S) I - S) c = vee(M - M^T),
    M = R^T R_bar, vee(A) = (A_21, A_02, A_10)."""
    S = R.transpose() @ F
    S = 0.5 * (S + S.transpose())
    M = R.transpose() @ R_bar
    F_bar = R_bar
    if ti.static(F.n == 2):
        c = (M[1, 0] - M[0, 1]) / S.trace()
        F_bar = R @ ti.Matrix([[0.0, -c], [c, 0.0]])
    else:
        m = ti.Vector([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
        K = S.trace() * ti.Matrix.identity(float, 3) - S  # symmetric: its inverse is its inverse transpose
        c = inverse_transpose_3(K) @ m
        F_bar = R @ ti.Matrix([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    return F_bar


@ti.func
def corotated_kirchhoff(F, mu, lam):
    """Fixed corotated stress: tau = 2 mu (F - R) F^T + lam (J - 1) J I."""
    R = polar_rotation(F)
    J = F.determinant()
    eye = ti.Matrix.identity(float, F.n)
    return 2.0 * mu * (F - R) @ F.transpose() + lam * (J - 1.0) * J * eye


@ti.func
def corotated_kirchhoff_vjp(F, mu, lam, tau_bar):
    """(dL/dF, dL/dmu, dL/dlam) of tau = corotated_kirchhoff(F, mu, lam), given dL/dtau."""
    R = polar_rotation(F)
    J = F.determinant()
    strain_part = F - R
    F_bar = 2.0 * mu * (tau_bar @ F + tau_bar.transpose() @ strain_part)
    F_bar += polar_rotation_vjp(F, R, -2.0 * mu * tau_bar @ F)
    pressure_bar = tau_bar.trace()
    F_bar += (pressure_bar * lam * (2.0 * J - 1.0)) * cofactor(F)
    mu_bar = 2.0 * (tau_bar * (strain_part @ F.transpose())).sum()
    return F_bar, mu_bar, pressure_bar * (J - 1.0) * J


@data_oriented
class Elastic:
    """Fixed corotated hyperelasticity (Stomakhin et al. 2012)."""

    name = "elastic"
    project_uses_lame = False  # whether ``project`` depends on mu or lam (its adjoint then reaches E and nu)

    @ti.func
    def kirchhoff(self, F, C, mu, lam, eta):
        return corotated_kirchhoff(F, mu, lam)

    @ti.func
    def kirchhoff_vjp(self, F, C, mu, lam, eta, tau_bar):
        """(dL/dF, dL/dC, dL/dmu, dL/dlam) of ``kirchhoff``, given dL/dtau."""
        F_bar, mu_bar, lam_bar = corotated_kirchhoff_vjp(F, mu, lam, tau_bar)
        return F_bar, ti.Matrix.zero(float, F.n, F.n), mu_bar, lam_bar

    @ti.func
    def project(self, F, mu, lam, yield_stress):
        return F

    @ti.func
    def project_vjp(self, F, mu, lam, yield_stress, out_bar):
        """(dL/dF, dL/dmu, dL/dlam) of ``project``, given dL/d(its output)."""
        return out_bar, 0.0, 0.0


@data_oriented
class Plastic(Elastic):
    """Elasto-plastic: corotated elasticity (``Elastic``'s stress) with a von Mises radial return.

    The strain measure is the corotated (Biot) strain e = S - I with F = R S.
    Its deviatoric part is scaled back onto the yield surface
    |dev e| <= sqrt(2/3) * yield_stress / (2 mu), which is von Mises'
    sqrt(3/2) |dev tau| <= yield_stress with the small-strain relation
    dev tau = 2 mu dev e. Volume change stays elastic, as in metals and clay.
    """

    name = "plastic"
    project_uses_lame = True  # the yield limit scales with 1 / mu

    @ti.func
    def strain_parts(self, F, mu, yield_stress):
        """R (F = R S), the mean and deviatoric parts of the corotated strain S - I, |dev|^2 and the
        yield limit on |dev|: what ``project`` and its adjoint both start from."""
        R = polar_rotation(F)
        S = R.transpose() @ F
        eye = ti.Matrix.identity(float, F.n)
        strain = 0.5 * (S + S.transpose()) - eye
        mean = strain.trace() / F.n
        dev = strain - mean * eye
        return R, mean, dev, (dev * dev).sum(), ti.sqrt(2.0 / 3.0) * yield_stress / (2.0 * mu)

    @ti.func
    def project(self, F, mu, lam, yield_stress):
        R, mean, dev, norm2, limit = self.strain_parts(F, mu, yield_stress)
        # min(1, limit/|dev|) without a branch and without sqrt(0) in the adjoint
        scale = limit / ti.sqrt(ti.max(norm2, limit * limit))
        return R @ ((1.0 + mean) * ti.Matrix.identity(float, F.n) + scale * dev)

    @ti.func
    def project_vjp(self, F, mu, lam, yield_stress, out_bar):
        """(dL/dF, dL/dmu, dL/dlam) of ``project`` (out = R Y, Y = (1 + mean) I + scale dev), given dL/dout."""
        R, mean, dev, norm2, limit = self.strain_parts(F, mu, yield_stress)
        eye = ti.Matrix.identity(float, F.n)
        scale = 1.0
        dev_bar = ti.Matrix.zero(float, F.n, F.n)
        mu_bar = 0.0
        Y_bar = R.transpose() @ out_bar
        scale_bar = (Y_bar * dev).sum()
        if norm2 > limit * limit:  # on the yield surface: scale = limit / |dev|
            scale = limit / ti.sqrt(norm2)
            dev_bar = (-scale * scale_bar / norm2) * dev  # d scale / d dev = -scale dev / |dev|^2
            mu_bar = -scale_bar * scale / mu  # d limit / d mu = -limit / mu
        dev_bar += scale * Y_bar
        strain_bar = dev_bar + ((Y_bar.trace() - dev_bar.trace()) / F.n) * eye
        P_bar = 0.5 * (strain_bar + strain_bar.transpose())
        R_bar = out_bar @ (eye + mean * eye + scale * dev).transpose() + F @ P_bar.transpose()
        return R @ P_bar + polar_rotation_vjp(F, R, R_bar), mu_bar, 0.0


@data_oriented
class Liquid:
    """Weakly compressible liquid: pressure from the volume ratio J, no shear.

    tau = K J (J - 1) I + J eta (C + C^T) with the bulk modulus
    K = lam + 2 mu / d and the viscosity eta (C ~ grad v). After each
    G2P the deformation gradient is reset to J^(1/d) I so that only the volume
    ratio is remembered (no elastic shear memory).
    """

    name = "liquid"
    project_uses_lame = False

    @ti.func
    def kirchhoff(self, F, C, mu, lam, eta):
        J = F.determinant()
        bulk = lam + 2.0 * mu / F.n
        return bulk * J * (J - 1.0) * ti.Matrix.identity(float, F.n) + J * eta * (C + C.transpose())

    @ti.func
    def kirchhoff_vjp(self, F, C, mu, lam, eta, tau_bar):
        """(dL/dF, dL/dC, dL/dmu, dL/dlam) of ``kirchhoff``, given dL/dtau."""
        J = F.determinant()
        bulk = lam + 2.0 * mu / F.n
        pressure_bar = tau_bar.trace()
        J_bar = pressure_bar * bulk * (2.0 * J - 1.0) + eta * (tau_bar * (C + C.transpose())).sum()
        bulk_bar = pressure_bar * J * (J - 1.0)
        return J_bar * cofactor(F), J * eta * (tau_bar + tau_bar.transpose()), 2.0 * bulk_bar / F.n, bulk_bar

    @ti.func
    def project(self, F, mu, lam, yield_stress):
        J = F.determinant()
        return J ** (1.0 / F.n) * ti.Matrix.identity(float, F.n)

    @ti.func
    def project_vjp(self, F, mu, lam, yield_stress, out_bar):
        """(dL/dF, dL/dmu, dL/dlam) of ``project``, given dL/d(its output): d J^(1/d) / dF = J^(1/d - 1) cof(F) / d."""
        J = F.determinant()
        return (out_bar.trace() * J ** (1.0 / F.n - 1.0) / F.n) * cofactor(F), 0.0, 0.0


MATERIALS = {cls.name: cls for cls in (Elastic, Plastic, Liquid)}
