"""The rounded max() that keeps switches C2: contact rules (``cosim.couplers.contact_rules``) and the
MPM's domain walls use it, so that losses through them have derivatives central differences converge to."""

import taichi as ti


@ti.func
def soft_ramp(z, width):
    """max(z, 0) made C2 over ``width`` without ever exceeding it (no push or limit adds energy):
    width u^3 (6 - 8u + 3u^2) with u = z / width on (0, width), exact outside; width 0: max(z, 0).

    C2, not C1: contact states sit exactly at a ramp's start (the speculative limit lands a particle
    on the surface, so the next substep's projection starts at 0), and a C1 ramp's second derivative
    jumps there, so central differences of any loss through contact erred by O(step): pull_door's
    30-step gradcheck gave 2e-5 at step 1e-6 and 2.7e-6 at 1e-7 with a cubic ramp, 1.6e-7 at 1e-6
    with this one."""
    u = ti.min(ti.max(z, 0.0), width) / ti.max(width, 1e-30)
    return width * u * u * u * (6.0 - 8.0 * u + 3.0 * u * u) + ti.max(z - width, 0.0)
