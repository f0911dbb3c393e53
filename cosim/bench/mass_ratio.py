"""`cosim bench coupling --sweep`: a light body resting on heavy material, across mass ratios.

The light body is a cloth sheet or a DART free plate (2D: a planar joint) lying on an elastic
block of density 1000 kg/m^3 that rests on the domain's floor; r = block density x dx / the body's
areal density [kg/m^2] (the material one cell deep against the body). Per ratio, float64, forecast
contact with friction:

- amplification: the body's velocity perturbed by 1e-4 m/s (vertical) at frame ``perturb_at``;
  the per-frame growth of the difference between the two rollouts, geometric mean over the frames
  after it until it settles (<= 1: perturbations die);
- late rms: the body's rms velocity relative to the material under it over the last quarter of
  the frames [m/s] (at rest: jitter of the exchange);
- rest height: the body's mean height over the same frames against the closed form, the
  block's top compressed by the body's weight ((rho g h^2 / 2 + w h) / E' with E' the
  oedometric modulus, w the body's weight per area) plus half the body's thickness.
"""

from __future__ import annotations

import numpy as np

RATIOS = (0.1, 0.5, 1.0, 5.0, 25.0, 100.0)
DENSITY = 1000.0  # [kg/m^3] the block
E, NU = 2.0e5, 0.3  # [Pa] the block: its own weight squeezes it by about 1 %
CELLS = 32
BLOCK = (0.5, 0.25)  # [m] width, height; on the floor at the domain's boundary layer
PLATE = (0.4, 0.02)  # [m] width, thickness
GRAVITY = 9.81
FLOOR = 2.75  # [cells] the block's bottom: its lowest particles (a quarter cell up) on the slip wall at 3 cells


def plate_scene(ratio: float, frames: int) -> dict:
    """The 2D plate-on-block scene at ``ratio`` (a scene dict for ``parse_scene``)."""
    dx = 1.0 / CELLS
    floor = FLOOR * dx  # the slip boundary's layer
    top = floor + BLOCK[1]
    areal = DENSITY * dx / ratio
    plate_density = areal / PLATE[1]
    link = {
        "name": "plate",
        "shape": {"type": "box", "size": list(PLATE)},
        "density": plate_density,
        "joint": {"type": "free", "position": [0.5, top + 0.5 * PLATE[1]]},
    }
    return {
        "name": f"plate_r{ratio:g}",
        "dim": 2,
        "precision": "float64",
        "steps": frames,
        "time": {"frame_dt": 2e-3, "substeps": "auto"},
        "mpm": {
            "grid": {"cells": CELLS},
            "boundary": {"type": "slip"},
            "bodies": [
                {
                    "name": "block",
                    "material": {"type": "elastic", "E": E, "nu": NU, "density": DENSITY},
                    "shape": {"type": "box", "center": [0.5, floor + 0.5 * BLOCK[1]], "size": list(BLOCK)},
                }
            ],
        },
        "articulated": {"skeletons": [{"name": "plate", "links": [link]}]},
        "contact": {"model": "forecast", "friction": 0.3},
    }


def rest_height(ratio: float) -> float:
    """[m] The plate's centre at rest: the block's top compressed under its own weight and the plate's,
    and half the plate (the forecast model holds the plate a particle radius above the top particles'
    centres: on the block's surface)."""
    dx = 1.0 / CELLS
    floor, h = FLOOR * dx, BLOCK[1]
    w = DENSITY * dx / ratio * GRAVITY  # [Pa] the plate's weight per area
    oedometric = E * (1 - NU) / ((1 + NU) * (1 - 2 * NU))
    squeeze = (DENSITY * GRAVITY * h * h / 2 + w * h) / oedometric
    return floor + h - squeeze + 0.5 * PLATE[1]


def settle(sim, frames: int) -> None:
    """Bring the block and the body to rest in their weights (dynamic relaxation): ``frames`` coupled steps;
    whenever the material's kinetic energy has passed a peak, every velocity is set to zero. The couplers'
    carried states start afresh after."""
    peak = 0.0
    for _ in range(frames):
        sim.step()
        state = sim.state()
        energy = float(np.sum(state["mpm"]["v"] ** 2))
        if energy >= peak:
            peak = energy
            continue
        peak = 0.0
        for key in ("v", "C"):
            state["mpm"][key] = np.zeros_like(state["mpm"][key])
        for name, engine_state in state.items():
            if name not in ("mpm", "couplers"):
                for key in ("qd", "v"):
                    if key in engine_state:
                        engine_state[key] = np.zeros_like(engine_state[key])
        sim.set_state(state)
    state = sim.state()
    if "couplers" in state:
        state["couplers"] = {name: None for name in state["couplers"]}
    sim.set_state(state)


def run_plate(ratio: float, frames: int = 200, perturb_at: int = 100, delta: float = 1e-4, rest: int = 100) -> dict:
    """The plate rows of the sweep (see the module docstring): two rollouts after ``rest`` settling frames,
    one perturbed."""
    from cosim.errors import SimulationError
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    sim = build_system(parse_scene(plate_scene(ratio, frames)))
    dart = sim.engines["dart"]
    try:
        settle(sim, rest)
    except SimulationError as err:
        return {"body": "plate", "ratio": ratio, "outcome": f"settling: {err}", "rest_height": rest_height(ratio)}
    start = sim.state()
    x0 = start["mpm"]["x"]
    beneath = np.abs(x0[:, 0] - 0.5) < 0.5 * PLATE[0]
    top_layer = np.flatnonzero(beneath & (x0[:, 1] > x0[beneath, 1].max() - 1.0 / CELLS))
    frame_dt = sim.frame_dt

    def rollout(kick: float):
        """(plate vy, plate y, the top layer's vertical velocity (its mean height's rate), outcome)."""
        sim.set_state(start)
        vy, y, under = [], [], []
        level = x0[top_layer, 1].mean()
        try:
            for n in range(frames):
                if n == perturb_at and kick:
                    s = dart.state()
                    s["qd"] = s["qd"].copy()
                    s["qd"][1] += kick
                    dart.set_state(s)
                sim.step()
                b = dart.body_states()
                vy.append(b["linear_velocity"][0, 1])
                y.append(b["position"][0, 1])
                now = sim.mpm.state()["x"][top_layer, 1].mean()
                under.append((now - level) / frame_dt)
                level = now
        except SimulationError as err:
            return np.array(vy), np.array(y), np.array(under), str(err)
        return np.array(vy), np.array(y), np.array(under), "ok"

    vy, y, under, outcome = rollout(0.0)
    out = {"body": "plate", "ratio": ratio, "outcome": outcome, "rest_height": rest_height(ratio)}
    if outcome != "ok":
        return out
    vy2, _, _, outcome2 = rollout(delta)
    d = np.abs(vy2[perturb_at:] - vy[perturb_at:])
    growth = d[1:] / np.maximum(d[:-1], 1e-300)
    live = d[:-1] > 1e-9 * delta  # the differences above round-off
    late = slice(3 * frames // 4, frames)
    out.update(
        amplification=float(np.exp(np.mean(np.log(np.maximum(growth[live], 1e-300))))) if live.any() else 0.0,
        late_rms=float(np.sqrt(np.mean((vy[late] - under[late]) ** 2))),
        height=float(np.mean(y[late])),
        outcome=outcome if outcome2 == "ok" else f"perturbed: {outcome2}",
    )
    return out
