"""The Taichi kernel of ``sdf_mesh.mesh_sdf``: per grid node, the closest point over every triangle
and the generalised winding number (the sign)."""

import taichi as ti


@ti.func
def _closest_on_triangle(p, a, b, c):
    """Closest point to p on triangle abc (Ericson, Real-Time Collision Detection 5.1.5). Not
    ``cloth_mesh_query.closest_point_on_triangle``: that one builds its barycentrics in the session's
    float type, and the SDF is computed in float64 whatever the scene's precision."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = ab.dot(ap), ac.dot(ap)
    result = a
    done = d1 <= 0 and d2 <= 0
    bp = p - b
    d3, d4 = ab.dot(bp), ac.dot(bp)
    if not done and d3 >= 0 and d4 <= d3:
        result, done = b, True
    vc = d1 * d4 - d3 * d2
    if not done and vc <= 0 and d1 >= 0 and d3 <= 0:
        result, done = a + d1 / (d1 - d3) * ab, True
    cp = p - c
    d5, d6 = ab.dot(cp), ac.dot(cp)
    if not done and d6 >= 0 and d5 <= d6:
        result, done = c, True
    vb = d5 * d2 - d1 * d6
    if not done and vb <= 0 and d2 >= 0 and d6 <= 0:
        result, done = a + d2 / (d2 - d6) * ac, True
    va = d3 * d6 - d5 * d4
    if not done and va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        result, done = b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b), True
    if not done:
        denom = 1.0 / (va + vb + vc)
        result = a + ab * (vb * denom) + ac * (vc * denom)
    return result


@ti.kernel
def mesh_sdf_kernel(
    points: ti.types.ndarray(), tris: ti.types.ndarray(), out: ti.types.ndarray(), closest: ti.types.ndarray()
):
    for i in range(points.shape[0]):
        p = ti.Vector([points[i, 0], points[i, 1], points[i, 2]], dt=ti.f64)
        best = 1e30
        best_q = p
        winding = 0.0
        for t in range(tris.shape[0]):
            a = ti.Vector([tris[t, 0, 0], tris[t, 0, 1], tris[t, 0, 2]], dt=ti.f64)
            b = ti.Vector([tris[t, 1, 0], tris[t, 1, 1], tris[t, 1, 2]], dt=ti.f64)
            c = ti.Vector([tris[t, 2, 0], tris[t, 2, 1], tris[t, 2, 2]], dt=ti.f64)
            q = _closest_on_triangle(p, a, b, c)
            if (p - q).norm_sqr() < best:
                best, best_q = (p - q).norm_sqr(), q
            # solid angle of the triangle seen from p (Van Oosterom and Strackee)
            ra, rb, rc = a - p, b - p, c - p
            la, lb, lc = ra.norm(), rb.norm(), rc.norm()
            num = ra.dot(rb.cross(rc))
            den = la * lb * lc + ra.dot(rb) * lc + rb.dot(rc) * la + rc.dot(ra) * lb
            winding += 2.0 * ti.atan2(num, den)
        sign = -1.0 if winding / (4.0 * 3.141592653589793) > 0.5 else 1.0
        out[i] = sign * ti.sqrt(best)
        for k in ti.static(range(3)):
            closest[i, k] = best_q[k]
