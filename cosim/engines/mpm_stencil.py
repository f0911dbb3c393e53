"""The MPM's stencil: quadratic B-spline weights of the 3^d grid nodes around a particle, and the sums
the transfers (P2G, G2P and their adjoints, the contact models' look-ahead) make over them.

``StencilFunctions`` is a base of ``MPMKernels``; its Taichi functions read the engine's ``dim``,
``inv_dx``, ``nodes`` and ``rows`` (``stencil_rows``).
"""

import itertools

import taichi as ti

from cosim.engines.data_oriented import data_oriented


def stencil_rows(dim: int) -> list[tuple[int, ...]]:
    """The stencil's rows of three nodes along the last axis: each row's offsets on the first dim - 1 axes."""
    return list(itertools.product(range(3), repeat=dim - 1))


@data_oriented
class StencilFunctions:
    """Stencil weights and the sums over the stencil, as ``ti.func`` methods of the MPM engine."""

    @ti.func
    def stencil(self, xp):
        """Base node, fractional position (in cells) and per-axis quadratic B-spline weights of the
        3^d nodes around position xp [m]; node ``base + offset`` has weight ``stencil_weight(w, offset)``."""
        base = self.stencil_base(xp)
        fx = xp * self.inv_dx - ti.cast(base, float)
        return base, fx, self.spline_weights(fx)

    @ti.func
    def stencil_base(self, xp):
        """The first of the 3^d stencil nodes around position xp [m] (kept inside the grid)."""
        lim = ti.Vector(self.nodes) - 3
        return ti.max(ti.min(ti.cast(xp * self.inv_dx - 0.5, ti.i32), lim), 0)

    @ti.func
    def spline_weights(self, fx):
        """Per-axis quadratic B-spline weights of the three stencil nodes at fractional position fx (in
        cells from the base node): ``w[o][k]`` for offset o on axis k."""
        return [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]

    @ti.func
    def stencil_weight(self, w: ti.template(), offset: ti.template()):
        """Product of the per-axis B-spline weights of stencil node ``offset`` (both compile-time)."""
        weight = 1.0
        for k in ti.static(range(self.dim)):
            weight *= w[offset[k]][k]
        return weight

    @ti.func
    def stencil_slopes(self, fx):
        """Per-axis derivatives d w / d fx of ``spline_weights`` (the same layout: ``slopes[o][k]``)."""
        return [fx - 1.5, -2.0 * (fx - 1.0), fx - 0.5]

    @ti.func
    def plus_steps(self, value, steps, offset: ti.template(), first: ti.template()):
        """value + sum_k offset[k] steps[:, first + k], for a compile-time ``offset``: zero offsets add
        nothing, the others a column. An affine field at a stencil node, a(o) = value + steps (o - fx), is
        written so: from its value at fx and its columns, without a matrix product per node (``_p2g`` and
        the adjoints)."""
        out = value
        for k in ti.static(range(len(offset))):
            if ti.static(offset[k] > 0):
                out += offset[k] * steps[:, first + k]
        return out

    # The stencil as rows of three nodes along the last axis: ``self.rows`` holds each row's offsets on the
    # first d - 1 axes. A node's weight is the row's weight times its own along the last axis, so a
    # gather sums each row first and weights it once: about half the arithmetic of a node-by-node sum.
    @ti.func
    def row_node(self, row: ti.template(), c: ti.template()):
        """The offset of node c (0, 1, 2 along the last axis) of row ``row``."""
        return ti.Vector([row[k] for k in ti.static(range(self.dim - 1))] + [c])

    @ti.func
    def row_weight(self, w, row: ti.template()):
        """Product of the per-axis weights of row ``row`` (its offsets on the first d - 1 axes)."""
        weight = 1.0
        for k in ti.static(range(self.dim - 1)):
            weight *= w[row[k]][k]
        return weight

    @ti.func
    def row_gradient(self, w, slopes, row: ti.template(), along, slope_sum):
        """d/d fx of sum over row ``row`` of W_n h_n, given the row's sums along the last axis
        ``along`` = sum_c w_c h_c and ``slope_sum`` = sum_c w'_c h_c (a d-vector, per cell: times 1/dx for
        d/dx)."""
        out = ti.Vector.zero(float, self.dim)
        for j in ti.static(range(self.dim - 1)):
            factor = along * slopes[row[j]][j]
            for k in ti.static(range(self.dim - 1)):
                if ti.static(k != j):
                    factor *= w[row[k]][k]
            out[j] = factor
        out[self.dim - 1] = self.row_weight(w, row) * slope_sum
        return out

    @ti.func
    def gather_moments(self, source, g, base, w):
        """Sums over the 3^d stencil nodes n (offset o_n, weight W_n, velocity v_n = ``source.velocity``):
        ``total`` = sum W_n v_n and ``first``, whose column k is sum W_n o_n[k] v_n. APIC's affine field is
        then 4 / dx (first - total fx^T). Row by row (``row_weight``)."""
        d = ti.static(self.dim)
        total = ti.Vector.zero(float, d)
        columns = [ti.Vector.zero(float, d) for _ in ti.static(range(d))]
        for row in ti.static(self.rows):
            along = ti.Vector.zero(float, d)  # sum over the row of w v
            moment = ti.Vector.zero(float, d)  # sum over the row of c w v, c the node's last offset
            for c in ti.static(range(3)):
                wv = w[c][d - 1] * source.velocity(g, base + self.row_node(row, c))
                along += wv
                if ti.static(c > 0):
                    moment += c * wv
            w_row = self.row_weight(w, row)
            total += w_row * along
            columns[d - 1] += w_row * moment
            for k in ti.static(range(d - 1)):
                if ti.static(row[k] > 0):
                    columns[k] += (row[k] * w_row) * along
        first = ti.Matrix.cols(columns)
        return total, first

    @ti.func
    def axis_weights(self, fx):
        """Per-axis quadratic B-spline weights of the three stencil nodes (``spline_weights``) and
        their derivatives d w / d fx, as 3 x d matrices (row: the node's offset, column: the axis)."""
        return ti.Matrix.rows(self.spline_weights(fx)), ti.Matrix.rows(self.stencil_slopes(fx))

    @ti.func
    def node_weight(self, weights, slopes, i, rest):
        """Stencil node offset (i, *rest), its weight and the weight's gradient [1/m] with respect to the
        particle position, from ``axis_weights``: for the contact models' adjoints, which loop over the
        first axis's ``i`` at run time and unroll the other axes (``rest``, compile-time)."""
        offset = ti.Vector.zero(ti.i32, self.dim)
        offset[0] = i
        w_first, s_first = weights[i, 0], slopes[i, 0]
        w_rest = 1.0
        for k in ti.static(range(1, self.dim)):
            offset[k] = rest[k - 1]
            w_rest *= weights[rest[k - 1], k]
        grad = ti.Vector.zero(float, self.dim)
        grad[0] = self.inv_dx * s_first * w_rest
        for k in ti.static(range(1, self.dim)):
            factor = self.inv_dx * w_first * slopes[rest[k - 1], k]
            for j in ti.static(range(1, self.dim)):
                if ti.static(j != k):
                    factor *= weights[rest[j - 1], j]
            grad[k] = factor
        return offset, w_first * w_rest, grad
