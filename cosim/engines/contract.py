"""The engine and coupler contracts: what crosses between engines, in which frame and unit.

Every engine adapter (``cosim/engines``) and every coupler (``cosim/couplers``) conforms
to one of the protocols below, and the coupled loop (``cosim.system``) knows them only
through these methods, never by type. Units are SI throughout: [m], [s], [kg], [N],
[N s] (impulse), [N m] (torque), [rad]. World frame: y is up (2D: the xy-plane).

Engines
-------
An engine holds its state between macro steps. ``state()`` returns it as a dict of
named NumPy arrays (float64) and ``set_state(s)`` restores it so that the next step is
bit for bit the same (the cloth: to the last bits of its final Newton step, whose linear solve
is preconditioned by an earlier step's factorisation, dropped by a restore; a rollout from a
restored state repeats bit for bit); ``step(inputs) -> (outputs, record)`` advances one macro step
(the frame ``frame_dt``) and ``vjp(record, grad_outputs) -> grad_inputs`` is the
vector-Jacobian product of that recorded step with respect to its state and every
input. Nothing is passed any other way: no hidden seeds, no call-order conventions.
``parameters()`` declares the engine's differentiable parameters (``Parameter``: an
initial-state array, a material parameter read with ``material()`` and set with
``set_parameters()``, or a per-step input); a hook an engine cannot honour raises
``NotImplementedError`` naming it.

The soft-body engine (MPM, ``cosim.engines.mpm.MPMEngine``, name ``"mpm"``):
    state     x (N, d) [m], v (N, d) [m/s], C (N, d, d) [1/s] APIC affine velocity,
              F (N, d, d) deformation gradient; particles in body order.
    inputs    dt [s] substep, substeps K, impulse (N, d) [N s] per particle over the
              macro step (controls) or None, boundaries {source: BoundaryStates}.
    outputs   state (after the step; without gradients a read-only mapping read from the
              device on first access, ``cosim.engines.slot_state``), reactions {source:
              Reactions}, health {body: BodyHealth} (max |v| [m/s], non-finite and
              out-of-grid particle counts, the first bad substep: ``cosim.engines.mpm_watch``).
    vjp       grad_outputs {state, reactions} -> {state, impulse, boundaries, E, nu}:
              the reaction adjoints are an argument, the boundary adjoints a result.

A manipulator engine (DART ``RigidEngine`` "dart", ``KinematicEngine`` "kinematic", ``ClothEngine`` by its name):
    inputs    action (A,) (layout per engine; None: zeros), forces (engine-specific
              external forces, e.g. DART: (bodies, 6) wrenches [torque; force] in the
              world frame, torque about the body origin [N m; N]), added_mass (a coupling's
              added mass, the cloth: (V,) [kg] in its inertia; None: none); a cloth also
              boundaries {source: ContactPlanes} (rigid bodies it meets).
    outputs   state (after the step); a cloth with boundaries: reactions {source: (c, 3) [N]}.
    vjp       {state, reactions} -> {state, action, forces} (and added_mass, boundaries where
              it takes them).

Boundary states and reactions (the MPM's side of a coupling)
--------------------------------------------------------------
A boundary source (``cosim.couplers.boundary``) is what the contact models see of a
manipulator: for a point x at substep s it answers the signed distance (negative
inside), the outward normal and the contact-point velocity, and it takes back the
reaction. Each source defines the layout of its states; the rigid sources (kinematic
bodies, DART links) share this one, per-substep states of their m bodies, substeps
k = 0..K-1 of the step:

    BoundaryStates  pos (K, m, d) [m] body origin, rot (K, m, d, d) body to world,
                    vel (K, m, d) [m/s] origin velocity, omega (K, m, 1|3) [rad/s]
                    world-frame angular velocity; a body point moves with
                    v_c = vel + omega x (x - pos).
    Reactions       impulse (K, m, d) [N s] = minus the momentum the contact gave the
                    material in substep k; angular_impulse (K, m, 1|3) [N m s] its
                    moment about pos[k].

Couplers
--------
Every interaction between two engines is one coupler. A coupler joins an engine (``engine``)
to the engine whose step meets it as a boundary (``medium``: "mpm", or a cloth meeting rigid
bodies) through one boundary source (``source``). Forward, per macro step: ``boundary(dt, K)``
turns the engine's current state into the medium's boundary input (the MPM: BoundaryStates for
the K substeps; a cloth: ``ContactPlanes``); after the medium's step, ``forces(record, reactions)``
turns that source's reactions into the engine's load {"forces", "added_mass"} (each optional;
``add_loads`` sums several couplers'). A medium other than the MPM steps before the engines it
loads; its step takes "boundaries" {source: input} and returns "reactions" {source: output}, and
its vjp takes "reactions" adjoints and returns "boundaries" adjoints, as the MPM's. Reverse:
``forces_vjp(record, grad_load, grad_state) -> (grad_reactions, carry, grad_state_before)``
before the MPM's vjp (``grad_state``: dL/d(the coupler's own carried state after the step),
None for couplers without one), ``boundary_vjp(record, grad_boundary, carry) ->
grad_engine_state`` after it (``carry``: what the force path contributes to the engine
state, e.g. torque arms). A coupler's carried state takes part in the chain rule: the
system's vjp reads its adjoint under "couplers" and returns the one before the step.

The loop (``cosim.system.CoupledSystem``), as in the paper's chain rule::

    for c in couplers of the MPM:   boundaries[c.source] = c.boundary(dt, K)
    s_M', reactions    = mpm.step(s_M, boundaries, impulse)
    for c in couplers of the MPM:   forces[c.engine] += c.forces(reactions[c.source])
    for e in engines:    the same exchange with the couplers whose medium is e, around
                         s_e', reactions_e = e.step(s_e, action_e, forces[e], boundaries_e)

    reverse: engines in reverse order, each vjp (with the reaction adjoints of the couplers
    it is the medium of) -> dL/ds_e, dL/da_e, dL/dF_e and boundary adjoints, which those
    couplers' boundary_vjp add to their engines' dL/ds; each MPM coupler's forces_vjp ->
    reaction adjoints; one MPM vjp with all of them -> dL/ds_M and boundary adjoints; each
    MPM coupler's boundary_vjp -> added to dL/ds_e.

Optional capabilities
---------------------
Beyond its protocol, an engine, coupler or boundary source may offer more; it says so in
its ``capabilities`` (a frozenset of the names in ``CAPABILITIES``) and the loop, the
objective and the contact models ask ``declares(obj, name)``, never ``hasattr``. What a
contact model needs to know of a boundary it reads from the source's ``ContactTraits``
(its parameters, not its kind).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

State = dict[str, np.ndarray]
BoundaryStates = dict[str, np.ndarray]  # pos, rot, vel, omega: (K, m, ...)
Reactions = dict[str, np.ndarray]  # impulse, angular_impulse: (K, m, ...)
BOUNDARY_KEYS = ("pos", "rot", "vel", "omega")
REACTION_KEYS = ("impulse", "angular_impulse")


@dataclass(frozen=True)
class Parameter:
    """A differentiable parameter an engine declares.

    ``kind``: "state" (an initial-state array, ``key`` its state key), "material" (an
    engine parameter set with ``set_parameters``, ``key`` its name) or "input" (a
    per-macro-step input, ``key`` its input name: impulse, action). ``scale``: its
    natural size (finite-difference and optimiser steps are fractions of it).
    """

    name: str
    engine: str
    kind: str
    key: str
    scale: float


@runtime_checkable
class Engine(Protocol):
    """One engine adapter (see the module docstring for inputs and outputs)."""

    name: str

    def state(self) -> State: ...

    def set_state(self, state: State) -> None: ...

    def step(self, inputs: dict[str, Any]) -> tuple[dict[str, Any], Any]: ...

    def vjp(self, record: Any, grad_outputs: dict[str, Any]) -> dict[str, Any]: ...

    def parameters(self) -> list[Parameter]: ...


@runtime_checkable
class Coupler(Protocol):
    """Joins engine ``engine`` to the engine ``medium`` (the MPM, a cloth) through boundary source ``source``."""

    name: str
    engine: str
    medium: str
    source: str

    def boundary(self, dt: float, substeps: int) -> tuple[BoundaryStates, Any]: ...

    def forces(self, record: Any, reactions: Reactions) -> dict[str, Any]: ...

    def forces_vjp(self, record: Any, grad_load: dict[str, Any], grad_state: Any = None) -> tuple[Any, Any, Any]: ...

    def boundary_vjp(self, record: Any, grad_boundary: BoundaryStates, carry: Any) -> State:
        """dL/d(the engine's state before the step) through the boundary; a coupler with a carried state may
        complete, in ``carry``, the dict of dL/d(its state before the step) that ``forces_vjp`` returned."""
        ...


CAPABILITIES = {
    # engines
    "points": "points() -> (n, 3) [m]: world points that must stay in the MPM's domain (a rigid body's origin, "
    "a cloth vertex); point_name(i) names one. The runner stops a run when one that started inside leaves it",
    "surface_speed": "surface_speed(frame_dt) -> [m/s]: the fastest surface the MPM meets over the next frame, "
    "which the substep count keeps under the CFL bound",
    "material": "material() -> {key: 0-d array} and set_parameters(values): material parameters",
    "material_grads": "a material_grads flag: its vjp skips material gradients while False",
    "mesh": "mesh (a ClothMesh) and state x, v (V, 3): a triangle mesh whose vertices losses and previews read",
    "energy": "energy_and_mass() -> (energy [J], mass [kg]) of its parts no action drives (kinetic, gravity, elastic), "
    "external_work(record) -> [J] the work its own prescribed parts did in that step, and for rigid engines "
    "passive_bodies() -> (bodies,) bool: it is in the runner's energy budget (``cosim.conservation``); an MPM "
    "coupler's budgeted() says which of its bodies are, a coupler whose medium is an engine reports "
    "external_work(record, frame_dt) of the bodies that are not",
    "body_states": "body_names, body_states() (per body position, rotation, velocities), flat_state(), dofs and "
    "body_states_vjp(...): rigid bodies a coupler pushes with wrenches (forces (bodies, 6)) and differentiates",
    # couplers
    "carried_state": "state() / set_state(s): a state of its own carried from step to step (the cloth's "
    "penetration tracing), part of the system's state under 'couplers'",
    "exchange_limit": "exchange_substeps: the most MPM substeps per exchange at which its light bodies are measured "
    "to rest stably on material (`cosim bench coupling`); a macro step makes as many exchanges as keep within it, and "
    "the runner warns when one in which they carried material takes more",
    # boundary sources
    "substep_hooks": "before_substep(src, s) and before_substep_grad(src, s) around each MPM substep",
    "added_mass": "its reactions carry 'mass', the material that follows it over a frame (a cloth: (V,) [kg] per "
    "vertex; rigid bodies: (n, k, k) per body on its twist), from the contact model set as its engagement "
    "(engagement(source, d, K, p), ti.func; its engine and offset); its reaction adjoint takes dL/d(mass); its "
    "boundary states take 'handover', the body's last velocity change, which handover(s, x, p) (ti.func) hands the "
    "engaged material (cosim.couplers.handover), and its state grads return dL/d(handover)",
    "node_queries": "a queries_nodes flag: while True it answers about grid nodes (p = -1), which the grid model asks",
}


def traits_of(source: Any) -> ContactTraits:
    """The ``ContactTraits`` a boundary source declares (``contact_traits``; a solid body's by default)."""
    return getattr(source, "contact_traits", SOLID)


def declares(obj: Any, capability: str) -> bool:
    """Whether ``obj`` (an engine, coupler or boundary source) declares ``capability`` (see ``CAPABILITIES``)."""
    if capability not in CAPABILITIES:
        raise KeyError(f"unknown capability {capability!r}; known: {sorted(CAPABILITIES)}")
    return capability in getattr(obj, "capabilities", frozenset())


@dataclass(frozen=True)
class ContactTraits:
    """What a contact model needs to know of a boundary source, declared by the source (``contact_traits``).

    ``offset``: hold particles at their radius from the surface (False: at the surface itself, a sheet
    without volume, whose contact keeps the paper's form). ``blend_all``: the forecast model's blended
    BC_p for every particle (a light sheet coupled explicitly; without the blend's damping towel_squash's
    towel moved 0.11 m in one frame). ``liquid_support``: liquid near it may be held by its own edge (the
    grid model's fill; a two-sided sheet says nothing of which side material is on). ``forecast_alpha``:
    the forecast model's gradient step this source needs at least (0.8 for a sheet: at 0.3, 46 of
    make_taco's filling particles crossed the tortilla), None for the model's default. ``grid_band`` [m]:
    the gap the grid model keeps from it for all material (a two-sided sheet), None for the model's band.
    """

    offset: bool = True
    blend_all: bool = False
    liquid_support: bool = True
    forecast_alpha: float | None = None
    grid_band: float | None = None


SOLID = ContactTraits()


def add_loads(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Sum of two engine loads ({"forces", "added_mass"}, each optional): what couplers hand one engine."""
    out = dict(a or {})
    for key, value in b.items():
        out[key] = value if out.get(key) is None else out[key] + value
    return out


def add_states(a: State | None, b: State | None) -> State | None:
    """Sum of two state-shaped gradients (None is zero)."""
    if a is None:
        return b
    if b is None:
        return a
    return {k: a[k] + b[k] for k in a}
