"""The MPM engine adapter: hooks for the contact models and the engine contract (``cosim.engines.contract``).

Gradients come from each substep's kernels' adjoints in reverse order: hand-written for
the particle-grid transfers (``cosim.engines.mpm_adjoint``), Taichi's reverse-mode
autodiff (``.grad()``) for the rest. States between macro steps are kept by the tape on
the host (a record holds the state before its step), and ``vjp`` recomputes the
substeps of the step it differentiates unless they are still resident from the
forward pass. Memory is O(S N + K (N + grid)), never O(S K N).

Boundary sources (``cosim.couplers.boundary``) are attached by name; each step's
``inputs["boundaries"]`` gives every source its per-substep states and the step's
``outputs["reactions"]`` returns what the contact models handed back. The engine
knows sources and hooks only through their methods, never by type.
"""

import weakref
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from cosim.engines.contract import declares
from cosim.engines.data_oriented import data_oriented
from cosim.engines.device_memory import adjoint_allocated
from cosim.engines.mpm_adjoint import MPMAdjointKernels
from cosim.engines.mpm_checkpoints import CheckpointStore, DeviceState
from cosim.engines.mpm_energy import TERMS as ENERGY_TERMS
from cosim.engines.mpm_energy import EnergyMeter
from cosim.engines.mpm_inputs import STATE_KEYS, MPMConfig, ParticleBody
from cosim.engines.mpm_watch import BodyHealth
from cosim.engines.slot_state import SlotState

__all__ = ["STATE_KEYS", "MPMConfig", "MPMEngine", "MPMRecord", "ParticleBody"]


@dataclass
class MPMRecord:
    """What ``vjp`` needs about one macro step."""

    state: Mapping | None  # before the step (host arrays or a DeviceState); None while the tape holds none
    dt: float  # [s] substep
    substeps: int
    impulse: np.ndarray | None = None  # (N, d) [N s]
    boundaries: dict = field(default_factory=dict)  # {source: BoundaryStates}
    token: int = -1  # the engine's id of this forward step (lets vjp skip a recompute)
    precision: type = np.float64  # the engine's, in which a kept checkpoint is stored (exactly: it was read from it)

    def keep_checkpoint(self, state: Mapping | None) -> None:
        """Hold ``state`` (the state before the step) in the engine's precision (a ``DeviceState`` is),
        or release it (None): the tape then recomputes it from an earlier checkpoint (``MPMEngine.replay``)."""
        if state is None or isinstance(state, DeviceState):
            self.state = state
        else:
            self.state = {k: v.astype(self.precision, copy=False) for k, v in state.items()}

    @property
    def nbytes(self) -> int:
        """Memory the record holds [bytes], on the host or (a ``DeviceState``) on the device."""
        return _nbytes(self.state) + _nbytes(self.impulse) + sum(_nbytes(b) for b in self.boundaries.values())


def _nbytes(value) -> int:
    """Bytes of the arrays in a value: an array, a ``DeviceState``, boundary states (nested dicts allowed:
    a cloth's tracking state); 0 for None."""
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    return getattr(value, "nbytes", 0)


@data_oriented
class MPMEngine(MPMAdjointKernels):
    """The soft-body engine ("mpm"): ``state`` / ``set_state`` / ``step`` / ``vjp`` / ``parameters``."""

    name = "mpm"
    capabilities = frozenset({"material", "material_grads"})

    def __init__(self, config: MPMConfig, bodies: list[ParticleBody]):
        self.boundaries: dict = {}  # name -> boundary source
        self._known_state = None  # the state the last step returned, while it is still the current one
        self._known_health = None  # the survey of the current state, once made
        self._known_energy = None  # its energy sums per body, when the survey took them (``survey_energies``)
        self.survey_energies = False  # the survey also sums the energies (set by whoever reads them every step)
        self._views: list = []  # weak references to the SlotState views handed out
        self._previous_start = -1  # forward only: the slot the last step started from
        self.state_version = 0  # changes whenever the current state does (``_forget``)
        self.checkpoints = CheckpointStore(self, config.checkpoints)  # gradients: states kept between steps
        super().__init__(config, bodies)
        self._material = self.material()  # E, nu per body now: the derived quantities' one source
        self._energy_meter = EnergyMeter(self)

    @property
    def slot(self) -> int:
        """The particle slot holding the current state (``x[slot, p]``): what a boundary source traces."""
        return self._slot

    # ------------------------------------------------------------ hooks and sources
    def attach_grid_hook(self, hook):
        """Let a contact model rewrite grid velocities after the grid update; returns its upstream.

        The hook reads the velocity upstream of it (``upstream.velocity(g, I)``: the engine's
        ``grid_v`` or the previous grid hook's output) and never writes it in place (the
        adjoint needs the input); G2P gathers from the last hook's ``@ti.func velocity(g, I)`` and
        scatters its adjoint through the hook's ``@ti.func velocity_grad(g, I, g_v)``.
        Fields listed in ``hook.scratch`` (grid-shaped vectors) are zeroed with the grid at
        the start of each substep, the adjoints of those in ``hook.grid_adjoints`` at the
        start of each substep's adjoint. Methods: ``apply(src, g, s, dt)`` for substep s of the
        macro step, particles in slot src, grid copy g; ``apply_grad(src, g, s, dt)``;
        ``zero_grad()`` (its own adjoints only). Its grid passes loop over grid copy g's box
        [``active_lo[g]``, ``active_hi[g]``), the nodes the particles reach (``_clear_box``); a hook
        that reads or writes nodes up to k beyond them sets ``hook.box_margin = k``. A hook with a
        ``@ti.func forward_pass(src, g, s, dt)`` doing what ``apply`` does lets a substep run
        as one launch (``MPMKernels._substep_fused``); without one the substep's phases launch apart.
        """
        self._check_unspecialised("grid hooks")
        upstream = self._grid_out
        self.grid_hooks.append(hook)
        self._grid_out = hook
        self.box_margin = max(self.box_margin, int(getattr(hook, "box_margin", 0)))
        return upstream

    def attach_particle_hook(self, hook) -> None:
        """Let a contact model add momentum [N s] to particles in P2G (e.g. penalty forces).

        Before each P2G every particle hook fills ``hook.output[g, p]``; methods
        ``apply(src, g, s, dt)``, ``apply_grad(src, g, s, dt)``, ``zero_grad()``.
        """
        self._check_unspecialised("particle hooks")
        self.particle_hooks.append(hook)

    def attach_boundary(self, name: str, source) -> None:
        """A boundary source the contact models read; its states come in ``inputs["boundaries"][name]``."""
        self._check_unspecialised("boundary sources")
        if name in self.boundaries:
            raise ValueError(f"a boundary source named '{name}' is already attached")
        self.boundaries[name] = source
        if declares(source, "substep_hooks"):
            self.substep_preparers.append(source.before_substep)
            self.substep_preparer_grads.append(source.before_substep_grad)

    def _check_unspecialised(self, what: str) -> None:
        if self._token > 0:
            raise ValueError(f"attach {what} before the first step (kernels are specialised on them)")

    # ------------------------------------------------------------ the contract
    def state(self) -> dict[str, np.ndarray]:
        """Particle state at the current macro step: x (n,d), v (n,d), C (n,d,d), F (n,d,d)."""
        return self._get_state(self._state_fields(), self._slot)

    def max_speed(self) -> float:
        """Largest velocity component [m/s] of any particle now (from ``health``: no particle state read)."""
        return max(h.speed for h in self.health().values())

    def health(self) -> dict[str, BodyHealth]:
        """Per body name: the current particles' largest velocity component [m/s], non-finite and
        out-of-grid counts, and the first substep of the last step that left a NaN or inf
        (``cosim.engines.mpm_watch``): surveyed on the device once per state, a few numbers read."""
        if self._known_health is None:
            meter = self._energy_meter if self.survey_energies else None
            self._known_health, self._known_energy = self.watch.survey(self._slot, meter)
        return self._known_health

    def energies(self) -> dict[str, dict[str, float]]:
        """Per body name: the current particles' kinetic, gravitational, strain and total energy [J] and
        volume sum V0 det F [m^3, 2D: m^2] (``cosim.engines.mpm_energy``: summed on the device; with
        ``survey_energies`` in the survey's pass over the particles)."""
        if self.survey_energies:
            self.health()
        sums = self._known_energy if self._known_energy is not None else self._energy_meter.body_sums(self._slot)
        out = {}
        for body, row in zip(self.bodies, sums):
            terms = {k: float(v) for k, v in zip(ENERGY_TERMS, row)}
            terms["total"] = terms["kinetic"] + terms["gravity"] + terms["strain"]
            out[body.name] = terms
        return out

    def control_work(self) -> float:
        """[J] Kinetic energy the last step's control impulses added: sum I . v + |I|^2 / 2m over the
        particles, v before the step (summed on the device; 0 without controls)."""
        if self.control is None:
            return 0.0
        return self._energy_meter.control_work(0 if self.cfg.requires_grad else self._previous_start)

    def set_state(self, state: Mapping) -> None:
        """Restore a state from ``state()`` or a step's (host arrays, a ``SlotState``, a ``DeviceState``);
        the next step starts from it bit for bit."""
        self._forget(0)  # a view of slot 0 (``state`` itself, maybe) reads it first
        self.checkpoints.write(state, self._state_fields(), 0)
        self._slot = 0
        self._resident = -1

    def parameters(self) -> list:
        """x0, v0 (initial state), E, nu per body (material) and, with controls, the impulses (input)."""
        from cosim.engines.contract import Parameter

        E = float(self.E.to_numpy().max())
        out = [
            Parameter("x0", self.name, "state", "x", self.dx),
            Parameter("v0", self.name, "state", "v", 1.0),
            Parameter("E", self.name, "material", "E", E),
            Parameter("nu", self.name, "material", "nu", 0.1),
        ]
        if self.control is not None:
            out.append(Parameter("impulse", self.name, "input", "impulse", 0.1 * float(self.mass.max())))
        return out

    def set_parameters(self, values: dict[str, np.ndarray]) -> None:
        """Per-body Young's moduli ``E`` [Pa] and Poisson's ratios ``nu`` (differentiable inputs)."""
        for key in ("E", "nu"):
            if key in values:
                getattr(self, key).from_numpy(self._real(values[key]))
        self._material = self.material()
        self._resident = -1
        self._known_energy = None  # the strain energy is the moduli's

    def material(self) -> dict[str, np.ndarray]:
        """The current per-body E and nu."""
        return {"E": self.E.to_numpy().astype(np.float64), "nu": self.nu.to_numpy().astype(np.float64)}

    def step(self, inputs: dict) -> tuple[dict, MPMRecord]:
        """One macro step: ``inputs`` dt [s], substeps, impulse (N, d) [N s] or None (spread evenly over
        the substeps in P2G), boundaries {source: BoundaryStates} for every attached source.
        Returns ({state, reactions {source: Reactions}, health {body: BodyHealth}}, record), ``health`` the
        device's NaN / speed / domain survey of the state after. That state is also the next step's record
        of the state before it: with gradients read once per step (the tape keeps it), else a ``SlotState``
        read on first access (and kept when its slot is overwritten). Do not modify it in place."""
        dt, K = float(inputs["dt"]), int(inputs["substeps"])
        boundaries = inputs.get("boundaries") or {}
        missing = sorted(set(self.boundaries) - set(boundaries))
        if missing:
            raise ValueError(f"MPM step: no boundary states for sources {missing}")
        before = self._known_state if self._known_state is not None else self._snapshot()
        record = MPMRecord(before, dt, K, inputs.get("impulse"), boundaries, precision=self.real)
        self._write_boundaries(boundaries)
        record.token = self.advance(dt, K, record.impulse)
        reactions = {name: source.reactions(K) for name, source in self.boundaries.items()}
        self._known_state = self._snapshot()
        return {"state": self._known_state, "reactions": reactions, "health": self.health()}, record

    def _snapshot(self) -> Mapping:
        """The current state for a record or the outputs: with gradients a copy the tape keeps (on the
        device while it fits, ``CheckpointStore``), else a view of its slot, read when something reads it."""
        if self.cfg.requires_grad:
            return self.checkpoints.read(self._state_fields(), self._slot)
        view = SlotState(self, self._slot)
        self._views = [ref for ref in self._views if ref() is not None] + [weakref.ref(view)]
        return view

    def advance(self, dt: float, substeps: int, impulse: np.ndarray | None = None) -> int:
        """``substeps`` substeps of ``dt`` seconds with the boundaries as written; returns the step's token.
        The bare stepping under ``step`` (benchmarks use it to time the kernels alone)."""
        self._set_control(impulse)
        self._binned = None  # block lists made afresh: a step's sums depend on its start state alone
        share = 1.0 / substeps
        if self.cfg.requires_grad:
            if substeps > self.cfg.grad_substeps:
                raise ValueError(f"{substeps} substeps exceed the {self.cfg.grad_substeps} built for gradients")
            self._forget(*range(self.n_slots))
            if self._slot != 0:
                self._copy_slot(self._slot, 0)
            route = [(s, s + 1) for s in range(substeps)]
        else:
            route = self._rotation(substeps)
            self._forget(*{dst for _, dst in route})
            self._previous_start = self._slot
        for s, (src, dst) in enumerate(route):
            self._substep(src, dst, dt, share, s)
            self._slot = dst
        self._token += 1
        self._resident = self._token if self.cfg.requires_grad else -1
        return self._token

    def vjp(self, record: MPMRecord, grad_outputs: dict) -> dict:
        """Vector-Jacobian product of one recorded macro step.

        ``grad_outputs``: "state" dL/d(state after) (keys of ``STATE_KEYS``) and "reactions"
        {source: dL/d(Reactions)} (missing sources: zero). Returns dL/d(state before) under
        "state", "boundaries" {source: dL/d(BoundaryStates)}, this step's share of dL/dE and
        dL/dnu per body, and "impulse" dL/d(impulse) with controls.
        """
        if not self.cfg.requires_grad:
            raise NotImplementedError("MPMEngine.vjp: this engine was built without gradients (requires_grad=False)")
        K, dt = record.substeps, record.dt
        share = 1.0 / K
        self._set_control(record.impulse)
        self._forget()  # a recompute moves the slots away from the forward state
        self._write_boundaries(record.boundaries)  # the step's boundary, for its backward (and recompute)
        if record.token != self._resident:
            self.set_state(record.state)
            self._binned = None  # as the forward's ``advance`` began: the recompute repeats it bit for bit
            for s in range(K):
                self._substep(s, s + 1, dt, share, s)
            self._slot = K
        self._binned = None  # the backward's lists made afresh too, whether or not it recomputed
        self._zero_grad()
        # before the reactions': a source's added mass adds to the end state's adjoint
        self.checkpoints.write(grad_outputs["state"], self._adjoint_fields(), K)
        reaction_grads = grad_outputs.get("reactions") or {}
        for name, source in self.boundaries.items():
            if name in reaction_grads:
                source.seed_reaction_grads(reaction_grads[name])
        for s in reversed(range(K)):
            self._substep_grad(s, dt, share)
        self._resident = -1
        moduli = np.zeros((len(self.bodies), 2), dtype=self.real)
        self._read_moduli_grads(moduli)  # dL/dE and dL/dnu in one read
        out = {
            "state": self.checkpoints.read(self._adjoint_fields(), 0),  # on the device while it fits
            "boundaries": {name: source.state_grads(K) for name, source in self.boundaries.items()},
            "E": moduli[:, 0].astype(np.float64),
            "nu": moduli[:, 1].astype(np.float64),
        }
        if self.control is not None:
            out["impulse"] = self.control.grad.to_numpy()[: self.n_particles].astype(np.float64)
        return out

    def replay(self, start: Mapping, records: list[MPMRecord]) -> list[Mapping]:
        """The state after each of ``records``' steps, recomputed from ``start`` (the state before the
        first) with each step's recorded dt, substeps, impulse and boundaries: the forward's states, bit
        for bit with the serial scatter (to round-off with atomics). Leaves the engine after the last."""
        self.set_state(start)
        after = []
        for r in records:
            self._write_boundaries(r.boundaries)
            self.advance(r.dt, r.substeps, r.impulse)
            after.append(self._snapshot())
        return after

    def _write_boundaries(self, boundaries: dict) -> None:
        for name, source in self.boundaries.items():
            source.write(boundaries[name])

    def _zero_grad(self) -> None:
        # the particle adjoints of each slot are started by its substep's ``_g2p_adjoint``, the grids' by
        # its ``_zero_grid_grad``: only what every substep adds to is zeroed here
        self._zero_moduli_grads()
        if self.control is not None:
            self.control.grad.fill(0)
        for hook in self.grid_hooks + self.particle_hooks:
            hook.zero_grad()
        for source in self.boundaries.values():
            source.zero_grad()

    def _set_control(self, impulse: np.ndarray | None) -> None:
        if self.control is None:
            if impulse is not None and np.any(impulse):
                raise ValueError("this engine was built without controls")
            return
        full = np.zeros((self.n_particles, self.dim)) if impulse is None else impulse
        self._write_vectors(self.control, np.ascontiguousarray(full, dtype=self.real))

    # ------------------------------------------------------------ slots
    def _rotation(self, substeps: int) -> list[tuple[int, int]]:
        """Forward-only (source, destination) slots of each substep: from the current slot into the two
        slots that neither this step nor the last one started from, in turn. The state before the step
        stays for a redo after a CFL violation and for its record's readers; the last step's stays while
        the coupled loop still holds that record, so its view is gone before its slot is overwritten."""
        start = self._slot
        a, b = [k for k in range(self.n_slots) if k not in (start, self._previous_start)][:2]
        return [(start if s == 0 else (a, b)[(s - 1) % 2], (a, b)[s % 2]) for s in range(substeps)]

    def _forget(self, *written: int) -> None:
        """The current state changes and slots ``written`` are about to be overwritten: drop what was
        known of the state, and let the ``SlotState`` views of those slots that are still held read
        their keys first."""
        self._known_state = self._known_health = self._known_energy = None
        self.state_version += 1
        for ref in self._views:
            view = ref()
            if view is not None and view._engine is self and view._slot in written:
                view.detach()

    def _state_fields(self) -> tuple:
        return tuple(getattr(self, k) for k in STATE_KEYS)

    def _adjoint_fields(self) -> tuple:
        return tuple(getattr(self, k).grad for k in STATE_KEYS)

    def read_slot(self, key: str | None, slot: int) -> np.ndarray | dict[str, np.ndarray]:
        """State key ``key`` (of ``STATE_KEYS``) of the particles in ``slot``, float64 on the host; every key
        (a dict) in one launch when ``key`` is None."""
        return self._get_state(self._state_fields(), slot) if key is None else self._get(getattr(self, key), slot)

    # ------------------------------------------------------------ helpers
    def gradient_buffers_allocated(self) -> bool:
        """True when any field carries an allocated adjoint (only with requires_grad)."""
        fields = [self.x, self.v, self.C, self.F, self.E, self.nu, self.grid_mm, self.grid_v]
        if self.control is not None:
            fields.append(self.control)
        return any(adjoint_allocated(f) for f in fields)

    def body_slices(self) -> dict[str, slice]:
        return {b.name: slice(lo, hi) for b, (lo, hi) in zip(self.bodies, self.ranges)}

    def lame(self, b: int) -> tuple[float, float]:
        """Lame parameters (mu, lambda) [Pa] of body b from its current E and nu (``set_parameters``)."""
        from cosim.engines.moduli import lame_parameters

        return lame_parameters(float(self._material["E"][b]), float(self._material["nu"][b]), self.dim)

    def wave_speed(self) -> tuple[float, str]:
        """The fastest elastic P-wave speed [m/s] over the bodies with their current E and nu, and its body."""
        from cosim.engines.moduli import wave_speed

        speeds = [
            wave_speed(float(self._material["E"][b]), float(self._material["nu"][b]), body.density, self.dim)
            for b, body in enumerate(self.bodies)
        ]
        worst = int(np.argmax(speeds))
        return speeds[worst], self.bodies[worst].name

    def viscous_time_step(self) -> tuple[float, str]:
        """The smallest explicit viscous time-step bound [s] over the bodies (inf without viscosity), and its body."""
        from cosim.engines.moduli import viscous_time_step

        bounds = [viscous_time_step(b.density, b.viscosity, self.dx, self.dim) for b in self.bodies]
        worst = int(np.argmin(bounds))
        return bounds[worst], self.bodies[worst].name
