"""`cosim bench contact --profile`: where a frame of the contact benchmark's grid run goes.

The paper's contact benchmark is a small scene (1,485 particles, a 64² grid): on a GPU its kernels take
microseconds, and a frame's time is what the host does around them (Python, launches, copies to and from
host arrays, each a wait for the device). This report splits a frame of the grid model's run (wall 1/32)
into what the profiler measured in kernels, the launches and host arrays the frame made and the tasks
the device ran (a GPU launches each task on its own; a serial one runs on one thread), then lists the
kernels. The wall time is taken with the profiler on (which adds a little to every task); the benchmark
itself (`cosim bench contact`) times the frames without it.
"""

from __future__ import annotations

import csv
import os
import time
from pathlib import Path

from cosim.bench.contact import GUARDS_OFF, THICKNESSES, ContainerRun
from cosim.bench.kernel_profile import by_kernel, counting_launches, profiler_records, task_counts
from cosim.errors import InputError
from cosim.guards import announce


def run_contact_profile(out_dir: Path, quick: bool = False, arch: str = "cpu", command: str | None = None) -> int:
    """Profile ``frames`` frames (50 with ``quick``, else 300) of the grid model's run after its first (which
    compiles); writes contact_profile.csv (a row per kernel) and contact_profile.md. Taichi must start here with
    its profiler (a process of its own: the ``cosim`` command)."""
    from cosim.bench.report import bench_command, report_header
    from cosim.runtime import ensure_taichi

    os.environ["COSIM_KERNEL_PROFILER"] = "1"
    ensure_taichi(arch, "float32")
    import taichi as ti
    from taichi.lang import impl

    if not impl.current_cfg().kernel_profiler:
        raise InputError(
            "bench contact --profile: Taichi already runs in this process without its kernel profiler; "
            "run it in a process of its own (the cosim command)"
        )
    announce(GUARDS_OFF)
    out_dir.mkdir(parents=True, exist_ok=True)
    frames = 50 if quick else 300
    run = ContainerRun("grid", None, THICKNESSES[0], frames + 1, arch=arch)
    run.advance(1)  # compiles
    sim, substeps = run.sim, 0
    ti.profiler.clear_kernel_profiler_info()
    with counting_launches() as tally:
        t0 = time.perf_counter()
        for _ in range(frames):
            substeps += sim.step().substeps
        ti.sync()
        wall = time.perf_counter() - t0
    records = profiler_records()
    kernels = by_kernel(records)
    per_frame = {key: count / frames for key, count in (tally | task_counts(records)).items()}
    in_kernels = sum(k[1] for k in kernels) / frames
    lines = [
        (
            f"Kernel profile of a frame of shake_container_2d (grid contact, wall 1/32), {frames} frames after the "
            f"first, Taichi on the {arch}, {substeps / frames:.2f} substeps a frame:"
        ),
        "",
        f"- wall: {1e3 * wall / frames:.3f} ms a frame (profiler on); in kernels {in_kernels:.3f} ms",
        (
            f"- {per_frame['launches']:.1f} launches ({per_frame['planned']:.1f} of them through their plans, not "
            f"Taichi's call: `cosim.engines.kernel_launch`), {per_frame['arrays']:.1f} host arrays and {per_frame['tasks']:.1f} "
            f"tasks a frame, {per_frame['serial']:.1f} of them serial (on a GPU each task is a launch of its own, a "
            "serial one on one thread)"
        ),
        "",
        "| kernel | ms a frame | launches a frame | tasks a launch | serial tasks a launch |",
        "|---|---|---|---|---|",
    ]
    rows = [[name, ms / frames, count / frames, *task_counts(records, name).values()] for name, ms, count in kernels]
    rows = [row[:3] + [row[3] / row[2] / frames, row[4] / row[2] / frames] for row in rows]
    lines += [f"| {name} | {ms:.4f} | {n:.2f} | {tasks:.1f} | {serial:.1f} |" for name, ms, n, tasks, serial in rows]
    with open(out_dir / "contact_profile.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["kernel", "ms_per_frame", "launches_per_frame", "tasks_per_launch", "serial_per_launch"])
        writer.writerows(rows)
    header = report_header(command or bench_command("contact", profile=True), guards_off=GUARDS_OFF)
    (out_dir / "contact_profile.md").write_text(header + "\n".join(lines) + "\n")
    print(header + "\n".join(lines))
    print(f"wrote {out_dir}/contact_profile.csv, contact_profile.md")
    return 0
