"""Taichi fields handed on from an object that is gone to the next one built with the same layout.

Taichi compiles a data-oriented object's kernels for that object's fields, so an engine built again
in the same process (the next test, sweep case or optimisation start) compiled every kernel anew,
although nothing but the fields differed. Given the same fields, its kernels lower to the same IR and
Taichi's in-process cache serves them compiled: only the Python front end runs again. Hence the
objects with kernels take their fields from here: the k-th field that an object of class C asks for
with a given kind, shape and gradient flag is the k-th field of an earlier object of class C, with
that layout, that has been collected, zeroed as a new field would be. Reuse never changes a
result: a kernel whose IR differs in anything else (a constant baked into it, another object's
field, a static loop) is compiled as before. Whoever keeps a field keeps its owner alive.

Taichi's fields live until ``ti.reset``: ``clear`` forgets them then (``cosim.runtime``).
"""

import gc
import time
import weakref

import taichi as ti

_free: dict[tuple, list] = {}  # layout key -> fields of collected owners
_live: dict[str, int] = {}  # owner class -> owners holding fields now
_last_collect = [0.0]
_generation = [0]  # bumped by ``clear``: owners of an earlier Taichi start-up hand nothing back
COLLECT_EVERY_S = 1.0  # a missed field runs the cycle collector at most this often


class _Held(list):
    """An owner's (key, field) pairs, handed back when the owner is collected."""

    def __init__(self, cls: str):
        super().__init__()
        self.cls = cls
        self.generation = _generation[0]


def scalar(owner, dtype, shape, needs_grad: bool = False):
    """``ti.field(dtype, shape=shape, needs_grad=needs_grad)`` for ``owner``, reused where it can be."""
    return _field(owner, ("scalar", dtype), shape, needs_grad)


def vector(owner, n: int, dtype, shape, needs_grad: bool = False):
    """``ti.Vector.field(n, dtype, shape=shape, needs_grad=needs_grad)`` for ``owner``."""
    return _field(owner, ("vector", n, dtype), shape, needs_grad)


def matrix(owner, n: int, m: int, dtype, shape, needs_grad: bool = False):
    """``ti.Matrix.field(n, m, dtype, shape=shape, needs_grad=needs_grad)`` for ``owner``."""
    return _field(owner, ("matrix", n, m, dtype), shape, needs_grad)


def clear() -> None:
    """Forget every field (before ``ti.reset``, which frees them)."""
    _free.clear()
    _live.clear()
    _generation[0] += 1


def _field(owner, kind: tuple, shape, needs_grad: bool):
    held = owner.__dict__.get("_pooled_fields")
    if held is None:
        cls = type(owner).__qualname__
        held = owner.__dict__["_pooled_fields"] = _Held(cls)
        _live[cls] = _live.get(cls, 0) + 1
        weakref.finalize(owner, _release, held)
    shape = (int(shape),) if isinstance(shape, int) else tuple(int(s) for s in shape)
    key = (held.cls, len(held), kind, shape, bool(needs_grad))
    field = _take(key)
    if field is None:
        field = _make(kind, shape, needs_grad)
    held.append((key, field))
    return field


def _take(key: tuple):
    free = _free.get(key)
    if not free and _live.get(key[0], 0) > 1 and time.monotonic() - _last_collect[0] > COLLECT_EVERY_S:
        _last_collect[0] = time.monotonic()
        gc.collect()  # an earlier owner in a reference cycle: collected now, its fields come back
        free = _free.get(key)
    if not free:
        return None
    field = free.pop(0)
    field.fill(0)
    if key[4]:
        field.grad.fill(0)
    return field


def _make(kind: tuple, shape: tuple, needs_grad: bool):
    if kind[0] == "scalar":
        return ti.field(kind[1], shape=shape, needs_grad=needs_grad)
    if kind[0] == "vector":
        return ti.Vector.field(kind[1], kind[2], shape=shape, needs_grad=needs_grad)
    return ti.Matrix.field(kind[1], kind[2], kind[3], shape=shape, needs_grad=needs_grad)


def _release(held: _Held) -> None:
    if held.generation != _generation[0]:
        return  # its fields went with ti.reset
    _live[held.cls] = _live.get(held.cls, 1) - 1
    for key, field in held:
        _free.setdefault(key, []).append(field)
