"""Reference problems of the accuracy benchmark where MPM material meets a rigid body (2D).

- ``FloatingBox``: a DART free box afloat on water; its submerged fraction against Archimedes;
- ``RestingBlock``: an elastic block resting on a static rigid support; its centre-of-mass height
  against the closed form of a block compressed by its own weight (how far each contact model lets
  it sink in, or holds it off).

Both sweep the contact model (``contact.model``: grid, particle, forecast).
"""

from __future__ import annotations

import numpy as np

from cosim.bench import accuracy_measures as am
from cosim.bench.accuracy_problem import MODELS, Problem, Setting


class FloatingBox(Problem):
    """A free box (0.25 m x 0.125 m, density 500) afloat on water (density 1000) in a 0.875 m tank.

    It starts at rest in a cavity of the water at the draft Archimedes gives and goes wherever the
    coupled model's own balance is. A damper on its joint (no force at rest; about 0.6 of critical
    damping of the heave, added mass included) settles that motion, and the water's viscosity
    (30 Pa s: no effect at rest) calms the sloshing the first settling stirs, so the surface is
    still enough to read within a second.
    """

    name = "buoyancy"
    title = "rigid + liquid: floating box's draft"
    error_measure = "|f - rho_box / rho_water| / (rho_box / rho_water), f the submerged fraction over the last 0.5 s"
    source = "closed form: Archimedes, submerged fraction = rho_box / rho_water = 0.5"
    contacts = MODELS
    default = Setting(64, 0.3, "float32", "grid")  # 2D coupled scenes (pull_door, shake_container): 64 cells
    frame_dt = 4e-3
    duration = 1.0
    average = 0.5  # [s]
    size, density, water, damper = (0.25, 0.125), 500.0, 1000.0, 400.0  # [m], [kg/m^3], [kg/m^3], [N s/m]
    floor, surface, left, right = 0.0625, 0.25, 0.0625, 0.9375  # [m] the tank's walls (2 cells at 32) and water

    def base_scene(self) -> dict:
        liquid = {"type": "liquid", "E": 2.0e5, "nu": 0.3, "density": self.water, "viscosity": 30.0}
        w, h = self.size
        bottom = self.surface - self.density / self.water * h
        lo, hi = 0.5 - w / 2, 0.5 + w / 2
        parts = {  # the water beside and below the box: (x range, y range)
            "water_left": ((self.left, lo), (self.floor, self.surface)),
            "water_right": ((hi, self.right), (self.floor, self.surface)),
            "water_below": ((lo, hi), (self.floor, bottom)),
        }
        bodies = [
            {
                "name": name,
                "material": liquid,
                "shape": {"type": "box", "center": [(x0 + x1) / 2, (y0 + y1) / 2], "size": [x1 - x0, y1 - y0]},
                "hydrostatic": True,
            }
            for name, ((x0, x1), (y0, y1)) in parts.items()
        ]
        link = {"name": "box", "shape": {"type": "box", "size": [w, h]}, "density": self.density}
        link["joint"] = {"type": "free", "position": [0.5, bottom + h / 2], "damping": self.damper}
        return {
            "dim": 2,
            "mpm": {
                "grid": {"cells": [32, 16], "dx": 1 / 32},
                "boundary": {"type": "slip", "thickness": 2},
                "bodies": bodies,
            },
            "articulated": {"skeletons": [{"name": "float", "links": [link]}]},
            "contact": {"model": "grid"},
            "output": {"preview": "none"},
        }

    def sample(self, sim, context: dict):
        center = sim.rigid.poses()[0][0]
        x = sim.mpm.state()["x"]
        return float(center[1]), am.surface_level(x, 0.5 * sim.dx, float(center[0]), 0.6 * self.size[0])

    def observe(self, sim, samples: list) -> dict:
        y, surface = am.hann_mean(samples[-max(1, round(self.average / sim.frame_dt)) :])
        inside = sum(sim.rigid.particles_inside(sim.mpm.state()["x"]).values())
        return {"fraction": am.submerged_fraction(surface, y, self.size[1]), "inside": inside}

    def error(self, observation: dict, reference: dict | None) -> float:
        return am.relative_error(observation["fraction"], self.density / self.water)


class RestingBlock(Problem):
    """An elastic block (0.1875 m square, E 1e5 Pa, nu 0.3) released touching a static rigid support
    (a kinematic box, frictionless) under gravity; 0.4 s."""

    name = "contact"
    title = "contact: block resting on a rigid support"
    error_measure = "|y_com - y_exact| / H, centre-of-mass height over the last 0.2 s (Hann-weighted mean)"
    source = "closed form: y = top + H/2 - rho g H^2 / (3 E'), E' = E / (1 - nu^2) (plane strain, free sides)"
    contacts = MODELS
    default = Setting(64, 0.3, "float32", "grid")
    duration = 0.4
    average = 0.2  # [s]
    top, side, E, nu, density = 0.3125, 0.1875, 1.0e5, 0.3, 1000.0  # [m], [m], [Pa], -, [kg/m^3]

    def base_scene(self) -> dict:
        block = {"type": "box", "center": [0.5, self.top + self.side / 2], "size": [self.side, self.side]}
        material = {"type": "elastic", "E": self.E, "nu": self.nu, "density": self.density}
        support = {"name": "support", "shape": {"type": "box", "size": [0.5, 0.125]}}
        support["position"] = [0.5, self.top - 0.0625]
        return {
            "dim": 2,
            "mpm": {
                "grid": {"cells": 32},
                "boundary": {"type": "slip", "thickness": 2},
                "bodies": [{"name": "block", "material": material, "shape": block}],
            },
            "rigid": {"bodies": [support]},
            "contact": {"model": "grid"},
            "output": {"preview": "none"},
        }

    def sample(self, sim, context: dict):
        return float(np.average(sim.mpm.state()["x"][:, 1], weights=sim.mpm.mass))

    def observe(self, sim, samples: list) -> dict:
        """The mean centre-of-mass height, and at the end the particles inside the support and the
        deepest one's depth [m] (negative: the gap of the lowest particle to the surface)."""
        x = sim.mpm.state()["x"]
        p, R = sim.rigid.poses()[0]
        depth = -sim.rigid.grids[0].sample((x - p) @ R)[0]
        com = am.hann_mean(samples[-max(1, round(self.average / sim.frame_dt)) :])
        return {"com": com, "inside": int(np.sum(depth > 0)), "depth": float(depth.max())}

    def error(self, observation: dict, reference: dict | None) -> float:
        exact = am.resting_com_height(self.top, self.side, self.E, self.nu, self.density, 9.81)
        return abs(observation["com"] - exact) / self.side
