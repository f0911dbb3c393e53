"""The exact one-step vector-Jacobian product of ``ClothEngine``, a mixin for readability.

At the converged step the free dofs satisfy G(x_f; p) = grad_f E = 0 for every input p (x_n, v_n,
the prescribed positions x_p = x_n,p + h a, the forces, the material). The implicit function
theorem gives dx_f/dp = -H_ff^-1 dG/dp with H the exact (unprojected) Hessian of E at x_{n+1}. With
L's adjoints gx = dL/dx_{n+1}, gv = dL/dv_{n+1} and v_{n+1} = (x_{n+1} - x_n)/h, the total adjoint
of x_{n+1} is gbar = gx + gv / h, and one solve H_ff lam = gbar_f gives (m the lumped masses):

    dL/dx_n  free: -gv/h + lam (M/h^2 + m c_m/h);  prescribed: gx_p - (H_pf lam)   (x_p moves with x_n,p)
    dL/dv_n  free: lam M / h;                       prescribed: 0
    dL/da_g  = h sum_{i in group g} (gbar_i - (H_pf lam)_i)
    dL/df    free: lam;  prescribed: 0 (a force on a prescribed vertex does not move anything)
    dL/dk_stretch = -lam . grad Psi_membrane(unit),  dL/dk_bend = -lam . grad Psi_bending(unit)
    dL/dc_mass = -lam . m v_{n+1},   dL/ddensity = -lam . a_v ((x - x^)/h^2 + c_m v_{n+1} - g)

(a_v the vertex areas; M = m + A the inertia with a coupling's added mass A, ``cosim.couplers.mpm_cloth``),
and dL/dA = -lam . (x_{n+1} - x^) / h^2 per free vertex (A enters G only as A (x - x^) / h^2).
Rigid contacts (``cloth_contact``): G holds -sum_i w_ij f_i, f_i the force of contact point i. The
reactions' adjoints ("force": dL/d(-f_i); "point": dL/d(where it acts), the plane point passed on) add (df_i/dy_i)^T dL/df_i to gbar at the point's vertices; the plane
point, normal and the point's start position s_i then get (df_i/dtheta)^T (dL/df_i + sum_j w_ij lam_j),
the direct path plus the solve's; s_i's goes to dL/dx_n, and so does the planes' own (the planes'
Jacobians with respect to the queried point s_i). Output "boundaries" {source: {point, normal, velocity}}
(velocity: the body's surface under each point, which friction is relative to).
H_ff may be indefinite (the unprojected Hessian of a buckled cloth): it is solved by conjugate gradients
preconditioned with an earlier step's factor of this backward pass (``cloth_linear``) or a symmetric-mode LU
while it is positive definite, else by LU with partial pivoting; an exactly singular H_ff raises
``SimulationError``. The
mixin reads the engine's ``frame_dt``, ``gravity``, ``free``, ``free_dofs``, ``pres_dofs``,
``ctrl_vertex``, ``ctrl_group``, ``controls``, ``energy``, ``_adjoint_factor``, ``_ff``, ``_pf`` and helpers.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse.linalg import splu

from cosim.engines.cloth_linear import ReusedFactorisation
from cosim.errors import SimulationError


class ClothAdjoint:
    """``vjp`` of the cloth engine."""

    _adjoint_factor: ReusedFactorisation  # the engine's
    _adjoint_next: int | None = None  # the step a backward pass reaches next (its factor is reused there only)

    def _adjoint_solve(self, H, b: np.ndarray, step: int) -> np.ndarray:
        """H^-1 b for the symmetric H of recorded step ``step``, to round-off. The factor of an earlier solve
        preconditions this one only within one backward pass (steps in turn, last to first), so that a
        pass's gradients depend on its records alone."""
        if step != self._adjoint_next:
            self._adjoint_factor.forget()
        self._adjoint_next = step - 1
        try:
            lam = self._adjoint_factor.solve_spd(H, b)  # the usual case, and faster than pivoting
            return splu(H).solve(b, trans="T") if lam is None else lam
        except RuntimeError as exc:
            raise SimulationError(
                f"cloth '{self.name}': the exact Hessian of step {step} is singular ({exc}); "
                "its adjoint is undefined there"
            ) from exc

    def vjp(self, record, grad_outputs: dict) -> dict:
        """{"state": {"x", "v"}, "reactions": {source: {"force", "point"}}} (dL/d(outputs), missing keys zero) ->
        {"state": {"x", "v"}, "action", "forces", "added_mass", "boundaries", "material"} of the recorded
        step (see the module docstring)."""
        V, h, mat = self.mesh.n_vertices, self.frame_dt, record.material
        grads = grad_outputs.get("state") or {}
        gx = np.zeros((V, 3)) if grads.get("x") is None else np.asarray(grads["x"], dtype=np.float64)
        gv = np.zeros((V, 3)) if grads.get("v") is None else np.asarray(grads["v"], dtype=np.float64)
        contacts = record.contacts
        if contacts is not None:  # dL/df of the contact points, from the reactions' adjoints (reaction = -f)
            g_force, g_at = np.zeros((len(contacts.face), 3)), np.zeros((len(contacts.face), 3))
            for source, g in (grad_outputs.get("reactions") or {}).items():
                g_force[contacts.sources[source]] -= g["force"]
                if g.get("point") is not None:  # where the reaction acts: the plane point, an input passed on
                    g_at[contacts.sources[source]] += g["point"]
            direct = self.contact.force_vjp(record.x_next, contacts, g_force)["y"]
            gx = gx + self.contact.spread(contacts, direct, V)
        gbar = gx + gv / h
        lam = np.zeros(3 * V)
        coupling = np.zeros(3 * V)
        if len(self.free_dofs):
            entries = self._element_hessians(record.x_next, mat, record.contacts)
            H = self._ff.matrix(entries, self._mass_diagonal(mat, record.added_mass))
            lam[self.free_dofs] = self._adjoint_solve(H, gbar.reshape(-1)[self.free_dofs], record.step)
            coupling[self.pres_dofs] = self._pf.matrix(entries) @ lam[self.free_dofs]
        lam, coupling = lam.reshape(V, 3), coupling.reshape(V, 3)
        m = self.masses(mat.density)[:, None]
        inertia = m if record.added_mass is None else m + record.added_mass[:, None]
        free = self.free[:, None]
        grad_x = np.where(free, -gv / h + lam * (inertia / h**2 + m * mat.c_mass / h), gx - coupling)
        grad_v = np.where(free, lam * inertia / h, 0.0)
        through_prescribed = gbar - coupling
        grad_action = np.zeros((len(self.controls), 3))
        np.add.at(grad_action, self.ctrl_group, h * through_prescribed[self.ctrl_vertex])
        g_mem, g_bend = self.energy.gradients(record.x_next)
        x_hat = record.x + h * record.v
        accel = (record.x_next - x_hat) / h**2 + mat.c_mass * record.v_next - self.gravity
        grad_added = -np.sum(np.where(free, lam, 0.0) * (record.x_next - x_hat), axis=1) / h**2
        planes = {}
        if contacts is not None:  # the planes and the step's start through the forces, directly and in G
            total = self.contact.force_vjp(record.x_next, contacts, g_force + self.contact.gathered(contacts, lam))
            total["point"] = total["point"] + g_at
            # a plane moves with the queried point (the contact point at the step's start) off flat faces
            g_query = (
                np.einsum("cki,ck->ci", contacts.point_jacobian, total["point"])
                + np.einsum("cki,ck->ci", contacts.normal_jacobian, total["normal"])
                + np.einsum("cki,ck->ci", contacts.velocity_jacobian, total["velocity"])
            )
            grad_x = grad_x + self.contact.spread(contacts, total["start"] + g_query, V)
            planes = {
                src: {key: total[key][rows] for key in ("point", "normal", "velocity")}
                for src, rows in contacts.sources.items()
            }
        return {
            "boundaries": planes,
            "added_mass": grad_added,
            "state": {"x": grad_x, "v": grad_v},
            "action": grad_action.reshape(-1),
            "forces": lam.copy(),
            "material": {
                "k_stretch": np.array(-np.sum(lam * g_mem)),
                "k_bend": np.array(-np.sum(lam * g_bend)),
                "c_mass": np.array(-np.sum(lam * m * record.v_next)),
                "density": np.array(-np.sum(lam * self.vertex_area[:, None] * accel)),
            },
        }
