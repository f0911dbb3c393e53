"""Worker processes that run fuzz cases with a wall-time limit each (hangs and hard crashes included).

Each worker is a spawned process (never forked: Taichi may hang in a fork) that keeps its Taichi
runtime across the cases it runs and answers one case at a time over a pipe. The driver hands
out cases as workers free up and gives each case ``timeout`` seconds [s] of wall time, start-up
included: a worker over it is killed and the case reported as a hang; a worker that dies
(a segfault in a kernel, an abort in DART) is reported as a crash with its exit code or signal
and the last lines of its log. Either way a fresh worker takes its place, and every
``recycle`` cases a worker is replaced anyway, which bounds the Taichi fields a long-lived
process accumulates. Workers print (Taichi's banner, DART's warnings) into ``log``, and keep their
compiled kernels in Taichi's offline cache under ``$COSIM_CACHE/taichi_fuzz`` (default
``~/.cache/cosim``), apart from the kernels every other run reuses.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Iterator
from multiprocessing.connection import wait
from pathlib import Path

_CONTEXT = multiprocessing.get_context("spawn")


def _serve(conn, job: Callable, threads: int, log: str) -> None:
    """A worker's loop: ``job(*args)`` for each ``args`` received until None arrives."""
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.environ["COSIM_CPU_THREADS"] = str(threads)
    # the kernels of random particle counts are rarely reused: cache them apart, so that they do not
    # push the kernels of the tests and the shipped scenes out of Taichi's size-limited offline cache
    cache = Path(os.environ.get("COSIM_CACHE", Path.home() / ".cache" / "cosim")) / "taichi_fuzz"
    os.environ.setdefault("TI_OFFLINE_CACHE_FILE_PATH", str(cache))
    from cosim.runtime import optimize_kernels

    optimize_kernels(False)  # compiles dominate a fuzz case; the cases check outcomes, not speed
    while True:
        args = conn.recv()
        if args is None:
            return
        conn.send(job(*args))


class _Worker:
    """One worker process, the case it is running (index, start time) and how many it has run."""

    def __init__(self, job: Callable, threads: int, log: str) -> None:
        self.log = log
        self.conn, child = _CONTEXT.Pipe()
        self.process = _CONTEXT.Process(target=_serve, args=(child, job, threads, log), daemon=True)
        self.process.start()
        child.close()
        self.case: int | None = None
        self.started = 0.0
        self.done = 0

    def submit(self, index: int, args: tuple) -> None:
        try:
            self.conn.send(args)
        except OSError:  # the worker is gone already: the driver's next wait sees its pipe closed
            pass
        self.case, self.started = index, time.monotonic()

    def stop(self) -> None:
        """Ask the worker to finish; kill it if it does not within a second (or is mid-case)."""
        if self.case is None and self.process.is_alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
            self.process.join(1.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.conn.close()

    def death(self) -> str:
        """Why the worker ended: its exit code or signal, and its log's last lines."""
        self.process.join(5.0)
        code = self.process.exitcode
        how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
        return f"the worker process died ({how}); its log ends: {tail(self.log)}"


def tail(path: str, lines: int = 4) -> str:
    """The last ``lines`` non-empty lines of a text file, joined with ' | ' ('' when unreadable)."""
    try:
        text = [line.strip() for line in Path(path).read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return " | ".join(text[-lines:])[-600:]


def run_guarded(
    job: Callable,
    argsets: list[tuple],
    workers: int = 1,
    timeout: float = 120.0,
    log_dir: Path | None = None,
    recycle: int = 50,
) -> Iterator[tuple[int, str, object, float]]:
    """``job(*args)`` for each of ``argsets`` on ``workers`` processes, yielded as (index, status, value,
    seconds) in the order they finish: status "ok" with the job's return value, "hang" (over ``timeout``
    [s]) or "died" with a message; seconds [s] of wall time since the case was handed out. ``job`` must be
    a module-level function and catch its own exceptions."""
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    logs = [os.devnull] * workers
    if log_dir is not None:
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        logs = [str(Path(log_dir) / f"worker_{k}.log") for k in range(workers)]
    pending = deque(enumerate(argsets))
    pool = [_Worker(job, threads, logs[k]) for k in range(min(workers, len(argsets)))]
    try:
        while pending or any(w.case is not None for w in pool):
            for w in pool:
                if w.case is None and pending:
                    w.submit(*pending.popleft())
            busy = [w for w in pool if w.case is not None]
            left = min(w.started + timeout for w in busy) - time.monotonic()
            ready = wait([w.conn for w in busy], timeout=max(0.0, left))
            for k, w in enumerate(pool):
                if w.case is None:
                    continue
                result = None
                if w.conn in ready:
                    try:
                        result = (w.case, "ok", w.conn.recv())
                    except (EOFError, OSError):
                        result = (w.case, "died", w.death())
                elif time.monotonic() - w.started > timeout:
                    result = (w.case, "hang", f"no result after {timeout:g} s; the worker was killed")
                if result is None:
                    continue
                yield (*result, time.monotonic() - w.started)
                w.done += 1
                if result[1] == "ok":
                    w.case = None
                if result[1] != "ok" or w.done >= recycle:
                    w.stop()  # kills a worker still in its case (a hang)
                    pool[k] = _Worker(job, threads, logs[k])
    finally:
        for w in pool:
            w.stop()
