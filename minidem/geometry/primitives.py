"""Contact geometry shared by every law: overlaps, contact-point velocities, and the
bookkeeping that keeps per-contact history in the current tangent plane.

Conventions (the law sees only the results):
* the contact normal ``n`` points from the second body (wall or particle j) to the
  first (particle i); the normal force acts on i along +n;
* ``normal_overlap`` > 0 in contact; ``normal_velocity`` is the rate of overlap
  (positive while approaching);
* ``tangential_increment`` is the displacement of i's contact point relative to the
  other body's over the step, in the tangent plane; the law returns the tangential
  spring force in the sense of that displacement, and the engine applies its opposite
  to i (and the force itself to j).
"""

import math

import numba


@numba.njit(cache=True, inline="always")
def cross(ax, ay, az, bx, by, bz):
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@numba.njit(cache=True, inline="always")
def plane_overlap(px, py, pz, radius, wall_point, wall_normal, wall):
    """Overlap of a sphere with an infinite plane: R - (x - p) . n."""
    distance = ((px - wall_point[wall, 0]) * wall_normal[wall, 0]
                + (py - wall_point[wall, 1]) * wall_normal[wall, 1]
                + (pz - wall_point[wall, 2]) * wall_normal[wall, 2])
    return radius - distance


@numba.njit(cache=True, inline="always")
def rotate_slot_into_plane(history, o, nx, ny, nz):
    """Carry the vector history slot history[o:o+3] into the current tangent plane as
    the contact rotates.

    The normal component is removed and the magnitude restored, so a rotating contact
    neither loses nor gains stored force (the LAMMPS/LIGGGHTS convention; see design
    notes on LAMMPS #3022).
    """
    hx, hy, hz = history[o], history[o + 1], history[o + 2]
    before = hx * hx + hy * hy + hz * hz
    # no early return for an empty slot (it stays zero: after = 0, scale 0): without a
    # branch the compiler hands the rotated values straight to the law, which reads the
    # slot next, instead of storing and loading them again
    along = hx * nx + hy * ny + hz * nz
    hx, hy, hz = hx - along * nx, hy - along * ny, hz - along * nz
    after = hx * hx + hy * hy + hz * hz
    # |h_before| / |h_after| with one square root (this runs for every contact, every step)
    scale = math.sqrt(before / after) if after > 0.0 else 0.0
    history[o], history[o + 1], history[o + 2] = hx * scale, hy * scale, hz * scale


@numba.njit(cache=True, inline="always")
def pair_contact_velocity(vix, viy, viz, wix, wiy, wiz, vjx, vjy, vjz, wjx, wjy, wjz,
                          lever_i, lever_j, nx, ny, nz):
    """Velocity of i's contact point relative to j's, for a normal n pointing from j to i.

    i's contact point is at -lever_i n from its centre, j's at +lever_j n from its own;
    with lever_i + lever_j equal to the centre distance both are the same point, so the
    contact torques balance the moment of the contact force about the pair and angular
    momentum is conserved. A fixed wall is the partner with v_j = w_j = 0 (then lever_i
    is the sphere's lever arm and lever_j does not matter). Returns (approach rate along
    -n, tangential velocity).

    The two spin terms are one cross product, w_i x (-lever_i n) - w_j x (lever_j n)
    = n x (lever_i w_i + lever_j w_j): 12 multiplications where two took 18 (this runs
    for every contact, every step).
    """
    sx, sy, sz = lever_i * wix + lever_j * wjx, lever_i * wiy + lever_j * wjy, lever_i * wiz + lever_j * wjz
    ax, ay, az = cross(nx, ny, nz, sx, sy, sz)
    cx, cy, cz = vix - vjx + ax, viy - vjy + ay, viz - vjz + az
    along = cx * nx + cy * ny + cz * nz
    return -along, (cx - along * nx, cy - along * ny, cz - along * nz)


@numba.njit(cache=True, inline="always")
def cylinder_overlap(px, py, pz, radius, base, axis, cylinder_radius, length, c):
    """Overlap of a sphere with the inside surface of a finite cylinder, and the normal
    (from the wall to the sphere, i.e. towards the axis).

    The surface spans axial coordinates [0, length] from ``base`` along the unit
    ``axis``; beyond its ends there is no contact (an open silo). Returns
    (overlap, nx, ny, nz); the overlap is <= 0 when not in contact.
    """
    rx, ry, rz = px - base[c, 0], py - base[c, 1], pz - base[c, 2]
    s = rx * axis[c, 0] + ry * axis[c, 1] + rz * axis[c, 2]
    if s < 0.0 or s > length[c]:
        return -1.0, 0.0, 0.0, 1.0
    rx, ry, rz = rx - s * axis[c, 0], ry - s * axis[c, 1], rz - s * axis[c, 2]
    rho = math.sqrt(rx * rx + ry * ry + rz * rz)
    if rho == 0.0:
        return radius - cylinder_radius[c], 0.0, 0.0, 1.0
    return radius + rho - cylinder_radius[c], -rx / rho, -ry / rho, -rz / rho


# feature of a triangle that holds the closest point
FACE, EDGE, VERTEX = 0, 1, 2


@numba.njit(cache=True, inline="always")
def _edge_projections(px, py, pz, tri, t, vertex, abx, aby, abz, acx, acy, acz):
    """(AB . (p - V), AC . (p - V)) for vertex V of triangle t."""
    vx, vy, vz = px - tri[t, vertex, 0], py - tri[t, vertex, 1], pz - tri[t, vertex, 2]
    return abx * vx + aby * vy + abz * vz, acx * vx + acy * vy + acz * vz


@numba.njit(cache=True, inline="always")
def triangle_closest_point(px, py, pz, tri, t):
    """Closest point of triangle ``tri[t]`` (3 vertices x 3) to p and the feature it lies
    on (FACE interior, an EDGE or a VERTEX): Ericson, Real-Time Collision Detection,
    section 5.1.5 (Voronoi regions of the triangle)."""
    ax, ay, az = tri[t, 0, 0], tri[t, 0, 1], tri[t, 0, 2]
    abx, aby, abz = tri[t, 1, 0] - ax, tri[t, 1, 1] - ay, tri[t, 1, 2] - az
    acx, acy, acz = tri[t, 2, 0] - ax, tri[t, 2, 1] - ay, tri[t, 2, 2] - az
    d1, d2 = _edge_projections(px, py, pz, tri, t, 0, abx, aby, abz, acx, acy, acz)
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, VERTEX
    d3, d4 = _edge_projections(px, py, pz, tri, t, 1, abx, aby, abz, acx, acy, acz)
    if d3 >= 0.0 and d4 <= d3:
        return tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2], VERTEX
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return ax + v * abx, ay + v * aby, az + v * abz, EDGE
    d5, d6 = _edge_projections(px, py, pz, tri, t, 2, abx, aby, abz, acx, acy, acz)
    if d6 >= 0.0 and d5 <= d6:
        return tri[t, 2, 0], tri[t, 2, 1], tri[t, 2, 2], VERTEX
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return ax + w * acx, ay + w * acy, az + w * acz, EDGE
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        bx, by, bz = tri[t, 1, 0], tri[t, 1, 1], tri[t, 1, 2]
        return bx + w * (tri[t, 2, 0] - bx), by + w * (tri[t, 2, 1] - by), bz + w * (tri[t, 2, 2] - bz), EDGE
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, FACE
