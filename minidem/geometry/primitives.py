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


# A turning contact (two spheres, a sphere on a cylinder or on a mesh's edge) hands the
# functions below its last step's normal a as seen from the current normal b: scaled to
# a . b = 1, i.e. a / (a . b) (``previous_normal``). In that form the smallest rotation
# taking a to b, and the half of it the step's displacement needs, are additions and
# multiplications only: a pair's form comes with one division from quantities its
# evaluation has anyway, and the tile of pair contacts stays vector code.


@numba.njit(cache=True, inline="always")
def seen_from(unit_normal, normal):
    """A unit previous normal in the form above; the current normal itself (no turn) for
    one more than 60 degrees away: no contact turns that far in a step, and the division
    stays finite."""
    ax, ay, az = unit_normal
    cosine = ax * normal[0] + ay * normal[1] + az * normal[2]
    if cosine > 0.5:
        scale = 1.0 / cosine
        return ax * scale, ay * scale, az * scale
    return normal


@numba.njit(cache=True, inline="always")
def turn_slot(history, o, previous_normal, normal):
    """Turn the vector history slot history[o:o+3] with the contact, from the last
    step's tangent plane (normal a) into the current one (normal b).

    The smallest rotation taking a to b maps a vector v of a's plane to
    v - (v . b) (a + b) / (1 + a . b) (Rodrigues' formula with v . a = 0). With a given
    as a' = a / (a . b), v - (v . b) (a' + b) / 2 differs from it by the fourth power of
    the step's angle over 8 (relative to v): the slot lands exactly in b's plane and
    keeps its length and its direction relative to the contact to that. Projecting onto
    b's plane and restoring the length (LAMMPS' and LIGGGHTS' convention, design notes
    on LAMMPS #3022) is off by the square of the angle every step: a first-order error
    in the time step (docs/time-step.md).
    """
    hx, hy, hz = history[o], history[o + 1], history[o + 2]
    half = 0.5 * (hx * normal[0] + hy * normal[1] + hz * normal[2])
    history[o] = hx - half * (previous_normal[0] + normal[0])
    history[o + 1] = hy - half * (previous_normal[1] + normal[1])
    history[o + 2] = hz - half * (previous_normal[2] + normal[2])


@numba.njit(cache=True, inline="always")
def turned_increment(tangential_velocity, normal_velocity, previous_normal, normal, spin_lever, dt):
    """The tangential displacement of a turning contact over the step, in the current
    tangent plane: the contact-point velocity at the middle of the step (where the
    drift's constant velocities belong), turned with the contact to its end.

    To first order in the step's turn from a to b, that adds to ``tangential_velocity``
    (taken with b) the normal velocity the half turn tilts into the plane,
    normal_velocity / 2 (a' - b), and the spin about the normal it tilts,
    (b . s) (a' x b) / 2 with s = lever_i w_i + lever_j w_j (``spin_lever``, the arms
    of the step's middle, as ``tangential_velocity``'s spin share; a' as for
    ``turn_slot``). Without them the increment is off by the step's angle in every step,
    a first-order error in the time step; with them by its square."""
    ax, ay, az = previous_normal
    bx, by, bz = normal
    half = 0.5 * normal_velocity
    twist = 0.5 * (bx * spin_lever[0] + by * spin_lever[1] + bz * spin_lever[2])
    kx, ky, kz = cross(ax, ay, az, bx, by, bz)
    return ((tangential_velocity[0] + half * (ax - bx) + twist * kx) * dt,
            (tangential_velocity[1] + half * (ay - by) + twist * ky) * dt,
            (tangential_velocity[2] + half * (az - bz) + twist * kz) * dt)


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
    s, rx, ry, rz, rho = _from_axis(px, py, pz, base, axis, c)
    if s < 0.0 or s > length[c]:
        return -1.0, 0.0, 0.0, 1.0
    if rho == 0.0:
        return radius - cylinder_radius[c], 0.0, 0.0, 1.0
    return radius + rho - cylinder_radius[c], -rx / rho, -ry / rho, -rz / rho


@numba.njit(cache=True, inline="always")
def _from_axis(px, py, pz, base, axis, c):
    """(axial coordinate s, the point's offset from the axis r, its length rho) for
    cylinder c."""
    rx, ry, rz = px - base[c, 0], py - base[c, 1], pz - base[c, 2]
    s = rx * axis[c, 0] + ry * axis[c, 1] + rz * axis[c, 2]
    rx, ry, rz = rx - s * axis[c, 0], ry - s * axis[c, 1], rz - s * axis[c, 2]
    return s, rx, ry, rz, math.sqrt(rx * rx + ry * ry + rz * rz)


@numba.njit(cache=True, inline="always")
def cylinder_normal(px, py, pz, base, axis, c, fallback):
    """The normal of cylinder c's surface towards a point, whatever its axial coordinate
    (the ends do not matter to where the normal points); ``fallback`` for a point on the
    axis."""
    _, rx, ry, rz, rho = _from_axis(px, py, pz, base, axis, c)
    if rho == 0.0:
        return fallback
    return -rx / rho, -ry / rho, -rz / rho


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
