"""Contact between MPM material and rigid bodies described by SDFs.

Implemented: the grid contact model (a boundary condition on grid velocities,
evaluated at grid nodes) and the particle-penalty model (a spring force on
particles inside a body, added in P2G). The forecast model of the paper plugs
into the same ``RigidBoundaries`` (body states, SDFs, reactions).

Conventions (see ``cosim.engines.kinematic``): body b at substep s has
position ``pos[s, b]`` and rotation ``rot[s, b]`` (body to world), linear
velocity ``vel[s, b]`` of its origin and angular velocity ``omega[s, b]`` in
the world frame (one component in 2D); a contact point x moves with
v_c = vel + omega x (x - pos). The reaction on body b in substep s is the
impulse ``impulse[s, b]`` [N s] = minus the momentum the contact gave the MPM
material, and ``angular_impulse[s, b]`` [N m s] its moment about the body
origin ``pos[s, b]``; the spatial force is both divided by dt.
"""

import numpy as np
import taichi as ti

from cosim.couplers.sdf import SDFField, SDFGrid

STANDARD_GRAVITY = 9.80665  # [m/s^2] the unit of the particle model's stiffness


@ti.data_oriented
class RigidBoundaries:
    """Rigid bodies as the MPM sees them: per-substep states, SDFs, reactions."""

    def __init__(self, sdfs: list[SDFGrid], dim: int, max_substeps: int, requires_grad: bool = False):
        self.dim = dim
        self.n = len(sdfs)
        self.wdim = 1 if dim == 2 else 3
        self.sdfs = [SDFField(g) for g in sdfs]
        shape = (max_substeps, self.n)
        grad = requires_grad
        self.pos = ti.Vector.field(dim, float, shape=shape, needs_grad=grad)
        self.rot = ti.Matrix.field(dim, dim, float, shape=shape, needs_grad=grad)
        self.vel = ti.Vector.field(dim, float, shape=shape, needs_grad=grad)
        self.omega = ti.Vector.field(self.wdim, float, shape=shape, needs_grad=grad)
        self.impulse = ti.Vector.field(dim, float, shape=shape, needs_grad=grad)
        self.angular_impulse = ti.Vector.field(self.wdim, float, shape=shape, needs_grad=grad)
        self.real = np.float64 if self.pos.dtype == ti.f64 else np.float32
        self._seed = None  # reaction adjoints for the next vjp (seed_reaction_grads)

    def set_states(self, pos: np.ndarray, rot: np.ndarray, vel: np.ndarray, omega: np.ndarray) -> None:
        """Body states for substeps 0..K-1: pos (K, n, d), rot (K, n, d, d), vel (K, n, d), omega (K, n, 1|3);
        clears those substeps' reactions. Only the K slots are written (the fields hold max_substeps)."""
        arrays = [np.ascontiguousarray(a, dtype=self.real) for a in (pos, rot, vel, omega)]
        self._write_states(*arrays, len(pos))

    @ti.kernel
    def _write_states(
        self,
        pos: ti.types.ndarray(),
        rot: ti.types.ndarray(),
        vel: ti.types.ndarray(),
        omega: ti.types.ndarray(),
        K: ti.i32,
    ):
        for s, b in ti.ndrange(K, self.n):
            for i in ti.static(range(self.dim)):
                self.pos[s, b][i] = pos[s, b, i]
                self.vel[s, b][i] = vel[s, b, i]
                self.impulse[s, b][i] = 0.0
                for j in ti.static(range(self.dim)):
                    self.rot[s, b][i, j] = rot[s, b, i, j]
            for i in ti.static(range(self.wdim)):
                self.omega[s, b][i] = omega[s, b, i]
                self.angular_impulse[s, b][i] = 0.0

    @ti.kernel
    def _read_reactions(self, impulse: ti.types.ndarray(), angular: ti.types.ndarray(), K: ti.i32):
        for s, b in ti.ndrange(K, self.n):
            for i in ti.static(range(self.dim)):
                impulse[s, b, i] = self.impulse[s, b][i]
            for i in ti.static(range(self.wdim)):
                angular[s, b, i] = self.angular_impulse[s, b][i]

    def reactions(self, K: int) -> tuple[np.ndarray, np.ndarray]:
        """Impulse (K, n, d) [N s] and angular impulse about the body origin (K, n, 1|3) of substeps 0..K-1."""
        impulse = np.zeros((K, self.n, self.dim), dtype=self.real)
        angular = np.zeros((K, self.n, self.wdim), dtype=self.real)
        self._read_reactions(impulse, angular, K)
        return impulse.astype(np.float64), angular.astype(np.float64)

    def state_grads(self, K: int) -> dict[str, np.ndarray]:
        """dL/d(body states) of substeps 0..K-1 after a vjp."""
        return {k: getattr(self, k).grad.to_numpy()[:K].astype(np.float64) for k in ("pos", "rot", "vel", "omega")}

    def seed_reaction_grads(self, impulse: np.ndarray, angular: np.ndarray) -> None:
        """dL/d(reactions) of the step about to be differentiated: (K, n, d) and (K, n, 1|3).
        The engine's vjp zeroes adjoints first (``zero_grad``), which then writes these."""
        self._seed = (impulse, angular)

    def zero_grad(self) -> None:
        for fld in (self.pos, self.rot, self.vel, self.omega, self.impulse, self.angular_impulse):
            if fld.grad is not None:
                fld.grad.fill(0)
        seed, self._seed = self._seed, None
        if seed is not None:
            for fld, values in zip((self.impulse, self.angular_impulse), seed):
                full = np.zeros(fld.shape + (values.shape[-1],), dtype=self.real)
                full[: len(values)] = values
                fld.grad.from_numpy(full)

    @ti.func
    def spin(self, w, r):
        """omega x r in world frame (2D: w has one component)."""
        out = ti.Vector.zero(float, self.dim)
        if ti.static(self.dim == 2):
            out = w[0] * ti.Vector([-r[1], r[0]])
        else:
            out = w.cross(r)
        return out

    @ti.func
    def frictional_bc(self, v, x, n, s, b, friction):
        """Velocity v at x after contact with body b (outward normal n): if approaching, the
        relative velocity loses its normal part and its tangential part shrinks by Coulomb
        friction, v_c + v_t max(0, 1 - mu |v_n| / |v_t|); separating velocities are kept."""
        vc = self.vel[s, b] + self.spin(self.omega[s, b], x - self.pos[s, b])
        rel = v - vc
        vn = rel.dot(n)
        out = v
        if vn < 0:
            vt = rel - vn * n
            vt_norm = ti.sqrt(vt.norm_sqr() + 1e-20)
            out = vc + ti.max(0.0, 1.0 + friction * vn / vt_norm) * vt
        return out

    @ti.func
    def moment(self, r, f):
        """r x f, as a 1-vector in 2D."""
        out = ti.Vector.zero(float, self.wdim)
        if ti.static(self.dim == 2):
            out[0] = r[0] * f[1] - r[1] * f[0]
        else:
            out = r.cross(f)
        return out


def kinematic_states(motions, t0: float, dt: float, K: int):
    """Per-substep states (pos, rot, vel, omega) of bodies following ``motions`` (kinematic.Motion),
    sampled at the start of each substep t0 + s dt, shaped for ``RigidBoundaries.set_states``."""
    dim = motions[0].dim
    pos = np.zeros((K, len(motions), dim))
    rot = np.zeros((K, len(motions), dim, dim))
    vel = np.zeros((K, len(motions), dim))
    omega = np.zeros((K, len(motions), 1 if dim == 2 else 3))
    for s in range(K):
        for b, motion in enumerate(motions):
            pos[s, b], rot[s, b] = motion.pose(t0 + s * dt)
            vel[s, b], w = motion.twist(t0 + s * dt)
            omega[s, b] = w
    return pos, rot, vel, omega


@ti.data_oriented
class GridContact:
    """Grid contact model: at grid nodes with signed distance below ``band`` (default half a
    cell: nodes strictly inside let a thick wall be entered by 0.8 dx, measured), the
    velocity relative to the body loses its approaching normal part and its tangential
    part is reduced by Coulomb friction: v_t * max(0, 1 - mu |v_n| / |v_t|)."""

    def __init__(self, engine, bodies: RigidBoundaries, friction: float, band: float | None = None):
        self.engine = engine
        self.bodies = bodies
        self.friction = float(friction)
        self.band = 0.5 * engine.dx if band is None else float(band)
        grad = engine.cfg.requires_grad
        self.output = ti.Vector.field(engine.dim, float, shape=engine.grid_v.shape, needs_grad=grad)
        engine.attach_grid_hook(self)

    @ti.kernel
    def _apply(self, g: ti.i32, s: ti.i32, dt: float):
        e, rb = self.engine, self.bodies
        for I in ti.grouped(ti.ndrange(*e.nodes)):
            v = e.grid_v[g, I]
            m = e.grid_m[g, I]
            xi = ti.cast(I, float) * e.dx
            if m > 0:  # empty nodes need no SDF lookup
                for b in ti.static(range(rb.n)):
                    p, R = rb.pos[s, b], rb.rot[s, b]
                    d, n_body = rb.sdfs[b].distance_normal(R.transpose() @ (xi - p))
                    if d < self.band:
                        v_new = rb.frictional_bc(v, xi, R @ n_body, s, b, self.friction)
                        dp = m * (v_new - v)  # momentum given to the material
                        rb.impulse[s, b] -= dp
                        rb.angular_impulse[s, b] -= rb.moment(xi - p, dp)
                        v = v_new
            self.output[g, I] = v

    @ti.func
    def velocity(self, g, I):
        return self.output[g, I]

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply(g, s, dt)

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply.grad(g, s, dt)

    def zero_grad(self) -> None:
        self.output.grad.fill(0)
        self.bodies.zero_grad()


@ti.data_oriented
class ParticlePenalty:
    """Particle contact model: a particle at signed distance d < 0 from a body receives
    the penalty force F = -k g0 m_p (d / dx) n, plus Coulomb friction (the tangential
    velocity relative to the body is reduced by at most mu |F_n| dt / m_p), added as
    momentum in P2G.

    ``stiffness`` k is dimensionless: the push on a particle one grid cell deep, in units
    of standard gravity g0. Scaling by the particle mass and the cell size makes one k
    mean the same penetration in cells at any particle size and resolution; the paper's
    k = 400 / 600 land in the range where the penetration-vs-rebound trade-off shows."""

    def __init__(self, engine, bodies: RigidBoundaries, stiffness: float, friction: float):
        self.engine = engine
        self.bodies = bodies
        self.stiffness = float(stiffness)
        self.accel_per_depth = self.stiffness * STANDARD_GRAVITY / engine.dx  # [1/s^2]
        self.friction = float(friction)
        grad = engine.cfg.requires_grad
        self.output = ti.Vector.field(engine.dim, float, shape=engine.affine.shape, needs_grad=grad)
        engine.attach_particle_hook(self)

    @ti.kernel
    def _apply(self, src: ti.i32, g: ti.i32, s: ti.i32, dt: float):
        e, rb = self.engine, self.bodies
        for p in range(e.n_particles):
            x, v = e.x[src, p], e.v[src, p]
            m = e.mass_of(p)
            dp_total = ti.Vector.zero(float, e.dim)
            for b in ti.static(range(rb.n)):
                pos, R = rb.pos[s, b], rb.rot[s, b]
                d, n_body = rb.sdfs[b].distance_normal(R.transpose() @ (x - pos))
                if d < 0:
                    n = R @ n_body
                    jn = -self.accel_per_depth * m * d * dt  # normal impulse, along +n
                    vc = rb.vel[s, b] + rb.spin(rb.omega[s, b], x - pos)
                    rel = v - vc
                    vt = rel - rel.dot(n) * n
                    vt_norm = ti.sqrt(vt.norm_sqr() + 1e-20)
                    jt = ti.min(self.friction * jn, m * vt_norm)  # friction impulse, against vt
                    dp = jn * n - jt * vt / vt_norm
                    rb.impulse[s, b] -= dp
                    rb.angular_impulse[s, b] -= rb.moment(x - pos, dp)
                    dp_total += dp
            self.output[g, p] = dp_total

    def apply(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply(src, g, s, dt)

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._apply.grad(src, g, s, dt)

    def zero_grad(self) -> None:
        self.output.grad.fill(0)
        self.bodies.zero_grad()


@ti.data_oriented
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

    BC_p for a particle at signed distance d < d_hat from a body, contact velocity v_c:
    the relative velocity loses its approaching normal part and its tangential part is
    reduced by Coulomb friction, v_out = v_c + v_t max(0, 1 - mu |v_n| / |v_t|); blended
    with the input by s = min(exp(-beta d), 1); if x + dt v_out would end inside the body,
    v_out gains -d_new / dt along the normal there (advect and project).

    The reaction on body b is minus the grid momentum change its particles' residuals cause,
    alpha sum_p m_p r_p over the particles it constrained, so the third law holds to round-off.
    """

    def __init__(
        self,
        engine,
        bodies: RigidBoundaries,
        friction: float,
        alpha: float = 0.8,
        threshold: float | None = None,
        beta: float | None = None,
    ):
        self.engine = engine
        self.bodies = bodies
        self.friction = float(friction)
        self.alpha = float(alpha)
        self.threshold = engine.dx if threshold is None else float(threshold)
        self.beta = 2.0 / engine.dx if beta is None else float(beta)
        grad = engine.cfg.requires_grad
        d = engine.dim
        per_particle = engine.affine.shape  # (grid copies, particles)
        self.v_init = ti.Vector.field(d, float, shape=per_particle, needs_grad=grad)
        self.residual = ti.Vector.field(d, float, shape=per_particle, needs_grad=grad)
        self.contact_body = ti.field(ti.i32, shape=per_particle)
        self.correction = ti.Vector.field(d, float, shape=engine.grid_v.shape, needs_grad=grad)
        self.scratch = [self.correction]  # zeroed by the engine with the grid each substep
        # benchmarks: the objective after / before the gradient step, per substep (a host sync each)
        self.track_objective = False
        self.objective_ratios: list[float] = []
        engine.attach_grid_hook(self)

    @ti.kernel
    def _forecast(self, src: ti.i32, g: ti.i32, s: ti.i32, dt: float):
        """Look-ahead G2P v_init = W^T v_hat, residual r = v_init - BC_p(v_init), which body set
        it (-1: none), and the scatter of constrained particles' W M_p r with their owner's
        reaction. One kernel (atomic adds only for constrained particles): each launch costs
        ~50 us on this CPU, as much as the work here."""
        e, rb = self.engine, self.bodies
        for p in range(e.n_particles):
            x = e.x[src, p]
            nearest = 1e30  # particles farther than the threshold from every body skip the look-ahead
            for b in ti.static(range(rb.n)):
                nearest = ti.min(nearest, rb.sdfs[b].distance(rb.rot[s, b].transpose() @ (x - rb.pos[s, b])))
            base, fx, w = e._stencil(x)
            v_init = ti.Vector.zero(float, e.dim)
            if nearest < self.threshold:
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    weight = e.stencil_weight(w, offset)
                    v_init += weight * e.grid_v[g, base + offset]
            self.v_init[g, p] = v_init
            v = v_init
            owner = -1
            for b in ti.static(range(rb.n)):
                pos, R = rb.pos[s, b], rb.rot[s, b]
                d, n_body = rb.sdfs[b].distance_normal(R.transpose() @ (x - pos))
                if d < self.threshold:
                    v_out = rb.frictional_bc(v, x, R @ n_body, s, b, self.friction)
                    smooth = ti.min(ti.exp(-self.beta * d), 1.0)
                    v_out = smooth * v_out + (1.0 - smooth) * v
                    x_new = x + dt * v_out
                    d_new, n_new_body = rb.sdfs[b].distance_normal(R.transpose() @ (x_new - pos))
                    if d_new < 0:
                        v_out += (-d_new / dt) * (R @ n_new_body)
                    v = v_out
                    owner = b
            r = v_init - v
            self.residual[g, p] = r
            self.contact_body[g, p] = owner
            if owner >= 0:  # correction += W M_p r; the owner's reaction is the momentum removed
                m_p = e.mass_of(p)
                for offset in ti.static(ti.grouped(ti.ndrange(*([3] * e.dim)))):
                    weight = e.stencil_weight(w, offset)
                    self.correction[g, base + offset] += (weight * m_p) * r
                # momentum given to the material: sum_i w_i (-alpha m_p r) = -alpha m_p r, with moment
                # sum_i (x_i - pos) x w_i dp = (x_p - pos) x dp (B-spline weights sum to 1 and
                # reproduce x_p), so one atomic pair per particle, not one per node (they all hit
                # the same two addresses: the near-wall work fell from 46 to 27 us per substep, measured)
                dp = (-self.alpha * m_p) * r
                for b in ti.static(range(rb.n)):
                    if owner == b:
                        rb.impulse[s, b] -= dp
                        rb.angular_impulse[s, b] -= rb.moment(x - rb.pos[s, b], dp)

    @ti.func
    def velocity(self, g, I):
        """v_g = v_hat - alpha correction / m, evaluated where G2P gathers it (no extra pass)."""
        e = self.engine
        v = e.grid_v[g, I]
        m = e.grid_m[g, I]
        if m > 0:
            v -= (self.alpha / m) * self.correction[g, I]
        return v

    @ti.kernel
    def _objective(self, src: ti.i32, g: ti.i32) -> ti.types.vector(2, float):
        """(|W^T v_hat - v_tgt|^2, |W^T v_g - v_tgt|^2) summed over constrained particles."""
        e = self.engine
        before, after = 0.0, 0.0
        for p in range(e.n_particles):
            if self.contact_body[g, p] >= 0:
                base, fx, w = e._stencil(e.x[src, p])
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
                self.objective_ratios.append(after / before)

    def apply_grad(self, src: int, g: int, s: int, dt: float) -> None:
        self._forecast.grad(src, g, s, dt)

    def zero_grad(self) -> None:
        for fld in (self.v_init, self.residual, self.correction):
            fld.grad.fill(0)
        self.bodies.zero_grad()
