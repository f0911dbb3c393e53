"""What `cosim run` writes about rigid bodies: the reaction wrenches the material exerts on them
(trajectory.npz and metrics.json, docs/outputs.md), keys that need no parsing of body names, and
`cosim render` drawing the rigid bodies exactly as the run's preview does.

One small 2D run serves every test: hydrostatic water (E = 1e5 Pa, 60 particles each, 12 kg per
metre of depth) at rest in two glasses with walls three cells thick, a kinematic one ``bowl`` and
the link ``cup`` of a welded DART skeleton ``cup`` (so its name is "cup/cup"), whose link frame
sits 0.1 m left of its glass's centre; 60 frames of 4 ms, a frame saved every 5 steps.
"""

from __future__ import annotations

import json

import imageio.v2 as imageio
import numpy as np
import pytest
import yaml
from conftest import scene_dict

from cosim.scene import load_scene

G = 9.81
EVERY, FRAME_DT, STEPS = 5, 4e-3, 60
OFFSET = 0.1  # [m] the cup's glass centre from its link origin, along +x
GLASS = {"type": "glass", "radius": 0.14, "height": 0.3, "thickness": 0.09375}
FLOOR = 0.44 - 0.15 + 0.09375  # [m] the glasses' inside bottom (both centred at y = 0.44)


def water(name: str, x: float) -> dict:
    """Water filling the glass centred at x to 0.16 m, wall to wall, started hydrostatic (5 mm clear of its walls
    the water, held by its own edge, first spread to them: a transient longer than the run)."""
    return {
        "name": name,
        "material": {"type": "liquid", "E": 1e5, "nu": 0.3, "viscosity": 1.0},
        "shape": {"type": "box", "center": [x, FLOOR + 0.08], "size": [2 * (0.14 - 0.09375), 0.16]},
        "hydrostatic": True,
    }


def cups_scene() -> dict:
    cup = {"name": "cup", "shape": GLASS, "density": 1000, "offset": [OFFSET, 0.0]}
    cup["joint"] = {"type": "weld", "position": [0.73 - OFFSET, 0.44]}
    return scene_dict(
        name="cups",
        steps=STEPS,
        time={"frame_dt": FRAME_DT, "substeps": "auto"},
        mpm={"grid": {"cells": 32}, "bodies": [water("left", 0.27), water("right", 0.73)]},
        rigid={"bodies": [{"name": "bowl", "shape": GLASS, "position": [0.27, 0.44]}]},
        articulated={"skeletons": [{"name": "cup", "links": [cup]}]},
        output={"every": EVERY, "velocities": True, "resolution": 160},
    )


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """The run's outputs (with the preview), its scene file, and the system's particle masses and
    rigid bodies after the rollout."""
    from cosim.run import run_scene

    out = tmp_path_factory.mktemp("cups")
    path = out / "cups.yaml"
    path.write_text(yaml.safe_dump(cups_scene()))
    seen = {}
    run_scene(load_scene(path), out, progress=False, after_rollout=lambda sim: seen.update(sim=sim))
    sim = seen["sim"]
    masses = {name: sim.mpm.mass[sl].copy() for name, sl in sim.slices.items()}
    traj = dict(np.load(out / "trajectory.npz"))
    metrics = json.loads((out / "metrics.json").read_text())
    return {"out": out, "scene": path, "traj": traj, "metrics": metrics, "masses": masses, "rigid": sim.rigid}


def test_reaction_on_each_glass_is_the_weight_of_its_water(run):
    """Momentum balance of each water body, which touches only its glass: the mean force on the glass
    over an interval is m g - (P_end - P_start) / T. Checked per saved frame (the force there is the
    mean over the 5 steps before it) against the particles' momenta to 1e-6 of the weight (measured
    2e-9: the grid contact's recorded impulses are exactly what it took from the material), and the
    mean over the last 30 steps (about two pressure-wave periods) is the weight within 2% (measured
    1.2% and 1.6%; 0.5% and 0.2% with the liquid held at node rows, which let it settle faster)."""
    traj, masses = run["traj"], run["masses"]
    force = traj["reaction_force"]
    assert force.shape == (STEPS // EVERY + 1, 2, 2)
    assert np.isnan(force[0]).all()  # no step has acted at the start
    for b, name in enumerate(("left", "right")):  # bowl holds left, cup right
        m = masses[name]
        weight = m.sum() * np.array([0.0, -G])
        momentum = np.einsum("p,fpd->fd", m, traj[f"v_{name}"].astype(np.float64))
        balance = weight - np.diff(momentum, axis=0) / (EVERY * FRAME_DT)
        assert np.abs(force[1:, b] - balance).max() < 1e-6 * m.sum() * G, name
        settled = force[-30 // EVERY :, b].mean(axis=0)
        assert abs(settled[1] / weight[1] - 1) < 0.02, (name, settled, weight)
        sideways = force[1:, b, 0].mean()  # whole run: from rest to nearly at rest, no net push
        assert abs(sideways) < 0.01 * m.sum() * G, (name, sideways)


def test_torque_is_about_the_body_origin(run):
    """Angular momentum balance about each body origin p over the whole run: the water starts at rest
    and ends nearly so, so its mean torque on the glass is that of its weight at its centroid,
    -M g (x_c - p)_x, x_c averaged over the run (trapezoid over the saved frames); within 2% of
    M g x 0.1 m (measured 0.2-0.6%). The cup's link origin is 0.1 m left of its glass's centre (a
    torque about the glass's centre would be near 0 there), the bowl's at its centre."""
    traj = run["traj"]
    torque = traj["reaction_torque"]
    assert torque.shape == (STEPS // EVERY + 1, 2, 1)
    levers = []
    for b, name in enumerate(("left", "right")):
        m = run["masses"][name]
        centroid = traj[f"x_{name}"][:, :, 0].astype(np.float64) @ m / m.sum()
        lever = np.mean(0.5 * (centroid[1:] + centroid[:-1])) - traj["rigid_pos"][0, b, 0]
        expected = -m.sum() * G * lever
        assert abs(torque[1:, b, 0].mean() - expected) < 0.02 * m.sum() * G * OFFSET, (name, torque[1:, b, 0].mean())
        levers.append(lever)
    assert abs(levers[0]) < 0.01 and abs(levers[1] - OFFSET) < 0.01, levers


def test_metrics_summarise_every_step(run):
    """metrics.json's reactions: one entry per rigid body in rigid_names order; the mean over all steps
    equals the mean of the saved frames' interval means (every step lies in one interval), the water
    starts at rest and ends nearly so, so the mean is the weight within 2%; max >= |final|."""
    traj, reactions = run["traj"], run["metrics"]["reactions"]
    assert [r["body"] for r in reactions] == ["bowl", "cup/cup"]
    for b, (entry, name) in enumerate(zip(reactions, ("left", "right"))):
        mean = traj["reaction_force"][1:, b].mean(axis=0)
        assert np.allclose(entry["force_mean"], mean, rtol=1e-9, atol=1e-9)
        assert np.allclose(entry["torque_mean"], traj["reaction_torque"][1:, b].mean(axis=0), atol=1e-9)
        weight = run["masses"][name].sum() * G
        assert abs(-entry["force_mean"][1] / weight - 1) < 0.02, entry
        assert entry["force_max"] >= np.linalg.norm(entry["force_final"]) > 0.5 * weight
        assert len(entry["torque_final"]) == 1 and entry["torque_max"] >= abs(entry["torque_final"][0])


def test_keys_need_no_parsing_of_body_names(run):
    """A DART link named like its skeleton ("cup/cup") appears in no key: rigid arrays are stacked
    along an axis named by rigid_names, with the skeleton and link names given apart; metrics list
    the bodies, so the sweep's '/'-joined columns stay unambiguous."""
    from cosim.scale.jobs import flatten

    traj, metrics = run["traj"], run["metrics"]
    assert not [k for k in traj if "/" in k or "cup" in k or "bowl" in k]
    assert list(traj["rigid_names"]) == ["bowl", "cup/cup"]
    assert list(traj["rigid_skeletons"]) == ["", "cup"] and list(traj["rigid_links"]) == ["bowl", "cup"]
    frames = len(traj["time"])
    assert traj["rigid_pos"].shape == (frames, 2, 2) and traj["rigid_rot"].shape == (frames, 2, 2, 2)
    assert np.allclose(traj["rigid_pos"][:, 1], [0.73 - OFFSET, 0.44])  # welded: the link origin stays
    assert metrics["reactions"][1]["skeleton"] == "cup" and metrics["reactions"][0]["skeleton"] is None
    columns = [k for k in flatten(metrics) if k.startswith("reactions/")]
    assert "reactions/1/force_mean/1" in columns and not [k for k in columns if "cup" in k]


def test_render_draws_the_rigid_bodies_as_the_run_preview_does(run, tmp_path):
    """`cosim render` of the run's trajectory gives the preview's pictures pixel for pixel, and the
    pixels under both glasses' surface points (the SDF's zero level, as the 2D preview draws a rigid
    body), where no water particle is drawn over them, have the rigid bodies' grey in every frame."""
    from cosim.cli import main
    from cosim.render.raster2d import RIGID_COLOR, Camera
    from cosim.render.surfaces import rigid_geometry

    out = tmp_path / "again.gif"
    assert main(["render", str(run["scene"]), str(run["out"] / "trajectory.npz"), str(out)]) == 0
    preview = np.asarray(imageio.mimread(run["out"] / "preview.gif"))
    again = np.asarray(imageio.mimread(out))
    assert again.shape == preview.shape and len(again) == len(run["traj"]["time"])
    assert np.array_equal(again, preview)
    traj = run["traj"]
    poses = [list(zip(p, R)) for p, R in zip(traj["rigid_pos"], traj["rigid_rot"])]
    camera = Camera(np.array([1.0, 1.0]), 160)
    particles = np.concatenate([traj["x_left"], traj["x_right"]], axis=1)
    for image, bodies, x in zip(again, rigid_geometry(run["rigid"].grids, poses, 2), particles):
        for points in bodies:  # those clear of the water's discs (2 px = 0.014 m; the later sets paint over)
            clear = points[np.linalg.norm(points[:, None] - x[None], axis=2).min(axis=1) > 0.03]
            assert len(clear) > 0.5 * len(points)
            px = np.round(camera.project(clear)).astype(int)
            colours = image[px[:, 1], px[:, 0], :3].astype(float)
            assert (np.abs(colours - RIGID_COLOR).max(axis=1) <= 3).all()


def test_render_refuses_a_trajectory_of_the_old_layout(run, tmp_path, capsys):
    """A trajectory with rigid bodies but per-body pose keys (before rigid_pos): a one-line error."""
    from cosim.cli import main

    old = {k: v for k, v in run["traj"].items() if not k.startswith("rigid_pos")}
    np.savez(tmp_path / "old.npz", **old, rigid_pos_bowl=run["traj"]["rigid_pos"][:, 0])
    assert main(["render", str(run["scene"]), str(tmp_path / "old.npz"), str(tmp_path / "x.gif")]) == 2
    err = capsys.readouterr().err
    assert "older cosim" in err and "run the scene again" in err and "Traceback" not in err
