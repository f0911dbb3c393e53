"""The machine a measurement ran on, in one line, for every report that gives a figure."""

from __future__ import annotations

import functools
import os
import platform
from pathlib import Path


@functools.lru_cache(maxsize=1)
def gpu_names() -> str:
    """The machine's NVIDIA GPUs as ``nvidia-smi`` names them ("2 x NVIDIA H100 80GB HBM3"), "" without one."""
    from cosim.engines.device_memory import nvidia_smi

    names = nvidia_smi("name")
    if not names:
        return ""
    return names[0] if len(names) == 1 else f"{len(names)} x {names[0]}"


def hardware_line() -> str:
    """CPU model, core count and memory of this machine, and its GPU where it has one, for reports."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        import psutil

        mem = f", {psutil.virtual_memory().total / 2**30:.0f} GiB"
    except ImportError:
        pass
    gpu = gpu_names()
    return f"{cpu}, {os.cpu_count()} cores{mem}{f', GPU {gpu}' if gpu else ''}, Python {platform.python_version()}"
