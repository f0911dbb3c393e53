"""The coupled system: the MPM and any number of manipulator engines joined by couplers.

``CoupledSystem`` runs the paper's loop over engines and couplers it knows only
through their contracts (``cosim.engines.contract``)::

    for c in couplers:   boundaries[c.source] = c.boundary(dt, K)
    s_M', reactions    = mpm.step(s_M, boundaries, impulse)
    for c in couplers:   forces[c.engine] += c.forces(reactions[c.source])
    for e in engines:    s_e' = e.step(s_e, action_e, forces[e])   (in order; an engine's output
                         "reactions" {later engine: forces} adds to that engine's forces)

and its reverse (``vjp``; engine-to-engine reactions, a cloth's contact on rigid links, are
not differentiated). It picks the substep count K from the CFL bound (or checks a
fixed one) and stops with a ``SimulationError`` naming the step, the body and the
quantity (and for NaN/inf the substep) as soon as a step produces NaN/inf, violates the CFL
bound or leaves the grid; the MPM engine checks its particles on the device and hands over
per-body counts (``MPMEngine.health``), not its state.
``rollout`` is the one loop behind ``cosim run``, the objective, gradcheck, optimize and
the benchmarks. Scenes assemble a system with ``cosim.scene.build_system``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from cosim.conservation import Conservation, control_work
from cosim.engines.contract import add_states, declares
from cosim.errors import SimulationError
from cosim.step_record import StepRecord

RETRIES = 4  # auto substeps: how often a step is redone with twice the substeps
TUNNEL_SHARE, TUNNEL_MIN = 0.01, 10  # particles through a rigid body in one step that stop the run


@dataclass
class Stepping:
    """Time stepping: frame [s], CFL bound, substep limits; ``fixed`` 0 means auto substeps."""

    frame_dt: float
    cfl: float
    max_substeps: int
    fixed: int
    grad_substeps: int
    requires_grad: bool


@dataclass
class Control:
    """Particles driven by impulses: ``indices`` into the engine's particles."""

    body: str
    indices: np.ndarray
    initial: np.ndarray  # (d,) [N s] per particle per macro step


@dataclass
class ActionPlan:
    """A manipulator engine's action sequence: ``sequence`` (segments, action size), each held ``hold`` steps."""

    sequence: np.ndarray
    hold: int
    bounds: tuple[np.ndarray, np.ndarray] | None = None  # per-entry (lower, upper), for optimisers
    scale: np.ndarray | None = None  # (action size,) each entry's natural size, for optimisers
    project: Any = None  # sequence -> the nearest allowed sequence (e.g. ReachProjection), for optimisers

    def segment(self, n: int, segments: int) -> int:
        """Which of ``segments`` held actions macro step n uses (the last one after the sequence)."""
        return min(n // self.hold, segments - 1)


class CoupledSystem:
    """The MPM, the manipulator engines (in stepping order) and their couplers."""

    def __init__(
        self,
        mpm,
        engines: list,
        couplers: list,
        stepping: Stepping,
        gravity,
        domain: np.ndarray,
        steps: int,
        controls: list[Control] | None = None,
        plans: dict[str, ActionPlan] | None = None,
        scene=None,
        rigid=None,
    ):
        self.mpm = mpm
        self.engines = {e.name: e for e in engines}
        self.couplers = list(couplers)
        self.stepping = stepping
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.domain = np.asarray(domain, dtype=np.float64)  # [m] upper corner of the grid
        self.steps = steps
        self.controls = list(controls or [])
        self.plans = dict(plans or {})
        self.slices = mpm.body_slices()
        self.frame_dt = stepping.frame_dt
        self.dx = mpm.dx
        self.grad_substeps = stepping.grad_substeps
        self.ctrl_index = (
            np.concatenate([c.indices for c in self.controls]) if self.controls else np.zeros(0, dtype=int)
        )
        self.step_index = 0
        self.max_cfl = 0.0
        self.last = None  # the record of the last step
        self.timings: dict[str, float] | None = None  # seconds per part when a benchmark sets a dict
        self.scene = scene  # the scene it was built from, if any (the default loss and reports read it)
        self.rigid = rigid  # cosim.couplers.rigid_view.RigidBodies: names, poses, counts of the rigid bodies
        self.initial = self.state()
        self.conservation = Conservation(mpm, self.gravity, self.domain)
        self.passed_through: dict[str, int] = {}  # "body/rigid body": particles that went through it
        watched = rigid is not None and rigid.sources  # rigid bodies the MPM sees (none: links it does not)
        self.tunnels = None
        if watched:
            from cosim.couplers.tunnelling import TunnelWatch  # Taichi: importing the system (ActionPlan) needs none

            self.tunnels = TunnelWatch(mpm, rigid.sources, 0.25 * self.dx)
        self.tunnel_share = TUNNEL_SHARE  # inf: count only (a benchmark measuring the contact's failures)
        # per engine that declares "points": which of them start inside the domain (those must stay in it)
        self.watched_points = {n: self._inside(e.points()) for n, e in self.engines.items() if declares(e, "points")}

    # ------------------------------------------------------------ state of every engine
    def state(self) -> dict[str, dict[str, np.ndarray]]:
        """{engine name: its state}, the MPM under "mpm"; couplers that carry a discrete state of
        their own (the cloth's penetration tracing) add it under "couplers" {name: state}."""
        out = {"mpm": self.mpm.state(), **{name: e.state() for name, e in self.engines.items()}}
        carried = {c.name: c.state() for c in self.couplers if declares(c, "carried_state")}
        if carried:
            out["couplers"] = carried
        return out

    def set_state(self, state: dict[str, dict[str, np.ndarray]], step_index: int = 0) -> None:
        self.mpm.set_state(state["mpm"])
        for name, e in self.engines.items():
            e.set_state(state[name])
        for c in self.couplers:
            if declares(c, "carried_state"):
                c.set_state(state["couplers"][c.name])
        self.step_index = step_index

    def reset(self) -> None:
        """Back to the initial state of every engine."""
        self.set_state(self.initial)
        self.max_cfl = 0.0

    # ------------------------------------------------------------ inputs
    def default_impulses(self) -> np.ndarray | None:
        """(steps, controlled particles, d) [N s]: the scene's control impulses, controls concatenated."""
        if not self.controls:
            return None
        per_control = [np.broadcast_to(c.initial, (self.steps, len(c.indices), len(c.initial))) for c in self.controls]
        return np.concatenate(per_control, axis=1).copy()

    def impulse_field(self, impulse: np.ndarray | None) -> np.ndarray | None:
        """Per-particle impulses (N, d) of one macro step from the controlled particles' (n_ctrl, d)."""
        if impulse is None:
            return None
        full = np.zeros((self.mpm.n_particles, self.mpm.dim))
        np.add.at(full, self.ctrl_index, impulse)
        return full

    def action(self, name: str, n: int, actions: dict[str, np.ndarray] | None = None) -> np.ndarray | None:
        """Engine ``name``'s action in macro step n (default: the scene's sequence)."""
        plan = self.plans.get(name)
        if plan is None:
            return None
        seq = plan.sequence if actions is None or name not in actions else actions[name]
        return seq[plan.segment(n, len(seq))]

    # ------------------------------------------------------------ forward
    def step(self, impulse: np.ndarray | None = None, actions: dict[str, np.ndarray] | None = None) -> StepRecord:
        """One macro step with checks: couplers' boundaries, the MPM's K substeps, couplers' forces,
        every engine's step. ``impulse`` (N, d) [N s]; ``actions`` {engine: this step's action}
        (default: the scene's sequences)."""
        st = self.stepping
        t0 = self.step_index * self.frame_dt
        tracked = self.conservation.begin_step(self.step_index)  # not a replay (reads the state it starts from)
        fixed = st.fixed or (st.grad_substeps if st.requires_grad else 0)
        speed = self.mpm.max_speed()
        if fixed:
            self._check_fixed_substeps(fixed)
        else:
            speed = max(speed, self.boundary_speed())  # a fixed count does not depend on it
        speed += float(np.linalg.norm(self.gravity)) * self.frame_dt
        K = fixed or self.auto_substeps(speed)
        poses = self.rigid.poses() if self.tunnels is not None else None  # where the bodies start the step
        if self.tunnels is not None:
            self.tunnels.begin()
        for attempt in range(RETRIES + 1):
            if K > st.max_substeps:
                raise SimulationError(
                    f"step {self.step_index}: the CFL bound needs {K} substeps, more than time.max_substeps = "
                    f"{st.max_substeps} (max speed {speed:.3g} m/s): the simulation is blowing up or "
                    "frame_dt is too long"
                )
            dt = self.frame_dt / K
            boundaries, coupler_records = {}, {}
            with self._timed("couplers"):
                for c in self.couplers:
                    boundaries[c.source], coupler_records[c.name] = c.boundary(dt, K)
            with self._timed("mpm"):
                outputs, mpm_record = self.mpm.step(
                    {"dt": dt, "substeps": K, "impulse": impulse, "boundaries": boundaries}
                )
            health = outputs["health"]
            self._check_finite(health, K)
            cfl, body = self._cfl(health, dt)
            if cfl <= st.cfl:
                break
            if fixed or attempt == RETRIES:
                if st.fixed:
                    fix = "raise time.substeps or set it to 'auto'"
                elif fixed:
                    fix = f"gradient runs fix the substeps at the start ({K} here); set time.substeps higher"
                else:
                    fix = "the motion is too violent for time.max_substeps"
                raise SimulationError(
                    f"step {self.step_index}: CFL number {cfl:.3f} > {st.cfl} in body '{body}' "
                    f"(max |v| dt / dx with dt = {dt:.3g} s); {fix}"
                )
            self.mpm.set_state(mpm_record.state)
            K *= 2
        self._check_domain(health)
        if tracked and self.step_index == 0 and self.tunnels is not None:
            self.tunnels.reset()
            self.passed_through = {}
        if tracked:
            self._account_energy(mpm_record, boundaries, outputs["reactions"])
        forces: dict[str, Any] = {}
        with self._timed("couplers"):
            for c in self.couplers:
                f = c.forces(coupler_records[c.name], outputs["reactions"][c.source])
                if f is not None:
                    forces[c.engine] = f if forces.get(c.engine) is None else forces[c.engine] + f
        engine_records, stepped = {}, set()
        for name, engine in self.engines.items():
            act = actions[name] if actions is not None and name in actions else self.action(name, self.step_index)
            with self._timed(name):
                engine_out, engine_records[name] = engine.step({"action": act, "forces": forces.get(name)})
            stepped.add(name)
            for target, f in (engine_out.get("reactions") or {}).items():  # e.g. a cloth pressing on DART links
                if target in stepped:
                    raise RuntimeError(f"engine '{name}' hands forces to '{target}', which steps before it")
                forces[target] = f if forces.get(target) is None else forces[target] + f
        self._check_engine_domain()
        if self.tunnels is not None and tracked:  # the bodies have moved too: their poses now end the step
            self._check_tunnelling(poses)
        self.max_cfl = max(self.max_cfl, cfl)
        self.step_index += 1
        self.last = StepRecord(t0, mpm_record, engine_records, coupler_records, {"reactions": outputs["reactions"]})
        return self.last

    def rollout(
        self,
        impulses: np.ndarray | None = None,
        actions: dict[str, np.ndarray] | None = None,
        tape=None,
        on_step: Callable[[int], None] | None = None,
    ) -> None:
        """All macro steps from the current state: ``impulses`` (steps, n_ctrl, d) [N s] (default the
        scene's), ``actions`` {engine: (segments, action size)} (default the scene's sequences).
        ``tape`` (``cosim.adjoint.tape.Tape``) records every step; ``on_step(n)`` is called with the
        state of macro step n in the engines (n = 0: the start)."""
        impulses = self.default_impulses() if impulses is None else impulses
        if on_step is not None:
            on_step(0)
        for n in range(self.steps):
            imp = self.impulse_field(None if impulses is None else impulses[n])
            step_actions = {name: self.action(name, n, actions) for name in self.plans}
            record = self.step(imp, step_actions)
            if tape is not None:
                tape.push(record)
            if on_step is not None:
                on_step(n + 1)

    # ------------------------------------------------------------ reverse
    def restore_checkpoints(self, records: list[StepRecord]) -> None:
        """Recompute the MPM checkpoints of ``records[1:]`` from that of ``records[0]`` by replaying the MPM
        with the steps' recorded boundaries and impulses (the manipulators need no replay: their records
        hold their states). The tape's ``checkpoint_every`` > 1 relies on it."""
        after = self.mpm.replay(records[0].mpm.state, [r.mpm for r in records[:-1]])
        for record, state in zip(records[1:], after):
            record.keep_checkpoint(state)

    def vjp(self, record: StepRecord, grad: dict[str, dict[str, np.ndarray]]) -> dict:
        """Vector-Jacobian product of one recorded macro step (the paper's backward equations).

        ``grad``: dL/d(state after) per engine name. Each manipulator's vjp gives dL/ds_e (own
        dynamics), dL/da_e and dL/dF_e; each coupler's ``forces_vjp`` turns dL/dF into reaction
        adjoints; one MPM vjp, given them all, returns dL/ds_M (direct and force paths) and the
        boundary adjoints; each coupler's ``boundary_vjp`` adds the boundary path to dL/ds_e.
        Returns {"state": per engine, "action": per engine, "impulse", "material": per engine
        {parameter key: this step's share}} (an engine's vjp reports its own under "material").
        """
        state_grads, action_grads, force_grads, material_grads = {}, {}, {}, {}
        for name in reversed(list(self.engines)):
            out = self.engines[name].vjp(record.engines[name], {"state": grad[name]})
            state_grads[name], action_grads[name], force_grads[name] = out["state"], out["action"], out["forces"]
            if out.get("material"):
                material_grads[name] = out["material"]
        reaction_grads, carries = {}, {}
        for c in self.couplers:
            g_forces = force_grads.get(c.engine)
            reaction_grads[c.source], carries[c.name] = c.forces_vjp(record.couplers[c.name], g_forces)
        reaction_grads = {k: v for k, v in reaction_grads.items() if v is not None}
        mpm = self.mpm.vjp(record.mpm, {"state": grad["mpm"], "reactions": reaction_grads})
        for c in self.couplers:
            g = c.boundary_vjp(record.couplers[c.name], mpm["boundaries"][c.source], carries[c.name])
            state_grads[c.engine] = add_states(state_grads[c.engine], g)
        return {
            "state": {"mpm": mpm["state"], **state_grads},
            "action": action_grads,
            "impulse": mpm.get("impulse"),
            "material": {"mpm": {"E": mpm["E"], "nu": mpm["nu"]}, **material_grads},
        }

    # ------------------------------------------------------------ time stepping and checks
    def auto_substeps(self, speed: float) -> int:
        """Substeps so that (|v| + c) dt / dx <= cfl, c the fastest elastic wave, and dt stays under the
        explicit viscous bound rho dx^2 / (2 d eta) of the most viscous liquid."""
        bound = min(self.stepping.cfl * self.dx / (speed + self.mpm.wave_speed()[0]), self.mpm.viscous_time_step()[0])
        return max(1, math.ceil(self.frame_dt / bound - 1e-9))

    def boundary_speed(self) -> float:
        """[m/s] The fastest boundary surface (rigid bodies, cloth vertices) over the next frame: the
        substep count keeps it under the CFL fraction of a cell per substep, as it does the particles."""
        speeds = [self.rigid.surface_speed(self.frame_dt)] if self.rigid is not None else []
        speeds += [e.surface_speed(self.frame_dt) for e in self.engines.values() if declares(e, "surface_speed")]
        return max(speeds, default=0.0)

    def _check_fixed_substeps(self, K: int) -> None:
        """A fixed substep count was checked against the scene's materials at build; E or nu set since
        (an optimisation, a gradient check) can move the stability bound dx / c past it."""
        c, body = self.mpm.wave_speed()
        dt = self.frame_dt / K
        if dt * c > self.dx:
            raise SimulationError(
                f"step {self.step_index}: {K} fixed substeps give dt = {dt:.3g} s, above the stability bound "
                f"dx / c = {self.dx / c:.3g} s of body '{body}' with its current E and nu (wave speed c = {c:.3g} "
                "m/s, set after the build); bound E (optimize) or raise time.substeps"
            )

    def _timed(self, key: str):
        return _Stopwatch(self.timings, key)

    def _account_energy(self, record, boundaries: dict, reactions: dict) -> None:
        """The work the boundaries and controls did on the material this step, and the energy check on
        the state it ended in, the engine's current one (``cosim.conservation``)."""
        cons = self.conservation
        for name, states in boundaries.items():
            cons.add_work(self.mpm.boundaries[name].work(states, reactions[name]))
        if record.impulse is not None:
            cons.add_work(control_work(record.impulse, record.state["v"], self.mpm.mass))
        cons.end_step(self.step_index)

    def _check_tunnelling(self, poses0: list) -> None:
        """Count the particles that went through a rigid body this step, the bodies at ``poses0`` when it
        began (``couplers.tunnelling``), into ``self.passed_through`` {"body/rigid body": count}; stop when a
        body goes through, i.e. more than ``TUNNEL_SHARE`` of its particles (at least ``TUNNEL_MIN``) in one
        step: the contact failed."""
        crossed = self.tunnels.step(poses0, self.rigid.poses())
        for j, rigid_name in enumerate(self.rigid.names):
            for i, (body, sl) in enumerate(self.slices.items()):
                n = int(crossed[i, j])
                if not n:
                    continue
                key = f"{body}/{rigid_name}"
                self.passed_through[key] = self.passed_through.get(key, 0) + n
                if n > max(TUNNEL_MIN, self.tunnel_share * (sl.stop - sl.start)):
                    model = self.scene.contact.model if self.scene is not None else "?"
                    others = " or ".join(m for m in ("forecast", "grid") if m != model)
                    raise SimulationError(
                        f"step {self.step_index}: {n} particles of body '{body}' went through rigid body "
                        f"'{rigid_name}' (contact model '{model}'): the contact cannot stop them at this speed "
                        f"and wall thickness; use contact.model {others}, a thicker wall or a smaller time.cfl"
                        + (", or a larger contact.stiffness" if model == "particle" else "")
                    )

    def _check_finite(self, health: dict, K: int) -> None:
        """Stop at the first body (in body order) whose particles hold a NaN or inf (``MPMEngine.health``),
        naming the quantity (the first of v, x, F, C with one) and the substep of K it appeared in."""
        names = {"x": "position", "v": "velocity", "F": "deformation gradient", "C": "affine velocity"}
        for body, h in health.items():
            key = next((k for k in ("v", "x", "F", "C") if h.non_finite[k]), None)
            if key is None:
                continue
            first = K - 1 if h.first_bad is None else h.first_bad  # None: no G2P saw it (mpm_watch); the last substep
            where = "in the state the step started from" if first < 0 else f"first in substep {first} (0-based) of {K}"
            raise SimulationError(
                f"step {self.step_index}: body '{body}': non-finite {names[key]} ({key}) in "
                f"{h.non_finite[key]} particles, {where}; the step is unstable: lower time.frame_dt, use more "
                "substeps or a smaller time.cfl, or check the material's E"
            )

    def _cfl(self, health: dict, dt: float) -> tuple[float, str]:
        """The largest CFL number max|v| dt / dx over the bodies and its body."""
        worst, name = 0.0, ""
        for body, h in health.items():
            c = h.speed * dt / self.dx
            if c > worst:
                worst, name = c, body
        return worst, name

    def _inside(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: which world points (n, 3) [m] lie in the grid's box [0, domain] (NaN: outside)."""
        p = np.asarray(points, dtype=np.float64)[:, : len(self.domain)]
        return np.all((p >= 0.0) & (p <= self.domain), axis=1)

    def _check_engine_domain(self) -> None:
        """Stop when a rigid body's origin or a cloth vertex that started in the grid's box has left it (or is
        no longer finite): nothing downstream would notice, and a run that threw a body away looked fine."""
        for name, started_inside in self.watched_points.items():
            engine = self.engines[name]
            points = engine.points()
            gone = np.flatnonzero(started_inside & ~self._inside(points))
            if len(gone):
                i = int(gone[0])
                where = (
                    "is not finite"
                    if not np.all(np.isfinite(points[i]))
                    else f"is at {np.round(points[i], 4).tolist()} m"
                )
                more = f" ({len(gone) - 1} more points too)" if len(gone) > 1 else ""
                raise SimulationError(
                    f"step {self.step_index}: engine '{name}': {engine.point_name(i)} left the grid domain "
                    f"[0, {self.domain.tolist()}] m and {where}{more}; the coupled step is unstable there: a body "
                    "much lighter than the material pushing it flutters under the once-per-frame exchange (make it "
                    "heavier), or check the forces, joints and controls acting on it"
                )

    def _check_domain(self, health: dict) -> None:
        """Stop when a body has particles within a cell of the grid's faces or beyond."""
        for body, h in health.items():
            if h.outside:
                raise SimulationError(
                    f"step {self.step_index}: body '{body}': {h.outside} particles left the grid domain "
                    f"[0, {self.domain.tolist()}] m; enable walls (mpm.boundary.type) or enlarge mpm.grid"
                )


class _Stopwatch:
    """Adds the wall time of a ``with`` block to ``timings[key]`` (nothing when timings is None)."""

    def __init__(self, timings: dict[str, float] | None, key: str):
        self.timings, self.key = timings, key

    def __enter__(self):
        if self.timings is not None:
            self.t = time.perf_counter()

    def __exit__(self, *exc):
        if self.timings is not None:
            self.timings[self.key] = self.timings.get(self.key, 0.0) + time.perf_counter() - self.t
