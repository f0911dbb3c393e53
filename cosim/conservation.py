"""The runner's conservation checks: the coupled system's energy may not grow beyond its start plus the
work done on it, and the liquids' volume is tracked.

The system's energy: the MPM's (kinetic, gravity, strain) plus every engine's that declares ``energy``
(``cosim.engines.contract``): a cloth's kinetic, elastic and gravity energy, DART's skeletons that no
action drives (DART's kinetic and potential energy). Contact between two budgeted parts is internal.
Work done on the system, summed every macro step, by what the budget does not hold:
- bodies whose motion is prescribed or driven (kinematic bodies, driven DART skeletons) on the material
  through contact (each MPM coupler's ``external_work``: for a rigid body -sum_k (J_k . v_k + L_k . w_k)
  over the substeps, J, L the reaction on the body, exact for a rigid velocity field) and on a cloth
  (the cloth-rigid couplers': minus the reaction times the body's velocity at the plane point, per frame);
- an engine's own prescribed parts (a cloth's controlled vertices: ``external_work`` of its step);
- the control impulses I on particles of mass m and velocity v: sum I . v + |I|^2 / 2m.
Gravity is inside the energy (its potential), so a falling body does no "work".

The MPM's energies and volumes are the engine's (``MPMEngine.energies``, summed on the device), of its
current state: ``begin_step`` is called before a step, ``end_step`` after every engine stepped.

After every macro step of a rollout that runs from step 0, E(t) > E(0) + W(t) + ``MARGIN`` * scale
stops the run with a ``SimulationError`` naming the body or engine whose energy grew most; scale = E(0)
above its floor (all mass at the domain's lowest point) plus sum |W|. A light body flung by the
material it touches (an unstable exchange) gains energy no work explains and is caught here. Replays from a checkpoint (set_state to
step k > 0) are steps already checked and are skipped. The check reads one small per-body table summed on
the device: one kernel launch for a small scene; for a large one the strain energy's polar decompositions,
a few percent of a step.

The margin, 10% of the scale: what a stable run can show above E(0) + W is bounded, an instability is not.
- MLS-MPM's explicit (symplectic Euler) update keeps a nearby energy exactly; the measured one oscillates
  about it by at most omega dt / 2 of a mode's energy, with omega dt <= pi cfl dx / L for a body's
  vibration modes (L its size; the CFL bound (|v| + c) dt <= cfl dx): 5% for a body 10 cells wide at
  cfl 0.3; the grid-scale modes, up to omega dt = 2 cfl, are damped by the transfers. No drift.
- Under gravity the update loses m g^2 dt^2 / 2 per substep; grid contact and plasticity only dissipate.
- APIC's affine velocity is not in E; it holds at most 4 (dx / L)^2 of a rotation's kinetic energy (4%
  at 10 cells), which it can hand back.
- The work is exact for a rigid body's velocity field and for control impulses (see above); a cloth's
  -sum impulse . v is a one-point rule per substep, O(dt) of |W|, which the scale holds.
Together under 10% of a body's kinetic and elastic energy at 10 cells and cfl 0.3, and the scale holds
that energy and the height above the floor besides.
An instability multiplies its energy at every substep, so it passes any fixed margin within a step or two
of showing: the margin sets the false alarms, not the detection. The shipped scenes stay far below it,
except where material starts within a cell of a rigid body: the forecast contact pushes it out in the
first step (pour_thin_glass's water on the cup's floor reaches half the margin, then decays).
"""

from __future__ import annotations

import itertools

import numpy as np

from cosim.errors import SimulationError

MARGIN = 0.1  # of the scale: the energy a stable run may show above its start plus the work (module docstring)
# a breach in step 0 is most often the start: material within a cell of a rigid body, or inside it, is pushed out
# (water started 0.6 cells inside a ring's wall: the forecast contact's push-out alone is several margins)
FIRST_STEP = (
    "; in a first step it is more often the start: material inside or within a cell of a rigid body is pushed out "
    "(the forecast contact most): start it clear of the bodies"
)


class Conservation:
    """Energy budget and liquid volume of one rollout of an MPM engine (``cosim.engines.mpm``)."""

    def __init__(self, engine, gravity, domain, share: float = MARGIN, others: dict | None = None):
        self.engine = engine
        engine.survey_energies = True  # read every step: summed in the survey's pass (``MPMEngine.energies``)
        self.others = dict(others or {})  # {name: engine declaring "energy"}, in the budget besides the MPM
        self.work = 0.0
        self.excess = None
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.share = share  # inf: measured, never stops a run (a benchmark that counts failures)
        corners = np.array(list(itertools.product(*[(0.0, float(L)) for L in domain])))
        # the lowest potential any particle can have: -g . x at the domain corner furthest along g
        mass = float(engine.mass.sum()) + sum(e.energy_and_mass()[1] for e in self.others.values())
        self.floor = -mass * float((corners @ self.gravity).max())
        self._next = None  # the step expected next; None: inactive until a rollout starts at step 0
        self.liquids = [b.name for b in engine.bodies if b.material == "liquid"]
        self.volume_ratio = (1.0, 1.0)  # (min, max) of the liquids' volume over their initial volume

    def start(self) -> None:
        """A rollout begins from the engine's current state (step 0)."""
        self.initial = self._energies()
        self.E0 = sum(e["total"] for e in self.initial.values())
        self.work = self.work_abs = 0.0
        self.excess = None  # the largest (E - E0 - W) / scale seen (negative: energy dissipated), None before a check
        self.volume0 = self._liquid_volume(self.initial)
        self.volume_ratio = (1.0, 1.0)
        self._next = 0

    def begin_step(self, step_index: int) -> bool:
        """Called before each step, the engine in the state it starts from; whether this step is being accounted."""
        if step_index == 0:
            self.start()
        elif step_index != self._next:
            self._next = None  # a replay from a checkpoint: already checked
        return self._next is not None

    def add_work(self, joules: float) -> None:
        """Work [J] done on the material during the current step."""
        self.work += joules
        self.work_abs += abs(joules)

    def end_step(self, step_index: int) -> None:
        """After step ``step_index`` (0-based), the engine in the state it ended in: the check."""
        if self._next is None:
            return
        self._next = step_index + 1
        now = self._energies()
        self._track_volume(now)
        E = sum(e["total"] for e in now.values())
        scale = max(self.E0 - self.floor, 0.0) + self.work_abs
        if scale <= 0.0:
            return
        excess = (E - self.E0 - self.work) / scale
        self.excess = excess if self.excess is None else max(self.excess, excess)
        if excess > self.share:
            body = max(now, key=lambda n: now[n]["total"] - self.initial[n]["total"])
            if body in self.others:
                gained = f"engine '{body}' gained most ({now[body]['total'] - self.initial[body]['total']:+.3g} J)"
                fix = "a body much lighter than the material pushing it is flung by the exchange (make it heavier)"
            else:
                grown = {k: now[body][k] - self.initial[body][k] for k in ("kinetic", "strain", "gravity")}
                gained = (
                    f"body '{body}' gained most (kinetic {grown['kinetic']:+.3g} J, strain "
                    f"{grown['strain']:+.3g} J, gravity {grown['gravity']:+.3g} J)"
                )
                fix = "lower time.cfl or raise time.substeps, or soften the contact"
            raise SimulationError(
                f"step {step_index}: the energy grew to {E:.4g} J from {self.E0:.4g} J at the start plus "
                f"{self.work:.4g} J of work done on the system; {gained}: the simulation is unstable; {fix}"
                + (FIRST_STEP if step_index == 0 else "")
            )

    def _energies(self) -> dict[str, dict[str, float]]:
        """{MPM body or engine name: {"total", ...}} [J] of the current states."""
        out = self.engine.energies()
        for name, e in self.others.items():
            out[name] = {"total": e.energy_and_mass()[0]}
        return out

    def _liquid_volume(self, energies: dict[str, dict[str, float]]) -> float:
        """[m^3, 2D: m^2] sum V0 det F over the liquids' particles, from ``MPMEngine.energies``."""
        return sum(energies[name]["volume"] for name in self.liquids)

    def _track_volume(self, energies: dict[str, dict[str, float]]) -> None:
        if self.liquids:
            ratio = self._liquid_volume(energies) / self.volume0
            self.volume_ratio = (min(self.volume_ratio[0], ratio), max(self.volume_ratio[1], ratio))
