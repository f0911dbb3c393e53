"""How much memory the engines' device has, and how much of it their Taichi fields take.

On a GPU the memory is the card's (``nvidia-smi``); on a CPU the device is the host, and nothing here
bounds it. ``checkpoint_budget`` is what a gradient run may keep on the device besides the fields
(``cosim.engines.mpm_checkpoints``); ``cosim.adjoint.memory`` reports the same numbers before a run.
"""

from __future__ import annotations

import math
import shutil
import subprocess

import numpy as np

from cosim.engines.arch import CPU_ARCHES, running_arch

HEADROOM = 0.10  # of a GPU's memory left free for Taichi's runtime, its kernels' scratch and other users


def nvidia_smi(query: str) -> list[str]:
    """``nvidia-smi --query-gpu=<query>``'s value per GPU (no units), [] without the tool or a GPU."""
    if shutil.which("nvidia-smi") is None:
        return []
    args = ["nvidia-smi", f"--query-gpu={query}", "--format=csv,noheader,nounits"]
    try:
        res = subprocess.run(args, capture_output=True, text=True, timeout=20, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [line.strip() for line in res.stdout.splitlines() if line.strip()] if res.returncode == 0 else []


def gpu_memory_bytes() -> int | None:
    """The first GPU's total memory [bytes] (``nvidia-smi``), None without the tool or a GPU."""
    totals = nvidia_smi("memory.total")
    return int(float(totals[0]) * 2**20) if totals else None


def checkpoint_budget(objects: list, arch: str | None = None) -> int | None:
    """Bytes the device may hold besides the Taichi fields reachable from ``objects``: None (no bound)
    on a CPU, on a GPU its memory less ``HEADROOM`` and the fields, 0 where its memory is unknown."""
    arch = running_arch() if arch is None else arch
    if arch in CPU_ARCHES:
        return None
    total = gpu_memory_bytes() if arch == "cuda" else None
    if total is None:
        return 0
    return max(0, int(total * (1 - HEADROOM)) - taichi_field_bytes(objects))


def adjoint_allocated(field) -> bool:
    """Whether a Taichi field's adjoint holds memory: every field has a ``grad`` field object, placed only
    with ``needs_grad``."""
    grad = getattr(field, "grad", None)
    return grad is not None and grad.snode.ptr is not None


def taichi_field_bytes(objects: list) -> int:
    """Bytes of the Taichi fields reachable from the objects through cosim objects' attributes, lists
    and dicts (each field counted once), with their adjoints."""
    import taichi as ti
    from taichi.lang.util import to_numpy_type

    seen: set[int] = set()
    total = 0
    pending = list(objects)
    while pending:
        value = pending.pop()
        if id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, ti.Field):
            entries = getattr(value, "n", 1) * getattr(value, "m", 1)
            size = math.prod(value.shape) * entries * np.dtype(to_numpy_type(value.dtype)).itemsize
            total += size * (2 if adjoint_allocated(value) else 1)
        elif isinstance(value, (list, tuple)):
            pending.extend(value)
        elif isinstance(value, dict):
            pending.extend(value.values())
        elif type(value).__module__.startswith("cosim") and hasattr(value, "__dict__"):
            pending.extend(vars(value).values())
    return total
