"""The compiled simulation: contact loops and the time-step loop.

This file is a template. ``minidem.simulation.compile_kernel`` copies it into the
kernel cache with the specialisation block below rewritten for one contact law and
one scene shape, so numba compiles one kernel per (law, scene shape) with the law's
force function inlined, and caches it across processes. Nothing here names a law.

Scene shape flags ("model only what a scene needs": a branch on a False flag is
removed by the compiler, so a single impact pays nothing for pairs or meshes):

    SPIN       angular velocities and torques (the law can produce tangential forces)
    PAIRS      sphere-sphere contacts through the Verlet list (more than one particle)
    CYLINDERS  finite cylinder walls
    MESHES     triangle-mesh walls
    PARALLEL   particle loops run with prange; small scenes run serial and TRACK
               contact statistics (first touch, separation, peaks) and the probe
    OPENING_KICK  the integrator (minidem.integrate): the fraction of the velocity
               update made before the drift, 0.5 velocity Verlet, 1 symplectic Euler

One step is three particle loops (velocity Verlet shown; symplectic Euler kicks the
whole dt in kick_drift and nothing in finish):

    kick_drift      v += F dt/2m, x += v dt; counts particles that moved more than
                    half the skin since the last neighbour-list build
    compute_forces  particle i owns its walls and the pairs (i, j > i) of its CSR
                    row: it computes them, writes its own force, and stores each pair's
                    force and torque direction for j
    finish          particle p adds the reactions of the pairs (i < p, p) in
                    ascending i (the reverse index), then v += F dt/2m

Every sum is taken in an order fixed by the neighbour list, never by the thread
schedule, so a run is bit-for-bit the same on any number of threads, and no two
threads write the same memory.

Contact conventions are those of ``minidem.contact``: n points from j (or the wall)
to i, the normal force acts on i along +n, the law's tangential force acts on i as -ft.
"""

import math

import numba

from minidem.contact import (
    EDGE,
    FACE,
    cross,
    cylinder_overlap,
    pair_contact_velocity,
    plane_overlap,
    relative_contact_velocity,
    rotate_history_into_plane,
    triangle_closest_point,
)
from minidem.integrate import drift, kick

# >>> specialisation block (rewritten by minidem.simulation.compile_kernel)
from minidem.builtin_laws.linear import linear_force as law_force  # noqa: E402

SPIN = True
PAIRS = True
CYLINDERS = True
MESHES = True
PARALLEL = False
OPENING_KICK = 0.5
# <<< specialisation block

# contact statistics and the probe are written by whichever particle has the contact:
# only race-free in a serial loop
TRACK = not PARALLEL
particle_range = numba.prange if PARALLEL else range
# Serial kernels inline the per-step functions into ``advance`` (numba IR inlining): one
# function is optimised and compiled once. Kept separate, each entry point is compiled
# on its own and then linked into ``advance``, which optimises the linked copy again:
# 40 % more CPU time in the cold compile of a single-impact kernel (6.9 s against 4.9 s,
# measured on the hmd kernel). Parallel loops (prange) cannot be inlined into the
# serial step loop.
INLINE = "never" if PARALLEL else "always"
# the Verlet list (pairs, mesh candidates) must be rebuilt when particles move too far
CHECK_DISPLACEMENT = PAIRS or MESHES
# the part of the velocity update made after the force evaluation (0: symplectic Euler)
CLOSING_KICK = 1.0 - OPENING_KICK

# status codes (status[0]); status[1], status[2] name the particle and wall/partner
OK, NON_FINITE_FORCE, TUNNELLED = 0, 1, 2
# partner kinds in status[3]
PLANE, CYLINDER, TRIANGLE, PARTICLE = 0, 1, 2, 3
# stats slots
FIRST_CONTACT_TIME, LAST_SEPARATION_TIME, MAX_OVERLAP, PEAK_NORMAL_FORCE, PEAK_TANGENTIAL_FORCE = range(5)
# probe slots: the contact of particle 0 with the probed wall, for per-step traces
PROBE_OVERLAP, PROBE_FN, PROBE_FT, PROBE_DISPLACEMENT = 0, 1, 2, 5  # FT and DISPLACEMENT are 3-vectors
# mesh contacts this close (relative to the radius) are the same edge or vertex seen
# from two triangles
_SAME_POINT = 1e-9


@numba.njit(cache=True, inline="always")
def fault(status, code, particle, partner, kind):
    if status[0] == OK:
        status[0], status[1], status[2], status[3] = code, particle, partner, kind


@numba.njit(cache=True, inline="always")
def note_transitions(stats, time, dt, overlap, previous):
    """First-touch and separation times, interpolated within the step."""
    if overlap > 0.0 and previous <= 0.0 and stats[FIRST_CONTACT_TIME] < 0.0:
        # clamped to the step: rounding may otherwise give a time just below zero, which
        # reads as 'no contact yet' and the run would never stop at separation
        stats[FIRST_CONTACT_TIME] = max(time - dt * overlap / (overlap - previous), time - dt)
    elif overlap <= 0.0 and previous > 0.0:
        stats[LAST_SEPARATION_TIME] = time - dt * (-overlap) / (previous - overlap)


@numba.njit(cache=True, inline="always")
def note_peaks(stats, overlap, fn, ftx, fty, ftz):
    stats[MAX_OVERLAP] = max(stats[MAX_OVERLAP], overlap)
    stats[PEAK_NORMAL_FORCE] = max(stats[PEAK_NORMAL_FORCE], fn)
    stats[PEAK_TANGENTIAL_FORCE] = max(stats[PEAK_TANGENTIAL_FORCE], math.sqrt(ftx * ftx + fty * fty + ftz * ftz))


# The per-particle helpers take plain arrays, unpacked from the argument tuples once
# per chunk of particles (force_range): unpacking tuples inside the particle loop costs
# reference-count traffic that made the step ten times slower.
@numba.njit(cache=True, inline="always")
def wall_contact(i, velocity, angular_velocity, mass, radius, constants_row, overlap, previous, nx, ny, nz,
                 history, dt):
    """The law's force on sphere i from a fixed wall whose normal at the contact is n.

    Lever arm R: the undeformed radius, as in the paper's rigid-body analysis (eqs
    3-8) and its measure y2 = 2 R w / ((1 + en) Vni).
    """
    normal_velocity, tangential_velocity = relative_contact_velocity(
        velocity[i, 0], velocity[i, 1], velocity[i, 2],
        angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2],
        radius[i], nx, ny, nz)
    increment = (tangential_velocity[0] * dt, tangential_velocity[1] * dt, tangential_velocity[2] * dt)
    fn, ftx, fty, ftz = law_force(constants_row, radius[i], mass[i], overlap, overlap - max(previous, 0.0),
                                  normal_velocity, increment, tangential_velocity, history)
    return fn, ftx, fty, ftz, increment


@numba.njit(cache=True, inline="always")
def finite(fn, ftx, fty, ftz):
    return math.isfinite(fn) and math.isfinite(ftx) and math.isfinite(fty) and math.isfinite(ftz)


@numba.njit(cache=True, inline="always")
def plane_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                 wall_point, wall_normal, wall_material, wall_history, wall_overlap,
                 dt, time, probe_wall, probe, stats, status, acc):
    """Sphere-plane contacts of particle i, added to acc = (fx, fy, fz, tx, ty, tz, count)."""
    fx, fy, fz, tx, ty, tz, count = acc
    px, py, pz = position[i, 0], position[i, 1], position[i, 2]
    for w in range(wall_point.shape[0]):
        overlap = plane_overlap(px, py, pz, radius[i], wall_point, wall_normal, w)
        previous = wall_overlap[i, w]
        wall_overlap[i, w] = overlap
        if TRACK:
            note_transitions(stats, time, dt, overlap, previous)
        if overlap <= 0.0:
            if previous > 0.0:
                wall_history[i, w, :] = 0.0  # contact ends: its history is dropped
            continue
        if overlap >= radius[i]:
            fault(status, TUNNELLED, i, w, PLANE)
            break
        count += 1
        nx, ny, nz = wall_normal[w, 0], wall_normal[w, 1], wall_normal[w, 2]
        # a plane's normal never turns, so its history needs no rotation
        fn, ftx, fty, ftz, increment = wall_contact(
            i, velocity, angular_velocity, mass, radius, constants[pair_row[material[i], wall_material[w]]],
            overlap, previous, nx, ny, nz, wall_history[i, w], dt)
        if not finite(fn, ftx, fty, ftz):
            fault(status, NON_FINITE_FORCE, i, w, PLANE)
            break
        fx += fn * nx - ftx
        fy += fn * ny - fty
        fz += fn * nz - ftz
        if SPIN:
            cx, cy, cz = cross(nx, ny, nz, ftx, fty, ftz)
            tx += radius[i] * cx
            ty += radius[i] * cy
            tz += radius[i] * cz
        if TRACK:
            note_peaks(stats, overlap, fn, ftx, fty, ftz)
            if i == 0 and w == probe_wall:
                probe[PROBE_OVERLAP] = overlap
                probe[PROBE_FN] = fn
                probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = ftx, fty, ftz
                probe[PROBE_DISPLACEMENT] += increment[0]
                probe[PROBE_DISPLACEMENT + 1] += increment[1]
                probe[PROBE_DISPLACEMENT + 2] += increment[2]
    if TRACK and i == 0 and 0 <= probe_wall and wall_overlap[0, probe_wall] <= 0.0:
        probe[PROBE_OVERLAP], probe[PROBE_FN] = wall_overlap[0, probe_wall], 0.0
        probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = 0.0, 0.0, 0.0
    return fx, fy, fz, tx, ty, tz, count


@numba.njit(cache=True, inline="always")
def curved_wall_contact(i, velocity, angular_velocity, mass, radius, vector_offsets, constants_row,
                        overlap, previous, nx, ny, nz, history, dt, acc):
    """A contact with a wall whose normal turns as the sphere moves over it (cylinder,
    mesh): the history is first carried into the current tangent plane."""
    fx, fy, fz, tx, ty, tz, count = acc
    if SPIN:
        rotate_history_into_plane(history, vector_offsets, nx, ny, nz)
    fn, ftx, fty, ftz, increment = wall_contact(i, velocity, angular_velocity, mass, radius, constants_row,
                                                overlap, previous, nx, ny, nz, history, dt)
    fx += fn * nx - ftx
    fy += fn * ny - fty
    fz += fn * nz - ftz
    if SPIN:
        cx, cy, cz = cross(nx, ny, nz, ftx, fty, ftz)
        tx += radius[i] * cx
        ty += radius[i] * cy
        tz += radius[i] * cz
    return (fx, fy, fz, tx, ty, tz, count + 1), fn, ftx, fty, ftz


@numba.njit(cache=True, inline="always")
def cylinder_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                    vector_offsets, base, axis, cylinder_radius, length, cylinder_material, history,
                    cylinder_overlap_prev, dt, time, stats, status, acc):
    for c in range(base.shape[0]):
        overlap, nx, ny, nz = cylinder_overlap(position[i, 0], position[i, 1], position[i, 2], radius[i],
                                               base, axis, cylinder_radius, length, c)
        previous = cylinder_overlap_prev[i, c]
        cylinder_overlap_prev[i, c] = overlap
        if TRACK:
            note_transitions(stats, time, dt, overlap, previous)
        if overlap <= 0.0:
            if previous > 0.0:
                history[i, c, :] = 0.0
            continue
        if overlap >= radius[i]:
            fault(status, TUNNELLED, i, c, CYLINDER)
            break
        acc, fn, ftx, fty, ftz = curved_wall_contact(
            i, velocity, angular_velocity, mass, radius, vector_offsets,
            constants[pair_row[material[i], cylinder_material[c]]], overlap, previous, nx, ny, nz,
            history[i, c], dt, acc)
        if not finite(fn, ftx, fty, ftz):
            fault(status, NON_FINITE_FORCE, i, c, CYLINDER)
            break
        if TRACK:
            note_peaks(stats, overlap, fn, ftx, fty, ftz)
    return acc


@numba.njit(cache=True, inline="always")
def mesh_contact_geometry(i, position, radius, triangles, t):
    """(overlap, normal, closest point, feature) of sphere i with triangle t."""
    px, py, pz = position[i, 0], position[i, 1], position[i, 2]
    cx, cy, cz, feature = triangle_closest_point(px, py, pz, triangles, t)
    dx, dy, dz = px - cx, py - cy, pz - cz
    distance = math.sqrt(dx * dx + dy * dy + dz * dz)
    if distance == 0.0:
        return radius[i], 0.0, 0.0, 1.0, cx, cy, cz, feature
    return radius[i] - distance, dx / distance, dy / distance, dz / distance, cx, cy, cz, feature


@numba.njit(cache=True, inline="always")
def mesh_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                vector_offsets, triangles, triangle_material, offsets, candidates, history, mesh_overlap,
                dt, time, stats, status, acc):
    """Sphere-triangle contacts of particle i with its candidate triangles.

    One contact per feature region: a face-interior contact always counts; an edge or
    vertex contact counts only when the sphere touches no face interior (else the face
    carries it, e.g. on a flat mesh split into triangles) and only once however many
    triangles share that edge or vertex (same closest point).
    """
    start, stop = offsets[i], offsets[i + 1]
    touches_face = False
    for k in range(start, stop):
        overlap, nx, ny, nz, cx, cy, cz, feature = mesh_contact_geometry(i, position, radius, triangles, candidates[k])
        if overlap > 0.0 and feature == FACE:
            touches_face = True
            break
    tolerance = (_SAME_POINT * radius[i]) ** 2
    for k in range(start, stop):
        t = candidates[k]
        overlap, nx, ny, nz, cx, cy, cz, feature = mesh_contact_geometry(i, position, radius, triangles, t)
        if overlap > 0.0 and feature != FACE:
            if touches_face:
                overlap = -1.0
            else:
                for earlier in range(start, k):
                    o2, n2x, n2y, n2z, c2x, c2y, c2z, f2 = mesh_contact_geometry(
                        i, position, radius, triangles, candidates[earlier])
                    if o2 > 0.0 and f2 != FACE and (c2x - cx) ** 2 + (c2y - cy) ** 2 + (c2z - cz) ** 2 <= tolerance:
                        overlap = -1.0
                        break
        previous = mesh_overlap[k]
        mesh_overlap[k] = overlap
        if TRACK:
            note_transitions(stats, time, dt, overlap, previous)
        if overlap <= 0.0:
            if previous > 0.0:
                history[k, :] = 0.0
            continue
        if overlap >= radius[i]:
            fault(status, TUNNELLED, i, t, TRIANGLE)
            break
        acc, fn, ftx, fty, ftz = curved_wall_contact(
            i, velocity, angular_velocity, mass, radius, vector_offsets,
            constants[pair_row[material[i], triangle_material[t]]], overlap, previous, nx, ny, nz,
            history[k], dt, acc)
        if not finite(fn, ftx, fty, ftz):
            fault(status, NON_FINITE_FORCE, i, t, TRIANGLE)
            break
        if TRACK:
            note_peaks(stats, overlap, fn, ftx, fty, ftz)
    return acc


@numba.njit(cache=True, inline="always")
def pair_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                vector_offsets, offsets, neighbours, history, pair_overlap, pair_force, pair_torque,
                dt, time, stats, status, acc):
    """Contacts (i, j) of row i of the Verlet half list.

    Lever arms R_i - d/2 and R_j - d/2 sum to the centre distance, so the pair's
    torques balance the moment of its force and angular momentum is conserved to
    round-off. The force on j and the direction n x ft of the torques are stored per
    list entry for ``finish``; the torque on i is R_i' (n x ft), on j it is R_j' (n x ft).
    """
    fx, fy, fz, tx, ty, tz, count = acc
    px, py, pz, ri = position[i, 0], position[i, 1], position[i, 2], radius[i]
    for e in range(offsets[i], offsets[i + 1]):
        j = neighbours[e]
        dx, dy, dz = px - position[j, 0], py - position[j, 1], pz - position[j, 2]
        distance_squared = dx * dx + dy * dy + dz * dz
        reach = ri + radius[j]
        previous = pair_overlap[e]
        if distance_squared >= reach * reach:
            if previous > 0.0 or TRACK:
                overlap = reach - math.sqrt(distance_squared)
                pair_overlap[e] = overlap
                if TRACK:
                    note_transitions(stats, time, dt, overlap, previous)
                if previous > 0.0:
                    history[e, :] = 0.0  # contact ends: its history is dropped
            continue
        distance = math.sqrt(distance_squared)
        overlap = reach - distance
        pair_overlap[e] = overlap
        if TRACK:
            note_transitions(stats, time, dt, overlap, previous)
        if distance == 0.0:
            fault(status, TUNNELLED, i, j, PARTICLE)
            break
        count += 1
        inverse = 1.0 / distance
        nx, ny, nz = dx * inverse, dy * inverse, dz * inverse
        lever_i, lever_j = ri - 0.5 * overlap, radius[j] - 0.5 * overlap
        if SPIN:
            rotate_history_into_plane(history[e], vector_offsets, nx, ny, nz)
            normal_velocity, tangential_velocity = pair_contact_velocity(
                velocity[i, 0], velocity[i, 1], velocity[i, 2],
                angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2],
                velocity[j, 0], velocity[j, 1], velocity[j, 2],
                angular_velocity[j, 0], angular_velocity[j, 1], angular_velocity[j, 2],
                lever_i, lever_j, nx, ny, nz)
        else:
            normal_velocity, tangential_velocity = pair_contact_velocity(
                velocity[i, 0], velocity[i, 1], velocity[i, 2], 0.0, 0.0, 0.0,
                velocity[j, 0], velocity[j, 1], velocity[j, 2], 0.0, 0.0, 0.0,
                lever_i, lever_j, nx, ny, nz)
        increment = (tangential_velocity[0] * dt, tangential_velocity[1] * dt, tangential_velocity[2] * dt)
        effective_radius = ri * radius[j] / reach
        effective_mass = mass[i] * mass[j] / (mass[i] + mass[j])
        fn, ftx, fty, ftz = law_force(constants[pair_row[material[i], material[j]]], effective_radius,
                                      effective_mass, overlap, overlap - max(previous, 0.0), normal_velocity,
                                      increment, tangential_velocity, history[e])
        if not finite(fn, ftx, fty, ftz):
            fault(status, NON_FINITE_FORCE, i, j, PARTICLE)
            break
        ex, ey, ez = fn * nx - ftx, fn * ny - fty, fn * nz - ftz
        fx += ex
        fy += ey
        fz += ez
        pair_force[e, 0], pair_force[e, 1], pair_force[e, 2] = ex, ey, ez
        if SPIN:
            cx, cy, cz = cross(nx, ny, nz, ftx, fty, ftz)
            tx += lever_i * cx
            ty += lever_i * cy
            tz += lever_i * cz
            pair_torque[e, 0], pair_torque[e, 1], pair_torque[e, 2] = cx, cy, cz
        if TRACK:
            note_peaks(stats, overlap, fn, ftx, fty, ftz)
    return fx, fy, fz, tx, ty, tz, count


@numba.njit(cache=True, error_model="numpy", inline=INLINE)
def force_range(first, last, particles, law, planes, cylinders, meshes, pairs, gravity, dt, time, tracking):
    """Gravity and the contacts owned by particles first..last-1; returns their count."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material = particles
    pair_row, constants, vector_offsets = law
    wall_point, wall_normal, wall_material, wall_history, wall_overlap = planes
    base, axis, cylinder_radius, length, cylinder_material, cylinder_history, cylinder_overlap_prev = cylinders
    triangles, triangle_material, mesh_offsets, mesh_candidates, mesh_history, mesh_overlap = meshes
    offsets, neighbours, pair_history, pair_overlap, pair_force, pair_torque, reverse_offsets, reverse_entries = pairs
    probe_wall, probe, stats, status = tracking
    active = 0
    for i in range(first, last):
        acc = (mass[i] * gravity[0], mass[i] * gravity[1], mass[i] * gravity[2], 0.0, 0.0, 0.0, 0)
        acc = plane_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                           wall_point, wall_normal, wall_material, wall_history, wall_overlap,
                           dt, time, probe_wall, probe, stats, status, acc)
        if CYLINDERS:
            acc = cylinder_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row,
                                  constants, vector_offsets, base, axis, cylinder_radius, length, cylinder_material,
                                  cylinder_history, cylinder_overlap_prev, dt, time, stats, status, acc)
        if MESHES:
            acc = mesh_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                              vector_offsets, triangles, triangle_material, mesh_offsets, mesh_candidates,
                              mesh_history, mesh_overlap, dt, time, stats, status, acc)
        if PAIRS:
            acc = pair_forces(i, position, velocity, angular_velocity, mass, radius, material, pair_row, constants,
                              vector_offsets, offsets, neighbours, pair_history, pair_overlap, pair_force,
                              pair_torque, dt, time, stats, status, acc)
        fx, fy, fz, tx, ty, tz, count = acc
        force[i, 0], force[i, 1], force[i, 2] = fx, fy, fz
        torque[i, 0], torque[i, 1], torque[i, 2] = tx, ty, tz
        active += count
    return active


# particles per parallel work item: large enough to amortise the call, small enough
# for the threads to share the work evenly
CHUNK = 256


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def compute_forces(particles, law, planes, cylinders, meshes, pairs, gravity, dt, time, tracking):
    """Gravity and every contact force on every particle, except the reactions of the
    pairs (i < p, p), which ``finish`` adds. Returns the number of contacts."""
    n = particles[0].shape[0]
    active = 0
    for chunk in particle_range((n + CHUNK - 1) // CHUNK):
        active += force_range(chunk * CHUNK, min(n, (chunk + 1) * CHUNK), particles, law, planes, cylinders,
                              meshes, pairs, gravity, dt, time, tracking)
    return active


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def finish(particles, pairs, dt):
    """Add the pair reactions to each particle, then the closing kick."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material = particles
    offsets, neighbours, history, pair_overlap, pair_force, pair_torque, reverse_offsets, reverse_entries = pairs
    for p in particle_range(position.shape[0]):
        if PAIRS:
            for k in range(reverse_offsets[p], reverse_offsets[p + 1]):
                e = reverse_entries[k]
                overlap = pair_overlap[e]
                if overlap > 0.0:
                    force[p, 0] -= pair_force[e, 0]
                    force[p, 1] -= pair_force[e, 1]
                    force[p, 2] -= pair_force[e, 2]
                    if SPIN:
                        lever = radius[p] - 0.5 * overlap
                        torque[p, 0] += lever * pair_torque[e, 0]
                        torque[p, 1] += lever * pair_torque[e, 1]
                        torque[p, 2] += lever * pair_torque[e, 2]
        if CLOSING_KICK > 0.0:
            kick(p, velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, CLOSING_KICK * dt,
                 SPIN)


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def kick_drift(particles, dt, position_at_build, half_skin_squared):
    """Opening kick and drift; returns how many particles have moved more than
    half the skin since the neighbour list was built."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material = particles
    moved_too_far = 0
    for p in particle_range(position.shape[0]):
        kick(p, velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, OPENING_KICK * dt, SPIN)
        drift(p, position, velocity, dt)
        if CHECK_DISPLACEMENT:
            dx = position[p, 0] - position_at_build[p, 0]
            dy = position[p, 1] - position_at_build[p, 1]
            dz = position[p, 2] - position_at_build[p, 2]
            if dx * dx + dy * dy + dz * dz > half_skin_squared:
                moved_too_far += 1
    return moved_too_far


@numba.njit(cache=True, error_model="numpy")
def advance(particles, law, planes, cylinders, meshes, pairs, gravity, position_at_build, half_skin_squared,
            dt, start_time, start_step, n_steps, resume, stop_at_separation, trace, tracking):
    """Advance up to n_steps; return (steps completed, neighbour list needs a rebuild).

    Returns early
    * after the drift of a step that took a particle more than half the skin from where
      the Verlet list was built: that step is not counted; the caller rebuilds the list
      and calls again with ``resume`` True, which completes it from its force evaluation;
    * after the step in which the last contact ended (``stop_at_separation``, once a
      contact has occurred; tracked scenes only);
    * on a fault (status[0] != OK).
    ``trace`` (rows = steps, may have 0 rows) receives the probed contact each step.
    Times are start_time + k dt, not a running sum, so long runs do not drift.
    """
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material = particles
    probe_wall, probe, stats, status = tracking
    for step in range(n_steps):
        if not (resume and step == 0):
            if kick_drift(particles, dt, position_at_build, half_skin_squared) > 0:
                return step, True
        time = start_time + (start_step + step + 1) * dt
        active = compute_forces(particles, law, planes, cylinders, meshes, pairs, gravity, dt, time, tracking)
        if status[0] != OK:
            return step + 1, False
        finish(particles, pairs, dt)
        if not TRACK and active > 0 and stats[FIRST_CONTACT_TIME] < 0.0:
            stats[FIRST_CONTACT_TIME] = time  # to the step: only the serial loop interpolates
        if step < trace.shape[0]:
            trace[step, 0] = time
            # element by element: a slice assignment of an array compiles numba's general
            # broadcasting copy, which cost several seconds of every cold compile
            for c in range(8):
                trace[step, 1 + c] = probe[c]
            for c in range(3):
                trace[step, 9 + c] = velocity[0, c]
                trace[step, 12 + c] = angular_velocity[0, c]
        if stop_at_separation and active == 0 and stats[FIRST_CONTACT_TIME] >= 0.0:
            return step + 1, False
    return n_steps, False


TRACE_COLUMNS = (
    "time_s", "normal_overlap_m", "normal_force_n", "tangential_force_x_n", "tangential_force_y_n",
    "tangential_force_z_n", "tangential_displacement_x_m", "tangential_displacement_y_m",
    "tangential_displacement_z_m", "velocity_x_m_s", "velocity_y_m_s", "velocity_z_m_s",
    "angular_velocity_x_rad_s", "angular_velocity_y_rad_s", "angular_velocity_z_rad_s",
)
