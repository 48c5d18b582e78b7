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
def relative_contact_velocity(vx, vy, vz, wx, wy, wz, lever_arm, nx, ny, nz):
    """Velocity of the contact point of a sphere whose centre is lever_arm away along +n.

    The contact point sits at -lever_arm n from the centre, so its velocity is
    v + w x (-lever_arm n). Returns (approach rate along -n, tangential velocity).
    """
    rx, ry, rz = cross(wx, wy, wz, -lever_arm * nx, -lever_arm * ny, -lever_arm * nz)
    cx, cy, cz = vx + rx, vy + ry, vz + rz
    along = cx * nx + cy * ny + cz * nz
    return -along, (cx - along * nx, cy - along * ny, cz - along * nz)


@numba.njit(cache=True, inline="always")
def rotate_history_into_plane(history, vector_offsets, nx, ny, nz):
    """Carry vector history into the current tangent plane as the contact rotates.

    The normal component is removed and the magnitude restored, so a rotating contact
    neither loses nor gains stored force (the LAMMPS/LIGGGHTS convention; see design
    notes on LAMMPS #3022).
    """
    for k in range(vector_offsets.shape[0]):
        o = vector_offsets[k]
        hx, hy, hz = history[o], history[o + 1], history[o + 2]
        before = math.sqrt(hx * hx + hy * hy + hz * hz)
        if before == 0.0:
            continue
        along = hx * nx + hy * ny + hz * nz
        hx, hy, hz = hx - along * nx, hy - along * ny, hz - along * nz
        after = math.sqrt(hx * hx + hy * hy + hz * hz)
        scale = before / after if after > 0.0 else 0.0
        history[o], history[o + 1], history[o + 2] = hx * scale, hy * scale, hz * scale
