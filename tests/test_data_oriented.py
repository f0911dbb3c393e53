"""cosim's ``data_oriented``: kernels of a class (and of its bases) bound to the instance the way Taichi binds
them, their adjoints included, with Python's own lookup for everything else."""

import numpy as np
import taichi as ti

from cosim.engines.data_oriented import data_oriented


@data_oriented
class Squares:
    def __init__(self, n: int):
        self.x = ti.field(float, shape=n, needs_grad=True)
        self.y = ti.field(float, shape=(), needs_grad=True)

    @ti.kernel
    def total(self, scale: float):
        for i in self.x:
            self.y[None] += scale * self.x[i] ** 2


@data_oriented
class Shifted(Squares):
    @ti.kernel
    def shift(self, by: float):
        for i in self.x:
            self.x[i] += by


def test_a_kernel_and_its_adjoint_act_on_their_own_instance():
    """Two instances, one kernel: each writes its own fields; the adjoint of sum(s x^2) is 2 s x; an inherited
    kernel and the subclass's own act on the subclass's instance."""
    a, b = Squares(4), Shifted(4)
    values = np.arange(4.0)
    a.x.from_numpy(values)
    b.x.from_numpy(-values)
    b.shift(1.0)
    a.total(3.0)
    b.total(0.5)
    assert a.y[None] == 3.0 * np.sum(values**2)
    assert b.y[None] == 0.5 * np.sum((1.0 - values) ** 2)
    a.y.grad[None] = 1.0
    a.total.grad(3.0)
    np.testing.assert_allclose(a.x.grad.to_numpy(), 6.0 * values)
    np.testing.assert_array_equal(b.x.grad.to_numpy(), 0.0)
