"""``data_oriented``: Taichi's ``ti.data_oriented`` class decorator without its per-attribute lookup.

``ti.data_oriented`` replaces the class's ``__getattribute__`` with a Python function that, for
every attribute read on an instance (fields, settings, and ``__class__`` in each ``isinstance``
Taichi's kernel launch makes on its template arguments), looks the name up in the class dict,
checks for properties and kernels, and recurses into attributes that are data-oriented objects
themselves: dozens of such calls per kernel launch, hundreds per macro step of a small scene, where
kernels take microseconds. Here the class keeps Python's own attribute lookup and each kernel in its
dict becomes a descriptor (``_KernelMethod``) that binds it to the instance as Taichi does, to a
``kernel_launch.BoundKernel``, which launches it without Taichi's per-call Python once compiled: only
reading a kernel costs more than reading a plain attribute. Properties whose getter is a kernel, which
Taichi supports and these classes do not use, are not supported.
"""

from __future__ import annotations

import taichi as ti

from cosim.engines.kernel_launch import BoundKernel
from cosim.engines.taichi_frontend import memoise_front_end

memoise_front_end()  # every class with kernels comes through here: their front end formats less


class _KernelMethod:
    """A class kernel in a class dict; read on an instance, the kernel bound to it (and its ``grad``),
    launched through ``cosim.engines.kernel_launch`` (Taichi's call only until it is compiled)."""

    def __init__(self, func):
        func._is_staticmethod = False
        self.func = func

    def __get__(self, instance, owner=None):
        if instance is None:
            return self.func
        return BoundKernel(instance, self.func)


def data_oriented(cls: type) -> type:
    """``ti.data_oriented(cls)`` with Python's attribute lookup and its kernels bound by ``_KernelMethod``."""
    cls = ti.data_oriented(cls)
    cls.__getattribute__ = object.__getattribute__
    for name, value in list(vars(cls).items()):
        if getattr(value, "_is_wrapped_kernel", False) and value._is_classkernel:
            setattr(cls, name, _KernelMethod(value))
    return cls
