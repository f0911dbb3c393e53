"""The lean launch of class kernels (``cosim.engines.kernel_launch``): once Taichi has compiled a kernel for a
call's kinds of arguments, later calls launch that compiled kernel without Taichi's call, chosen by the same
template arguments and array types as Taichi chooses, with the same numbers; what it does not cover goes to
Taichi, errors included."""

import numpy as np
import pytest
import taichi as ti
from taichi.lang.kernel_impl import _BoundedDifferentiableMethod

from cosim.engines import kernel_launch
from cosim.engines.data_oriented import data_oriented

N = 7


@data_oriented
class Accumulator:
    """y += +-(a x + k) (the sign a template argument), and y read out as (y, 2 y) pairs."""

    def __init__(self):
        self.y = ti.field(float, shape=N)

    @ti.kernel
    def add(self, a: float, k: ti.i32, x: ti.types.ndarray(), negate: ti.template()):
        for i in range(N):
            v = a * x[i] + k
            if ti.static(negate):
                v = -v
            self.y[i] += v

    @ti.kernel
    def pairs(self, out: ti.types.ndarray(dtype=ti.math.vec2, ndim=1)):
        for i in range(N):
            out[i] = ti.Vector([self.y[i], 2 * self.y[i]])


def taichis_own(acc: Accumulator, name: str):
    """The kernel bound as ``ti.data_oriented`` binds it: Taichi's call every time (the reference)."""
    return _BoundedDifferentiableMethod(acc, getattr(Accumulator, name))


@pytest.fixture
def taichi_calls(monkeypatch) -> list:
    """The names of the kernels launched through Taichi's call, in order."""
    calls, original = [], kernel_launch._taichi_call

    def counted(kernel, args, kwargs):
        calls.append(kernel.func.__name__)
        return original(kernel, args, kwargs)

    monkeypatch.setattr(kernel_launch, "_taichi_call", counted)
    return calls


def calls_of_every_kind(add):
    """add's calls: both signs, float64 and float32 NumPy arrays and a Taichi one, ints of NumPy and
    Python, twice over."""
    x64 = np.linspace(-1.0, 2.0, N)
    on_device = ti.ndarray(ti.f64, N)
    on_device.from_numpy(x64[::-1].copy())
    for a, k, x, negate in [
        (1.5, 2, x64, False),
        (1.5, 2, x64, True),
        (0.25, np.int32(-3), x64.astype(np.float32), False),
        (3.0, -1, on_device, True),
        (-0.5, 1, x64, False),  # planned from here on
        (2, 4, x64, True),
        (0.75, 5, x64.astype(np.float32), False),
        (-1.25, 2, on_device, True),
    ]:
        add(a, k, x, negate)


def test_planned_launches_run_the_kernel_taichi_compiled_for_their_template_and_array_arguments(taichi_calls):
    """The second of each kind of call (sign, array dtype, NumPy's or Taichi's array) launches through its
    plan and leaves y bit for bit where Taichi's own calls do; a plan that ignored the template argument or
    the array's dtype or kind would add with the wrong sign, read float32 as float64 or a device array as a
    host one."""
    mine, reference = Accumulator(), Accumulator()
    calls_of_every_kind(mine.add)
    calls_of_every_kind(taichis_own(reference, "add"))
    np.testing.assert_array_equal(mine.y.to_numpy(), reference.y.to_numpy())
    assert taichi_calls == ["add"] * 4  # the first call of each of the four kinds
    out, want = np.zeros((N, 2)), np.zeros((N, 2))
    mine.pairs(out)
    mine.pairs(out)  # planned: a vector element type
    taichis_own(reference, "pairs")(want)
    np.testing.assert_array_equal(out, want)
    assert taichi_calls == ["add"] * 4 + ["pairs"]


def test_what_a_plan_does_not_cover_goes_through_taichi_and_its_checks(taichi_calls):
    """After a planned call: a string for an int, a strided array and a keyword argument each go to Taichi,
    which refuses the first two; a field made since (not yet placed in a tree) sends the next call to Taichi
    too, which places it."""
    acc, x = Accumulator(), np.ones(N)
    acc.add(1.0, 1, x, False)
    acc.add(1.0, 1, x, False)
    assert taichi_calls == ["add"]
    with pytest.raises(ti.TaichiRuntimeTypeError):
        acc.add(1.0, "1", x, False)
    with pytest.raises(ValueError, match="Non contiguous"):
        acc.add(1.0, 1, np.ones(2 * N)[::2], False)
    acc.add(1.0, 1, x, negate=False)
    assert taichi_calls == ["add"] * 4
    later = ti.field(float, shape=3)
    acc.add(1.0, 1, x, False)
    assert taichi_calls == ["add"] * 5
    later.fill(2.0)
    np.testing.assert_array_equal(later.to_numpy(), 2.0)
    np.testing.assert_array_equal(acc.y.to_numpy(), 4 * 2.0)  # the four calls that ran: 1 x + 1 each
