"""The pointwise rules the contact models are built from: boundary conditions on one velocity,
the rounded max() that keeps them C2, a particle's offset from a surface, the forecast model's
default step. Kernels of ``cosim.couplers.contact`` inline them."""

import taichi as ti

from cosim.engines.contract import traits_of
from cosim.engines.smooth import soft_ramp

STANDARD_GRAVITY = 9.80665  # [m/s^2] the unit of the particle model's stiffness
BLEND_WHERE = ("liquids", "all", "none")  # forecast: which particles get the paper's blended BC_p
SPECULATIVE_SOFT = 2.0  # the speculative limit is rounded over this fraction of the gap (``soft_ramp``)
STICK_SOFT = 0.1  # Coulomb's stick limit is rounded over this fraction of the speeds (``coulomb_slip``)
STICTION_SPEED = 1e-4  # [m/s] and over this speed, so that friction is smooth at zero speed and push
PROJECT_SOFT = 1e-2  # [cells] advect-and-project's push is rounded over this much
AUTO_OFFSET = -1.0  # a contact offset below 0: each particle's radius (``surface_offset``)
APPROACH_SOFT = 1e-4  # [m/s] the blended BC's removal of an approach is rounded over this speed (a tenth
# of what gravity adds in a 1e-4 s substep)
BLEND_SOFT = 1e-2  # [cells] the forecast blend's corner at the surface is rounded over this
GRID_SUPPORT = ("material", "nodes")  # grid model: liquids held by their own edge, or all material at node rows
LIQUID_REACH = 3.0  # [cells] grid model: nodes farther from a body than this skip the liquid's reading
LIQUID_BAND_SHIFT = 2.0  # [cells] grid model: how far into a body the band moves at a node of liquid only
DENSE_FILL = (0.5, 0.9)  # grid model: liquid is read as a half-space where its stencil's fullest node fills above
SOLID_SOFT = 0.05  # grid model: the extra solid in a stencil is counted from 0 up, rounded over this share
CELL_SHARE = (1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0)  # the quadratic B-spline's integral over each neighbour's cell
TAPER = 0.25  # forecast: the fraction of the threshold over which BC_p's weight falls to 0
# [cells] forecast: material within this gap of a surface it is not blended with touches it (``engagement``)
TOUCH = 0.1


@ti.func
def frictional_bc(v, n, vc, friction):
    """Velocity v after contact with a surface of outward normal n moving with vc: if approaching,
    the relative velocity loses its normal part and its tangential part shrinks by Coulomb
    friction, vc + v_t max(0, 1 - mu |v_n| / |v_t|); separating velocities are kept. Both switches
    are rounded (``soft_ramp``, ``coulomb_slip``): with bare ones water crossing vn = 0 put kinks
    along any direction, and pour_water's 30-step gradcheck was 4.6e-5 off; rounded, 3e-8."""
    rel = v - vc
    vn = rel.dot(n)
    vt = rel - vn * n
    removed = soft_ramp(-vn, APPROACH_SOFT)  # the approach taken away, C2 at vn = 0
    return vc + (vn + removed) * n + coulomb_slip(vt, friction * removed) * vt


@ti.func
def surface_offset(engine: ti.template(), offset: ti.template(), p):
    """[m] How far from a surface particle p's centre is held: ``offset`` if >= 0, else (AUTO_OFFSET)
    the particle's radius, so that its material, not its centre, meets the geometry. (An expression,
    not a branch: Taichi's adjoint of a local variable assigned in a static branch came out wrong.)"""
    return ti.static(float(offset < 0)) * engine.radius_of(p) + ti.static(max(offset, 0.0))


def default_alpha(dim: int, sources: list) -> float:
    """The forecast model's gradient step: 0.8 in 2D; in 3D 0.3 (0.8 spread each particle's correction
    over its 27 nodes' neighbours and cost an elastic sphere a tenth of its restitution), but 0.8 with a
    cloth sheet (at 0.3, 46 of make_taco's filling particles crossed the tortilla)."""
    needed = [traits_of(src).forecast_alpha for src in sources if traits_of(src).forecast_alpha is not None]
    return max([0.8 if dim == 2 else 0.3, *needed])


def source_offset(source, offset: float) -> float:
    """The offset [m] (AUTO_OFFSET: the particle's radius) a contact model keeps from ``source``: 0 from
    a source whose ``ContactTraits.offset`` is False (a cloth sheet, whose contact keeps the paper's form)."""
    return offset if traits_of(source).offset else 0.0


@ti.func
def speculative_bc(v, n, vc, friction, gap, dt):
    """Velocity v after a look-ahead contact with a surface ``gap`` [m] away (outward normal n, moving
    with vc): the relative normal velocity may approach at most at -gap/dt, so the particle reaches
    the surface at the end of the substep and no sooner (gap < 0: it leaves the surface at -gap/dt);
    the tangential part loses Coulomb friction mu times the normal velocity taken away. Continuous in
    v, gap and the surface's motion; nothing changes for a particle that would not reach the surface
    within dt, so an approaching body is not braked before it touches (no dashpot, see ForecastContact)."""
    rel = v - vc
    vn = rel.dot(n)
    vt = rel - vn * n
    # rounded over a width proportional to |gap|: a particle's first touch is C2, and so is the push
    # out of one inside (with the bare max() there, squeeze_plasticine with an elastic block was 4.8e-5
    # off at 60 steps, 2.5e-6 rounded); resting contact (gap 0) keeps the exact limit
    raised = soft_ramp(-gap / dt - vn, SPECULATIVE_SOFT * ti.abs(gap) / dt)
    return vc + (vn + raised) * n + coulomb_slip(vt, friction * raised) * vt


@ti.func
def coulomb_slip(vt, limit):
    """The fraction of the tangential velocity vt [m/s] that Coulomb friction keeps when it may take
    away ``limit`` [m/s] of speed: 1 - limit / max(|vt|, limit) (stick below the limit), with the
    max() rounded from above, so it never takes more than Coulomb's, over a tenth of the two speeds
    plus STICTION_SPEED. That last term makes it smooth where the speed and the limit vanish
    together (the friction cone's apex; rounded over the two speeds alone, squeeze_plasticine's
    60-step gradcheck was 1.2e-4 off, with it 1.6e-6); below STICTION_SPEED friction holds a little
    less than Coulomb's (a particle in stick keeps about 0.25% of its slip speed)."""
    speed = ti.sqrt(vt.norm_sqr() + 1e-30)
    width = STICK_SOFT * (speed + limit) + STICTION_SPEED
    top = 0.5 * (speed + limit + ti.sqrt((speed - limit) ** 2 + width * width))  # >= max(speed, limit)
    return 1.0 - limit / top


@ti.func
def reach_of_fill(phi):
    """[cells] How far material filling a share phi of a node's cell reaches past the node, if it
    filled a half-space: the inverse of B(u) = integral of the quadratic B-spline up to u. Exact
    on |u| <= 1/2 (the cubic u^3 - 9u/4 + 3 (phi - 1/2) = 0, solved in closed form); beyond it B's
    tails are flat, so the inverse would magnify the fill's noise without bound, and it continues
    along its tangent instead (slope 2; C1): at phi = 0 and 1 it gives -/+5/6 where B gives -/+3/2.
    Those nodes are over a cell from the material's edge, where the contact gap is not held."""
    c = ti.min(ti.max(-4.0 * (phi - 0.5) / ti.sqrt(3.0), -1.0), 1.0)
    middle = ti.sqrt(3.0) * ti.cos((2.0 * 3.141592653589793 - ti.acos(c)) / 3.0)
    u = middle
    if phi < 1.0 / 6.0:
        u = -0.5 + 2.0 * (phi - 1.0 / 6.0)
    elif phi > 5.0 / 6.0:
        u = 0.5 + 2.0 * (phi - 5.0 / 6.0)
    return u


@ti.func
def occupancy(d, dx):
    """Share [-] of a node's cell inside a body at signed distance d [m] from the node: 1 - smoothstep
    of d over (-dx, dx), 1/2 at the surface (C1)."""
    t = ti.min(ti.max(0.5 * (d / dx + 1.0), 0.0), 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)
