"""What each shipped scene is for, as numbers from its `cosim run` outputs (trajectory.npz, metrics.json).

``BEHAVIOUR[scene] = (steps, check)``: the CLI test runs the scene for ``steps`` macro steps (None: the
scene's own count) and calls ``check(trajectory, metrics, scene)``. Scenes checked by their own tests
(the optimisation tasks, the cloth scenes) are not here. Bounds are physics (slip walls keep the
tangential momentum, Ritter's ideal dam-break front bounds the real one, an unforced body only loses
energy) or the scene's stated purpose (water ends in the glass), with the measured values in comments.
"""

from __future__ import annotations

import math

import numpy as np


def _body(traj, name: str) -> np.ndarray:
    return traj[f"x_{name}"].astype(np.float64)


def _velocity(traj, com: np.ndarray, i: int, j: int) -> np.ndarray:
    return (com[j] - com[i]) / (traj["time"][j] - traj["time"][i])


def elastic_bounce(traj, metrics, scene) -> None:
    """The block slides along the slip floor at its initial 0.5 m/s and bounces off it elastically."""
    com = _body(traj, "block").mean(axis=1)
    vx = _velocity(traj, com, 0, -1)[0]
    assert abs(vx - 0.5) < 0.005, vx  # a slip floor exerts no tangential force (measured 0.5000)
    low = int(np.argmin(com[:, 1]))
    assert 0 < low < len(com) - 5
    fall, rise = com[0, 1] - com[low, 1], com[-1, 1] - com[low, 1]
    assert rise > 0.6 * fall, (fall, rise)  # a bounce, not a splat (measured 0.72)
    energy = traj["energy_total"]
    assert energy[-1] <= energy[0] and energy[-1] > 0.8 * energy[0], energy[[0, -1]]  # measured 0.86


def dam_break(traj, metrics, scene) -> None:
    """The column collapses: its front reaches the far wall no sooner than Ritter's ideal front
    (x0 + 2 sqrt(g h0) t, inviscid shallow water) and within twice its time; the water keeps its area."""
    x = _body(traj, "water")
    t = traj["time"]
    x0, h0 = x[0, :, 0].max(), np.ptp(x[0, :, 1])
    far = scene.cells[0] * scene.dx - 4 * scene.dx  # the wall's inner face, less a cell
    t_ritter = (far - x0) / (2 * math.sqrt(9.81 * h0))
    arrived = t[np.argmax(x[:, :, 0].max(axis=1) >= far)]
    assert x[:, :, 0].max(axis=1)[-1] >= far
    assert t_ritter <= arrived <= 2 * t_ritter, (t_ritter, arrived)  # measured 1.6x Ritter's time
    energy = traj["energy_total"]
    assert energy[-1] < energy[0]
    liquid_volume_kept(metrics)


def liquid_volume_kept(metrics) -> None:
    """The weakly compressible liquid keeps its volume (sum V0 det F) within 5% (the stated bound;
    measured over 10,000 steps: 0.9912..1.0000 dam break, 0.9709..1.0013 shaken ring)."""
    volume = metrics["liquid_volume_ratio"]
    assert 0.95 < volume["min"] <= volume["max"] < 1.05, volume


def plastic_squash(traj, metrics, scene) -> None:
    """The cube lands, flattens to under half its height and stays flat (plastic: no recovery)."""
    y = _body(traj, "dough")[:, :, 1]
    height = np.ptp(y, axis=1)
    assert height[-1] < 0.5 * height[0], height[[0, -1]]  # measured 0.27
    late = height[int(0.75 * len(height)) :]
    assert np.ptp(late) < 0.06 * late.mean(), late  # measured 3%: an elastic cube would spring back
    xz = np.ptp(_body(traj, "dough")[-1][:, [0, 2]], axis=0)
    assert abs(xz[0] - xz[1]) < 0.02 * xz.mean()  # the square footprint spreads symmetrically


def jelly_torus(traj, metrics, scene) -> None:
    """The torus slides at its initial 0.8 m/s until it nears the wall and bounces off the floor."""
    com = _body(traj, "torus").mean(axis=1)
    t = traj["time"]
    before_wall = int(np.searchsorted(t, 0.36))
    vx = _velocity(traj, com, 0, before_wall)[0]
    assert abs(vx - 0.8) < 0.01, vx  # slip floor: measured 0.800
    vy = np.diff(com[: before_wall + 1, 1]) / np.diff(t[: before_wall + 1])
    low = int(np.argmin(com[: before_wall + 1, 1]))
    impact, rebound = -vy[:low].min(), vy[low:].max()
    assert rebound > 0.3 * impact, (impact, rebound)  # elastic rebound: measured 0.46


def held(metrics, container: str) -> float:
    """Share of the particles a container holds at the end."""
    return metrics["particles_held"][container] / metrics["particles"]


def pour_thin_glass(traj, metrics, scene) -> None:
    """The cup empties into the thin-walled glass."""
    assert held(metrics, "cup") < 0.05  # measured 0.5%
    assert held(metrics, "glass") > 0.75, metrics["particles_held"]  # measured 83%


def shake_container(traj, metrics, scene) -> None:
    """Shaken for 0.6 s, the ring holds its water: none spilled, at most 2% in its wall (grid contact)."""
    assert metrics["particles_elsewhere"] == 0 and held(metrics, "container") > 0.98, metrics["particles_held"]
    liquid_volume_kept(metrics)


BEHAVIOUR = {
    "elastic_bounce_2d": (None, elastic_bounce),
    "dam_break_2d": (None, dam_break),
    "plastic_squash_3d": (None, plastic_squash),
    "jelly_torus_3d": (None, jelly_torus),
    "pour_thin_glass": (None, pour_thin_glass),
    "shake_container_2d": (300, shake_container),
}
