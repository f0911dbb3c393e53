"""What Taichi's kernels cost, read from its kernel profiler, and how many launches and host arrays a piece of
code makes: the tables of ``cosim bench mpm --profile`` and ``cosim bench contact --profile``.

Taichi's profiler records each task of a launch (a kernel's top-level loops and the serial code between them,
``_p2g_c84_0_kernel_1_range_for``); on a GPU each task is a launch of its own, and a serial one runs on one thread
(the statements between loops, and a loop's bounds when they are read from a field).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager


def profiler_records() -> list[list]:
    """Taichi's kernel profiler's records since it was last cleared: [task, ms in all, count], the device's
    work finished first."""
    import taichi as ti

    ti.sync()
    prof = ti.profiler.kernel_profiler.get_default_kernel_profiler()
    prof.get_total_time()  # collects the records into _statistical_results
    return [[s.name, s.total_time, s.counter] for s in prof._statistical_results.values()]  # no public list in 1.7


def by_kernel(records: list) -> list[list]:
    """Taichi's per-task records [name, ms, count] summed per kernel: a launch's tasks
    (``_p2g_c84_0_kernel_1_range_for``) and its template instances (``_c84_0``, ``_c84_1``) are one row
    ``[kernel, ms, launches]`` (``_p2g``; adjoints keep ``_reverse_grad``), most time first."""
    launches: dict[str, list] = {}
    for name, ms, count in records:
        instance, _, _ = name.partition("_kernel_")
        row = launches.setdefault(instance, [0.0, 0.0])
        row[0] += ms
        row[1] = max(row[1], count)  # every task of a launch runs once per launch
    kernels: dict[str, list] = {}
    for instance, (ms, count) in launches.items():
        name = re.sub(r"_c\d+_\d+", "", instance)
        row = kernels.setdefault(name, [name, 0.0, 0.0])
        row[1] += ms
        row[2] += count
    return sorted(kernels.values(), key=lambda r: -r[1])


def by_task(records: list, kernel: str) -> list[tuple[str, float]]:
    """The parallel loops of ``kernel`` (a ``by_kernel`` row's name) with more than one: [(task, ms)], in
    the kernel's order, a task's template instances summed (``kernel_3_range_for``: its fourth loop)."""
    tasks: dict[str, float] = {}
    for name, ms, _count in records:
        instance, _, task = name.partition("_kernel_")
        if re.sub(r"_c\d+_\d+", "", instance) == kernel:
            tasks[f"kernel_{task}"] = tasks.get(f"kernel_{task}", 0.0) + ms
    order = sorted(tasks, key=lambda t: int(re.match(r"kernel_(\d+)", t).group(1)))
    return [(t, tasks[t]) for t in order] if len(order) > 1 else []


def task_counts(records: list, kernel: str | None = None) -> dict[str, int]:
    """{"tasks": n, "serial": m}: tasks run (each a launch of its own on a GPU) and those of them on one thread,
    of every kernel or of ``kernel`` (a ``by_kernel`` row's name)."""
    mine = [r for r in records if kernel is None or re.sub(r"_c\d+_\d+", "", r[0].partition("_kernel_")[0]) == kernel]
    tasks = sum(count for _name, _ms, count in mine)
    serial = sum(count for name, _ms, count in mine if name.endswith("_serial"))
    return {"tasks": tasks, "serial": serial}


@contextmanager
def counting_launches() -> Iterator[dict]:
    """Counts Taichi kernel launches and the host (NumPy) arrays handed to them while inside (on a GPU each
    host array is a copy and a wait): yields {"launches": n, "arrays": m, "planned": k}, k of the launches
    through their plan (``cosim.engines.kernel_launch``), not Taichi's call."""
    import numpy as np
    from taichi.lang import kernel_impl

    from cosim.engines import kernel_launch

    original, lean = kernel_impl.Kernel.__call__, kernel_launch._set_and_launch
    tally = {"launches": 0, "arrays": 0, "planned": 0}

    def count(args: tuple) -> None:
        tally["launches"] += 1
        tally["arrays"] += sum(isinstance(a, np.ndarray) for a in args)

    def counted(self, *args, **kwargs):  # Taichi's call (a first call, a field's own kernels)
        count(args)
        return original(self, *args, **kwargs)

    def counted_lean(plan, kinds, args):  # a planned launch (``cosim.engines.kernel_launch``)
        count(args)
        tally["planned"] += 1
        return lean(plan, kinds, args)

    kernel_impl.Kernel.__call__, kernel_launch._set_and_launch = counted, counted_lean
    try:
        yield tally
    finally:
        kernel_impl.Kernel.__call__, kernel_launch._set_and_launch = original, lean
