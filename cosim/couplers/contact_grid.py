"""The grid contact model (``GridContact``): a velocity limit at grid nodes near a body, solids held at
the paper's band, liquids by their own edge read off the nodes' volume fractions. A grid hook of the
MPM engine; see ``cosim.couplers.contact`` for what the three models share and docs/contact.md for the
numbers behind each choice."""

import taichi as ti

from cosim.couplers.boundary import NODE
from cosim.couplers.contact_rules import (
    CELL_SHARE,
    DENSE_FILL,
    GRID_SUPPORT,
    LIQUID_BAND_SHIFT,
    LIQUID_REACH,
    SOLID_SOFT,
    occupancy,
    reach_of_fill,
    speculative_bc,
)
from cosim.engines import field_pool
from cosim.engines.contract import declares, traits_of
from cosim.engines.data_oriented import data_oriented
from cosim.engines.smooth import soft_ramp


@data_oriented
class GridContact:
    """Grid contact model: at grid nodes the velocity relative to a body may approach it at most at
    gap / dt (``speculative_bc``: at gap 0 its approaching normal part goes and its tangential part
    is reduced by Coulomb friction, v_t max(0, 1 - mu |dv_n| / |v_t|)). A node's gap:

    - solids (the paper's model): the node's distance d less the ``band`` (default half a cell), so
      rows within the band hold the material off. A solid spans the stencil, and a resting block
      sits within 0.01 cells of its support wherever the surface falls between rows (measured);
    - liquids (``support: material``, the default): the distance of the liquid near the node to the
      surface, d - dx u, where u [cells] is how far it reaches past the node towards the body, read
      off the node's liquid volume fraction phi = sum_p w_ip V_p / dx^dim as if the liquid filled a
      half-space (``reach_of_fill``), after adding the bodies' solid in the stencil beyond a flat
      body's (``_liquid_reach``). Held at node rows (``support: nodes``), a liquid stops where
      the outermost held row's stencil first reaches it: water dropped on a plate settled 0.5-0.9
      cells high, a floating box floated 0.04-0.38 cells high, depending on where the surface fell
      between rows; held by its own edge, 0.02-0.12 cells low and -0.04 to +0.07 (docs/contact.md).
      Solids are not held so: met all at once at the surface instead of over the held rows' stencil,
      an elastic sphere (3D, 32 cells) kept 0.77 of its speed instead of the domain wall's 0.91.

    Nodes carrying both are held by the liquid's edge and by the band moved 2 cells into the body
    in proportion to the liquid's share of the node's mass, where the liquid is dense enough to be
    read as a half-space (``_dense_liquid``; a splash is held by the band), continuously. Beyond a
    gap of one cell a node keeps its velocity, continuously: the limit there lets material cross a
    cell per substep. A cloth sheet (``grid_band``) keeps d - grid_band for all material: it is
    two-sided, so a fill says nothing of which side the material is on."""

    def __init__(self, engine, sources: list, friction: float, band: float | None = None, support: str = "material"):
        self.engine = engine
        self.sources = list(sources)
        for source in self.sources:  # this model asks about grid nodes (p = -1)
            if declares(source, "node_queries"):
                source.queries_nodes = True
        self.friction = float(friction)
        if support not in GRID_SUPPORT:
            raise ValueError(f"grid support must be one of {GRID_SUPPORT}, got {support!r}")
        self.support = support
        self.band = 0.5 * engine.dx if band is None else float(band)
        grad = engine.cfg.requires_grad
        self.output = field_pool.vector(self, engine.dim, float, shape=engine.grid_v.shape, needs_grad=grad)
        self.liquid = None  # per node: (liquid volume fraction phi, liquid mass) [-, kg]
        self.solid = None  # per node next to liquid: the share of its cell inside the bodies [-]
        if self._reads_liquid():
            self.liquid = field_pool.vector(self, 2, float, shape=engine.grid_v.shape, needs_grad=grad)
            self.solid = field_pool.scalar(self, float, shape=engine.grid_v.shape, needs_grad=grad)
            self.scratch = [self.liquid, self.solid]  # zeroed by the engine with the grid each substep
            # the solid share is read at a node's neighbours and written next to liquid (``_occupy``,
            # ``_liquid_reach``): one node beyond the nodes the particles reach
            self.box_margin = 1
        # grid-shaped fields whose adjoints the engine zeroes over the box in each substep's adjoint
        self.grid_adjoints = [self.output] + ([self.liquid, self.solid] if self.liquid is not None else [])
        self.upstream = engine.attach_grid_hook(self)

    def _band_of(self, source) -> float:
        """[m] The gap kept from ``source``: its declared ``grid_band`` (a sheet), else the model's band."""
        band = traits_of(source).grid_band
        return self.band if band is None else band

    def _held_by_liquid(self, source) -> bool:
        """Whether liquid near ``source`` is held by its own edge (``support: material``, not a sheet)."""
        return self.support == "material" and traits_of(source).liquid_support

    def _liquid_held_at(self, source) -> bool:
        """Whether this model reads the liquid fill at ``source``'s nodes (for ``ti.static``)."""
        return self.liquid is not None and self._held_by_liquid(source)

    def _reads_liquid(self) -> bool:
        has_liquid = any(body.material == "liquid" for body in self.engine.bodies)
        return has_liquid and any(self._held_by_liquid(src) for src in self.sources)

    @ti.func
    def _liquid_share(self, p):
        """What liquid particle p adds to a node per unit weight: (V_p / dx^dim, m_p)."""
        e = self.engine
        return ti.Vector([e.p_vol[e.body_id[p]] * e.inv_dx**e.dim, e.mass_of(p)])

    @ti.kernel
    def _scatter_liquid(self, src: ti.i32, g: ti.i32):
        """Per node, the liquid's volume fraction sum_p w_ip V_p / dx^dim and mass sum_p w_ip m_p."""
        self._scatter_liquid_pass(src, g)

    @ti.func
    def _scatter_liquid_pass(self, src: ti.template(), g: ti.template()):
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.capacity if ti.static(e.constant_loop_bounds) else e.count[None]):
            if e.is_liquid(p) and not e.idle(p):  # a thread per particle slot (``constant_loop_bounds``)
                base, _fx, w = e.stencil(e.x[src, p])
                share = self._liquid_share(p)
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    self.liquid[g, base + offset] += e.stencil_weight(w, offset) * share

    @ti.kernel
    def _liquid_adjoint(self, src: ti.i32, g: ti.i32):
        """Adjoint of ``_scatter_liquid``: its adjoint gathered into the liquid particles' positions'."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.capacity if ti.static(e.constant_loop_bounds) else e.count[None]):
            if e.is_liquid(p) and not e.idle(p):  # a thread per particle slot (``constant_loop_bounds``)
                base, fx, _w = e.stencil(e.x[src, p])
                weights, slopes = e.axis_weights(fx)
                share = self._liquid_share(p)
                g_x = ti.Vector.zero(float, e.dim)
                for i in range(3):  # first axis at run time, the others unrolled (``node_weight``)
                    for rest in ti.static(ti.grouped(ti.ndrange(*([3] * (e.dim - 1))))):
                        offset, _weight, grad_w = e.node_weight(weights, slopes, i, rest)
                        g_x += grad_w * self.liquid.grad[g, base + offset].dot(share)
                e.x.grad[src, p] += g_x

    @ti.func
    def _near_liquid(self, g, I):
        """1 if node I or a neighbour carries liquid (only there is the solid share read)."""
        e = self.engine
        near = 0
        for offset in ti.static(ti.grouped(ti.ndrange(*([(-1, 2)] * e.dim)))):
            J = ti.min(ti.max(I + offset, 0), ti.Vector(e.nodes) - 1)
            if self.liquid[g, J][1] > 0:
                near = 1
        return near

    @ti.func
    def _dense_liquid(self, g, I):
        """1 where the liquid around node I is dense enough to be read as a half-space (some node of
        its stencil at least DENSE_FILL[1] full), 0 for a splash (every node under DENSE_FILL[0]),
        smoothly between; elsewhere the band holds liquid too. A splash read as a half-space seemed
        far off and went through a wall two cells thick (13 particles out in ``cosim bench contact``,
        2 with DENSE_FILL (0.5, 0.8), 0 with (0.5, 0.9); at (0.6, 0.9) water dropped on a plate was
        caught by the band, 0.7 cells high)."""
        e = self.engine
        fullest = 0.0
        for offset in ti.static(ti.grouped(ti.ndrange(*([(-1, 2)] * e.dim)))):
            J = ti.min(ti.max(I + offset, 0), ti.Vector(e.nodes) - 1)
            fullest = ti.max(fullest, self.liquid[g, J][0])
        t = ti.min(ti.max((fullest - DENSE_FILL[0]) / (DENSE_FILL[1] - DENSE_FILL[0]), 0.0), 1.0)
        return t * t * (3.0 - 2.0 * t)

    # The loops of ``_occupy`` and ``_apply`` are written in their kernels, not inlined from a ``ti.func``
    # (Taichi differentiates both and refuses such a loop), and again in ``forward_pass``.
    @ti.kernel
    def _occupy(self, g: ti.i32, s: ti.i32):
        """Per node next to liquid, the share of its cell inside the bodies (``occupancy``, summed, at
        most 1): the solid the liquid's fill is read against (``_liquid_reach``)."""
        e = self.engine
        ti.loop_config(serialize=e.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (e.active_lo[g][k], e.active_hi[g][k]) if ti.static(e.bounded_grid) else (0, e.nodes[k])
                    for k in ti.static(range(e.dim))
                ]
            )
        ):
            self._occupy_node(g, I, s)

    @ti.func
    def _occupy_node(self, g, I, s):
        e = self.engine
        if self._near_liquid(g, I):
            xi = ti.cast(I, float) * e.dx
            inside = 0.0
            for src in ti.static(self.sources):
                if ti.static(self._held_by_liquid(src)):
                    for b in ti.static(range(src.n)):
                        inside += occupancy(src.distance(s, b, xi, NODE), e.dx)
            self.solid[g, I] = ti.min(inside, 1.0)

    @ti.func
    def _liquid_reach(self, g, I, d, n):
        """[cells] How far the liquid reaches past node I towards a body at distance d, normal n: its
        fill phi read as a half-space's (``reach_of_fill``) after adding the solid in the node's
        stencil beyond what a flat body at d would hold. Against a flat body that adds nothing; in a
        container's corner the other wall fills part of the stencil, and read alone the fill made
        the liquid seem farther off than it was (water in a cup 2.6 cells wide first sank half a cell
        into its floor). Less solid than a flat body's (a thin wall) is not subtracted: it made the
        liquid seem farther off from a wall two cells thick and let it through."""
        e = self.engine
        solid, flat = 0.0, 0.0
        for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
            share = 1.0
            for k in ti.static(range(e.dim)):
                share *= CELL_SHARE[offset[k]]
            J = ti.min(ti.max(I + offset - 1, 0), ti.Vector(e.nodes) - 1)
            solid += share * self.solid[g, J]
            flat += share * occupancy(d + e.dx * n.dot(ti.cast(offset - 1, float)), e.dx)
        return reach_of_fill(self.liquid[g, I][0] + soft_ramp(solid - flat, SOLID_SOFT))

    @ti.kernel
    def _apply(self, g: ti.i32, s: ti.i32, dt: float):
        e = self.engine
        ti.loop_config(serialize=e.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (e.active_lo[g][k], e.active_hi[g][k]) if ti.static(e.bounded_grid) else (0, e.nodes[k])
                    for k in ti.static(range(e.dim))
                ]
            )
        ):
            self._apply_node(g, I, s, dt)

    @ti.func
    def _apply_node(self, g, I, s, dt):
        """Node I: the bodies' speculative contact on the upstream velocity, their reactions; into ``output``."""
        e = self.engine
        v = self.upstream.velocity(g, I)
        m = e.node_mass(g, I)
        xi = ti.cast(I, float) * e.dx
        if m > 0:  # empty nodes need no boundary lookup
            for src in ti.static(self.sources):
                for b in ti.static(range(src.n)):
                    d, n = src.distance_normal(s, b, xi, NODE)
                    gap = d - ti.static(self._band_of(src))
                    if ti.static(self._liquid_held_at(src)):  # noqa: SIM102 (compile-time, then run-time)
                        # beyond LIQUID_REACH cells the liquid's gap exceeds a cell whatever its fill (it
                        # reaches at most about 1.2 cells past a node), so both gaps leave the node free
                        if d < LIQUID_REACH * e.dx:
                            share = ti.min(self.liquid[g, I][1] / m, 1.0) * self._dense_liquid(g, I)
                            gap += LIQUID_BAND_SHIFT * e.dx * share
                            gap = ti.min(gap, d - e.dx * self._liquid_reach(g, I, d, n))
                    # a node a cell beyond keeps its velocity unless material crosses a cell per substep
                    if gap < e.dx:
                        vc = src.contact_velocity(s, b, xi, NODE)
                        v_new = speculative_bc(v, n, vc, self.friction, ti.max(gap, 0.0), dt)
                        src.add_reaction(s, b, xi, m * (v_new - v), NODE)  # momentum given to the material
                        v = v_new
        self.output[g, I] = v

    @ti.func
    def forward_pass(self, src: ti.template(), g: ti.template(), s: ti.template(), dt: ti.template()):
        """``apply``'s loops, inlined in the engine's one-launch substep (``MPMKernels._substep_fused``)."""
        e = self.engine
        if ti.static(self._reads_liquid()):
            self._scatter_liquid_pass(src, g)
            ti.loop_config(serialize=e.serial_grid_loops)
            for I in ti.grouped(
                ti.ndrange(
                    *[
                        (e.active_lo[g][k], e.active_hi[g][k]) if ti.static(e.bounded_grid) else (0, e.nodes[k])
                        for k in ti.static(range(e.dim))
                    ]
                )
            ):
                self._occupy_node(g, I, s)
        ti.loop_config(serialize=e.serial_grid_loops)
        for I in ti.grouped(
            ti.ndrange(
                *[
                    (e.active_lo[g][k], e.active_hi[g][k]) if ti.static(e.bounded_grid) else (0, e.nodes[k])
                    for k in ti.static(range(e.dim))
                ]
            )
        ):
            self._apply_node(g, I, s, dt)

    @ti.func
    def velocity(self, g, I):
        return self.output[g, I]

    @ti.func
    def velocity_grad(self, g, I, g_v):
        self.output.grad[g, I] += g_v

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        if self.liquid is not None:
            self._scatter_liquid(src, g)
            self._occupy(g, s)
        self._apply(g, s, dt)

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply.grad(g, s, dt)
        if self.liquid is not None:
            self._occupy.grad(g, s)
            self._liquid_adjoint(src, g)

    def zero_grad(self) -> None:
        """Nothing: this model's adjoints are all grid-shaped, zeroed per substep by the engine (``grid_adjoints``)."""
