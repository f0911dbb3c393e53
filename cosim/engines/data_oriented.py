"""``data_oriented``: Taichi's ``ti.data_oriented`` class decorator with a faster attribute lookup.

``ti.data_oriented`` replaces the class's ``__getattribute__`` with a Python function that, for
every attribute read on an instance (fields, settings, and ``__class__`` in each ``isinstance``
Taichi's kernel launch makes on its template arguments), looks the name up in the class dict,
checks for properties and kernels, and recurses into attributes that are data-oriented objects
themselves: dozens of such calls per kernel launch. On small scenes, where kernels take
microseconds, that is a large share of a step. The lookup below does the same for what our classes hold
(plain attributes, methods, kernels): the attribute by the normal rules, and a kernel bound to
the instance the way Taichi binds it. Properties whose getter is a kernel, which Taichi supports
and these classes do not use, are not.
"""

from __future__ import annotations

import types

import taichi as ti
from taichi.lang.kernel_impl import _BoundedDifferentiableMethod

from cosim.engines.taichi_frontend import memoise_front_end

memoise_front_end()  # every class with kernels comes through here: their front end formats less


def _getattribute(self, name: str):
    value = object.__getattribute__(self, name)
    if type(value) is types.MethodType:
        func = value.__func__
        if getattr(func, "_is_wrapped_kernel", False) and func._is_classkernel:
            func._is_staticmethod = False
            bound = _BoundedDifferentiableMethod(self, func)
            bound.__name__ = func.__name__
            return bound
    return value


def data_oriented(cls: type) -> type:
    """``ti.data_oriented(cls)`` with the faster ``__getattribute__`` above."""
    cls = ti.data_oriented(cls)
    cls.__getattribute__ = _getattribute
    return cls
