"""The compiled simulation: contact loops and the time-step loop.

This file is a template. ``minidem.simulation.compile_kernel`` copies it into the
kernel cache with the specialisation block below rewritten for one contact law and
one scene shape (spin or not), so numba compiles one kernel per law with the law's
force function inlined, and caches it across processes. Nothing here names a law.
"""

import math

import numba

from minidem.contact import cross, plane_overlap, relative_contact_velocity
from minidem.integrate import drift, half_kick

# >>> specialisation block (rewritten by minidem.simulation.compile_kernel)
from minidem.builtin_laws.linear import linear_force as law_force  # noqa: E402

SPIN = True
# <<< specialisation block

# status codes (status[0]); status[1], status[2] name the particle and wall/partner
OK, NON_FINITE_FORCE, TUNNELLED = 0, 1, 2
# stats slots
FIRST_CONTACT_TIME, LAST_SEPARATION_TIME, MAX_OVERLAP, PEAK_NORMAL_FORCE, PEAK_TANGENTIAL_FORCE = range(5)
# probe slots: the contact of particle 0 with the probed wall, for per-step traces
PROBE_OVERLAP, PROBE_FN, PROBE_FT, PROBE_DISPLACEMENT = 0, 1, 2, 5  # FT and DISPLACEMENT are 3-vectors


@numba.njit(cache=True)
def wall_forces(position, velocity, angular_velocity, force, torque, mass, radius, material,
                wall_point, wall_normal, wall_material, pair_row, constants,
                wall_history, wall_overlap, dt, time, probe_wall, probe, stats, status):
    """Add the forces of every sphere-plane contact; return the number of contacts."""
    active = 0
    for i in range(position.shape[0]):
        px, py, pz = position[i, 0], position[i, 1], position[i, 2]
        for w in range(wall_point.shape[0]):
            overlap = plane_overlap(px, py, pz, radius[i], wall_point, wall_normal, w)
            previous = wall_overlap[i, w]
            wall_overlap[i, w] = overlap
            if overlap <= 0.0:
                if previous > 0.0:
                    wall_history[i, w, :] = 0.0  # contact ends: its history is dropped
                    stats[LAST_SEPARATION_TIME] = time - dt * (-overlap) / (previous - overlap)
                continue
            if previous <= 0.0 and stats[FIRST_CONTACT_TIME] < 0.0:
                stats[FIRST_CONTACT_TIME] = time - dt * overlap / (overlap - previous)
            if overlap >= radius[i]:
                status[0], status[1], status[2] = TUNNELLED, i, w
                return active
            active += 1
            nx, ny, nz = wall_normal[w, 0], wall_normal[w, 1], wall_normal[w, 2]
            normal_velocity, tangential_velocity = relative_contact_velocity(
                velocity[i, 0], velocity[i, 1], velocity[i, 2],
                angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2],
                radius[i], nx, ny, nz)
            increment = (tangential_velocity[0] * dt, tangential_velocity[1] * dt, tangential_velocity[2] * dt)
            fn, ftx, fty, ftz = law_force(
                constants[pair_row[material[i], wall_material[w]]], radius[i], mass[i], overlap,
                overlap - max(previous, 0.0), normal_velocity, increment,
                tangential_velocity, wall_history[i, w])
            if not (math.isfinite(fn) and math.isfinite(ftx) and math.isfinite(fty) and math.isfinite(ftz)):
                status[0], status[1], status[2] = NON_FINITE_FORCE, i, w
                return active
            force[i, 0] += fn * nx - ftx
            force[i, 1] += fn * ny - fty
            force[i, 2] += fn * nz - ftz
            if SPIN:
                # lever arm R: the undeformed radius, as in the paper's rigid-body
                # analysis (eqs 3-8) and its measure y2 = 2 R w / ((1 + en) Vni)
                tx, ty, tz = cross(nx, ny, nz, ftx, fty, ftz)
                torque[i, 0] += radius[i] * tx
                torque[i, 1] += radius[i] * ty
                torque[i, 2] += radius[i] * tz
            ft = math.sqrt(ftx * ftx + fty * fty + ftz * ftz)
            stats[MAX_OVERLAP] = max(stats[MAX_OVERLAP], overlap)
            stats[PEAK_NORMAL_FORCE] = max(stats[PEAK_NORMAL_FORCE], fn)
            stats[PEAK_TANGENTIAL_FORCE] = max(stats[PEAK_TANGENTIAL_FORCE], ft)
            if i == 0 and w == probe_wall:
                probe[PROBE_OVERLAP] = overlap
                probe[PROBE_FN] = fn
                probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = ftx, fty, ftz
                probe[PROBE_DISPLACEMENT] += increment[0]
                probe[PROBE_DISPLACEMENT + 1] += increment[1]
                probe[PROBE_DISPLACEMENT + 2] += increment[2]
        if i == 0 and 0 <= probe_wall and wall_overlap[0, probe_wall] <= 0.0:
            probe[PROBE_OVERLAP], probe[PROBE_FN] = wall_overlap[0, probe_wall], 0.0
            probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = 0.0, 0.0, 0.0
    return active


@numba.njit(cache=True)
def compute_forces(position, velocity, angular_velocity, force, torque, mass, radius, material,
                   gravity, wall_point, wall_normal, wall_material, pair_row, constants,
                   wall_history, wall_overlap, dt, time, probe_wall, probe, stats, status):
    for i in range(position.shape[0]):
        force[i, 0] = mass[i] * gravity[0]
        force[i, 1] = mass[i] * gravity[1]
        force[i, 2] = mass[i] * gravity[2]
        torque[i, 0] = 0.0
        torque[i, 1] = 0.0
        torque[i, 2] = 0.0
    return wall_forces(position, velocity, angular_velocity, force, torque, mass, radius, material,
                       wall_point, wall_normal, wall_material, pair_row, constants,
                       wall_history, wall_overlap, dt, time, probe_wall, probe, stats, status)


@numba.njit(cache=True)
def advance(position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia,
            radius, material, gravity, wall_point, wall_normal, wall_material, pair_row, constants,
            wall_history, wall_overlap, dt, start_time, start_step, n_steps, stop_at_separation,
            probe_wall, probe, trace, stats, status):
    """Advance up to n_steps; return the number of steps taken.

    Stops early after the step in which the last contact ended (when
    stop_at_separation and a contact has occurred), or on a fault (status[0] != OK).
    ``trace`` (rows = steps, may have 0 rows) receives the probed contact each step.
    Times are start_time + k dt, not a running sum, so long runs do not drift.
    """
    for step in range(n_steps):
        half_kick(velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, dt, SPIN)
        drift(position, velocity, dt)
        time = start_time + (start_step + step + 1) * dt
        active = compute_forces(position, velocity, angular_velocity, force, torque, mass, radius,
                                material, gravity, wall_point, wall_normal, wall_material, pair_row,
                                constants, wall_history, wall_overlap, dt, time, probe_wall, probe,
                                stats, status)
        if status[0] != OK:
            return step + 1
        half_kick(velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, dt, SPIN)
        if step < trace.shape[0]:
            trace[step, 0] = time
            trace[step, 1:9] = probe[:8]
            trace[step, 9:12] = velocity[0]
            trace[step, 12:15] = angular_velocity[0]
        if stop_at_separation and active == 0 and stats[FIRST_CONTACT_TIME] >= 0.0:
            return step + 1
    return n_steps


TRACE_COLUMNS = (
    "time_s", "normal_overlap_m", "normal_force_n", "tangential_force_x_n", "tangential_force_y_n",
    "tangential_force_z_n", "tangential_displacement_x_m", "tangential_displacement_y_m",
    "tangential_displacement_z_m", "velocity_x_m_s", "velocity_y_m_s", "velocity_z_m_s",
    "angular_velocity_x_rad_s", "angular_velocity_y_rad_s", "angular_velocity_z_rad_s",
)
