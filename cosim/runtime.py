"""Taichi start-up, once per process, with the scene's architecture and precision.

Taichi can be initialised only once at a time; a scene asking for another
precision or architecture re-initialises it, which invalidates every Taichi
field made before. One process therefore runs one configuration at a time,
and tests group themselves by precision.
"""

from __future__ import annotations

import os

_current: tuple[str, str] | None = None


def taichi_precision(precision: str):
    import taichi as ti

    return {"float32": ti.f32, "float64": ti.f64}[precision]


def ensure_taichi(arch: str = "cpu", precision: str = "float64") -> None:
    """Initialise Taichi for ``arch`` ('cpu' or 'cuda') and ``precision``.

    A no-op when Taichi already runs with the same settings. 'cuda' falls back
    to the CPU with a warning when no GPU is present (Taichi's own behaviour).
    """
    global _current
    key = (arch, precision)
    if _current == key:
        return
    import taichi as ti

    if _current is not None:
        ti.reset()
    arch_obj = {"cpu": ti.cpu, "cuda": ti.cuda, "gpu": ti.gpu}[arch]
    debug = os.environ.get("COSIM_TAICHI_DEBUG", "") == "1"
    ti.init(
        arch=arch_obj,
        default_fp=taichi_precision(precision),
        default_ip=ti.i32,
        debug=debug,
        log_level=ti.WARN,
        random_seed=0,
    )
    _current = key


def current() -> tuple[str, str] | None:
    """The (arch, precision) Taichi runs with, or None before start-up."""
    return _current
