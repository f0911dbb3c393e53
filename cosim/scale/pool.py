"""Run jobs on Ray actors: local Ray on this machine's cores by default, a cluster given its address.

Each actor is one worker process that keeps its Taichi runtime and kernel cache across the
cases it runs (Taichi initialises once per process and compiles a kernel once per
configuration). Actors declare the CPUs they use (Ray's default for actors is 0, which would
oversubscribe the cores), and Taichi in each is capped to that many threads. Cases are handed
out by ``ray.util.ActorPool`` as workers free up; results come back in the order they finish.
A job that raises is returned as a failure with its message, and the other cases go on.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any


@dataclass
class Outcome:
    """One case: its index in the input, whether it succeeded, and its result or error message."""

    index: int
    ok: bool
    value: Any


class _Worker:
    """A Ray actor (made remote in ``run_jobs``): Taichi capped to ``threads``, then runs jobs."""

    def __init__(self, threads: int, optimize_kernels: bool) -> None:
        os.environ["COSIM_CPU_THREADS"] = str(threads)
        if optimize_kernels:
            from cosim.runtime import optimize_kernels as enable

            enable(True)

    def run(self, index: int, job: Callable, args: tuple) -> Outcome:
        try:
            return Outcome(index, True, job(*args))
        except Exception as exc:  # noqa: BLE001 - any failure is this case's result; the others go on
            return Outcome(index, False, f"{type(exc).__name__}: {exc}")


def default_workers() -> int:
    """The cores of this machine."""
    return os.cpu_count() or 1


def on_ray(workers: int | None, address: str | None) -> bool:
    """Whether cases go to Ray: more than one worker asked for, or a cluster address."""
    return bool(address) or (workers or 1) > 1


def run_cases(
    job: Callable, argsets: list[tuple], workers: int | None = None, address: str | None = None
) -> Iterator[Outcome]:
    """``run_jobs`` when ``on_ray``, else every case in this process, one after the other, with the
    same ``Outcome``s (a failing case is recorded and the rest go on)."""
    if on_ray(workers, address):
        yield from run_jobs(job, argsets, workers, address)
        return
    for index, args in enumerate(argsets):
        try:
            yield Outcome(index, True, job(*args))
        except Exception as exc:  # noqa: BLE001 - any failure is this case's result; the others go on
            yield Outcome(index, False, f"{type(exc).__name__}: {exc}")


def run_jobs(
    job: Callable,
    argsets: list[tuple],
    workers: int | None = None,
    address: str | None = None,
) -> Iterator[Outcome]:
    """``job(*args)`` for every ``args`` of ``argsets`` on ``workers`` Ray actors, yielded as they finish.

    Without ``address``: a local Ray with ``workers`` processes (default: the cores) and no
    dashboard; each worker gets cores // workers Taichi threads. With it: the cluster at that
    address, one CPU per worker, ``workers`` defaulting to the cluster's CPUs.
    """
    import ray
    from ray.util import ActorPool

    if address is None:
        workers = workers or default_workers()
        threads = max(1, default_workers() // workers)
        ray.init(num_cpus=workers * threads, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    else:
        ray.init(address=address, log_to_driver=False, logging_level=logging.ERROR)
        threads = 1
        workers = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
    from cosim.runtime import kernels_optimized

    try:
        remote = ray.remote(num_cpus=threads)(_Worker)
        actors = [remote.remote(threads, kernels_optimized()) for _ in range(min(workers, len(argsets)) or 1)]
        pool = ActorPool(actors)
        tasks = list(enumerate(argsets))
        yield from pool.map_unordered(lambda actor, task: actor.run.remote(task[0], job, task[1]), tasks)
    finally:
        ray.shutdown()
