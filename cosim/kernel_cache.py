"""Taichi's offline kernel cache shared by processes: its lock windows taken in turn, a dead writer's lock cleared.

How Taichi 1.7.4 locks its cache (``taichi/util/lock.h``, ``kernel_compilation_manager.cpp``,
``offline_cache.h``): ``ticache.lock`` in the cache directory, an empty file made with
``open(O_CREAT | O_EXCL)`` and deleted when done; it holds no PID. A process that finds it tries 4 more
times 50 ms apart (0.2 s), then warns "Lock ... failed" and goes on without the cache. Each Taichi
program takes it three times: to load the cache's index at its first kernel compile (on failure every
kernel compiles again), and at ``ti.reset`` or exit to trim the cache and to write the kernels it
compiled (on failure they are lost). Writing many kernels holds it longer than the others' 0.2 s of
retries. A process killed inside a window leaves the file for good: three warnings
and a cold start on every later run. A kernel file the kill cut short is never rewritten either (Taichi
writes only files that do not exist), so that kernel compiles on every run. Taichi's advice, ``ti cache
clean``, deletes the whole cache.

cosim takes each window (``window``) under an flock of its own, ``cosim.lock`` in the cache directory
(the kernel releases it when its holder dies), and writes its PID to ``cosim.owner`` while inside:

- cosim processes sharing a cache (pytest-xdist or Ray workers) take turns instead of missing each
  other's 0.2 s;
- ``cosim.owner`` found under the flock is a window whose process died: its ``ticache.lock`` and the
  kernel files written since it began are removed, with a one-line notice;
- a ``ticache.lock`` without it (another Taichi program's, or older than this) is removed with a notice
  when older than ``STALE_S``; a younger one still there after ``REPORT_AFTER_S`` is reported once with
  the command that removes it.

``start`` (after ``ti.init``) loads the index in a window and registers ``finish`` (``ti.reset`` in a
window) for exit, so Taichi writes the cache while Python still handles signals: a Ctrl-C then waits for
the write, where during the interpreter's teardown it killed it (the lock left, most kernel files
unwritten). A process killed outright (SIGKILL, or SIGTERM, which skips exit hooks) writes nothing
if it is between windows, or leaves the lock the next start clears.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import taichi as ti

TAICHI_LOCK = "ticache.lock"
FLOCK, OWNER = "cosim.lock", "cosim.owner"
STALE_S = 60.0  # no Taichi window lasts this long: writing even many kernels takes well under a second
REPORT_AFTER_S = 2.0  # how long a younger foreign lock may stay before it is reported
WAIT_S = 600.0  # the longest wait for another process's window before going on without the flock
_state = {"exit_registered": False, "reported": False}


@ti.kernel
def _no_op():
    pass


def cache_dir() -> Path | None:
    """The running Taichi's offline cache directory, None when its cache is off."""
    cfg = ti.lang.impl.current_cfg()
    return Path(cfg.offline_cache_file_path) if cfg.offline_cache else None


def start() -> None:
    """After ``ti.init``: Taichi loads its cache index (a no-op kernel's compile) in a window, a stale lock
    cleared first; ``finish`` is registered for exit."""
    with window(cache_dir()):
        _no_op()
    if not _state["exit_registered"]:
        atexit.register(_at_exit)
        _state["exit_registered"] = True


def finish() -> None:
    """``ti.reset`` in a window: Taichi trims its cache and writes the kernels it compiled since ``start``."""
    with window(cache_dir()):
        ti.reset()


def _at_exit() -> None:
    if ti.lang.impl.get_runtime().prog is not None:
        try:
            finish()
        except KeyboardInterrupt:  # Ctrl-C during the dump: Python raises it once Taichi has written the cache
            pass


@contextlib.contextmanager
def window(directory: Path | None) -> Iterator[None]:
    """Hold cosim's flock on the cache ``directory`` (None: no cache, nothing held), with a stale lock
    cleared and this process's PID in ``cosim.owner`` for the block's length."""
    if directory is None:
        yield
        return
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd = os.open(directory / FLOCK, os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:  # a read-only cache: Taichi will say so itself
        yield
        return
    owner = directory / OWNER
    try:
        held = _flock(fd, directory)
        if held:
            clear_stale_lock(directory)
            owner.write_text(f"{os.getpid()}\n")
        try:
            yield
        finally:
            if held:
                owner.unlink(missing_ok=True)
    finally:
        os.close(fd)  # releases the flock


def clear_stale_lock(directory: Path) -> None:
    """Under the flock: remove a dead window's ``ticache.lock`` and kernel files, or a foreign lock older
    than ``STALE_S`` (module docstring); report a younger foreign one once."""
    lock, owner = directory / TAICHI_LOCK, directory / OWNER
    try:
        began = owner.stat().st_mtime_ns
        pid = owner.read_text().strip() or "?"
    except OSError:
        began = None
    if began is not None:
        cut = [p for p in _kernel_files(directory) if _mtime_ns(p) >= began]
        for path in cut:
            path.unlink(missing_ok=True)
        had_lock = lock.exists()
        lock.unlink(missing_ok=True)
        owner.unlink(missing_ok=True)
        if had_lock or cut:
            _notice(
                f"cleared the Taichi kernel cache's lock {lock} left by cosim process {pid}, killed while it "
                f"held it ({len(cut)} kernel files it was writing removed)"
            )
        return
    try:
        age = time.time() - lock.stat().st_mtime
    except OSError:
        return
    if age > STALE_S:
        lock.unlink(missing_ok=True)
        _notice(f"removed a stale Taichi kernel-cache lock {lock} ({age:.0f} s old; no process writes for that long)")
    elif not _gone(lock, REPORT_AFTER_S) and not _state["reported"]:
        _state["reported"] = True
        _notice(
            f"the Taichi kernel cache is locked by another program since {age:.0f} s ago ({lock}); if none is "
            f"running, remove the lock: rm {lock}"
        )


def _flock(fd: int, directory: Path) -> bool:
    """Take the flock on ``fd``, waiting for another process's window up to ``WAIT_S``; whether it is held."""
    waited, told = time.monotonic(), False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            pass
        except OSError:  # a file system without flock: go on as Taichi alone would
            return False
        seconds = time.monotonic() - waited
        if seconds > WAIT_S:
            _notice(f"another process has held {directory / FLOCK} for {seconds:.0f} s; going on without it")
            return False
        if seconds > 10.0 and not told:
            told = True
            _notice(f"waiting for another cosim process to finish with the kernel cache in {directory}")
        time.sleep(0.02)


def _gone(path: Path, seconds: float) -> bool:
    """Whether ``path`` disappears within ``seconds`` (a live writer's lock does)."""
    end = time.monotonic() + seconds
    while path.exists():
        if time.monotonic() > end:
            return False
        time.sleep(0.02)
    return True


def _kernel_files(directory: Path) -> list[Path]:
    return list(directory.glob("*.tic"))


def _mtime_ns(path: Path) -> int:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return -1


def _notice(text: str) -> None:
    print(f"cosim: {text}", file=sys.stderr, flush=True)


def compile_seconds() -> float:
    """Seconds the running Taichi spent compiling kernels or loading them from the cache since its start-up
    (a warm start: little; 0.0 before one)."""
    prog = ti.lang.impl.get_runtime().prog
    return 0.0 if prog is None else float(prog.get_total_compilation_time())
