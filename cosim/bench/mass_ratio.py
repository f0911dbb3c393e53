"""The mass-ratio sweep of `cosim bench coupling`: a light body resting on heavy material.

The light body is a DART free plate (2D, a planar joint) or a cloth sheet (3D) lying on an
elastic block of density 1000 kg/m^3 that rests on the domain's floor; r = block density x dx /
the body's areal density [kg/m^2] (the material one cell deep against the body). Float64, forecast
contact with friction 0.3. The block is first brought to rest in its weight alone, the body laid on
its top where it touches (``lay_on``), and both brought to rest (``settle``); then, per ratio and
coupling scheme (the added-mass coupling, "strong", or the explicit exchange):

- amplification: the body's vertical velocity perturbed by 1e-4 m/s at frame ``perturb_at`` of a
  second rollout; the geometric mean over the frames after it of the per-frame growth of the
  difference between the two rollouts' body velocities (<= 1: perturbations die);
- late rms [m/s]: the body's vertical velocity relative to the block's top layer under it (the
  rate of that layer's mean height) over the last quarter of the frames: the jitter of the exchange
  at rest;
- height error [m]: the body's mean height over those frames against the closed form: the top
  of the settled block without the body, lowered by the body's weight w per area squeezing
  the block uniaxially (w h / E', E' = E / (1 - nu^2) in plane strain, E in 3D), plus half the plate
  (the plate meets the material a particle radius above the top particles' centres, the sheet at
  them);
- outcome: "ok", or the runner's message where a guard stopped the run.

``substeps`` fixes the MPM substeps per frame (auto: the CFL bound's) and ``exchanges`` how many exchanges
a frame makes (auto: the system's choice, ``start.exchanges_per_frame``). The report's second sweep
(``mass_ratio_report.substep_sweep``) varies the substeps, exchanging once per frame and as the system
chooses: what makes a body jitter is the number of substeps it is held frozen over between two exchanges,
not the frame's length (exchanging once per frame, the plate at r = 1 rests at 4 substeps per 2 ms and at 4
per 0.5 ms on a block 16 times stiffer, and jitters at 8 per 2 ms or 10 per 1 ms), which is why the couplers
declare their ``exchange_substeps`` and the system splits a frame that needs more.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RATIOS = (0.1, 0.5, 1.0, 5.0, 25.0, 100.0)
DENSITY = 1000.0  # [kg/m^3] the block
E, NU = 2.0e5, 0.3  # [Pa] the block: its own weight squeezes it by about 1 %
GRAVITY = 9.81
FLOOR = 2.75  # [cells] the block's bottom: its lowest particles (a quarter cell up) on the slip wall at 3 cells
FRICTION = 0.3


@dataclass(frozen=True)
class Setup:
    """One light body on the block: dimension, grid cells, block size (width, height[, depth]) [m], the body's
    size (plate: width, thickness; cloth: side) [m]."""

    body: str  # "plate" | "cloth"
    dim: int
    cells: int
    block: tuple
    size: tuple

    @property
    def dx(self) -> float:
        return 1.0 / self.cells

    @property
    def engine(self) -> str:
        """The light body's engine in the built scene (``scene_dict``)."""
        return "dart" if self.body == "plate" else "sheet"

    @property
    def top(self) -> float:
        """[m] The block's surface at the start (its top particles a quarter cell below it)."""
        return FLOOR * self.dx + self.block[1]


PLATE = Setup("plate", 2, 32, (0.5, 0.25), (0.4, 0.02))
CLOTH = Setup("cloth", 3, 16, (0.5, 0.25, 0.5), (0.4,))
SETUPS = {"plate": PLATE, "cloth": CLOTH}


def scene_dict(
    setup: Setup, ratio: float, frames: int, substeps: int | str = "auto", exchanges: int | str = "auto"
) -> dict:
    """The light body on the block at ``ratio``, ``substeps`` per 2 ms frame in ``exchanges`` exchanges (a scene
    dict for ``parse_scene``)."""
    dx, floor = setup.dx, FLOOR * setup.dx
    areal = DENSITY * dx / ratio
    centre = [0.5, floor + 0.5 * setup.block[1]] + ([0.5] if setup.dim == 3 else [])
    block = {
        "name": "block",
        "material": {"type": "elastic", "E": E, "nu": NU, "density": DENSITY},
        "shape": {"type": "box", "center": centre, "size": list(setup.block)},
    }
    data = {
        "name": f"{setup.body}_r{ratio:g}",
        "dim": setup.dim,
        "precision": "float64",
        "steps": frames,
        "time": {"frame_dt": 2e-3, "substeps": substeps, "exchanges": exchanges},
        "mpm": {"grid": {"cells": setup.cells}, "boundary": {"type": "slip"}, "bodies": [block]},
        "contact": {"model": "forecast", "friction": FRICTION},
    }
    if setup.body == "plate":
        width, thickness = setup.size
        link = {
            "name": "plate",
            "shape": {"type": "box", "size": [width, thickness]},
            "density": areal / thickness,
            "joint": {"type": "free", "position": [0.5, setup.top + 0.5 * thickness]},
        }
        data["articulated"] = {"skeletons": [{"name": "plate", "links": [link]}]}
    else:
        side = setup.size[0]
        sheet = {"type": "rectangle", "center": [0.5, setup.top - 0.25 * dx, 0.5], "size": [side, side]}
        data["cloth"] = [
            {
                "name": setup.engine,
                "mesh": {**sheet, "resolution": [7, 7]},
                "material": {"stretch": 500, "bend": 0.015, "density": areal},
            }
        ]
    return data


def squeeze(setup: Setup, ratio: float) -> float:
    """[m] How far the body's weight lowers the block's top (uniaxial: w h / E')."""
    w = DENSITY * setup.dx / ratio * GRAVITY  # [Pa]
    modulus = E / (1 - NU * NU) if setup.dim == 2 else E
    return w * setup.block[1] / modulus


class Probe:
    """The body's height and vertical velocity, and the top layer's, in a built system."""

    def __init__(self, setup: Setup, sim):
        self.setup, self.sim = setup, sim
        self.engine = sim.engines[setup.engine]

    def height_velocity(self) -> tuple[float, float]:
        if self.setup.body == "plate":
            b = self.engine.body_states()
            return float(b["position"][0, 1]), float(b["linear_velocity"][0, 1])
        s = self.engine.state()
        return float(s["x"][:, 1].mean()), float(s["v"][:, 1].mean())

    def kick(self, delta: float) -> None:
        """Add ``delta`` [m/s] to the body's vertical velocity (every free vertex of a sheet)."""
        s = {k: np.array(v) for k, v in self.engine.state().items()}
        if self.setup.body == "plate":
            s["qd"][1] += delta
        else:
            s["v"][self.engine.free, 1] += delta
        self.engine.set_state(s)

    def surface_offset(self) -> float:
        """[m] The body's centre above the top particles' centres at contact."""
        if self.setup.body == "plate":
            return 0.25 * self.setup.dx + 0.5 * self.setup.size[1]
        return 0.0


def settle(sim, frames: int) -> None:
    """Bring the block and the body to rest in their weights (dynamic relaxation): ``frames`` coupled steps;
    whenever the kinetic energy of the material and the body together has passed a peak, every velocity is
    set to zero (the material's alone misses a heavy body oscillating on it). The couplers' carried velocities
    start afresh after; their tracing state is kept (afresh, material that a falling sheet pushed across
    would be legal on the wrong side)."""
    peak = 0.0
    for _ in range(frames):
        sim.step()
        state = sim.state()
        energy = _kinetic_energy(sim, state)
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
    for name, carried in state.get("couplers", {}).items():
        if carried is not None and "boundary_v" in carried:
            carried["boundary_v"] = None
    sim.set_state(state)


def _kinetic_energy(sim, state: dict) -> float:
    """[J] The material's kinetic energy and the light body's (a sheet's vertices, a plate's)."""
    total = sum(terms["kinetic"] for terms in sim.mpm.energies().values())
    for name, engine in sim.engines.items():
        if name == "mpm":
            continue
        if "qd" in state[name]:  # DART's state: its skeletons' own account
            total += sum(float(skel.computeKineticEnergy()) for skel in engine.skeletons)
        else:
            total += 0.5 * float(np.sum(engine.masses()[:, None] * state[name]["v"] ** 2))
    return total


@dataclass(frozen=True)
class SettledBlock:
    """The block brought to rest in its weight alone (``settled_block``): its top particles' mean height [m]
    (the closed form's reference) and the material's state, on which the body is laid."""

    top: float
    state: dict


def settled_block(setup: Setup, rest: int) -> SettledBlock:
    """The block settled for ``rest`` frames without a body (``settle``)."""
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    data = scene_dict(setup, 1.0, rest)
    data.pop("articulated", None)
    data.pop("cloth", None)
    sim = build_system(parse_scene(data))
    settle(sim, rest)
    state = sim.mpm.state()
    x = state["x"]
    return SettledBlock(float(x[x[:, 1] > x[:, 1].max() - 0.5 * setup.dx, 1].mean()), state)


def lay_on(setup: Setup, sim, block: SettledBlock) -> None:
    """Start ``sim`` from the settled block with the body laid on its top, where it touches: a plate's bottom a
    particle radius above the highest particle's centre under it, a sheet a thousandth of a cell above it
    (the sheet meets material at the particles' centres; the margin gives each particle a side to trace).
    Laid higher, a light sheet hovers: the blended contact holds it like a dashpot across its band and it
    sinks at a speed proportional to its weight (``ForecastContact``)."""
    x = block.state["x"]
    under = np.all(np.abs(x[:, [0, -1]] - 0.5) < 0.5 * setup.size[0], axis=1)
    highest = float(x[under, 1].max())
    state = sim.state()
    state["mpm"] = {key: np.array(value) for key, value in block.state.items()}
    name = setup.engine
    if setup.body == "plate":
        built_at = setup.top + 0.5 * setup.size[1]  # the free joint's origin (``scene_dict``); q is relative to it
        state[name]["q"][1] = highest + 0.25 * setup.dx + 0.5 * setup.size[1] - built_at
    else:
        state[name]["x"][:, 1] = highest + 1e-3 * setup.dx
    sim.set_state(state)


def run(
    setup: Setup,
    ratio: float,
    strong: bool = True,
    frames: int = 200,
    perturb_at: int = 100,
    rest: int = 100,
    block: SettledBlock | None = None,
    delta: float = 1e-4,
    substeps: int | str = "auto",
    exchanges: int | str = "auto",
) -> dict:
    """One row of the sweep (module docstring). ``block``: the block settled alone (``settled_block``),
    computed when not given; ``substeps``: MPM substeps per frame ("auto": the CFL bound's, 4 for the plate's
    block and 2-3 for the sheet's) in ``exchanges`` exchanges ("auto": the system's choice, 1 for comparison)."""
    from cosim.errors import SimulationError
    from cosim.scene import parse_scene
    from cosim.scene.build import build_system

    block = settled_block(setup, rest) if block is None else block
    sim = build_system(parse_scene(scene_dict(setup, ratio, frames, substeps, exchanges)))
    lay_on(setup, sim, block)
    for coupler in sim.mpm_couplers:
        coupler.added_mass = strong
    probe = Probe(setup, sim)
    row = {"body": setup.body, "ratio": ratio, "scheme": "strong" if strong else "explicit", "substeps": substeps}
    row["exchanges"] = sim.exchanges
    try:
        settle(sim, rest)
    except SimulationError as err:
        return row | {"outcome": f"settling: {err}"}
    start = sim.state()
    x0 = start["mpm"]["x"]
    under = np.all(np.abs(x0[:, [0, -1]] - 0.5) < 0.5 * setup.size[0], axis=1)
    layer = np.flatnonzero(under & (x0[:, 1] > x0[under, 1].max() - setup.dx))

    def rollout(kick: float) -> tuple[np.ndarray, str]:
        """(frames, 3): the body's height, its vertical velocity, the top layer's; and the outcome."""
        sim.set_state(start)
        rows, level = [], x0[layer, 1].mean()
        try:
            for n in range(frames):
                if n == perturb_at and kick:
                    probe.kick(kick)
                sim.step()
                now = sim.mpm.state()["x"][layer, 1].mean()
                rows.append((*probe.height_velocity(), (now - level) / sim.frame_dt))
                level = now
        except SimulationError as err:
            return np.array(rows), str(err)
        return np.array(rows), "ok"

    base, outcome = rollout(0.0)
    if outcome != "ok":
        return row | {"outcome": outcome}
    kicked, outcome = rollout(delta)
    if outcome != "ok":
        return row | {"outcome": f"perturbed: {outcome}"}
    d = np.abs(kicked[perturb_at:, 1] - base[perturb_at:, 1])
    live = d[:-1] > 1e-9 * delta  # the differences above round-off
    growth = d[1:][live] / d[:-1][live]
    late = slice(3 * frames // 4, frames)
    expected = block.top - squeeze(setup, ratio) + probe.surface_offset()
    return row | {
        "amplification": float(np.exp(np.mean(np.log(growth)))) if live.any() else 0.0,
        "late_rms": float(np.sqrt(np.mean((base[late, 1] - base[late, 2]) ** 2))),
        "height_error": float(np.mean(base[late, 0]) - expected),
        "outcome": "ok",
    }
