"""Soft-body reference problems of the accuracy benchmark: a liquid, an elastic and a plastic one.

- ``DamBreak``: a water column collapsing along a tank (2D); its front history against a reference run;
- ``BarVibration``: a free elastic strip in its first longitudinal mode (2D); the period against
  the closed form of the plane-strain bar;
- ``PlasticDrop``: a plasticine cube thrown onto a sticky floor (3D); its final height against a
  reference run.
"""

from __future__ import annotations

import math

import numpy as np

from cosim.bench import accuracy_measures as am
from cosim.bench.accuracy_problem import Problem, Setting


class DamBreak(Problem):
    """A water column (0.15625 m wide, 0.3125 m tall) collapsing along a 1 m tank for 0.3 s.

    Written at 64 cells per metre with 2-cell walls (1/32 m), so that the walls stay put up to the
    reference's 512 cells per metre (16 cells, the most ``mpm.boundary.thickness`` allows).
    """

    name = "dam_break"
    title = "liquid: dam-break front"
    error_measure = "RMS over 0.3 s of the front's difference from the reference's, / the reference front's travel"
    source = "reference run (2x the finest grid, cfl 0.15, float64)"
    base_cells = 64
    cells = (64, 128, 256)
    default = Setting(128, 0.3, "float32")  # dam_break_2d: dx = 1/128 m
    closed_form = False
    frame_dt = 2.5e-3
    duration = 0.3
    wall, width, height = 1 / 32, 0.15625, 0.3125  # [m] the column stands against the left wall, on the floor

    def base_scene(self) -> dict:
        water = {"type": "liquid", "E": 2.0e5, "nu": 0.3, "density": 1000}
        column = {"type": "box", "center": [self.wall + self.width / 2, self.wall + self.height / 2]}
        column["size"] = [self.width, self.height]
        return {
            "dim": 2,
            "mpm": {
                "grid": {"cells": [64, 32], "dx": 1 / 64},  # a 1 m x 0.5 m tank
                "boundary": {"type": "slip", "thickness": 2},
                "bodies": [{"name": "water", "material": water, "shape": column, "hydrostatic": True}],
            },
            "output": {"preview": "none"},
        }

    def sample(self, sim, context: dict):
        return am.front_position(sim.mpm.state()["x"], 0.5 * sim.dx)

    def observe(self, sim, samples: list) -> dict:
        return {"front": [float(f) for f in samples]}

    def error(self, observation: dict, reference: dict | None) -> float:
        ref = np.asarray(reference["front"])
        return am.rms_difference(np.asarray(observation["front"]), ref) / (ref[-1] - ref[0])


class BarVibration(Problem):
    """A free elastic strip (0.625 m x 0.125 m, E 1e5 Pa, nu 0.3, no gravity) started in its first
    longitudinal mode, v_x = v0 cos(pi (X - x0) / L) (``prepare``), for 2.25 periods."""

    name = "elastic_bar"
    title = "elastic: free bar's fundamental period"
    error_measure = "|T - T_exact| / T_exact, T from the zero crossings of the modal displacement"
    source = "closed form: plane-strain bar with lateral inertia (Rayleigh-Love), T = 2 pi / omega"
    length, width, E, nu, density, v0 = 0.625, 0.125, 1.0e5, 0.3, 1000.0, 0.05  # [m], [m], [Pa], -, [kg/m^3], [m/s]
    periods = 2.25  # simulated

    @property
    def omega(self) -> float:
        """[rad/s] The closed form's angular frequency."""
        return am.bar_angular_frequency(self.length, self.width, self.E, self.nu, self.density)

    @property
    def duration(self) -> float:  # type: ignore[override]
        return self.periods * 2 * math.pi / self.omega

    @property
    def x0(self) -> float:
        """[m] The bar's left end."""
        return 0.5 - self.length / 2

    def base_scene(self) -> dict:
        bar = {"type": "box", "center": [0.5, 0.5], "size": [self.length, self.width]}
        material = {"type": "elastic", "E": self.E, "nu": self.nu, "density": self.density}
        return {
            "dim": 2,
            "mpm": {
                "grid": {"cells": 32},
                "boundary": {"type": "none", "thickness": 2},  # no walls; 2 cells keeps refine_grid in range
                "gravity": [0.0, 0.0],
                "bodies": [{"name": "bar", "material": material, "shape": bar}],
            },
            "output": {"preview": "none"},
        }

    def prepare(self, sim) -> dict:
        """Start in the Rayleigh-Love mode: v_x = v0 cos(k X), and the lateral velocity that goes with
        its contraction, v_y = nu_e k v0 (Y - y_c) sin(k X) (without it, 0.6% of the axial velocity
        projects onto lateral motion instead: measured in the modal amplitude). Returns the rest
        positions and masses the modal coordinate projects with."""
        state = sim.state()
        x = state["mpm"]["x"]
        k, nu_e = np.pi / self.length, self.nu / (1.0 - self.nu)
        v = np.zeros_like(x)
        v[:, 0] = self.v0 * np.cos(k * (x[:, 0] - self.x0))
        v[:, 1] = nu_e * k * self.v0 * (x[:, 1] - 0.5) * np.sin(k * (x[:, 0] - self.x0))
        state["mpm"]["v"] = v
        sim.set_state(state)
        return {"rest": x.copy(), "mass": sim.mpm.mass}

    def modal(self, x: np.ndarray, context: dict) -> float:
        """[m] The modal displacement q of positions ``x``."""
        return am.modal_coordinate(x, context["rest"], context["mass"], self.x0, self.length)

    def sample(self, sim, context: dict):
        return self.modal(sim.mpm.state()["x"], context)

    def observe(self, sim, samples: list) -> dict:
        t = np.arange(len(samples)) * sim.frame_dt
        return {"period": am.oscillation_period(t, np.asarray(samples))}

    def error(self, observation: dict, reference: dict | None) -> float:
        return am.relative_error(observation["period"], 2 * math.pi / self.omega)


class PlasticDrop(Problem):
    """A plasticine cube (0.25 m, E 5e4 Pa, von Mises yield 2000 Pa) thrown down at 1.5 m/s from
    1/16 m above a sticky floor (3D), 0.3 s: it squashes to about half its height and stays."""

    name = "plastic_drop"
    title = "plastic: squashed cube's final height (3D)"
    error_measure = "|H - H_ref| / H_ref, H = sqrt(12 Var(y) + h^2) averaged over the last 0.05 s"
    source = "reference run (2x the finest grid, cfl 0.15, float64)"
    dim = 3
    base_cells = 16
    cells = (16, 24, 32, 48)
    default = Setting(32, 0.3, "float32")  # plastic_squash_3d: 32^3
    closed_form = False
    frame_dt = 4e-3
    duration = 0.3
    average = 0.05  # [s] the final height is averaged over the end of the run

    def base_scene(self) -> dict:
        dough = {"type": "plastic", "E": 5.0e4, "nu": 0.3, "density": 1000, "yield_stress": 2000}
        cube = {"type": "box", "center": [0.5, 0.3125, 0.5], "size": [0.25, 0.25, 0.25]}
        return {
            "dim": 3,
            "mpm": {
                "grid": {"cells": 16},
                "boundary": {"type": "sticky", "thickness": 2},  # the floor at 1/8 m
                "bodies": [{"name": "dough", "material": dough, "shape": cube, "velocity": [0.0, -1.5, 0.0]}],
            },
            "output": {"preview": "none"},
        }

    def sample(self, sim, context: dict):
        return am.effective_height(sim.mpm.state()["x"][:, 1], 0.5 * sim.dx)

    def observe(self, sim, samples: list) -> dict:
        last = max(1, round(self.average / sim.frame_dt))
        return {"height": float(np.mean(samples[-last:]))}

    def error(self, observation: dict, reference: dict | None) -> float:
        return am.relative_error(observation["height"], reference["height"])
