"""Class kernels launched without Taichi's per-call Python once they are compiled for their arguments.

Taichi's ``Kernel.__call__`` spends tens of microseconds of Python on every launch before the kernel runs: it sorts every
argument into a template key (several ``isinstance`` tests each), looks the compiled instance up by that key,
checks the fields are placed, then sets each argument through a chain of type tests. A small scene's frame
launches ten kernels whose loops take microseconds (``cosim bench contact --profile``), and on a GPU the
host's time is the frame's time. ``BoundKernel`` does that sorting once per (instance, kernel, argument
kinds): the first call of a kind goes through Taichi (which compiles it and checks everything); later calls
with template arguments that are the same objects (or equal numbers, strings, tuples of them), scalars of
the kernel's types and arrays (NumPy's or Taichi's) of the same dtype and dimensions only set the scalars
and array pointers on a launch context and launch the code Taichi compiled for them: the same compiled
kernel with the same arguments, hence the same numbers.

Taichi's call still takes whatever the lean path does not cover: keyword arguments, matrix, struct and
argument-pack arguments, kernels that return values or print, non-contiguous arrays, Taichi's own autodiff
tapes, a call while new fields wait to be placed, and a Taichi runtime started anew. Taichi is pinned
(1.7.4): the launch-context calls used here are those its ``launch_kernel`` makes.
"""

from __future__ import annotations

import numpy as np
from taichi.lang import impl
from taichi.lang._ndarray import Ndarray
from taichi.lang.enums import Layout
from taichi.lang.exception import TaichiCompilationError, TaichiRuntimeError, handle_exception_from_cpp
from taichi.lang.util import cook_dtype
from taichi.types import ndarray_type, primitive_types
from taichi.types.annotations import template
from taichi.types.utils import is_signed

_TEMPLATE, _FLOAT, _INT, _UINT, _ARRAY = range(5)
_SCALARS = (bool, int, float, str, type(None), np.generic)
_UNSET = object()  # a kernel's kinds not yet read


def _argument_kinds(kernel) -> tuple | None:
    """(kind, element dimensions of an array) of each of ``kernel``'s arguments, or None where one is of a
    kind the lean path does not set."""
    kinds = []
    for argument in kernel.arguments:
        anno = argument.annotation
        if isinstance(anno, template):
            kinds.append((_TEMPLATE, 0))
        elif id(anno) in primitive_types.real_type_ids:
            kinds.append((_FLOAT, 0))
        elif id(anno) in primitive_types.integer_type_ids:
            kinds.append((_INT if is_signed(cook_dtype(anno)) else _UINT, 0))
        elif isinstance(anno, ndarray_type.NdarrayType) and anno.layout == Layout.AOS:
            scalar = anno.dtype is None or id(anno.dtype) in primitive_types.type_ids
            kinds.append((_ARRAY, 0 if scalar else anno.dtype.ndim))
        else:
            return None
    return tuple(kinds)


def _template_key(value):
    """What tells one compiled instance from another: a number or string by type and value, a tuple by its
    items, anything else by identity (the plan holds the object, so its id is not reused meanwhile); None
    where the lean path does not key it (a list, a dict, a set, or a tuple holding one)."""
    if isinstance(value, _SCALARS):
        return (type(value), value)  # the type too: Taichi's key takes 1 and True as one, this plan need not
    if type(value) is tuple:
        items = tuple(_template_key(item) for item in value)
        return None if None in items else items
    if isinstance(value, (list, dict, set)):
        return None
    return id(value)


class _Plan:
    """One compiled instance of a kernel: Taichi's kernel, its compiled code (a reference into the program's
    cache of compiled kernels, which keeps it for the program's life) and that program."""

    __slots__ = ("code", "compiled", "held", "program")

    def __init__(self, compiled, program, held: tuple):
        self.compiled = compiled  # Taichi's C++ kernel
        self.program = program
        self.code = program.compile_kernel(program.config(), program.get_device_caps(), compiled)  # served cached
        self.held = held  # the template arguments, alive while their ids key this plan


class BoundKernel:
    """A class kernel bound to its instance (Taichi's ``_BoundedDifferentiableMethod``, with ``grad``),
    launched through its ``_Plan`` once Taichi has compiled it for arguments of the same kinds."""

    __slots__ = ("__name__", "adjoint", "owner", "primal")

    def __init__(self, owner, wrapped):
        self.owner = owner
        self.primal = wrapped._primal
        self.adjoint = wrapped._adjoint
        self.__name__ = wrapped.__name__

    def __call__(self, *args, **kwargs):
        return _launch(self.primal, self.owner, args, kwargs)

    def grad(self, *args, **kwargs):
        return _launch(self.adjoint, self.owner, args, kwargs)


def _launch(kernel, owner, args: tuple, kwargs: dict):
    """``kernel(owner, *args)``: through its plan where one fits and the runtime is idle, else through Taichi
    (and then planned: Taichi has compiled it and placed every field)."""
    args = (owner, *args)
    kinds = _kinds(kernel)
    plannable = not kwargs and kinds is not None and len(args) == len(kinds)
    key = _call_key(kinds, args) if plannable else None
    plans = owner.__dict__.setdefault("_kernel_plans", {}) if key is not None else None
    plan = plans.get((kernel, key)) if plans is not None else None
    runtime = impl.get_runtime()
    if plan is not None and plan.program is runtime.prog and _runtime_idle(runtime):
        _set_and_launch(plan, kinds, args)
        return None
    out = _taichi_call(kernel, args, kwargs)
    if key is not None and not kernel.has_print:
        compiled = kernel.compiled_kernels[kernel.ensure_compiled(*args)]
        held = tuple(a for a, (kind, _) in zip(args[1:], kinds[1:]) if kind == _TEMPLATE)
        plans[(kernel, key)] = _Plan(compiled, runtime.prog, held)
    return out


def _kinds(kernel) -> tuple | None:
    """``_argument_kinds`` of a kernel, kept on it (its arguments are read when it is made)."""
    kinds = getattr(kernel, "_lean_kinds", _UNSET)
    if kinds is _UNSET:
        kinds = None if kernel.return_type is not None else _argument_kinds(kernel)
        kernel._lean_kinds = kinds
    return kinds


def _runtime_idle(runtime) -> bool:
    """No Taichi autodiff tape recording, the runtime started and no field waiting to be placed."""
    fields = impl._root_fb
    return (
        runtime.materialized
        and not runtime.target_tape
        and not runtime.fwd_mode_manager
        and (fields.finalized or fields.empty)
    )


def _call_key(kinds: tuple, args: tuple):
    """The key of a call's plan among its owner's (``args[0]``, not in the key), or None where an argument
    takes Taichi's path."""
    key = []
    for (kind, element_dims), value in zip(kinds[1:], args[1:]):
        if kind == _TEMPLATE:
            part = _template_key(value)
            if part is None:
                return None
            key.append(part)
        elif kind == _FLOAT:
            if not isinstance(value, (float, int, np.floating, np.integer)):
                return None
        elif kind == _ARRAY:
            if type(value) is np.ndarray and value.flags.c_contiguous:
                key.append((value.dtype, value.ndim, value.shape[value.ndim - element_dims :] if element_dims else ()))
            elif isinstance(value, Ndarray):  # Taichi's own array, on the device (checkpoints)
                key.append((type(value), value.element_type, len(value.shape), value.grad is not None))
            else:
                return None
        elif not isinstance(value, (int, np.integer)):
            return None
    return tuple(key)


def _set_and_launch(plan: _Plan, kinds: tuple, args: tuple) -> None:
    """Set the call's scalars and array pointers on a launch context and launch the planned kernel: what
    Taichi's ``Kernel.launch_kernel`` does for these kinds of arguments."""
    context = plan.compiled.make_launch_context()
    index = 0
    for (kind, element_dims), value in zip(kinds, args):
        if kind == _TEMPLATE:
            continue
        slot = (index,)
        if kind == _FLOAT:
            context.set_arg_float(slot, float(value))
        elif kind == _INT:
            context.set_arg_int(slot, int(value))
        elif kind == _UINT:
            context.set_arg_uint(slot, int(value))
        elif type(value) is np.ndarray:
            shape = value.shape[: value.ndim - element_dims] if element_dims else value.shape
            context.set_arg_external_array_with_shape(slot, int(value.ctypes.data), value.nbytes, shape, 0)
        elif value.grad is None:
            context.set_arg_ndarray(slot, value.arr)
        else:
            context.set_arg_ndarray_with_grad(slot, value.arr, value.grad.arr)
        index += 1
    try:
        plan.program.launch_kernel(plan.code, context)
    except Exception as e:  # noqa: BLE001  (as Taichi's launch reports a failed kernel: its C++ exceptions)
        raise handle_exception_from_cpp(e) from None


def _taichi_call(kernel, args: tuple, kwargs: dict):
    """Taichi's own call, with its error messages as its bound methods give them."""
    try:
        return kernel(*args, **kwargs)
    except (TaichiCompilationError, TaichiRuntimeError) as e:
        if impl.get_runtime().print_full_traceback:
            raise
        raise type(e)("\n" + str(e)) from None
