"""The runner's conservation checks: the MPM's energy may not grow beyond its start plus the work done
on it, and the liquids' volume is tracked.

Work done on the material, summed every macro step:
- each boundary source's contact work (``work(states, reactions)``): for a rigid body
  -sum_k (J_k . v_k + L_k . w_k) over the substeps (J, L the reaction on the body, exact for a rigid
  velocity field); for a cloth -sum impulse . v over its vertices;
- the control impulses I on particles of mass m and velocity v: sum I . v + |I|^2 / 2m.
Gravity is inside the energy (its potential), so a falling body does no "work".

The energies and volumes are the engine's (``MPMEngine.energies``, summed on the device), of its current
state: ``begin_step`` is called before a step, ``end_step`` after it.

Every ``every`` macro steps of a rollout that runs from step 0, E(t) > E(0) + W(t) + ``share`` * scale
stops the run with a ``SimulationError`` naming the body whose energy grew most; scale = E(0) above
its floor (all mass at the domain's lowest point) plus sum |W|, so the check tolerates round-off and
the small energy the particle representation can gain (APIC's affine part is not in E), and catches
instabilities, which grow without bound. Replays from a checkpoint (set_state to step k > 0) are steps
already checked and are skipped.
"""

from __future__ import annotations

import itertools

import numpy as np

from cosim.errors import SimulationError


class Conservation:
    """Energy budget and liquid volume of one rollout of an MPM engine (``cosim.engines.mpm``)."""

    def __init__(self, engine, gravity, domain, every: int = 10, share: float = 0.1):
        self.engine = engine
        self.work = 0.0
        self.excess = None
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.every, self.share = every, share
        corners = np.array(list(itertools.product(*[(0.0, float(L)) for L in domain])))
        # the lowest potential any particle can have: -g . x at the domain corner furthest along g
        self.floor = -float(engine.mass.sum()) * float((corners @ self.gravity).max())
        self._next = None  # the step expected next; None: inactive until a rollout starts at step 0
        self.liquids = [b.name for b in engine.bodies if b.material == "liquid"]
        self.volume_ratio = (1.0, 1.0)  # (min, max) of the liquids' volume over their initial volume

    def start(self) -> None:
        """A rollout begins from the engine's current state (step 0)."""
        self.initial = self.engine.energies()
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
        """After step ``step_index`` (0-based), the engine in the state it ended in: the check every ``every`` steps."""
        if self._next is None:
            return
        self._next = step_index + 1
        if self._next % self.every:
            return
        now = self.engine.energies()
        self._track_volume(now)
        E = sum(e["total"] for e in now.values())
        scale = max(self.E0 - self.floor, 0.0) + self.work_abs
        if scale <= 0.0:
            return
        excess = (E - self.E0 - self.work) / scale
        self.excess = excess if self.excess is None else max(self.excess, excess)
        if excess > self.share:
            body = max(now, key=lambda n: now[n]["total"] - self.initial[n]["total"])
            grown = {k: now[body][k] - self.initial[body][k] for k in ("kinetic", "strain", "gravity")}
            raise SimulationError(
                f"step {step_index}: the energy grew to {E:.4g} J from {self.E0:.4g} J at the start plus "
                f"{self.work:.4g} J of work done on the material; body '{body}' gained most (kinetic "
                f"{grown['kinetic']:+.3g} J, strain {grown['strain']:+.3g} J, gravity {grown['gravity']:+.3g} J): "
                "the simulation is unstable; lower time.cfl or raise time.substeps, or soften the contact"
            )

    def _liquid_volume(self, energies: dict[str, dict[str, float]]) -> float:
        """[m^3, 2D: m^2] sum V0 det F over the liquids' particles, from ``MPMEngine.energies``."""
        return sum(energies[name]["volume"] for name in self.liquids)

    def _track_volume(self, energies: dict[str, dict[str, float]]) -> None:
        if self.liquids:
            ratio = self._liquid_volume(energies) / self.volume0
            self.volume_ratio = (min(self.volume_ratio[0], ratio), max(self.volume_ratio[1], ratio))


def control_work(impulse: np.ndarray, velocity: np.ndarray, mass: np.ndarray) -> float:
    """[J] Kinetic energy impulses ``impulse`` (N, d) [N s] add to particles of velocity (N, d) [m/s] and
    mass (N,) [kg]: I . v + |I|^2 / 2m."""
    return float(np.sum(impulse * velocity) + np.sum(np.sum(impulse * impulse, axis=1) / (2.0 * mass)))
