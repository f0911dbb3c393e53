"""Taichi's kernel-cache lock (cosim.kernel_cache): a run killed while Taichi writes the cache leaves a lock that
the next run clears, starting warm; stale and foreign locks are told apart."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

from cosim import kernel_cache


def _compile_seconds(out) -> float:
    return json.loads((out / "float32" / "metrics.json").read_text())["kernel_compile_s"]


def _complete(command: list[str], env: dict) -> subprocess.CompletedProcess:
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=300, check=False)


def _run(precision: str, out) -> list[str]:
    return [
        sys.executable, "-m", "cosim.cli", "run", "elastic_bounce_2d", "--steps", "1", "--no-preview", "--quiet",
        "--precision", precision, "--out", str(out / precision),
    ]  # fmt: skip


def test_a_run_killed_while_writing_the_kernel_cache_leaves_the_next_run_warm(tmp_path):
    """A cold float32 run fills a fresh cache; a float64 run (kernels of its own) is SIGKILLed while Taichi holds
    ticache.lock and writes its kernel files. The next float32 run prints no lock warning, says it cleared
    the lock, loads every kernel from the cache (compile time under a tenth of the cold run's, no kernel file
    written) and removes the files the killed run was writing (one cut short would never be rewritten)."""
    cache = tmp_path / "cache"
    env = os.environ | {"COSIM_TAICHI_CACHE": str(cache)}
    cold = _complete(_run("float32", tmp_path), env)
    assert cold.returncode == 0, cold.stderr
    kept = {p.name for p in cache.glob("*.tic")}
    cold_s = _compile_seconds(tmp_path)
    lock = cache / kernel_cache.TAICHI_LOCK

    victim = subprocess.Popen(_run("float64", tmp_path), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while victim.poll() is None:
        if lock.exists() and len(list(cache.glob("*.tic"))) > len(kept):  # inside Taichi's dump
            victim.send_signal(signal.SIGKILL)
            break
        time.sleep(0.002)
    victim.wait(timeout=60)
    assert victim.returncode == -signal.SIGKILL, "the float64 run ended before it was caught writing the cache"
    assert lock.exists()

    warm = _complete(_run("float32", tmp_path), env)
    assert warm.returncode == 0, warm.stderr
    assert "Lock" not in warm.stderr, warm.stderr
    assert "cleared the Taichi kernel cache's lock" in warm.stderr
    assert not lock.exists()
    assert _compile_seconds(tmp_path) < 0.1 * cold_s
    assert {p.name for p in cache.glob("*.tic")} == kept


def test_a_foreign_lock_is_removed_when_stale_and_reported_when_recent(tmp_path, capsys, monkeypatch):
    """Without cosim's owner file a lock is another program's: older than STALE_S it is removed with a
    notice; a recent one that stays is reported once with the rm command and left alone."""
    monkeypatch.setattr(kernel_cache, "REPORT_AFTER_S", 0.05)
    monkeypatch.setitem(kernel_cache._state, "reported", False)
    lock = tmp_path / kernel_cache.TAICHI_LOCK
    lock.touch()
    old = time.time() - 2 * kernel_cache.STALE_S
    os.utime(lock, (old, old))
    kernel_cache.clear_stale_lock(tmp_path)
    assert not lock.exists()
    assert "removed a stale Taichi kernel-cache lock" in capsys.readouterr().err

    lock.touch()
    kernel_cache.clear_stale_lock(tmp_path)
    kernel_cache.clear_stale_lock(tmp_path)
    assert lock.exists()
    assert capsys.readouterr().err.count(f"rm {lock}") == 1


def test_a_dead_windows_lock_and_kernel_files_go_and_older_files_stay(tmp_path, capsys):
    """cosim.owner left under the flock: its process died in a window; the lock and the kernel files
    written since the window began are removed, older kernel files kept."""
    old = tmp_path / "Told.tic"
    old.write_bytes(b"x")
    past = time.time() - 100
    os.utime(old, (past, past))
    (tmp_path / kernel_cache.OWNER).write_text("12345\n")
    cut = tmp_path / "Tnew.tic"
    cut.write_bytes(b"y")
    (tmp_path / kernel_cache.TAICHI_LOCK).touch()
    with kernel_cache.window(tmp_path):
        assert (tmp_path / kernel_cache.OWNER).read_text().strip() == str(os.getpid())
        assert not (tmp_path / kernel_cache.TAICHI_LOCK).exists()
    assert old.exists() and not cut.exists() and not (tmp_path / kernel_cache.OWNER).exists()
    assert "left by cosim process 12345" in capsys.readouterr().err


def test_the_window_waits_for_another_process(tmp_path):
    """Another process holding the flock makes ``window`` wait until it lets go."""
    script = tmp_path / "hold.py"
    script.write_text(
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "print('held', flush=True)\n"
        "time.sleep(0.5)\n"
    )
    holder = subprocess.Popen([sys.executable, str(script), str(tmp_path / kernel_cache.FLOCK)], stdout=subprocess.PIPE)
    assert holder.stdout.readline().strip() == b"held"
    t0 = time.perf_counter()
    with kernel_cache.window(tmp_path):
        waited = time.perf_counter() - t0
    holder.wait(timeout=10)
    assert 0.2 < waited < 5.0
