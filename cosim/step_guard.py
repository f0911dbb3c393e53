"""The runner's guards around one coupled step (``CoupledSystem.step``): monitors, not part of the exchange.

Per macro step: the substep count from the CFL bound (or a fixed count, checked against the
material's stability bound) and the retry with twice the substeps while a step breaks the bound;
NaN/inf in the material at the substep it appeared; particles leaving the grid; the energy budget of
the whole coupled system (``cosim.conservation``); undriven rigid-body origins and cloth vertices
leaving the grid (engines that declare ``points``); particles through a rigid body
(``cosim.couplers.tunnelling``). Each stops the
run with a ``SimulationError`` naming the step, the body and the quantity, and a fix.
"""

from __future__ import annotations

import warnings

import numpy as np

from cosim.conservation import Conservation
from cosim.engines.contract import declares
from cosim.errors import CouplingWarning, SimulationError

RETRIES = 4  # auto substeps: how often a step is redone with twice the substeps
TUNNEL_SHARE, TUNNEL_MIN = 0.01, 10  # particles through a rigid body in one step that stop the run


class StepGuard:
    """The guards of ``system`` (a ``CoupledSystem``): ``begin_step``, then per exchange ``begin_exchange`` /
    ``substeps`` / ``retry`` / ``after_material`` / ``end_exchange``, once per macro step."""

    def __init__(self, system):
        self.system = system
        budgeted = {name: e for name, e in system.engines.items() if declares(e, "energy")}
        self.conservation = Conservation(system.mpm, system.gravity, system.domain, others=budgeted)
        self.passed_through: dict[str, int] = {}  # "body/rigid body": particles that went through it
        self.tunnel_share = TUNNEL_SHARE  # inf: count only (a benchmark measuring the contact's failures)
        self.max_cfl = 0.0
        self._exchange_warned = False
        self.tunnels = None
        rigid = system.rigid
        if rigid is not None and rigid.sources:  # rigid bodies the MPM sees (none: links it does not)
            from cosim.couplers.tunnelling import TunnelWatch  # Taichi: importing the system needs none

            self.tunnels = TunnelWatch(system.mpm, rigid.sources, 0.25 * system.dx)
        # per engine that declares "points": which start inside the domain (those must stay in it)
        self.watched_points = {
            name: self._inside(e.points()) for name, e in system.engines.items() if declares(e, "points")
        }

    # ------------------------------------------------------------ around the exchange
    def begin_step(self) -> None:
        """Before anything moves in a macro step: the energy budget's start (not in a replay)."""
        self._tracked = self.conservation.begin_step(self.system.step_index)

    def begin_exchange(self) -> None:
        """Before each exchange of the macro step: the rigid poses it starts from."""
        s = self.system
        self._poses = s.rigid.poses() if self.tunnels is not None else None  # where the bodies start the exchange
        if self.tunnels is not None:
            self.tunnels.begin()
        self._attempt, self._cfl = 0, 0.0

    def substeps(self) -> int:
        """K for this step: the fixed count (gradient runs fix it at the start; checked against the
        current E and nu), else the CFL bound over the material's and the boundaries' speeds."""
        s, st = self.system, self.system.stepping
        self._fixed = st.fixed or (st.grad_substeps if st.requires_grad else 0)
        speed = s.mpm.max_speed()
        if self._fixed:
            self._check_fixed_substeps(self._fixed)
        else:
            speed = max(speed, s.boundary_speed())  # a fixed count does not depend on it
        self._speed = speed + float(np.linalg.norm(s.gravity)) * s.exchange_dt
        K = self._fixed or s.auto_substeps(self._speed)
        self._check_limit(K)
        self._check_exchange(K)
        return K

    def _check_exchange(self, K: int) -> None:
        """Warn (once per run) when an exchange takes more substeps than a strong coupling whose bodies carried
        material in the last step is measured stable at (``exchange_limit``): the body jitters on the material.
        The exchanges per frame are chosen at the build from the first frame's substeps; faster motion since
        can need more."""
        s = self.system
        if self._exchange_warned or s.last is None:
            return
        for c in s.mpm_couplers:
            if not declares(c, "exchange_limit") or K <= c.exchange_substeps:
                continue
            carried = s.last.outputs.get("reactions", {}).get(c.source, {}).get("mass")
            if carried is not None and np.any(np.asarray(carried) > 0):
                self._exchange_warned = True
                shorter = s.frame_dt * c.exchange_substeps / K
                warnings.warn(
                    f"step {s.step_index}: {K} MPM substeps in one exchange ({s.exchanges} per {s.frame_dt:.3g} s "
                    f"frame, chosen from the first frame), more than the {c.exchange_substeps} at which coupler "
                    f"'{c.name}' is measured to hold a light body at rest on material (docs/bench/coupling.md, "
                    f"substeps per frame): it may jitter on the material. Lower time.frame_dt to about "
                    f"{shorter:.2g} s (and raise steps to match) so that each exchange takes fewer substeps",
                    CouplingWarning,
                    stacklevel=2,
                )
                return

    def retry(self, health: dict, dt: float, K: int) -> int | None:
        """After the material's K substeps: stop at a NaN/inf; None when the CFL bound held, else the
        substep count to redo the step with (auto substeps), or stop (fixed, or out of retries)."""
        st = self.system.stepping
        self._check_finite(health, K)
        cfl, body = self._worst_cfl(health, dt)
        if cfl <= st.cfl:
            self._cfl = cfl
            return None
        if self._fixed or self._attempt == RETRIES:
            if st.fixed:
                fix = "raise time.substeps or set it to 'auto'"
            elif self._fixed:
                fix = f"gradient runs fix the substeps at the start ({K} here); set time.substeps higher"
            else:
                fix = "the motion is too violent for time.max_substeps"
            raise SimulationError(
                f"step {self.system.step_index}: CFL number {cfl:.3f} > {st.cfl} in body '{body}' "
                f"(max |v| dt / dx with dt = {dt:.3g} s); {fix}"
            )
        self._attempt += 1
        self._check_limit(2 * K)
        return 2 * K

    def after_material(self, mpm_record, boundaries: dict, outputs: dict) -> None:
        """Particles within the grid; the work the boundaries and controls did on the material this step and
        the energy check on the state it ended in (``cosim.conservation``)."""
        s = self.system
        self._check_domain(outputs["health"])
        if self._tracked and s.step_index == 0 and self.tunnels is not None:
            self.tunnels.reset()
            self.passed_through = {}
        if not self._tracked:
            return
        cons = self.conservation
        for c in s.mpm_couplers:  # contact work of bodies outside the budget (prescribed, driven) is external
            per_body = s.mpm.boundaries[c.source].work(boundaries[c.source], outputs["reactions"][c.source])
            cons.add_work(float(np.sum(per_body * ~np.asarray(c.budgeted()))))
        if mpm_record.impulse is not None:
            cons.add_work(s.mpm.control_work())

    def end_exchange(self, engine_records: dict, coupler_records: dict, last: bool = True) -> None:
        """After every engine stepped in an exchange: the work the engines' prescribed parts and the bodies
        outside the budget did on them; after the macro step's ``last`` exchange the energy budget of the
        whole system; their points within the grid, particles through rigid bodies."""
        s = self.system
        if self._tracked:
            cons = self.conservation
            for name, e in s.engines.items():
                if declares(e, "energy"):
                    cons.add_work(e.external_work(engine_records[name]))
                for c in s.engine_couplers[name]:
                    cons.add_work(c.external_work(coupler_records[c.name], s.exchange_dt))
            if last:
                cons.end_step(s.step_index)
        self._check_engine_domain()
        if self.tunnels is not None and self._tracked:  # the bodies have moved too: their poses now end the step
            self._check_tunnelling(self._poses)
        self.max_cfl = max(self.max_cfl, self._cfl)

    # ------------------------------------------------------------ the checks
    def _check_limit(self, K: int) -> None:
        st = self.system.stepping
        if K > st.max_substeps:
            raise SimulationError(
                f"step {self.system.step_index}: the CFL bound needs {K} substeps, more than time.max_substeps = "
                f"{st.max_substeps} (max speed {self._speed:.3g} m/s): the simulation is blowing up or "
                "frame_dt is too long"
            )

    def _check_fixed_substeps(self, K: int) -> None:
        """A fixed substep count was checked against the scene's materials at build; E or nu set since
        (an optimisation, a gradient check) can move the stability bound dx / c past it."""
        s = self.system
        c, body = s.mpm.wave_speed()
        dt = s.exchange_dt / K
        if dt * c > s.dx:
            raise SimulationError(
                f"step {s.step_index}: {K} fixed substeps give dt = {dt:.3g} s, above the stability bound "
                f"dx / c = {s.dx / c:.3g} s of body '{body}' with its current E and nu (wave speed c = {c:.3g} "
                "m/s, set after the build); bound E (optimize) or raise time.substeps"
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
                f"step {self.system.step_index}: body '{body}': non-finite {names[key]} ({key}) in "
                f"{h.non_finite[key]} particles, {where}; the step is unstable: lower time.frame_dt, use more "
                "substeps or a smaller time.cfl, or check the material's E"
            )

    def _worst_cfl(self, health: dict, dt: float) -> tuple[float, str]:
        """The largest CFL number max|v| dt / dx over the bodies and its body."""
        worst, name = 0.0, ""
        for body, h in health.items():
            c = h.speed * dt / self.system.dx
            if c > worst:
                worst, name = c, body
        return worst, name

    def _check_domain(self, health: dict) -> None:
        """Stop when a body has particles within a cell of the grid's faces or beyond."""
        for body, h in health.items():
            if h.outside:
                raise SimulationError(
                    f"step {self.system.step_index}: body '{body}': {h.outside} particles left the grid domain "
                    f"[0, {self.system.domain.tolist()}] m; enable walls (mpm.boundary.type) or enlarge mpm.grid"
                )

    def _inside(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: which world points (n, 3) [m] lie in the grid's box [0, domain] (NaN: outside)."""
        domain = self.system.domain
        p = np.asarray(points, dtype=np.float64)[:, : len(domain)]
        return np.all((p >= 0.0) & (p <= domain), axis=1)

    def _check_engine_domain(self) -> None:
        """Stop when a rigid body's origin or a cloth vertex that started in the grid's box has left it (or is
        no longer finite): nothing downstream would notice, and a run that threw a body away looked fine."""
        s = self.system
        for name, started_inside in self.watched_points.items():
            engine = s.engines[name]
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
                    f"step {s.step_index}: engine '{name}': {engine.point_name(i)} left the grid domain "
                    f"[0, {s.domain.tolist()}] m and {where}{more}; the coupled step is unstable there: a body "
                    "much lighter than the material pushing it flutters under the once-per-frame exchange (make it "
                    "heavier), or check the forces, joints and controls acting on it"
                )

    def _check_tunnelling(self, poses0: list) -> None:
        """Count the particles that went through a rigid body this step, the bodies at ``poses0`` when it
        began (``couplers.tunnelling``), into ``passed_through`` {"body/rigid body": count}; stop when a
        body goes through, i.e. more than ``tunnel_share`` of its particles (at least ``TUNNEL_MIN``) in one
        step: the contact failed."""
        s = self.system
        crossed = self.tunnels.step(poses0, s.rigid.poses())
        for j, rigid_name in enumerate(s.rigid.names):
            for i, (body, sl) in enumerate(s.slices.items()):
                n = int(crossed[i, j])
                if not n:
                    continue
                key = f"{body}/{rigid_name}"
                self.passed_through[key] = self.passed_through.get(key, 0) + n
                if n > max(TUNNEL_MIN, self.tunnel_share * (sl.stop - sl.start)):
                    model = s.scene.contact.model if s.scene is not None else "?"
                    others = " or ".join(m for m in ("forecast", "grid") if m != model)
                    raise SimulationError(
                        f"step {s.step_index}: {n} particles of body '{body}' went through rigid body "
                        f"'{rigid_name}' (contact model '{model}'): the contact cannot stop them at this speed "
                        f"and wall thickness; use contact.model {others}, a thicker wall or a smaller time.cfl"
                        + (", or a larger contact.stiffness" if model == "particle" else "")
                    )
