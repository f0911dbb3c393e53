"""The coupled system: the MPM and any number of manipulator engines joined by couplers.

``CoupledSystem`` runs the paper's loop over engines and couplers it knows only
through their contracts (``cosim.engines.contract``)::

    for c in MPM couplers:   boundaries[c.source] = c.boundary(dt, K)
    s_M', reactions        = mpm.step(s_M, boundaries, impulse)
    for c in MPM couplers:   loads[c.engine] += c.forces(reactions[c.source])
    for e in engines:        (in order) the same exchange with the couplers whose medium is e
                             (a cloth meeting rigid bodies), around s_e' = e.step(s_e, action_e, loads[e])

once per macro step, or as many times as ``Stepping.exchanges`` says (a light body's coupler rests it
only up to so many substeps between two exchanges, ``cosim.scene.start.exchanges_per_frame``), each
engine then stepping ``exchange_dt`` = frame_dt / exchanges; and its reverse (``vjp``). The runner's
guards (``cosim.step_guard``) sit around the exchange: they pick the substep count K from the CFL
bound (or check a fixed one), redo a step that broke it, and stop with a ``SimulationError``
naming the step, the body and the quantity as soon as a step produces NaN/inf, violates the CFL
bound, leaves the grid, breaks the energy budget or lets material through a rigid body; the MPM
engine checks its particles on the device and hands over per-body counts (``MPMEngine.health``),
not its state.
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

from cosim.engines.contract import add_loads, add_states, declares
from cosim.step_guard import StepGuard
from cosim.step_record import FrameRecord, StepRecord


@dataclass
class Stepping:
    """Time stepping: frame [s], CFL bound, substep limits; ``fixed`` 0 means auto substeps."""

    frame_dt: float
    cfl: float
    max_substeps: int
    fixed: int
    grad_substeps: int
    requires_grad: bool
    exchanges: int = 1  # exchanges per macro step: each engine steps frame_dt / exchanges between two


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
        self.couplers = list(couplers)  # all of them; the MPM's and each engine's by ``medium``:
        self.mpm_couplers = [c for c in self.couplers if c.medium == "mpm"]
        self.engine_couplers = {name: [c for c in self.couplers if c.medium == name] for name in self.engines}
        unknown = {c.medium for c in self.couplers} - {"mpm", *self.engines}
        if unknown:
            raise ValueError(f"couplers name media that are not engines of the system: {sorted(unknown)}")
        self.stepping = stepping
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.domain = np.asarray(domain, dtype=np.float64)  # [m] upper corner of the grid
        self.steps = steps
        self.controls = list(controls or [])
        self.plans = dict(plans or {})
        self.slices = mpm.body_slices()
        self.frame_dt = stepping.frame_dt  # [s] a macro step: actions, losses and outputs count these
        self.exchanges = stepping.exchanges
        self.exchange_dt = stepping.frame_dt / stepping.exchanges  # [s] what each engine steps between exchanges
        self.dx = mpm.dx
        self.grad_substeps = stepping.grad_substeps
        self.ctrl_index = (
            np.concatenate([c.indices for c in self.controls]) if self.controls else np.zeros(0, dtype=int)
        )
        self.step_index = 0
        self.last = None  # the record of the last step
        self.timings: dict[str, float] | None = None  # seconds per part when a benchmark sets a dict
        self.scene = scene  # the scene it was built from, if any (the default loss and reports read it)
        self.rigid = rigid  # cosim.couplers.rigid_view.RigidBodies: names, poses, counts of the rigid bodies
        self.initial = self.state()
        self.guard = StepGuard(self)  # the runner's checks around each step (cosim.step_guard)

    # the guard's measurements, read by the runner's metrics and the benchmarks
    @property
    def conservation(self):
        return self.guard.conservation

    @property
    def passed_through(self) -> dict[str, int]:
        return self.guard.passed_through

    @property
    def max_cfl(self) -> float:
        return self.guard.max_cfl

    @property
    def tunnel_share(self) -> float:
        return self.guard.tunnel_share

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
        self.guard.max_cfl = 0.0

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
    def step(
        self, impulse: np.ndarray | None = None, actions: dict[str, np.ndarray] | None = None
    ) -> StepRecord | FrameRecord:
        """One macro step: ``exchanges`` exchanges (one unless a light body's coupler needs more, ``Stepping``),
        each the couplers' boundaries, the MPM's K substeps, the couplers' forces and every engine's step, inside
        the runner's guards (``cosim.step_guard``). ``impulse`` (N, d) [N s] (shared evenly by the exchanges);
        ``actions`` {engine: this step's action} (default: the scene's sequences). Returns the ``StepRecord``
        (a ``FrameRecord`` of them with several exchanges)."""
        self.guard.begin_step()
        share = impulse if impulse is None or self.exchanges == 1 else impulse / self.exchanges
        subs = [self._exchange(m, share, actions) for m in range(self.exchanges)]
        self.step_index += 1
        self.last = subs[0] if len(subs) == 1 else FrameRecord(subs)
        return self.last

    def _exchange(self, m: int, impulse: np.ndarray | None, actions: dict | None) -> StepRecord:
        """Exchange m of the macro step: boundaries, the MPM's substeps (redone with more while they break the
        CFL bound), reactions, every engine's step of ``exchange_dt``."""
        guard, t0 = self.guard, self.step_index * self.frame_dt + m * self.exchange_dt
        guard.begin_exchange()
        K = guard.substeps()
        while True:  # the guard doubles K while a step breaks the CFL bound (auto substeps)
            dt = self.exchange_dt / K
            with self._timed("couplers"):
                exchange = {c.name: c.boundary(dt, K) for c in self.mpm_couplers}  # engine states -> boundaries
            boundaries = {c.source: exchange[c.name][0] for c in self.mpm_couplers}
            with self._timed("mpm"):
                inputs = {"dt": dt, "substeps": K, "impulse": impulse, "boundaries": boundaries}
                outputs, mpm_record = self.mpm.step(inputs)
            retry = guard.retry(outputs["health"], dt, K)
            if retry is None:
                break
            self.mpm.set_state(mpm_record.state)
            K = retry
        guard.after_material(mpm_record, boundaries, outputs)
        coupler_records = {name: record for name, (_states, record) in exchange.items()}
        with self._timed("couplers"):  # reactions -> each engine's load (forces, added mass)
            loads = self._loads(coupler_records, outputs["reactions"])
        engine_records = self._step_engines(loads, actions, coupler_records)
        guard.end_exchange(engine_records, coupler_records, last=m == self.exchanges - 1)
        return StepRecord(t0, mpm_record, engine_records, coupler_records, {"reactions": outputs["reactions"]})

    def _loads(self, coupler_records: dict, reactions: dict) -> dict[str, dict]:
        """{engine: the sum of its MPM couplers' loads ({"forces", "added_mass"})} from the MPM's reactions."""
        loads: dict[str, dict] = {}
        for c in self.mpm_couplers:
            loads[c.engine] = add_loads(loads.get(c.engine), c.forces(coupler_records[c.name], reactions[c.source]))
        return loads

    def _step_engines(self, loads: dict[str, dict], actions: dict | None, coupler_records: dict) -> dict[str, Any]:
        """Every manipulator engine's step in order, each with its action, its load and the boundaries of
        the couplers it is the medium of, whose reactions then load their engines (which step later)."""
        records, stepped = {}, set()
        for name, engine in self.engines.items():
            act = actions[name] if actions is not None and name in actions else self.action(name, self.step_index)
            couplers = self.engine_couplers[name]
            with self._timed("couplers"):
                exchange = {c.name: c.boundary(self.exchange_dt, 1) for c in couplers}
            inputs = {"action": act, **loads.get(name, {})}
            if couplers:
                inputs["boundaries"] = {c.source: exchange[c.name][0] for c in couplers}
            with self._timed(name):
                out, records[name] = engine.step(inputs)
            stepped.add(name)
            for c in couplers:
                coupler_records[c.name] = exchange[c.name][1]
                load = c.forces(coupler_records[c.name], out["reactions"][c.source])
                if load and c.engine in stepped:
                    raise RuntimeError(f"coupler '{c.name}' loads engine '{c.engine}', which steps before '{name}'")
                loads[c.engine] = add_loads(loads.get(c.engine), load)
        return records

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
        subs = [sub for r in records for sub in r.exchanges]
        after = self.mpm.replay(subs[0].mpm.state, [r.mpm for r in subs[:-1]])
        for record, state in zip(subs[1:], after):
            record.keep_checkpoint(state)

    def vjp(self, record: StepRecord | FrameRecord, grad: dict[str, dict[str, np.ndarray]]) -> dict:
        """Vector-Jacobian product of one recorded macro step: its exchanges' (``_exchange_vjp``) from the last
        to the first, their action and material gradients summed, the impulse's averaged (each exchange got
        its share)."""
        if isinstance(record, StepRecord):
            return self._exchange_vjp(record, grad)
        outs = []
        for sub in reversed(record.exchanges):
            outs.append(self._exchange_vjp(sub, grad))
            grad = outs[-1]["state"]
        impulses = [o["impulse"] for o in outs if o.get("impulse") is not None]
        return {
            "state": grad,
            "action": _summed([o["action"] for o in outs]),
            "impulse": sum(impulses) / len(outs) if impulses else None,
            "material": {
                name: _summed([o["material"].get(name, {}) for o in outs])
                for name in {n for o in outs for n in o["material"]}
            },
        }

    def _exchange_vjp(self, record: StepRecord, grad: dict[str, dict[str, np.ndarray]]) -> dict:
        """Vector-Jacobian product of one recorded exchange (the paper's backward equations).

        ``grad``: dL/d(state after) per engine name. The manipulators in reverse order: each vjp gives
        dL/ds_e (own dynamics), dL/da_e and dL/dF_e, and, for an engine that is a coupler's medium (a
        cloth meeting rigid bodies), takes that coupler's reaction adjoints (its ``forces_vjp`` of the
        later engine's dL/dF) and returns the boundary adjoints, which its ``boundary_vjp`` adds to the
        later engine's dL/ds. Then each MPM coupler's ``forces_vjp`` turns dL/dF into reaction adjoints;
        one MPM vjp, given them all, returns dL/ds_M (direct and force paths) and the boundary
        adjoints; each MPM coupler's ``boundary_vjp`` adds the boundary path to dL/ds_e.
        Returns {"state": per engine, "action": per engine, "impulse", "material": per engine
        {parameter key: this step's share}} (an engine's vjp reports its own under "material").
        """
        state_grads, action_grads, force_grads, material_grads = {}, {}, {}, {}
        reaction_grads, carries, carried_grads = {}, {}, {}
        after = grad.get("couplers") or {}  # dL/d(a coupler's own state after the step)

        def loads_vjp(c) -> None:  # dL/d(c's load on its engine) -> dL/d(reactions of c's source)
            reaction_grads[c.source], carries[c.name], carried_grads[c.name] = c.forces_vjp(
                record.couplers[c.name], force_grads.get(c.engine, {}), after.get(c.name)
            )

        for name in reversed(list(self.engines)):  # later engines first: a medium's loads feed later engines
            couplers = self.engine_couplers[name]
            for c in couplers:
                loads_vjp(c)
            given = {c.source: reaction_grads[c.source] for c in couplers if reaction_grads[c.source] is not None}
            out = self.engines[name].vjp(record.engines[name], {"state": grad[name], "reactions": given})
            state_grads[name], action_grads[name] = add_states(state_grads.get(name), out["state"]), out["action"]
            force_grads[name] = {"forces": out["forces"], "added_mass": out.get("added_mass")}  # dL/d(its load)
            if out.get("material"):
                material_grads[name] = out["material"]
            for c in couplers:
                g = c.boundary_vjp(record.couplers[c.name], out["boundaries"][c.source], carries[c.name])
                state_grads[c.engine] = add_states(state_grads.get(c.engine), g)
        for c in self.mpm_couplers:
            loads_vjp(c)
        mpm_grads = {c.source: reaction_grads[c.source] for c in self.mpm_couplers}
        mpm_grads = {k: v for k, v in mpm_grads.items() if v is not None}
        mpm = self.mpm.vjp(record.mpm, {"state": grad["mpm"], "reactions": mpm_grads})
        for c in self.mpm_couplers:
            g = c.boundary_vjp(record.couplers[c.name], mpm["boundaries"][c.source], carries[c.name])
            state_grads[c.engine] = add_states(state_grads[c.engine], g)
        carried_grads = {name: g for name, g in carried_grads.items() if g is not None}
        return {
            "state": {"mpm": mpm["state"], **state_grads, **({"couplers": carried_grads} if carried_grads else {})},
            "action": action_grads,
            "impulse": mpm.get("impulse"),
            "material": {"mpm": {"E": mpm["E"], "nu": mpm["nu"]}, **material_grads},
        }

    # ------------------------------------------------------------ time stepping and checks
    def auto_substeps(self, speed: float) -> int:
        """Substeps per exchange so that (|v| + c) dt / dx <= cfl, c the fastest elastic wave, and dt stays
        under the explicit viscous bound rho dx^2 / (2 d eta) of the most viscous liquid."""
        bound = min(self.stepping.cfl * self.dx / (speed + self.mpm.wave_speed()[0]), self.mpm.viscous_time_step()[0])
        return max(1, math.ceil(self.exchange_dt / bound - 1e-9))

    def boundary_speed(self) -> float:
        """[m/s] The fastest boundary surface (rigid bodies, cloth vertices) over the next exchange: the
        substep count keeps it under the CFL fraction of a cell per substep, as it does the particles."""
        speeds = [self.rigid.surface_speed(self.exchange_dt)] if self.rigid is not None else []
        speeds += [e.surface_speed(self.exchange_dt) for e in self.engines.values() if declares(e, "surface_speed")]
        return max(speeds, default=0.0)

    def _timed(self, key: str):
        return _Stopwatch(self.timings, key)


def _summed(parts: list[dict]) -> dict:
    """{key: the sum of the parts' values} over the keys any part has (None values skipped; None if all are)."""
    out = {}
    for part in parts:
        for key, value in part.items():
            if value is not None:
                out[key] = value if out.get(key) is None else out[key] + value
            else:
                out.setdefault(key, None)
    return out


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
