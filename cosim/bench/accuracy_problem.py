"""One reference problem of ``cosim bench accuracy``: settings, its scene, its run and its error.

A problem is a small scene written at a base grid and refined by
``cosim.scene.accuracy.refine_grid`` (the ``accuracy`` hint's own mechanism), so a ``Setting`` is
(cells per metre, time.cfl, precision, contact model). Its run returns an *observation*
(numbers and short histories, JSON-friendly, with the run's cost); ``error`` compares it with a
closed form, or with the observation of the problem's reference run (2x the finest grid, the
smallest CFL number, float64). Errors are relative (dimensionless). The problems themselves are in
``accuracy_soft``, ``accuracy_coupled`` and ``accuracy_gradient``, listed in ``accuracy_problems``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

CFLS = (0.15, 0.3, 0.6, 0.9)
PRECISIONS = ("float32", "float64")
MODELS = ("grid", "particle", "forecast")


@dataclass(frozen=True)
class Setting:
    """One point of a sweep: grid cells per metre, CFL number, precision, contact model ('' if none)."""

    cells: int
    cfl: float
    precision: str
    contact: str = ""

    def label(self) -> str:
        contact = f", {self.contact}" if self.contact else ""
        return f"{self.cells} cells/m, cfl {self.cfl:g}, {self.precision}{contact}"


class Problem:
    """A reference problem; subclasses give the scene, what is sampled per macro step, and the error."""

    name = ""
    title = ""
    error_measure = ""  # what ``error`` is, in words
    source = ""  # the closed form or the reference it is compared with
    dim = 2
    base_cells = 32  # ``base_scene`` is written for this many cells per metre
    cells: tuple[int, ...] = (32, 64, 128, 256)  # swept
    default = Setting(64, 0.3, "float32")  # the shipped defaults for this kind of scene
    contacts: tuple[str, ...] = ()  # contact models swept (empty: no rigid body)
    closed_form = True  # False: compared with the reference run
    frame_dt = 2e-3  # [s]
    duration = 0.3  # [s]

    # ------------------------------------------------------------ the scene and the sweep
    def base_scene(self) -> dict:
        raise NotImplementedError

    @property
    def steps(self) -> int:
        """Macro steps of a run."""
        return math.ceil(self.duration / self.frame_dt - 1e-9)

    def scene_data(self, setting: Setting) -> dict:
        """The scene of ``setting`` as YAML-like data: the base scene's grid refined to ``setting.cells``
        per metre, then time.cfl, precision, steps, frame_dt and the contact model set."""
        from cosim.scene.accuracy import refine_grid
        from cosim.scene.assignments import apply_assignments

        base = self.base_scene()
        data = refine_grid(base, setting.cells / self.base_cells, key=f"{self.name} setting")
        if _wall(data) != _wall(base):
            raise ValueError(
                f"{self.name} at {setting.cells} cells/m: the walls would move (thickness range 2-16 cells)"
            )
        sets = [f"time.cfl={setting.cfl}", f"precision={setting.precision}", f"steps={self.steps}"]
        sets += [f"time.frame_dt={self.frame_dt}"] + ([f"contact.model={setting.contact}"] if setting.contact else [])
        return apply_assignments({**data, "name": f"accuracy_{self.name}"}, sets)

    def settings(self, quick: bool = False) -> list[Setting]:
        """The sweep: every grid x CFL number at the default precision and contact model, plus the other
        precision and the other contact models at the default CFL number; quick: the coarsest default."""
        d = self.default
        if quick:
            return [Setting(self.cells[0], d.cfl, d.precision, d.contact)]
        out = [Setting(c, cfl, d.precision, d.contact) for c in self.cells for cfl in CFLS]
        out += [Setting(c, d.cfl, p, d.contact) for c in self.cells for p in PRECISIONS if p != d.precision]
        out += [Setting(c, d.cfl, d.precision, m) for c in self.cells for m in self.contacts if m != d.contact]
        return out

    def reference_setting(self, quick: bool = False) -> Setting | None:
        """2x the finest swept grid (quick: 2x the coarsest), the smallest CFL number, float64; None
        when the problem has a closed form."""
        if self.closed_form:
            return None
        return Setting(2 * self.cells[0 if quick else -1], min(CFLS), "float64", self.default.contact)

    # ------------------------------------------------------------ the run
    def build(self, setting: Setting, requires_grad: bool = False):
        """The coupled system of ``setting``'s scene."""
        from cosim.scene import parse_scene
        from cosim.scene.build import build_system

        scene = parse_scene(self.scene_data(setting), origin=f"accuracy {self.name}")
        return build_system(scene, requires_grad=requires_grad)

    def run(self, setting: Setting) -> dict:
        """Run ``setting``; its observation plus ``seconds`` and ``cpu_seconds`` (wall and CPU time of the
        macro steps after the first, which compiles the kernels; the sampling between steps is not
        timed), ``sim_seconds`` (the simulated time of those steps), ``particles`` and ``substeps``."""
        sim = self.build(setting)
        context = self.prepare(sim)
        samples = [self.sample(sim, context)]
        seconds, cpu_seconds, substeps = 0.0, 0.0, 0
        for n in range(sim.steps):
            t0, c0 = time.perf_counter(), time.process_time()
            sim.step()
            if n > 0:
                seconds += time.perf_counter() - t0
                cpu_seconds += time.process_time() - c0
            substeps += sim.last.substeps
            samples.append(self.sample(sim, context))
        out = self.observe(sim, samples)
        out.update(seconds=seconds, cpu_seconds=cpu_seconds, sim_seconds=(sim.steps - 1) * sim.frame_dt)
        out.update(particles=int(sim.mpm.n_particles), substeps=substeps)
        return out

    def prepare(self, sim) -> dict:
        """Change the built system's initial state if the problem needs it; returns what ``sample`` needs."""
        return {}

    def sample(self, sim, context: dict):
        """What is kept of each macro step's state (the first call: the initial state); nothing by default."""

    def observe(self, sim, samples: list) -> dict:
        """The run's observation from its samples and final state."""
        raise NotImplementedError

    def error(self, observation: dict, reference: dict | None) -> float:
        """The relative error of ``observation`` (against ``reference``'s when not a closed form)."""
        raise NotImplementedError


def _wall(data: dict) -> float:
    """[m] The domain walls' thickness of scene data (``refine_grid`` keeps it while it can)."""
    grid, boundary = data["mpm"]["grid"], data["mpm"].get("boundary") or {}
    cells = grid["cells"] if isinstance(grid["cells"], list) else [grid["cells"]]
    return round(boundary.get("thickness", 3) * grid.get("dx", 1.0 / max(cells)), 12)
