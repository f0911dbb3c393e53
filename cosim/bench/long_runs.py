"""`cosim bench long`: one shipped scene of each type for 10,000 macro steps, under the runner's checks.

Each scene runs as `cosim run` would (``cosim.scale.jobs.run_case``: the runner's energy budget, the
tunnelling and CFL/NaN/domain guards on), far past its own length. Reported per scene: the outcome
(ran, or the guard's message), wall time, the largest energy excess over start + work done (negative:
dissipated), the work done on the material, the liquids' volume drift (min and max of sum V0 det F over
its start) and the particles that went through rigid bodies. ``OUT/long.csv`` and ``OUT/long.md``.
"""

from __future__ import annotations

import csv
from pathlib import Path

from cosim.errors import InputError
from cosim.hardware import hardware_line
from cosim.scale.pool import on_ray, run_cases

# one shipped scene per kind of scene: material x dimension x what it couples
SCENE_TYPES = {
    "elastic_bounce_2d": "elastic, 2D, controls",
    "dam_break_2d": "liquid, 2D",
    "plastic_squash_3d": "plastic, 3D, sticky walls",
    "jelly_torus_3d": "elastic mesh body, 3D",
    "shake_container_2d": "liquid in a moving kinematic container, 2D",
    "pour_water": "liquid and DART skeletons, 3D",
    "cloth_catch": "elastic, cloth and a DART box, 3D",
}
COLUMNS = [
    "scene",
    "type",
    "steps",
    "outcome",
    "wall_time_s",
    "energy_budget/max_excess",
    "energy_budget/work_done_J",
    "liquid_volume_ratio/min",
    "liquid_volume_ratio/max",
    "passed_through",
    "max_cfl",
]


def run_long_bench(
    out_dir: Path,
    steps: int = 10_000,
    quick: bool = False,
    workers: int | None = None,
    address: str | None = None,
    scenes: list[str] | None = None,
    command: str | None = None,
) -> int:
    """Run ``scenes`` (default every one of ``SCENE_TYPES``) for ``steps`` macro steps (``quick``: 200);
    writes long.csv and long.md (headed by ``command``, the date and the hardware); exit 3 if one stopped."""
    from cosim.bench.report import bench_command, report_header
    from cosim.scale.jobs import run_case
    from cosim.scene.shipped import scenes_dir

    steps = 200 if quick else steps
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = list(scenes or SCENE_TYPES)
    shipped = sorted(path.stem for path in scenes_dir().glob("*.yaml"))
    unknown = [name for name in names if name not in shipped]
    if unknown:
        raise InputError(f"bench long --scene: no shipped scene named {unknown}; the shipped scenes are {shipped}")
    cases = [(str(scenes_dir() / f"{name}.yaml"), {}, [], steps, False) for name in names]
    where = f"Ray, {workers or 'all'} workers" if on_ray(workers, address) else "one process, in turn"
    print(f"long runs: {len(names)} scenes x {steps} macro steps ({where}) on {hardware_line()}", flush=True)
    rows = []
    for outcome in run_cases(run_case, cases, workers, address):
        name = names[outcome.index]
        row = {"scene": name, "type": SCENE_TYPES.get(name, ""), "steps": steps}
        if outcome.ok:
            m = outcome.value
            through = int(sum(v for k, v in m.items() if k.startswith("particles_passed_through/")))
            row |= {k: m.get(k, "") for k in COLUMNS if k in m} | {"outcome": "ran", "passed_through": through}
        else:
            row["outcome"] = outcome.value
        rows.append(row)
        print(f"  {name}: {row['outcome']}, {_summary(row)}", flush=True)
    rows.sort(key=lambda r: names.index(r["scene"]))
    with open(out_dir / "long.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    (out_dir / "long.md").write_text(report_header(command or bench_command("long")) + _table(rows, steps))
    print(f"wrote {out_dir / 'long.csv'}, {out_dir / 'long.md'}")
    return 0 if all(r["outcome"] == "ran" for r in rows) else 3


def _number(row: dict, key: str, fmt: str) -> str:
    value = row.get(key)
    return "-" if value is None or value == "" else format(value, fmt)


def _summary(row: dict) -> str:
    if row["outcome"] != "ran":
        return ""
    return (
        f"{_number(row, 'wall_time_s', '.0f')} s, energy excess {_number(row, 'energy_budget/max_excess', '+.3g')} "
        f"(work {_number(row, 'energy_budget/work_done_J', '.3g')} J), liquid volume "
        f"{_number(row, 'liquid_volume_ratio/min', '.4f')}..{_number(row, 'liquid_volume_ratio/max', '.4f')}, "
        f"through walls {row['passed_through']}"
    )


def _table(rows: list[dict], steps: int) -> str:
    lines = [
        f"Long runs: {steps} macro steps per scene",
        "",
        "| scene | type | outcome | wall s | max energy excess | work J | liquid volume min..max | through walls |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["outcome"] != "ran":
            lines.append(f"| {r['scene']} | {r['type']} | {r['outcome']} | | | | | |")
            continue
        volume = f"{_number(r, 'liquid_volume_ratio/min', '.4f')}..{_number(r, 'liquid_volume_ratio/max', '.4f')}"
        lines.append(
            f"| {r['scene']} | {r['type']} | ran | {_number(r, 'wall_time_s', '.0f')} "
            f"| {_number(r, 'energy_budget/max_excess', '+.3g')} | {_number(r, 'energy_budget/work_done_J', '.3g')} "
            f"| {volume} | {r['passed_through']} |"
        )
    return "\n".join(lines) + "\n"
