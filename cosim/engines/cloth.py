"""Our differentiable cloth: backward Euler solved to convergence, with the exact adjoint of that step.

Why this design: an
explicit integrator is CFL-bound (stable dt ~ 1/sqrt(k), 32x more steps over 3 decades of
stiffness); projective dynamics converges slowly at the tolerances gradients need and fits only
projective energies; XPBD/VBD have no usable gradients. Backward Euler written as an energy
minimisation is stable at any stiffness, and a step solved to a tight residual is a smooth function
of its inputs whose derivative the implicit function theorem gives exactly. So: Newton to
convergence forward (never accepting a non-converged iterate), one linear solve with the exact
Hessian backward, float64 throughout, every block checked against central differences.

The step (h = ``frame_dt`` [s], M lumped masses [kg], g gravity [m/s^2]):
    x_{n+1} = argmin_x E(x),
    E(x) = |x - x^|_M^2 / (2 h^2) + c_m |x - x_n|_M^2 / (2 h) + Psi(x) - f^T x - (M g)^T x,
    x^ = x_n + h v_n,   v_{n+1} = (x_{n+1} - x_n) / h,
so grad E = 0 is M (v_{n+1} - v_n) / h = -c_m M v_{n+1} - grad Psi + f + M g: backward Euler with
mass-proportional Rayleigh damping (dissipation potential c_m |v|_M^2 / 2 times h; it damps rigid
motion too, "damping to ground"; c_m = 0 conserves linear momentum exactly). Backward Euler adds its
own numerical damping: a mode of frequency w loses energy by the factor 1 / (1 + c_m h + w^2 h^2)
per step. Angular momentum is not conserved exactly (BE changes it by O(h^2) per step).

Psi = k_stretch * sum_faces A ||F - R(F)||^2 + k_bend * sum_hinges 3|e|^2/(A1+A2) (theta - theta0)^2
(``cloth_energy``). Units: k_stretch [N/m] (energy per area per squared strain; in uniaxial
stretch the membrane tension is T = 2 k_stretch (stretch - 1) [N/m], no Poisson effect), k_bend
[N m] = [J] (energy per squared radian, area-normalised), density [kg/m^2], c_m [1/s].
Mapping to DiffCloth/SoftMAC (``Triangle.h``/``TriangleBending.h``: E = 1/2 k A ||F - proj||^2 and
E = 1/2 k 3/(A0+A1) ||sum_i w_i x_i - proj||^2 with cotangent weights, whose norm is |e| theta to
first order): ours = theirs / 2, i.e. taco k_stretch 2500, k_bend 0.75; towel 500 and 0.015.

Lumped mass: density * one third of each adjacent face's rest area. Fixed vertices keep their
position; controlled vertices move in groups, x_{n+1} = x_n + h a_g with one velocity a_g [m/s]
per group (action layout (groups * 3,), group-major; None: zeros); both are eliminated from the
solve (prescribed positions). External forces ``forces`` (V, 3) [N] are constant over the step
(None: zeros; nothing on prescribed vertices); a coupling's ``added_mass`` A (V,) [kg] joins the
inertia term only, (m + A)(v_{n+1} - v_n) / h, not gravity or damping (``cosim.couplers.mpm_cloth``).

Newton: the search direction uses the exact Hessian when its free block is positive definite (read
off the pivots of a symmetric-mode LU, or met as negative curvature by conjugate gradients), else the
per-element Hessians projected to PSD (batched eigh), rigid-contact friction by its majorizing curvature
(``cloth_contact.point_hessians``). Projection alone always descends but converges only linearly where the
exact Hessian differs (compressed ARAP faces, bent hinges): measured, it stalled at 1e-8 N on a crumpled
sheet, while the exact Hessian, positive definite there thanks to M / h^2, converges quadratically.
Backtracking line search on E (round-off aware); the linear solves (to float64's floor) by conjugate
gradients preconditioned with the sparse LU of an earlier iteration or step (SuperLU, MMD ordering on
A^T + A, symmetric mode, the CSC pattern built once per mesh), factorised afresh only when they stop
converging fast (``cloth_linear``); converged
when ||grad E||_inf over free dofs <= tol, tol = max(rtol * m_max * 9.81 m/s^2 (+ rtol max|f|),
round-off floor 64 eps (|x|_max + size) (m_max (1 + c_m h) / h^2 + 8 k_stretch + 8 k_bend / l_min^2
+ the stiffest active rigid-contact spring)),
the floor being where float64 cannot resolve the gradient any better; a residual that has stopped
improving within 100x of it counts as converged (the floor is an estimate). Not converged within
``max_iterations``: ``SimulationError`` naming the step and the residual. ``vjp``: ``cloth_adjoint``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cosim.engines.cloth_adjoint import ClothAdjoint
from cosim.engines.cloth_contact import ContactSet, RigidContact
from cosim.engines.cloth_energy import ElasticEnergy, SparsePattern, hessian_entries, project_psd
from cosim.engines.cloth_linear import REFACTOR_AFTER, ReusedFactorisation
from cosim.engines.cloth_mesh import ClothMesh
from cosim.engines.cloth_solve import ClothSolver, StepData
from cosim.errors import InputError

MATERIAL_KEYS = ("k_stretch", "k_bend", "c_mass", "density")
G_REF = 9.81  # [m/s^2] reference acceleration of the residual tolerance (also with gravity off)


@dataclass(frozen=True)
class ClothMaterial:
    """k_stretch [N/m], k_bend [N m], c_mass [1/s] (mass-proportional damping), density [kg/m^2]."""

    k_stretch: float = 1000.0
    k_bend: float = 1e-3
    c_mass: float = 0.0
    density: float = 0.2

    def __post_init__(self) -> None:
        for key in MATERIAL_KEYS:
            value = getattr(self, key)
            if not np.isfinite(value) or value < 0 or (key in ("k_stretch", "density") and value == 0):
                raise InputError(
                    f"cloth material {key} must be finite and {'> 0' if key in ('k_stretch', 'density') else '>= 0'}, got {value}"
                )


@dataclass
class ClothRecord:
    """One step: the state before and after, the inputs, the material, and how the solve went."""

    step: int
    x: np.ndarray  # (V, 3) [m] before
    v: np.ndarray  # (V, 3) [m/s] before
    action: np.ndarray  # (groups * 3,) [m/s]
    forces: np.ndarray  # (V, 3) [N]
    x_next: np.ndarray
    v_next: np.ndarray
    material: ClothMaterial
    iterations: int
    residual: float  # [N] ||grad E||_inf at the accepted iterate
    tolerance: float  # [N]
    contacts: ContactSet | None = None
    added_mass: np.ndarray | None = None  # (V,) [kg] inertia the coupling added to the step (None: none)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.x, self.v, self.action, self.forces, self.x_next, self.v_next))


class ClothEngine(ClothAdjoint, ClothSolver):
    """A triangle-mesh cloth (see the module docstring); conforms to ``cosim.engines.contract.Engine``."""

    capabilities = frozenset({"points", "surface_speed", "material", "mesh", "energy"})

    def __init__(
        self,
        mesh: ClothMesh,
        material: ClothMaterial,
        fixed=(),
        controls=(),
        gravity=(0.0, -9.81, 0.0),
        frame_dt: float = 2e-3,
        name: str = "cloth",
        rtol: float = 1e-10,
        max_iterations: int = 200,
        cg_iterations: int = REFACTOR_AFTER,
    ) -> None:
        if not frame_dt > 0:
            raise InputError(f"cloth '{name}': frame_dt must be > 0, got {frame_dt}")
        self.name, self.mesh, self.frame_dt = name, mesh, float(frame_dt)
        self.gravity = np.asarray(gravity, dtype=np.float64).reshape(3)
        self.rtol, self.max_iterations = float(rtol), int(max_iterations)
        self._material = material
        V = mesh.n_vertices
        self.fixed = self._indices(fixed, "fixed")
        self.controls = [self._indices(g, f"controls[{i}]") for i, g in enumerate(controls)]
        self.ctrl_vertex = np.concatenate([np.zeros(0, dtype=np.int64), *self.controls])
        self.ctrl_group = np.repeat(np.arange(len(self.controls)), [len(g) for g in self.controls]).astype(np.int64)
        prescribed = np.concatenate([self.fixed, self.ctrl_vertex])
        if len(np.unique(prescribed)) != len(prescribed):
            raise InputError(
                f"cloth '{name}': a vertex is fixed or controlled twice (fixed and control groups overlap)"
            )
        self.free = np.ones(V, dtype=bool)
        self.free[prescribed] = False
        dof_free = np.repeat(self.free, 3)
        self.free_dofs, self.pres_dofs = np.flatnonzero(dof_free), np.flatnonzero(~dof_free)
        self.energy = ElasticEnergy(mesh)
        self.vertex_area = mesh.vertex_areas()
        rows, cols = hessian_entries(self.energy.dofs)
        free_map, pres_map = np.full(3 * V, -1), np.full(3 * V, -1)
        free_map[self.free_dofs] = np.arange(len(self.free_dofs))
        pres_map[self.pres_dofs] = np.arange(len(self.pres_dofs))
        nf, npres = len(self.free_dofs), len(self.pres_dofs)
        self._ff = SparsePattern(rows, cols, free_map, free_map, (nf, nf), diagonal=True)
        self._pf = SparsePattern(rows, cols, pres_map, free_map, (npres, nf))
        edges = mesh.vertices[mesh.edges[:, 1]] - mesh.vertices[mesh.edges[:, 0]]
        self._l_min = float(np.linalg.norm(edges, axis=1).min())
        self._size = float(np.ptp(mesh.vertices, axis=0).max())
        self._area = float(mesh.rest_area.sum())
        self.x = mesh.vertices.copy()
        self.v = np.zeros((V, 3))
        self.steps = 0
        self.last_solve: dict = {}
        self.contact: RigidContact | None = None
        self.cg_iterations = int(cg_iterations)  # CG iterations a solve may take (0: a fresh LU for each)
        self._factor = ReusedFactorisation(self.cg_iterations)  # the Newton solves' (``cloth_linear``)
        self._adjoint_factor = ReusedFactorisation(self.cg_iterations)  # the adjoints', within a backward pass

    @property
    def factorisations(self) -> int:
        """Sparse LU factorisations of the Hessian so far, Newton steps and adjoints (``cloth_linear``)."""
        return self._factor.factorisations + self._adjoint_factor.factorisations

    def attach_rigid_contact(self, thickness: float, friction: float = 0.0) -> None:
        """Let the cloth collide with rigid bodies (``cosim.engines.cloth_contact``): contact thickness
        [m] and friction coefficient mu; each step's planes come as the input "boundaries"."""
        self.contact = RigidContact(self.mesh.faces, self.masses(), self.frame_dt, thickness, friction)

    def energy_and_mass(self) -> tuple[float, float]:
        """(kinetic + elastic + gravity energy [J], mass [kg]) now."""
        m = self.masses()
        kinetic = 0.5 * float(np.sum(m[:, None] * self.v**2))
        return kinetic + self.elastic_energy(self.x) - float(np.sum(m[:, None] * self.gravity * self.x)), float(m.sum())

    def external_work(self, record: ClothRecord) -> float:
        """[J] Work the prescribed (fixed, controlled) vertices did on the cloth in the recorded step: the
        force holding each on its path (grad E at the end of the step, its inertia without added mass)
        times its displacement."""
        if self.free.all():
            return 0.0
        data = self._step_data(record.x, record.v, record.forces, record.material)
        data.contacts = record.contacts
        held = self._gradient(record.x_next, data)[~self.free]
        return float(np.sum(held * (record.x_next - record.x)[~self.free]))

    def _indices(self, idx, what: str) -> np.ndarray:
        idx = np.asarray(idx, dtype=np.int64).reshape(-1)
        if len(idx) and (idx.min() < 0 or idx.max() >= self.mesh.n_vertices):
            raise InputError(f"cloth '{self.name}': {what} vertex indices must lie in [0, {self.mesh.n_vertices})")
        return idx

    # ------------------------------------------------------------------------------------- the contract
    @property
    def action_size(self) -> int:
        return 3 * len(self.controls)

    def state(self) -> dict[str, np.ndarray]:
        """``x`` (V, 3) [m] vertex positions, ``v`` (V, 3) [m/s] velocities (copies)."""
        return {"x": self.x.copy(), "v": self.v.copy()}

    def points(self) -> np.ndarray:  # the vertices must stay in the MPM's domain
        return self.x

    def point_name(self, i: int) -> str:
        return f"vertex {i}"

    def surface_speed(self, frame_dt: float) -> float:
        """[m/s] The fastest vertex now (the MPM's substep count keeps the sheet under a cell per substep)."""
        return float(np.linalg.norm(self.v, axis=1).max()) if len(self.v) else 0.0

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore a ``state()``. The linear solves' reused factor is dropped, so a rollout from here repeats
        bit for bit; against the run that went on from this state, the next step can differ in the last bits of
        its final Newton update (solved by conjugate gradients preconditioned with another factor)."""
        V = self.mesh.n_vertices
        for key in ("x", "v"):
            if np.shape(state[key]) != (V, 3):
                raise InputError(
                    f"cloth '{self.name}': state {key} must have shape ({V}, 3), got {np.shape(state[key])}"
                )
        self.x = np.array(state["x"], dtype=np.float64)
        self.v = np.array(state["v"], dtype=np.float64)
        self._factor.forget()

    def material(self) -> dict[str, np.ndarray]:
        """k_stretch [N/m], k_bend [N m], c_mass [1/s], density [kg/m^2], each a 0-d array."""
        return {k: np.array(getattr(self._material, k), dtype=np.float64) for k in MATERIAL_KEYS}

    def set_parameters(self, values: dict[str, np.ndarray]) -> None:
        """Set any of the material parameters (keys of ``material()``; others are ignored)."""
        current = {k: float(getattr(self._material, k)) for k in MATERIAL_KEYS}
        current.update({k: float(np.asarray(values[k])) for k in MATERIAL_KEYS if k in values})
        self._material = ClothMaterial(**current)
        self._factor.forget()

    def parameters(self) -> list:
        """Initial state x, v; the action sequence (with control groups); the material parameters."""
        from cosim.engines.contract import Parameter

        n = self.name
        out = [Parameter(f"{n}.x0", n, "state", "x", self._l_min), Parameter(f"{n}.v0", n, "state", "v", 1.0)]
        if self.controls:
            out.append(Parameter(f"{n}.action", n, "input", "action", 1e-2))
        out += [
            Parameter(f"{n}.{k}", n, "material", k, max(float(getattr(self._material, k)), 1e-3)) for k in MATERIAL_KEYS
        ]
        return out

    def step(self, inputs: dict) -> tuple[dict, ClothRecord]:
        """One frame: ``inputs`` action, forces, added_mass, boundaries {source: ContactPlanes} (each
        None or see the module docstring). Returns ({"state": state after, "reactions": {source: {"force":
        (c, 3) [N] on the rigid body, "point": (c, 3) [m] where it acts (the plane points)}}}, record)."""
        action, forces, added = self._inputs(inputs.get("action"), inputs.get("forces"), inputs.get("added_mass"))
        x_n, v_n, mat = self.x, self.v, self._material
        data = self._step_data(x_n, v_n, forces, mat, added)
        planes = inputs.get("boundaries") or {}
        if planes and self.contact is None:
            raise InputError(f"cloth '{self.name}': contact planes given but no rigid contact attached")
        if planes:
            data.contacts = self.contact.prepare(x_n, planes)
        x_next, iterations, residual, tol = self._solve(data, self._prescribed_next(x_n, action))
        v_next = (x_next - x_n) / self.frame_dt
        record = ClothRecord(
            self.steps, x_n, v_n, action, forces, x_next, v_next, mat, iterations, residual, tol, data.contacts, added
        )
        self.last_solve = {"step": self.steps, "iterations": iterations, "residual": residual, "tolerance": tol}
        self.x, self.v = x_next, v_next
        self.steps += 1
        outputs = {"state": self.state()}
        if data.contacts is not None:
            on_bodies = -self.contact.forces(x_next, data.contacts)
            outputs["reactions"] = {
                src: {"force": on_bodies[rows], "point": data.contacts.point[rows]}
                for src, rows in data.contacts.sources.items()
            }
        return outputs, record

    def _inputs(self, action, forces, added=None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(action, forces, added mass or None where it is all zero), checked."""
        V, name = self.mesh.n_vertices, f"cloth '{self.name}'"
        action = np.zeros(self.action_size) if action is None else np.asarray(action, dtype=np.float64).reshape(-1)
        if action.shape != (self.action_size,):
            raise InputError(
                f"{name}: action must have length {self.action_size} (3 per control group), got {action.size}"
            )
        forces = np.zeros((V, 3)) if forces is None else np.asarray(forces, dtype=np.float64)
        if forces.shape != (V, 3):
            raise InputError(f"{name}: forces must have shape ({V}, 3) [N], got {forces.shape}")
        added = np.zeros(V) if added is None else np.asarray(added, dtype=np.float64)
        if added.shape != (V,) or np.any(added < 0):
            raise InputError(f"{name}: added_mass must have shape ({V},) and be >= 0 [kg], got {added.shape}")
        if not (np.all(np.isfinite(action)) and np.all(np.isfinite(forces)) and np.all(np.isfinite(added))):
            raise InputError(f"{name}: action, forces or added_mass contain non-finite values")
        return action, forces, (added if np.any(added > 0) else None)

    # ------------------------------------------------------------------------------------- the solve

    def masses(self, density: float | None = None) -> np.ndarray:
        """(V,) [kg] lumped vertex masses."""
        return (self._material.density if density is None else density) * self.vertex_area

    def elastic_energy(self, x: np.ndarray) -> float:
        """Psi(x) [J] at positions x (V, 3) with the current material."""
        mem, bend = self.energy.energies(x)
        return self._material.k_stretch * mem + self._material.k_bend * bend

    def _step_data(self, x_n, v_n, forces, mat: ClothMaterial, added: np.ndarray | None = None) -> StepData:
        data = StepData(x_n, x_n + self.frame_dt * v_n, forces, mat, added_mass=added)
        data.mass = self.masses(mat.density)[:, None]
        data.inertia = data.mass if added is None else data.mass + added[:, None]
        return data

    def _prescribed_next(self, x_n: np.ndarray, action: np.ndarray) -> np.ndarray:
        """(V, 3) positions after the step of the prescribed vertices (others: x_n)."""
        x = x_n.copy()
        if len(self.ctrl_vertex):
            x[self.ctrl_vertex] += self.frame_dt * action.reshape(-1, 3)[self.ctrl_group]
        return x

    def _potential(self, x: np.ndarray, d: StepData) -> tuple[float, float]:
        """The incremental potential E(x) [J] and a bound on its round-off error [J]: each term's error is
        a few eps times the magnitudes it is computed from (|x - x^| (|x| + |x^|) for the inertia,
        I1 + 2 sqrt(I1 + 2J) + 2 ~ 8 per unit area for the membrane, |f| |x| for the loads)."""
        h, mat = self.frame_dt, d.material
        dx_hat, dx_n = x - d.x_hat, x - d.x_n
        inertia = 0.5 * np.sum(d.inertia * dx_hat**2) / h**2 + 0.5 * mat.c_mass * np.sum(d.mass * dx_n**2) / h
        mem, bend = self.energy.energies(x)
        external = -np.sum(d.forces * x) - np.sum(d.mass * self.gravity * x)
        contact = self.contact.energy(x, d.contacts) if d.contacts is not None else 0.0
        size = np.abs(x) + np.abs(d.x_hat)
        gross = (
            np.sum(d.inertia * np.abs(dx_hat) * size) / h**2
            + mat.c_mass * np.sum(d.mass * np.abs(dx_n) * size) / h
            + mat.k_stretch * (8 * self._area + mem)
            + mat.k_bend * bend
            + np.sum(np.abs(d.forces * x))
            + np.sum(np.abs(d.mass * self.gravity * x))
            + contact
        )
        total = inertia + mat.k_stretch * mem + mat.k_bend * bend + external + contact
        return total, 64 * np.finfo(np.float64).eps * gross

    def _gradient(self, x: np.ndarray, d: StepData) -> np.ndarray:
        """grad E (V, 3) [N]."""
        h, mat = self.frame_dt, d.material
        g_mem, g_bend = self.energy.gradients(x)
        inertia = d.inertia * (x - d.x_hat) / h**2 + d.mass * (mat.c_mass * (x - d.x_n) / h - self.gravity)
        g = inertia + mat.k_stretch * g_mem + mat.k_bend * g_bend - d.forces
        if d.contacts is not None:
            g += self.contact.gradient(x, d.contacts)
        return g

    def _element_hessians(
        self, x: np.ndarray, mat: ClothMaterial, contacts: ContactSet | None = None, project: bool = False
    ) -> np.ndarray:
        """Flat entries of all element Hessians of Psi (membrane with the rigid contacts' face blocks,
        then bending), exact or (``project``) each projected to PSD (the contact blocks already are)."""
        H_mem, H_bend = self.energy.hessians(x)
        if project:
            H_mem, H_bend = project_psd(H_mem), project_psd(H_bend)
        face = mat.k_stretch * H_mem
        if contacts is not None:
            face = face + self.contact.face_hessians(x, contacts, len(self.mesh.faces), majorize=project)
        return np.concatenate([face.ravel(), mat.k_bend * H_bend.ravel()])

    def _mass_diagonal(self, mat: ClothMaterial, added: np.ndarray | None = None) -> np.ndarray:
        """Diagonal of d^2 E / dx^2 from inertia (with ``added`` (V,) [kg]) and damping, over the free dofs."""
        m = self.masses(mat.density)
        inertia = m if added is None else m + added
        h = self.frame_dt
        return np.repeat(inertia / h**2 + mat.c_mass * m / h, 3)[self.free_dofs]

    def _tolerance(self, d: StepData) -> float:
        mat = d.material
        m_max, i_max = float(d.mass.max()), float(d.inertia.max())
        h = self.frame_dt
        wanted = self.rtol * (m_max * G_REF + float(np.abs(d.forces).max()))
        stiffness = (i_max + m_max * mat.c_mass * h) / h**2 + 8 * mat.k_stretch + 8 * mat.k_bend / self._l_min**2
        if d.contacts is not None and len(d.contacts.stiffness):  # active penalty springs (~100 m / h^2)
            stiffness += float(d.contacts.stiffness.max())
        floor = 64 * np.finfo(np.float64).eps * (float(np.abs(d.x_n).max()) + self._size) * stiffness
        return max(wanted, floor)
