"""The contact models between MPM material and manipulators: grid, particle penalty, forecast.

Each model is written once against the boundary-source interface
(``cosim.couplers.boundary``: signed distance, outward normal, contact-point
velocity, reaction) and takes any number of sources at once (rigid bodies and,
later, cloth in one scene); kernels unroll over sources and their bodies at
compile time, so no kernel branches on a source's type. Grid and forecast
models are grid hooks of the MPM engine (they read the velocity upstream of
them, ``upstream.velocity(g, I)``, and offer their own to whatever gathers
next); the particle model is a particle hook (momentum added in P2G). A
reaction is minus the momentum the contact gave the material, with its moment
about the body origin.
"""

import taichi as ti

from cosim.couplers.contact_rules import (
    AUTO_OFFSET,
    BLEND_SOFT,
    BLEND_WHERE,
    CELL_SHARE,
    DENSE_FILL,
    GRID_SUPPORT,
    LIQUID_BAND_SHIFT,
    PROJECT_SOFT,
    SOLID_SOFT,
    STANDARD_GRAVITY,
    TAPER,
    default_alpha,
    frictional_bc,
    occupancy,
    reach_of_fill,
    soft_ramp,
    source_offset,
    speculative_bc,
    surface_offset,
)
from cosim.engines.data_oriented import data_oriented


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
        self.friction = float(friction)
        if support not in GRID_SUPPORT:
            raise ValueError(f"grid support must be one of {GRID_SUPPORT}, got {support!r}")
        self.support = support
        self.band = 0.5 * engine.dx if band is None else float(band)
        grad = engine.cfg.requires_grad
        self.output = ti.Vector.field(engine.dim, float, shape=engine.grid_v.shape, needs_grad=grad)
        self.liquid = None  # per node: (liquid volume fraction phi, liquid mass) [-, kg]
        self.solid = None  # per node next to liquid: the share of its cell inside the bodies [-]
        if self._reads_liquid():
            self.liquid = ti.Vector.field(2, float, shape=engine.grid_m.shape, needs_grad=grad)
            self.solid = ti.field(float, shape=engine.grid_m.shape, needs_grad=grad)
            self.scratch = [self.liquid, self.solid]  # zeroed by the engine with the grid each substep
        self.upstream = engine.attach_grid_hook(self)

    def _held_by_liquid(self, source) -> bool:
        """Whether liquid near ``source`` is held by its own edge (``support: material``, not a sheet)."""
        return self.support == "material" and not getattr(source, "sheet", False)

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
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if e.is_liquid(p):
                base, _fx, w = e.stencil(e.x[src, p])
                share = self._liquid_share(p)
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    self.liquid[g, base + offset] += e.stencil_weight(w, offset) * share

    @ti.kernel
    def _liquid_adjoint(self, src: ti.i32, g: ti.i32):
        """Adjoint of ``_scatter_liquid``: its adjoint gathered into the liquid particles' positions'."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if e.is_liquid(p):
                base, fx, _w = e.stencil(e.x[src, p])
                weights, slopes = e.axis_weights(fx)
                share = self._liquid_share(p)
                g_x = ti.Vector.zero(float, e.dim)
                for i in range(3):  # the stencil as in the engine's adjoints (``node_weight``)
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

    @ti.kernel
    def _occupy(self, g: ti.i32, s: ti.i32):
        """Per node next to liquid, the share of its cell inside the bodies (``occupancy``, summed, at
        most 1): the solid the liquid's fill is read against (``_liquid_reach``)."""
        e = self.engine
        ti.loop_config(serialize=e.serial_grid_loops)
        for I in ti.grouped(ti.ndrange(*e.nodes)):
            if self._near_liquid(g, I):
                xi = ti.cast(I, float) * e.dx
                inside = 0.0
                for src in ti.static(self.sources):
                    if ti.static(self._held_by_liquid(src)):
                        for b in ti.static(range(src.n)):
                            inside += occupancy(src.distance(s, b, xi, -1), e.dx)
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
        for I in ti.grouped(ti.ndrange(*e.nodes)):
            v = self.upstream.velocity(g, I)
            m = e.grid_m[g, I]
            xi = ti.cast(I, float) * e.dx
            if m > 0:  # empty nodes need no boundary lookup
                for src in ti.static(self.sources):
                    for b in ti.static(range(src.n)):
                        d, n = src.distance_normal(s, b, xi, -1)
                        gap = d - ti.static(getattr(src, "grid_band", self.band))
                        if ti.static(self._liquid_held_at(src)):
                            share = ti.min(self.liquid[g, I][1] / m, 1.0) * self._dense_liquid(g, I)
                            gap += LIQUID_BAND_SHIFT * e.dx * share
                            gap = ti.min(gap, d - e.dx * self._liquid_reach(g, I, d, n))
                        # a node a cell beyond keeps its velocity unless material crosses a cell per substep
                        if gap < e.dx:
                            vc = src.contact_velocity(s, b, xi, -1)
                            v_new = speculative_bc(v, n, vc, self.friction, ti.max(gap, 0.0), dt)
                            src.add_reaction(s, b, xi, m * (v_new - v), -1)  # momentum given to the material
                            v = v_new
            self.output[g, I] = v

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
        self.output.grad.fill(0)
        if self.liquid is not None:
            self.liquid.grad.fill(0)
            self.solid.grad.fill(0)


@data_oriented
class ParticlePenalty:
    """Particle contact model: a particle closer to a body than its offset (default its radius,
    see ``surface_offset``), gap = d - offset < 0, receives the penalty force
    F = -k g0 m_p (gap / dx) n, plus Coulomb friction (the tangential
    velocity relative to the body is reduced by at most mu |F_n| dt / m_p), added as
    momentum in P2G.

    ``stiffness`` k is dimensionless: the push on a particle one grid cell deep, in units
    of standard gravity g0. Scaling by the particle mass and the cell size makes one k
    mean the same penetration in cells at any particle size and resolution; the paper's
    k = 400 / 600 land in the range where the penetration-vs-rebound trade-off shows."""

    def __init__(self, engine, sources: list, stiffness: float, friction: float, offset: float | None = None):
        self.engine = engine
        self.sources = list(sources)
        self.offset = AUTO_OFFSET if offset is None else float(offset)
        self.stiffness = float(stiffness)
        self.accel_per_depth = self.stiffness * STANDARD_GRAVITY / engine.dx  # [1/s^2]
        self.friction = float(friction)
        grad = engine.cfg.requires_grad
        self.output = ti.Vector.field(engine.dim, float, shape=engine.affine.shape, needs_grad=grad)
        engine.attach_particle_hook(self)

    @ti.kernel
    def _apply(self, src: ti.i32, g: ti.i32, s: ti.i32, dt: float):
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            x, v = e.x[src, p], e.v[src, p]
            m = e.mass_of(p)
            dp_total = ti.Vector.zero(float, e.dim)
            for source in ti.static(self.sources):
                for b in ti.static(range(source.n)):
                    d, n = source.distance_normal(s, b, x, p)
                    gap = d - surface_offset(e, ti.static(source_offset(source, self.offset)), p)
                    if gap < 0:
                        jn = -self.accel_per_depth * m * gap * dt  # normal impulse, along +n
                        rel = v - source.contact_velocity(s, b, x, p)
                        vt = rel - rel.dot(n) * n
                        vt_norm = ti.sqrt(vt.norm_sqr() + 1e-20)
                        jt = ti.min(self.friction * jn, m * vt_norm)  # friction impulse, against vt
                        dp = jn * n - jt * vt / vt_norm
                        source.add_reaction(s, b, x, dp, p)
                        dp_total += dp
            self.output[g, p] = dp_total

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply(src, g, s, dt)

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply.grad(src, g, s, dt)

    def zero_grad(self) -> None:
        self.output.grad.fill(0)


@data_oriented
class ForecastContact:
    """Forecast contact model (SoftMAC): look ahead with a G2P of the free grid velocities,
    fix the particle velocities with BC_p, then take one gradient step on the grid velocities:

        v_init = W^T v_hat
        v_tgt  = BC_p(v_init)                       (per particle, below)
        v_g    = v_hat - alpha M_g^-1 W M_p (W^T v_hat - v_tgt)

    Normalisation: the paper writes the step with the bare weights W; we scatter each
    residual's momentum like P2G and divide by the node mass (M_p, M_g: particle and grid
    masses), so alpha = 1 moves a node to the mass-weighted mean of its particles' targets
    whatever the particle density. A node near the surface touched by few particles then
    gets its full correction (with bare weights it got 0.2 x their weight sum and a disc
    thrown at 4 m/s entered a thick wall by 0.25 cells; measured). The paper's alpha = 0.2
    with bare weights equals ours at alpha = 0.2 x sum_p w_ip ~ 0.2 x particles per cell:
    0.8 in 2D (the default here; 4 particles per cell at spacing dx/2), 1.6 in 3D.

    BC_p for a particle whose gap g = d - offset to a body (d its signed distance, offset its
    radius by default: ``surface_offset``) is below d_hat, contact velocity v_c, takes one of two
    forms, chosen per particle by ``blend`` (liquids | all | none):
    - blended (the paper's BC_p; by default for liquid particles): the approaching normal part is
      removed whatever the gap, v_out = v_c + v_t max(0, 1 - mu |v_n| / |v_t|), and blended with
      the input by s = min(exp(-beta g), 1), tapered to 0 over the last quarter of d_hat so that s
      is continuous where a particle enters the band. Applied every substep, that blend is a
      dashpot of rate s / dt on everything inside the band: liquid meets a wall without rebound
      (0 rebounds in ``cosim bench contact``, 15 without it), but an elastic body is braked before
      it touches (restitution of a disc thrown at a wall: 0.27 at 0.3 m/s and 0.73 at 1 m/s,
      against 0.94 at the MPM domain wall).
    - speculative (``speculative_bc``; solids by default): the relative normal velocity may
      approach at most at -g / dt, so the particle reaches the surface at the end of the substep
      and no sooner; the tangential part loses Coulomb friction for the normal velocity removed
      (restitution 0.89 and 0.87 there).
    Then, if x + dt v_out would end closer than the offset, v_out gains the missing distance / dt
    along the normal there (advect and project). Bodies within d_hat of one particle apply BC_p
    in turn.

    Reactions: the residual r = v_init - v_tgt is the sum of each body's share r_b (the
    velocity its BC_p removed), and body b receives alpha m_p r_b, minus the grid momentum
    its share of the gradient step gives the material, so each body's reaction is its own
    and the third law holds to round-off.
    """

    def __init__(
        self,
        engine,
        sources: list,
        friction: float,
        alpha: float | None = None,
        threshold: float | None = None,
        beta: float | None = None,
        blend: str = "liquids",
        offset: float | None = None,
    ):
        self.engine = engine
        self.sources = list(sources)
        self.friction = float(friction)
        self.alpha = default_alpha(engine.dim, self.sources) if alpha is None else float(alpha)
        self.threshold = engine.dx if threshold is None else float(threshold)
        self.beta = 2.0 / engine.dx if beta is None else float(beta)
        if blend not in BLEND_WHERE:
            raise ValueError(f"forecast blend must be one of {BLEND_WHERE}, got {blend!r}")
        self.blend_where = blend
        self.offset = AUTO_OFFSET if offset is None else float(offset)
        grad = engine.cfg.requires_grad
        d = engine.dim
        per_particle = engine.affine.shape  # (grid copies, particles)
        self.v_init = ti.Vector.field(d, float, shape=per_particle, needs_grad=grad)
        self.residual = ti.Vector.field(d, float, shape=per_particle, needs_grad=grad)
        self.constrained = ti.field(ti.i32, shape=per_particle)
        self.correction = ti.Vector.field(d, float, shape=engine.grid_v.shape, needs_grad=grad)
        self.scratch = [self.correction]  # zeroed by the engine with the grid each substep
        # benchmarks: the objective (before, after) the gradient step, per substep (a host sync each)
        self.track_objective = False
        self.objective_terms: list[tuple[float, float]] = []
        self.upstream = engine.attach_grid_hook(self)

    @ti.func
    def _within_threshold(self, s, x, p):
        """1 if a body is closer to x than the threshold (only those particles look ahead), else 0."""
        nearest = 1e30
        for source in ti.static(self.sources):
            offset = surface_offset(self.engine, ti.static(source_offset(source, self.offset)), p)
            for b in ti.static(range(source.n)):
                nearest = ti.min(nearest, source.distance(s, b, x, p) - offset)
        return ti.select(nearest < self.threshold, 1, 0)

    @ti.func
    def _constrain(self, s, x, p, v_init, m_p, dt):
        """BC_p of every body within the threshold applied in turn to v_init; returns the target
        velocity. Each body's share r_b = v - v_out of the residual gives the material
        sum_i w_i (-alpha m_p r_b) = -alpha m_p r_b, with moment (x_p - pos) x dp (B-spline weights
        sum to 1 and reproduce x_p): one reaction per body."""
        v = v_init
        for source in ti.static(self.sources):
            for b in ti.static(range(source.n)):
                d, n = source.distance_normal(s, b, x, p)
                offset = surface_offset(self.engine, ti.static(source_offset(source, self.offset)), p)
                if d - offset < self.threshold:
                    vc = source.contact_velocity(s, b, x, p)
                    v_out = v
                    blended = 0
                    if ti.static(self.blend_where == "all" or getattr(source, "sheet", False)):
                        blended = 1
                    elif ti.static(self.blend_where == "liquids"):
                        blended = self.engine.is_liquid(p)
                    if blended:
                        smooth = self.blend(d - offset)
                        v_out = smooth * frictional_bc(v, n, vc, self.friction) + (1.0 - smooth) * v
                    else:
                        v_out = speculative_bc(v, n, vc, self.friction, d - offset, dt)
                    d_new, n_new = source.distance_normal(s, b, x + dt * v_out, p)
                    if d_new < offset:
                        v_out += (soft_ramp(offset - d_new, PROJECT_SOFT * self.engine.dx) / dt) * n_new
                    source.add_reaction(s, b, x, (-self.alpha * m_p) * (v - v_out), p)
                    v = v_out
        return v

    @ti.kernel
    def _forecast(self, src: ti.i32, g: ti.i32, s: ti.i32, dt: float):
        """Look-ahead G2P v_init = W^T v_hat, BC_p (``_constrain``), and the scatter of the
        constrained particles' W M_p r. One kernel (atomic adds only for constrained particles):
        each launch costs ~50 us on this CPU, as much as the work here."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            x = e.x[src, p]
            constrained = self._within_threshold(s, x, p)
            base, _fx, w = e.stencil(x)
            v_init = ti.Vector.zero(float, e.dim)
            r = ti.Vector.zero(float, e.dim)
            if constrained:
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    v_init += e.stencil_weight(w, offset) * self.upstream.velocity(g, base + offset)
                r = v_init - self._constrain(s, x, p, v_init, e.mass_of(p), dt)
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):  # correction += W M_p r
                    self.correction[g, base + offset] += (e.stencil_weight(w, offset) * e.mass_of(p)) * r
            self.v_init[g, p] = v_init
            self.residual[g, p] = r
            self.constrained[g, p] = constrained

    @ti.kernel
    def _residual(self, src: ti.i32, g: ti.i32, s: ti.i32, dt: float):
        """The residual r = v_init - BC_p(v_init) of ``_forecast`` alone: the part of the forecast
        whose adjoint Taichi derives (the stencil transfers around it have hand-written ones)."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if self.constrained[g, p]:
                x = e.x[src, p]
                self.residual[g, p] = self.v_init[g, p] - self._constrain(s, x, p, self.v_init[g, p], e.mass_of(p), dt)

    @ti.kernel
    def _scatter_adjoint(self, src: ti.i32, g: ti.i32):
        """Adjoint of ``_forecast``'s correction scatter (correction_i += w_i m_p r): the correction's
        adjoint gathered into r's and x's, per constrained particle."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if self.constrained[g, p]:
                base, fx, _w = e.stencil(e.x[src, p])
                weights, slopes = e.axis_weights(fx)
                r = self.residual[g, p]
                g_r = ti.Vector.zero(float, e.dim)
                g_x = ti.Vector.zero(float, e.dim)
                for i in range(3):  # the stencil as in the engine's adjoints (``node_weight``)
                    for rest in ti.static(ti.grouped(ti.ndrange(*([3] * (e.dim - 1))))):
                        offset, weight, grad_w = e.node_weight(weights, slopes, i, rest)
                        g_corr = self.correction.grad[g, base + offset]
                        g_r += weight * g_corr
                        g_x += grad_w * g_corr.dot(r)
                self.residual.grad[g, p] += e.mass_of(p) * g_r
                e.x.grad[src, p] += e.mass_of(p) * g_x

    @ti.kernel
    def _gather_adjoint(self, src: ti.i32, g: ti.i32):
        """Adjoint of ``_forecast``'s look-ahead gather (v_init = sum_i w_i v_hat_i): v_init's adjoint
        scattered onto the upstream velocity's and gathered into x's, per constrained particle."""
        e = self.engine
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if self.constrained[g, p]:
                base, fx, _w = e.stencil(e.x[src, p])
                weights, slopes = e.axis_weights(fx)
                g_v_init = self.v_init.grad[g, p]
                g_x = ti.Vector.zero(float, e.dim)
                for i in range(3):  # the stencil as in the engine's adjoints (``node_weight``)
                    for rest in ti.static(ti.grouped(ti.ndrange(*([3] * (e.dim - 1))))):
                        offset, weight, grad_w = e.node_weight(weights, slopes, i, rest)
                        node = base + offset
                        g_x += grad_w * g_v_init.dot(self.upstream.velocity(g, node))
                        self.upstream.velocity_grad(g, node, weight * g_v_init)
                e.x.grad[src, p] += g_x

    @ti.func
    def blend(self, d):
        """Weight of BC_p at signed distance d [m]: min(exp(-beta d), 1) (its corner at d = 0 rounded
        over BLEND_SOFT cells, from the side of a stronger blend), tapered to 0 over the last
        quarter of the threshold by a C2 smoothstep, so a particle entering the band feels no jump (with
        the bare exponential it jumped by e^-2 there and finite differences of any loss through contact
        did not converge; measured on towel_squash)."""
        t = ti.min(ti.max((self.threshold - d) / (TAPER * self.threshold), 0.0), 1.0)
        return (
            ti.exp(-self.beta * soft_ramp(d, BLEND_SOFT * self.engine.dx)) * t * t * t * (10.0 - 15.0 * t + 6.0 * t * t)
        )

    @ti.func
    def velocity(self, g, I):
        """v_g = v_hat - alpha correction / m, evaluated where G2P gathers it (no extra pass)."""
        e = self.engine
        v = self.upstream.velocity(g, I)
        m = e.grid_m[g, I]
        if m > 0:
            v -= (self.alpha / m) * self.correction[g, I]
        return v

    @ti.func
    def velocity_grad(self, g, I, g_v):
        """Adjoint of ``velocity(g, I)``: into the upstream velocity's, the node mass's and the correction's."""
        e = self.engine
        self.upstream.velocity_grad(g, I, g_v)
        m = e.grid_m[g, I]
        if m > 0:
            correction = self.correction[g, I]
            e.grid_m.grad[g, I] += (self.alpha / (m * m)) * correction.dot(g_v)
            self.correction.grad[g, I] -= (self.alpha / m) * g_v

    @ti.kernel
    def _objective(self, src: ti.i32, g: ti.i32) -> ti.types.vector(2, float):
        """(|W^T v_hat - v_tgt|^2, |W^T v_g - v_tgt|^2) summed over constrained particles."""
        e = self.engine
        before, after = 0.0, 0.0
        ti.loop_config(serialize=e.serial_particle_loops)
        for p in range(e.count[None]):
            if self.constrained[g, p]:
                base, _fx, w = e.stencil(e.x[src, p])
                v = ti.Vector.zero(float, e.dim)
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    weight = e.stencil_weight(w, offset)
                    v += weight * self.velocity(g, base + offset)
                target = self.v_init[g, p] - self.residual[g, p]
                before += self.residual[g, p].norm_sqr()
                after += (v - target).norm_sqr()
        return ti.Vector([before, after])

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        self._forecast(src, g, s, dt)
        if self.track_objective:
            before, after = self._objective(src, g)
            if before > 0:
                self.objective_terms.append((float(before), float(after)))

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._scatter_adjoint(src, g)
        self._residual.grad(src, g, s, dt)
        self._gather_adjoint(src, g)

    def zero_grad(self) -> None:
        for fld in (self.v_init, self.residual, self.correction):
            fld.grad.fill(0)


def attach_contact(engine, sources: list, settings) -> object:
    """The contact model ``settings.model`` (grid | particle | forecast) between ``engine`` and ``sources``."""
    if settings.model == "grid":
        return GridContact(engine, sources, settings.friction, settings.band, settings.support)
    if settings.model == "forecast":
        return ForecastContact(
            engine,
            sources,
            settings.friction,
            settings.alpha,
            settings.threshold,
            settings.smoothing,
            settings.blend,
            settings.offset,
        )
    return ParticlePenalty(engine, sources, settings.stiffness, settings.friction, settings.offset)
