"""`cosim bench cloth`: what the cloth engine and its MPM coupling cost, with the published scale anchors.

Four parts, in one process, float64 throughout (the cloth is float64 anyway; gradient runs are):

- step: the cloth step alone (``cloth_step.run_cloth_step_bench``): Newton iterations, forward and
  adjoint ms per step for square sheets of about 400, 2k and 10k vertices (``quick``: no 10k);
- query: the nearest-face query of ``MeshQuery`` (spatial hash) against its brute-force kernel
  over every face, for 1k and 10k faces and 30k points, about 40 % of them within the band; the
  host-side hash build is timed on its own; both must return the same faces (checked);
- coupled: towel_squash (plasticine + towel, forecast contact, tracing on) against the MPM alone
  (the same particles and grid, no cloth) and the cloth alone (the same towel and actions, no
  MPM): ms per macro step forward, and forward + backward of a shorter rollout (requires_grad);
  coupled / (MPM + cloth);
- taco: a SoftMAC-taco-sized case (a 217-vertex disc over ~10k particles, 200 steps), forward +
  backward, seconds per optimisation iteration.

Times are medians of ``repeat`` runs after a warm-up that compiles every kernel. Writes
``OUT/cloth.json`` (every number) and ``OUT/cloth.md`` (the tables).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

ANCHORS = [
    (
        "DiffCloth (Li et al. 2022): ~150-245 ms per forward step and 8-18 ms per backward step for a "
        "1426-vertex T-shirt (hardware not stated)."
    ),
    (
        "SoftMAC (IROS 2024) taco: 217-vertex tortilla, 10k particles, 200 steps: 20.45 s per optimisation "
        "iteration on a T4 GPU."
    ),
]
QUERY_FACES = (1000, 10000)
QUERY_POINTS = 30000
QUERY_BAND = 1.0 / 64  # [m] one cell of a 64^3 grid, where 30k particles is a typical body
QUERY_SPREAD = 2.5  # points lie within +-2.5 bands of the sheet: ~40 % inside the band


def _median_ms(samples: list[float]) -> float:
    return 1e3 * float(np.median(samples))


# ------------------------------------------------------------------------------------------ query


def wavy_sheet(faces: int, size: float = 0.5):
    """A ``size`` [m] square sheet of about ``faces`` triangles, rippled (amplitude 2 cm) so that
    faces are not axis-aligned."""
    from cosim.engines import cloth_mesh

    n = max(2, round(math.sqrt(faces / 2)) + 1)
    mesh = cloth_mesh.rectangle((size, size), (n, n), center=(0.5, 0.5, 0.5), normal="y")
    v = mesh.vertices.copy()
    v[:, 1] += 0.02 * np.sin(2 * np.pi * v[:, 0] / 0.25) * np.sin(2 * np.pi * v[:, 2] / 0.3)
    return v, mesh.faces


def query_points(verts: np.ndarray, faces: np.ndarray, n: int, band: float, seed: int = 0) -> np.ndarray:
    """``n`` points over the sheet's footprint, each within +-QUERY_SPREAD bands (along y) of a random
    point on a random face."""
    rng = np.random.default_rng(seed)
    f = rng.integers(0, len(faces), n)
    w = rng.dirichlet(np.ones(3), n)
    on = np.einsum("nk,nkd->nd", w, verts[faces[f]])
    on[:, 1] += rng.uniform(-QUERY_SPREAD * band, QUERY_SPREAD * band, n)
    return on


def measure_query(faces: int, points: int = QUERY_POINTS, band: float = QUERY_BAND, repeat: int = 5) -> dict:
    """Hash vs brute-force nearest-face query (Taichi initialised by the caller); raises if they differ."""
    from cosim.couplers.cloth_mesh_query import MeshQuery, face_hash

    verts, tri = wavy_sheet(faces)
    pts = query_points(verts, tri, points, band)
    q = MeshQuery(tri, len(verts), band)
    q.update(verts)
    hashed = q.query(pts)  # compile
    brute = q.query(pts, brute=True)
    if not (np.array_equal(hashed[0], brute[0]) and np.allclose(hashed[1], brute[1], rtol=0, atol=1e-12)):
        bad = int(np.sum(hashed[0] != brute[0]))
        raise AssertionError(f"hash and brute-force nearest faces differ for {bad} of {points} points")
    build, update, t_hash, t_brute = [], [], [], []
    for _ in range(repeat):
        t = time.perf_counter()
        face_hash(verts, q.faces_np, band, q.table)
        build.append(time.perf_counter() - t)
        t = time.perf_counter()
        q.update(verts)
        update.append(time.perf_counter() - t)
        t = time.perf_counter()
        q.query(pts)
        t_hash.append(time.perf_counter() - t)
        t = time.perf_counter()
        q.query(pts, brute=True)
        t_brute.append(time.perf_counter() - t)
    return {
        "faces": len(tri),
        "points": points,
        "band_m": band,
        "within_band": float(np.mean(hashed[0] >= 0)),
        "hash_build_ms": _median_ms(build),
        "update_ms": _median_ms(update),
        "hash_query_ms": _median_ms(t_hash),
        "brute_query_ms": _median_ms(t_brute),
        "brute_vs_hash": float(np.median(t_brute) / np.median(t_hash)),
        "same_faces": True,
    }


# ------------------------------------------------------------------------------------------ coupled


def _scene(overrides: dict | None = None):
    from cosim.scene import load_scene
    from cosim.scene.shipped import scenes_dir

    return load_scene(scenes_dir() / "towel_squash.yaml", {"precision": "float64", **(overrides or {})})


MPM_ONLY = {"cloth": [], "gradient": {"params": ["v0"]}, "optimize": {"params": ["v0"]}}


def _forward_system(scene, steps: int, repeat: int) -> tuple[list[float], int, dict]:
    """Per repetition: wall time per macro step of ``steps`` steps from the initial state."""
    from cosim.scene.build import build_system

    sim = build_system(scene)
    sim.step()  # compiles
    out = []
    for _ in range(repeat):
        sim.reset()
        sim.timings = {}
        t = time.perf_counter()
        for _ in range(steps):
            record = sim.step()
        out.append((time.perf_counter() - t) / steps)
        parts, sim.timings = sim.timings, None
    return out, record.mpm.substeps, {k: v / steps for k, v in parts.items()}


def _cloth_alone(scene, steps: int, repeat: int, backward: bool) -> list[float]:
    """Per repetition: the towel alone (the scene's actions, no MPM forces), seconds per step of the
    forward (``backward``: forward recorded, plus the adjoint of every step)."""
    from cosim.scene.cloth import build_cloth

    engine, plan = build_cloth(scene, 0)
    initial = engine.state()
    engine.step({"action": plan.sequence[0]})  # JAX compiles
    out = []
    for _ in range(repeat):
        engine.set_state(initial)
        engine.steps = 0
        records = []
        t = time.perf_counter()
        for n in range(steps):
            records.append(engine.step({"action": plan.sequence[plan.segment(n, len(plan.sequence))]})[1])
        if backward:
            grad = {"x": np.ones_like(initial["x"]), "v": np.zeros_like(initial["v"])}
            for record in reversed(records):
                grad = engine.vjp(record, {"state": grad})["state"]
        out.append((time.perf_counter() - t) / steps)
    return out


def _forward_backward(scene, steps: int, repeat: int) -> tuple[list[float], float]:
    """Per repetition: seconds per macro step of a recorded rollout plus its backward; and the
    compile (first evaluation) seconds."""
    from cosim.adjoint.objective import Objective
    from cosim.scene.build import build_system

    obj = Objective(build_system(scene, requires_grad=True, steps=steps))
    params = obj.initial_params()
    t = time.perf_counter()
    obj.evaluate(params, grad=True)
    first = time.perf_counter() - t
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        obj.evaluate(params, grad=True)
        out.append((time.perf_counter() - t) / steps)
    return out, first


def measure_coupled(steps: int, grad_steps: int, repeat: int) -> dict:
    """towel_squash coupled vs MPM alone vs cloth alone, forward and forward + backward."""
    scene, mpm_only = _scene(), _scene(MPM_ONLY)
    coupled, k, parts = _forward_system(scene, steps, repeat)
    mpm, k_mpm, _ = _forward_system(mpm_only, steps, repeat)
    cloth = _cloth_alone(scene, steps, repeat, backward=False)
    out = {
        "particles": int(sum(len(b) for b in _particles(scene))),
        "cloth_vertices": int(scene.cloth[0].mesh.resolution[0] * scene.cloth[0].mesh.resolution[1]),
        "grid": f"{scene.cells[0]}^3",
        "substeps": k,
        "substeps_mpm_alone": k_mpm,
        "steps": steps,
        "coupled_ms": _median_ms(coupled),
        "mpm_ms": _median_ms(mpm),
        "cloth_ms": _median_ms(cloth),
        "coupled_parts_ms": {key: 1e3 * v for key, v in parts.items()},
    }
    out["coupled_vs_sum"] = out["coupled_ms"] / (out["mpm_ms"] + out["cloth_ms"])
    if grad_steps:
        gscene = _scene({"steps": grad_steps})
        g_coupled, first = _forward_backward(gscene, grad_steps, repeat)
        g_mpm, _ = _forward_backward(_scene({**MPM_ONLY, "steps": grad_steps}), grad_steps, repeat)
        g_cloth = _cloth_alone(gscene, grad_steps, repeat, backward=True)
        out.update(
            {
                "grad_steps": grad_steps,
                "grad_compile_s": first,
                "fwd_bwd_coupled_ms": _median_ms(g_coupled),
                "fwd_bwd_mpm_ms": _median_ms(g_mpm),
                "fwd_bwd_cloth_ms": _median_ms(g_cloth),
            }
        )
        out["fwd_bwd_coupled_vs_sum"] = out["fwd_bwd_coupled_ms"] / (out["fwd_bwd_mpm_ms"] + out["fwd_bwd_cloth_ms"])
    return out


def _particles(scene):
    from cosim.scene.particles import body_positions

    return body_positions(scene)


# ------------------------------------------------------------------------------------------ taco

# The tortilla (SoftMAC's taco material, k_stretch 2500 N/m, k_bend 0.75 N m in our units) is dropped
# 1 cm onto the filling and settles on it, its two rims held by controls at zero velocity (the
# action sequence is still a differentiable input). Rims pulled down at 0.1-0.3 m/s made the sheet
# flap (vertex speeds up to 5 m/s) until the tracing travel bound stopped the run after 50-150
# steps, with a lighter filling sooner: not diagnosed yet, so the case measures cost, not the task.
TACO = {
    "name": "taco_bench",
    "dim": 3,
    "precision": "float64",
    "time": {"frame_dt": 2.0e-3, "substeps": "auto"},
    "mpm": {
        "grid": {"cells": 48},
        "boundary": {"type": "sticky"},
        "bodies": [
            {
                "name": "filling",
                "material": {"type": "plastic", "E": 5.0e4, "nu": 0.3, "density": 1000, "yield_stress": 1500},
                "shape": {"type": "box", "center": [0.5, 0.12, 0.5], "size": [0.3, 0.12, 0.3]},
            }
        ],
    },
    "cloth": [
        {
            "name": "tortilla",
            "mesh": {"type": "disc", "center": [0.5, 0.19, 0.5], "radius": 0.25, "rings": 8},
            "material": {"stretch": 2500, "bend": 0.75, "density": 0.2},
            "controls": [
                {"name": "left", "vertices": {"region": {"min": [0.2, 0.15, 0.3], "max": [0.3, 0.3, 0.7]}}},
                {"name": "right", "vertices": {"region": {"min": [0.7, 0.15, 0.3], "max": [0.8, 0.3, 0.7]}}},
            ],
            "actions": {"hold": 200, "initial": [0.0] * 6},  # held: see TACO's comment
        }
    ],
    "contact": {"model": "forecast", "friction": 0.2},
    "loss": {"type": "weighted_positions", "body": "filling"},
    "gradient": {"params": ["action"]},
    "optimize": {"params": ["action"]},
}


def measure_taco(steps: int, repeat: int) -> dict:
    """Forward + backward of the taco-sized scene over ``steps`` macro steps: seconds per iteration."""
    from cosim.scene import parse_scene

    scene = parse_scene({**TACO, "steps": steps}, origin="taco_bench")
    per_step, first = _forward_backward(scene, steps, repeat)
    from cosim.scene.cloth import build_mesh

    mesh = build_mesh(scene.cloth[0].mesh, scene.source_dir, "cloth[0].mesh")
    return {
        "cloth_vertices": mesh.n_vertices,
        "particles": int(sum(len(b) for b in _particles(scene))),
        "grid": f"{scene.cells[0]}^3",
        "steps": steps,
        "first_iteration_s": first,
        "iteration_s": steps * float(np.median(per_step)),
        "softmac_t4_s": 20.45,
    }


# ------------------------------------------------------------------------------------------ report


def _lines(result: dict) -> list[str]:
    lines = [
        f"Cloth benchmark: float64; medians of {result['repeat']} runs",
        "",
        "Cloth step alone (square sheet, pinned edge, gravity, dt 2e-3 s, k_stretch 1000 N/m, k_bend 0.015 N m):",
        "",
        "Linear solves by conjugate gradients preconditioned with an earlier LU (the engine's), against a fresh",
        "LU for every solve (direct):",
        "",
        (
            "| vertices | Newton iterations | forward ms/step | adjoint ms/step | LU a step "
            "| direct: forward ms/step | direct: adjoint ms/step | direct: LU a step |"
        ),
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["step"]["results"]:
        lines.append(
            f"| {r['vertices']} | {r['newton_iterations']:.1f} | {r['forward_ms']:.1f} | {r['adjoint_ms']:.1f} "
            f"| {r['factorisations_per_step']:.2f} | {r['direct_forward_ms']:.1f} | {r['direct_adjoint_ms']:.1f} "
            f"| {r['direct_factorisations_per_step']:.2f} |"
        )
    lines += [
        "",
        f"Nearest-face query, {QUERY_POINTS} points, band {QUERY_BAND:.4g} m (hash == brute force checked):",
        "",
        "| faces | within band | hash build ms (host) | update ms (build + upload) | hash query ms | brute ms | brute / hash |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["query"]:
        lines.append(
            f"| {r['faces']} | {100 * r['within_band']:.0f} % | {r['hash_build_ms']:.2f} | {r['update_ms']:.2f} | "
            f"{r['hash_query_ms']:.2f} | {r['brute_query_ms']:.1f} | {r['brute_vs_hash']:.0f} |"
        )
    c = result.get("coupled")
    if c:
        lines += [
            "",
            (
                f"towel_squash ({c['particles']} particles, {c['grid']}, {c['cloth_vertices']}-vertex towel, "
                f"K = {c['substeps']} substeps), ms per macro step:"
            ),
            "",
            "| | coupled | MPM alone | cloth alone | coupled / (MPM + cloth) |",
            "|---|---|---|---|---|",
            (
                f"| forward ({c['steps']} steps) | {c['coupled_ms']:.1f} | {c['mpm_ms']:.1f} | {c['cloth_ms']:.1f} | "
                f"{c['coupled_vs_sum']:.2f} |"
            ),
        ]
        if "fwd_bwd_coupled_ms" in c:
            lines.append(
                f"| forward + backward ({c['grad_steps']} steps) | {c['fwd_bwd_coupled_ms']:.1f} | "
                f"{c['fwd_bwd_mpm_ms']:.1f} | {c['fwd_bwd_cloth_ms']:.1f} | {c['fwd_bwd_coupled_vs_sum']:.2f} |"
            )
    t = result.get("taco")
    if t:
        lines += [
            "",
            (
                f"Taco-sized case ({t['cloth_vertices']}-vertex disc, {t['particles']} particles, {t['grid']}, "
                f"{t['steps']} steps): {t['iteration_s']:.1f} s per forward + backward iteration on this CPU "
                f"(first, with compilation: {t['first_iteration_s']:.1f} s); SoftMAC: {t['softmac_t4_s']} s on a "
                "T4 GPU (a different machine class)."
            ),
        ]
    lines += ["", "Scale anchors (published, not measured here):"] + [f"- {a}" for a in ANCHORS]
    return lines


def _write_partial(out_dir: Path, result: dict) -> None:
    """The parts measured so far (a long run keeps them if a later part fails)."""
    (out_dir / "cloth.json").write_text(json.dumps(result, indent=1) + "\n")


def run_cloth_bench(out_dir: Path, quick: bool = False, repeat: int = 3, command: str | None = None) -> int:
    """Every part; writes OUT/cloth.json and OUT/cloth.md (headed by ``command``, the date and the hardware) and
    prints the tables."""
    import datetime

    from cosim.bench.cloth_step import run_cloth_step_bench
    from cosim.bench.report import bench_command, report_header
    from cosim.hardware import hardware_line
    from cosim.runtime import ensure_taichi

    ensure_taichi("cpu", "float64")
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {"hardware": hardware_line(), "date": datetime.date.today().isoformat(), "repeat": repeat}
    sizes = [400, 2000] if quick else [400, 2000, 10000]
    print(f"  cloth step: {sizes} vertices", flush=True)
    result["step"] = run_cloth_step_bench(sizes, steps=4 if quick else 10)
    _write_partial(out_dir, result)
    print("  nearest-face query", flush=True)
    result["query"] = [measure_query(f, repeat=max(repeat, 5)) for f in QUERY_FACES]
    _write_partial(out_dir, result)
    print("  towel_squash: coupled, MPM alone, cloth alone", flush=True)
    steps, grad_steps = (10, 0) if quick else (60, 40)
    result["coupled"] = measure_coupled(steps, grad_steps, repeat)
    _write_partial(out_dir, result)
    if not quick:
        print("  taco-sized case", flush=True)
        result["taco"] = measure_taco(200, 1)
    lines = _lines(result)
    (out_dir / "cloth.json").write_text(json.dumps(result, indent=1) + "\n")
    header = report_header(command or bench_command("cloth"))
    (out_dir / "cloth.md").write_text(header + "\n".join(lines) + "\n")
    print(header + "\n".join(lines))
    print(f"wrote {out_dir}/cloth.json, cloth.md")
    return 0
