"""The compiled simulation: contact loops and the time-step loop.

This file is a template. ``minidem.engine.simulation.compile_kernel`` copies it into the
kernel cache with the specialisation block below rewritten for one contact law and
one scene shape, so numba compiles one kernel per (law, scene shape) with the law's
force function inlined, and caches it across processes. Nothing here names a law.

Scene shape flags ("model only what a scene needs": a branch on a False flag is
removed by the compiler, so a single impact pays nothing for pairs or meshes):

    SPIN       angular velocities and torques (the law can produce tangential forces)
    COUPLES    the law also takes the relative rotation and spin and returns a couple (rolling or
               twisting resistance): applied to i, its opposite to j
    REACH      the law acts beyond touch (adhesion): a contact lives while its overlap
               is above -reach, the last column of its constants row (the law sees the
               negative overlap and ends its own contact within that); the Verlet list
               is built with the skin plus the largest reach. Without it a contact is
               an overlap > 0, as always
    PAIRS      sphere-sphere contacts through the Verlet list (more than one particle)
    CYLINDERS  finite cylinder walls
    MESHES     triangle-mesh walls
    PARALLEL   particle loops run with prange (scenes large enough for a second
               thread to pay, simulation.PARALLEL_MIN_PARTICLES); the others run serial
    TRACK      contact statistics (first touch, separation, peaks) and the probe are
               recorded (small scenes and runs to separation; serial kernels only: they
               are written by whichever particle has the contact, race-free only there)
    END_VELOCITY  the law is handed the velocities predicted at the end of the step
               (a single sphere, and the tracked loop of small scenes; see below)
    OPENING_KICK  the integrator (minidem.engine.integrate): the fraction of the velocity
               update made before the drift, 0.5 velocity Verlet, 1 symplectic Euler

One step is two parallel particle passes (velocity Verlet shown; symplectic Euler
kicks the whole dt before the drift and nothing after the forces), each over one block
of consecutive particles per thread:

    compute_forces      particle i owns its walls and the pairs (i, j > i) of its row of
                        the Verlet half list: it computes them through the one contact
                        evaluation (``contact_response``; pairs a tile at a time in
                        vector code, ``evaluate_pair_tile`` and ``settle_group``), writes its own force (or
                        hands it to finish_range in registers, see below), and
                        gives j its share of each pair (the opposite force, j's torque)
    finish_kick_drift   particle p adds the reactions of its touching pairs (i < p, p)
                        in ascending i, v += F dt/2m (and, at a
                        sample step, its kinetic energy); then, unless the
                        step ends a chunk, the next step's v += F dt/2m, x += v dt and
                        the count of particles that moved more than half the skin since
                        the last neighbour-list build (``finish_range``)

Most particles are finished inside compute_forces, as soon as their own contacts are
done, while their data are still in cache: legal for p when every row i < p that lists
it (holds its reactions, reads its position) is in p's own block, done by then
(``first_partner``, see ``minidem.engine.blocks``). On one thread that is every particle
and the step is one pass; on two, finish_kick_drift is left with the particles that have a partner in the block
before theirs (about one layer of a pile), and each block leaves as many in all, taking
its last particles to make up the number, so no thread waits alone on that pass
(``minidem.engine.blocks.defer_finishing``).

Where a pair's reaction goes follows from that. A j finished in the force pass gets it
summed straight into its own force and torque rows, which hold only its reactions
during the pass (zeroed as each particle's drift is done, ``finish_range`` and
``kick_drift``) and are read back when j is finished: nothing else on one thread. A j
left to finish_kick_drift (a partner in an earlier block, whose thread may reach the
pair at any time, or one defer_finishing leaves there; its force rows hold its own
contacts' force meanwhile) gets it stored at
the pair's slot in its row of the transposed list (the force in ``reaction``, j's
torque in ``partner_torque``), marked touching (reaction_in_use),
and adds those rows in ascending i, from zero, as the rows were summed: the same
operations either way. The call's last step also stores every pair's
force at its slot, for the contact forces of the state the run sees
(``State.contact_pairs``).

Every sum is taken in an order fixed by the neighbour list, never by the thread
schedule, so a run is bit-for-bit the same on any number of threads, and no two
threads write the same memory.

Contact conventions are those of ``minidem.geometry.primitives``: n points from j (or the wall)
to i, the normal force acts on i along +n, the law's tangential force acts on i as -ft.
"""

import math

import numba
import numpy as np
from numba.core.compiler import Compiler

from minidem.geometry.primitives import (
    FACE,
    cross,
    cylinder_normal,
    cylinder_overlap,
    pair_contact_velocity,
    plane_overlap,
    seen_from,
    triangle_closest_point,
    turn_slot,
    turned_increment,
)
from minidem.contact.history import history_column, history_row, history_row_of
from minidem.engine.integrate import block_sum, drifted, kick_spin, kicked, kinetic_energy_of, turns
# the blocks of particles per thread are chosen outside the kernel (advance's bounds and
# first_partner); named here too, where the kernel's two passes are described
from minidem.engine.blocks import cycle_counter, defer_finishing  # noqa: F401

# >>> specialisation block (rewritten by minidem.engine.simulation.compile_kernel)
# In the template itself, never compiled (the engine reads only its constants), a
# placeholder force with a law's signature: the engine imports no law by name.
def law_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
              normal_velocity, tangential_increment, tangential_velocity, history):
    return 0.0, 0.0, 0.0, 0.0


law_force_alone = law_force

SPIN = True
COUPLES = False
REACH = False
PAIRS = True
CYLINDERS = True
MESHES = True
PARALLEL = False
TRACK = True
END_VELOCITY = True
VECTOR_OFFSETS = (0,)
OPENING_KICK = 0.5
# <<< specialisation block

particle_range = numba.prange if PARALLEL else range
# Serial kernels inline the per-step functions into ``advance`` (numba IR inlining): one
# function is optimised and compiled once. Kept separate, each entry point is compiled
# on its own and then linked into ``advance``, which optimises the linked copy again:
# 40 % more CPU time in the cold compile of a single-impact kernel (6.9 s against 4.9 s,
# measured on the hmd kernel). Parallel loops (prange) cannot be inlined into the
# serial step loop.
INLINE = "never" if PARALLEL else "always"
# the part of the velocity update made after the force evaluation (0: symplectic Euler)
CLOSING_KICK = 1.0 - OPENING_KICK
# the Verlet list (pairs, mesh candidates) must be rebuilt when particles move too far
CHECK_DISPLACEMENT = PAIRS or MESHES
# the law keeps vector history (offsets VECTOR_OFFSETS) that must follow a turning contact
ROTATE_HISTORY = SPIN and len(VECTOR_OFFSETS) > 0
# END_VELOCITY (simulation.predicts_end_velocity: a single sphere, and the tracked serial
# loop of small scenes): the law is handed the contact's velocity at the end of the step,
# where the force is applied, predicted from the drift's velocity (half a step old:
# velocity Verlet) by the closing kick of the last step's force: v + CLOSING_KICK dt
# F_last / m, for each sphere of a pair. The step's displacements are exact with the
# drift's velocity; a force in proportion to the velocity (a dashpot) is not: with it
# every damped impact was first order in dt (as in LAMMPS, LIGGGHTS and Yade, which read
# the half-step velocity); the prediction is off by dt (F_new - F_last) / 2m, second
# order (docs/time-step.md, "Dashpots"). The last step's force is kept in the particles'
# last_force rows, 48 bytes a particle: the multi-particle path, where that would be a
# twelfth of a particle's memory, reads the drift's velocity as its peers do.
# fast-math flags of the particle loops: none (every operation as written; the finite
# checks must see NaN and infinity)
FAST = False

# status codes (status[0]); status[1], status[2] name the particle and wall/partner
OK, NON_FINITE_FORCE, TUNNELLED = 0, 1, 2
# partner kinds in status[3]
PLANE, CYLINDER, TRIANGLE, PARTICLE = 0, 1, 2, 3
# stats slots
FIRST_CONTACT_TIME, LAST_SEPARATION_TIME, MAX_OVERLAP, PEAK_NORMAL_FORCE, PEAK_TANGENTIAL_FORCE = range(5)
# probe slots: the contact of particle 0 with the probed wall, for per-step traces
PROBE_OVERLAP, PROBE_FN, PROBE_FT, PROBE_DISPLACEMENT = 0, 1, 2, 5  # FT and DISPLACEMENT are 3-vectors
ZERO = (0.0, 0.0, 0.0)
# to_end of a contact whose law reads the drift's velocities: (dv, dw_i, dw_j) all zero
NO_CHANGE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
# a mesh contact point this close (relative to the radius) to another contact's tangent
# plane lies on the same surface (round-off of a flat mesh)
_SAME_POINT = 1e-9


@numba.njit(cache=True, inline="always")
def fault(status, code, particle, partner, kind):
    if status[0] == OK:
        status[0], status[1], status[2], status[3] = code, particle, partner, kind


@numba.njit(cache=True, inline="always")
def note_transitions(stats, time, dt, overlap, previous):
    """First-touch and separation times, interpolated within the step. A contact live
    at the run's first instant (the zero-length first call, dt = 0: a sphere placed
    overlapping within the validator's tolerance, or moved there by analytic flight)
    began then, whatever its last overlap at the list build said."""
    if overlap > 0.0 and (previous <= 0.0 or dt == 0.0) and stats[FIRST_CONTACT_TIME] < 0.0:
        # clamped to the step: rounding may otherwise give a time just below zero, which
        # reads as 'no contact yet' and the run would never stop at separation
        stats[FIRST_CONTACT_TIME] = time if dt == 0.0 else max(time - dt * overlap / (overlap - previous), time - dt)
    elif overlap <= 0.0 and previous > 0.0 and dt > 0.0:
        # (not at the first call: a touch within round-off, its overlap clamped to 0
        # there, is not a separation, whatever the list build's overlap said)
        stats[LAST_SEPARATION_TIME] = time - dt * (-overlap) / (previous - overlap)


@numba.njit(cache=True, inline="always")
def note_peaks(stats, overlap, fn, ftx, fty, ftz):
    stats[MAX_OVERLAP] = max(stats[MAX_OVERLAP], overlap)
    stats[PEAK_NORMAL_FORCE] = max(stats[PEAK_NORMAL_FORCE], fn)
    stats[PEAK_TANGENTIAL_FORCE] = max(stats[PEAK_TANGENTIAL_FORCE], math.sqrt(ftx * ftx + fty * fty + ftz * ftz))


@numba.njit(cache=True, inline="always")
def non_negative(index):
    """An index read from an array, which the compiler may then take to be >= 0 (it
    always is). numba supports negative indices: every access a[k] with a signed k of
    unknown sign costs a shift, a mask and an add per array (k + (k < 0) * len(a)), which
    LLVM drops only where it can prove k >= 0. A loop variable gets the same proof from
    ``if k < 0: continue`` at the top of its loop (a bound such as max(first, 0) does not
    carry through the loop): in the settle scene (hm, one thread, 20,000 particles,
    callgrind) the particle loop's share of the force pass was 216 instructions a
    particle and step against 160 when its first index was the literal 0, and the contact
    evaluation 318 against 290 with its partner and slot indices bounded."""
    return max(index, 0)


@numba.njit(cache=True, inline="always")
def engaged_above(constants, row):
    """The overlap above which a contact lives: 0, or -reach for a law acting beyond
    touch (REACH: the last column of its constants row; a compile-time branch, so a law
    without reach reads nothing and compares with 0 as before)."""
    if REACH:
        return -constants[row, constants.shape[1] - 1]
    return 0.0


@numba.njit(cache=True, inline="always")
def touches_at_start(dt, overlap, lives_above, size, dv, normal):
    """A sphere touching a plane or another sphere when the run starts (the zero-length
    first call, dt = 0: the paper's start, analytic flight's touch, Chung and Ooi's
    pairs), within the round-off of placing it there (_SAME_POINT of ``size``, its
    radius or the pair's reach, either side: a wall through z = 0.1 or with the normal
    (0, 1, 1) leaves the sphere placed on it 1e-17 m in or out), and moving into it
    (``dv``, its velocity relative to the partner's, against ``normal``, from the
    partner to it): in contact from that
    instant, with the force of the touch itself, as in the reference solution. A linear
    dashpot's c v at zero overlap is the force's jump there, and a first step without it
    missed half a step's impulse of it, a first-order error (e of LS at e = 0.5: 1.0e-4
    at 4,000 steps per contact, halving with the step). Only with END_VELOCITY (whose
    law reads the touch's velocity at the step's end, the velocity of the touch itself
    here); at dt > 0 never, where the step that ends touching has not carried the
    contact."""
    if not END_VELOCITY or dt != 0.0 or not abs(overlap - lives_above) <= _SAME_POINT * size:
        return False
    return dv[0] * normal[0] + dv[1] * normal[1] + dv[2] * normal[2] < 0.0


@numba.njit(cache=True, inline="always")
def closing_kick(p, last_force, inverse_mass, inverse_inertia, dt):
    """(dv, dw) of particle p from the drift's velocities to the end of the step, by
    the closing kick of the last step's force (END_VELOCITY; the prediction's error is
    dt (F_new - F_last) / 2m)."""
    kick_scale = CLOSING_KICK * dt * inverse_mass[p]
    spin_scale = CLOSING_KICK * dt * inverse_inertia[p] if SPIN else 0.0
    return (kick_scale * last_force[p, 0], kick_scale * last_force[p, 1], kick_scale * last_force[p, 2],
            spin_scale * last_force[p, 3], spin_scale * last_force[p, 4], spin_scale * last_force[p, 5])


@numba.njit(cache=True, inline="always")
def pair_touches_at_start(dt, reach, lives_above, separation, vi, velocity, j):
    """``touches_at_start`` for a pair: ``separation`` = p_i - p_j, vi the velocity of i."""
    distance = math.sqrt(separation[0] * separation[0] + separation[1] * separation[1]
                         + separation[2] * separation[2])
    inverse = 1.0 / distance if distance > 0.0 else 0.0
    return touches_at_start(dt, reach - distance, lives_above, reach,
                            (vi[0] - velocity[j, 0], vi[1] - velocity[j, 1], vi[2] - velocity[j, 2]),
                            (separation[0] * inverse, separation[1] * inverse, separation[2] * inverse))


@numba.njit(cache=True, inline="always")
def end_pair_contact(e, pair_history, reaction_slot, reaction, reaction_in_use):
    """Pair entry e stops touching: its history is dropped, and a reaction stored at its
    slot (finish_kick_drift's, or a call's last step's) is zero from now on and no longer
    read by finish_range."""
    pair_history[e, :] = 0.0
    r = non_negative(reaction_slot[e])
    if reaction_in_use[r]:
        reaction[r, :] = 0.0
        reaction_in_use[r] = 0


@numba.njit(cache=True, inline="always")
def finite(fn, ftx, fty, ftz):
    """Whether a contact's force is finite, as one test on the sum: it is NaN or infinite
    when a term is (inf - inf is NaN), and otherwise only when finite terms overflow
    (a force near 1e308 N, a contact blown up all the same). Four tests, each a branch,
    ran for every contact."""
    return math.isfinite(fn + ftx + fty + ftz)


@numba.njit(cache=True, inline="always")
def rotate_history(history, previous_normal, normal):
    """Turn every vector slot of the law's history with the contact, from the last
    step's tangent plane into the current one. Unrolled over the law's (compile-time)
    slot offsets: a loop here would cost two atomic reference-count updates per array
    argument and contact (see below)."""
    for offset in numba.literal_unroll(VECTOR_OFFSETS):
        turn_slot(history, offset, previous_normal, normal)


# Performance rule for everything called per particle or per contact: a helper that takes
# arrays must be straight-line code (no loop). numba cannot prune the reference-count
# updates of array arguments across a loop inside an inlined helper, and each is an
# atomic add on the array's shared header: ~50 of them per particle made the step
# several times slower on one thread, and on two threads the headers' cache lines
# bounced between the cores (ten times slower than one thread). Loops over walls,
# triangles and neighbours therefore live in force_range itself.
@numba.njit(cache=True, inline="always")
def contact_response(law, constants_row, history, overlap, previous, normal, previous_normal, curved, vi, wi, vj,
                     wj, to_end, lever_i, lever_j, lever_growth, effective_radius, effective_mass, rolling_inertia, dt,
                     stats):
    """The one evaluation every contact goes through (sphere-plane, -cylinder,
    -triangle and -sphere): history turned with the contact, contact-point velocity and
    the law. Vectors are 3-tuples; n points from the partner to i. ``curved``: the normal
    can turn (a pair, a cylinder, a triangle mesh), and ``previous_normal`` is then the
    contact's normal at the last step (the partners' positions one drift back: the
    velocities here are the drift's) in the form minidem.geometry.primitives describes,
    with which the history is turned exactly and the step's displacement taken at its
    middle (``turned_increment``; the lever arms there are lever_i + lever_growth and
    lever_j + lever_growth: a pair's arms, R - d/2, grow back by a quarter of the step's
    overlap increment from the step's middle to its end); a plane's (``curved`` False)
    is not read.

    ``law``: the law's force function, ``law_force`` in the tile of pair contacts (a law
    numba inlines is inlined there, where it becomes vector code) and ``law_force_alone``
    at a wall (the same law compiled on its own, ContactLaw.force_alone, called: one
    copy fewer of a combination's code inside the kernel, 1.7 s of the ~11 s its first
    compile takes for scenarios/settle.toml, compiled beside it, see
    minidem.engine.warmup).

    ``to_end`` = (dv, dw_i, dw_j), 3-tuples joined: the change of v_i - v_j and of
    each spin from the drift's velocities here to the step's end (END_VELOCITY; else
    NO_CHANGE): the law's velocities are taken there, the increment with the drift's.
    ``rolling_inertia``: the pair's, for a law with couples (COUPLES; declarations.COUPLE_ARGUMENTS).

    A wall is a partner that does not move (v_j = w_j = 0, lever_j = 0); its lever arm
    lever_i is the undeformed radius, as in the paper's rigid-body analysis (eqs 3-8).
    Returns ((force on i), (n x ft), (couple on i), fn, ft, displacement increment,
    finite); the caller reports a non-finite force as a fault. The status array is not
    an argument: numba increments and decrements the reference count of an array passed
    to an inlined function that uses it in a branch, on every call: two atomic adds per
    contact on a header the threads share (removing them took the force pass of the
    settle scene, N = 20,000, lattice, one thread, from 1.42 to 1.36 ms a step).
    """
    nx, ny, nz = normal
    if ROTATE_HISTORY and curved:
        rotate_history(history, previous_normal, normal)
    normal_velocity, tangential_velocity = pair_contact_velocity(
        vi[0], vi[1], vi[2], wi[0], wi[1], wi[2], vj[0], vj[1], vj[2], wj[0], wj[1], wj[2], lever_i, lever_j,
        nx, ny, nz)
    if curved:
        spin_lever, middle_velocity = ZERO, tangential_velocity
        if SPIN:
            # the spin's share of the contact velocity with the arms of the step's middle
            # (else a pair's increment is off by n x (dd/4)(w_i + w_j) dt: first order)
            wx, wy, wz = wi[0] + wj[0], wi[1] + wj[1], wi[2] + wj[2]
            spin_lever = (lever_i * wi[0] + lever_j * wj[0] + lever_growth * wx,
                          lever_i * wi[1] + lever_j * wj[1] + lever_growth * wy,
                          lever_i * wi[2] + lever_j * wj[2] + lever_growth * wz)
            gx, gy, gz = cross(nx, ny, nz, lever_growth * wx, lever_growth * wy, lever_growth * wz)
            middle_velocity = (tangential_velocity[0] + gx, tangential_velocity[1] + gy, tangential_velocity[2] + gz)
        increment = turned_increment(middle_velocity, normal_velocity, previous_normal, normal, spin_lever, dt)
    else:
        increment = (tangential_velocity[0] * dt, tangential_velocity[1] * dt, tangential_velocity[2] * dt)
    if END_VELOCITY:
        normal_velocity, tangential_velocity = pair_contact_velocity(
            vi[0] + to_end[0], vi[1] + to_end[1], vi[2] + to_end[2], wi[0] + to_end[3], wi[1] + to_end[4],
            wi[2] + to_end[5], vj[0], vj[1], vj[2], wj[0] + to_end[6], wj[1] + to_end[7], wj[2] + to_end[8],
            lever_i, lever_j, nx, ny, nz)
    mx, my, mz = 0.0, 0.0, 0.0
    if COUPLES:
        # rolling and twisting resistance: the law sees the rotation of i relative to j
        # over the step (the drift's spins, as the displacement increment) and the
        # relative spin at the step's end (to_end, as the contact velocity: a rolling or
        # twisting dashpot second order), and returns a pure couple on i (j gets its
        # opposite: no moment of a force to balance)
        sx, sy, sz = wi[0] - wj[0], wi[1] - wj[1], wi[2] - wj[2]
        fn, ftx, fty, ftz, mx, my, mz = law(
            constants_row, effective_radius, effective_mass, overlap, overlap - max(previous, 0.0), normal_velocity,
            increment, tangential_velocity, history, (sx * dt, sy * dt, sz * dt),
            (sx + to_end[3] - to_end[6], sy + to_end[4] - to_end[7], sz + to_end[5] - to_end[8]), normal,
            rolling_inertia)
        ok = finite(fn, ftx, fty, ftz) and finite(mx, my, mz, 0.0)
    else:
        fn, ftx, fty, ftz = law(constants_row, effective_radius, effective_mass, overlap,
                                      overlap - max(previous, 0.0), normal_velocity, increment, tangential_velocity,
                                      history)
        ok = finite(fn, ftx, fty, ftz)
    ex, ey, ez = fn * nx - ftx, fn * ny - fty, fn * nz - ftz
    cx, cy, cz = 0.0, 0.0, 0.0
    if SPIN:
        cx, cy, cz = cross(nx, ny, nz, ftx, fty, ftz)
    if TRACK and ok:
        note_peaks(stats, overlap, fn, ftx, fty, ftz)
    return (ex, ey, ez), (cx, cy, cz), (mx, my, mz), fn, (ftx, fty, ftz), increment, ok


@numba.njit(cache=True, inline="always")
def add_contact(acc, lever_i, on_i, direction, couple):
    """acc = (fx, fy, fz, tx, ty, tz, count) with one more contact: its force on i, and
    its torque on i, lever_i (n x ft) plus the couple."""
    fx, fy, fz, tx, ty, tz, count = acc
    ex, ey, ez = on_i
    cx, cy, cz = direction
    if COUPLES:
        mx, my, mz = couple
        return (fx + ex, fy + ey, fz + ez, tx + lever_i * cx + mx, ty + lever_i * cy + my, tz + lever_i * cz + mz,
                count + 1)
    return fx + ex, fy + ey, fz + ez, tx + lever_i * cx, ty + lever_i * cy, tz + lever_i * cz, count + 1


@numba.njit(cache=True, inline="always")
def evaluate_contact(acc, constants_row, history, overlap, previous, normal, previous_normal, curved, vi, wi, to_end,
                     lever_i, effective_radius, effective_mass, dt, stats):
    """``contact_response`` added to acc (``add_contact``): a wall contact's evaluation
    (the wall at rest, no lever arm of its own). Returns (acc, then contact_response's
    values)."""
    # a sphere's rolling inertia about its contact point, I + m r^2 = 1.4 m r^2 (the wall's
    # term of declarations.COUPLE_ARGUMENTS is absent: it does not turn)
    rolling_inertia = 1.4 * effective_mass * effective_radius * effective_radius if COUPLES else 0.0
    on_i, direction, couple, fn, ft, increment, ok = contact_response(
        law_force_alone, constants_row, history, overlap, previous, normal, previous_normal, curved, vi, wi, ZERO,
        ZERO, to_end, lever_i, 0.0, 0.0, effective_radius, effective_mass, rolling_inertia, dt, stats)
    return add_contact(acc, lever_i, on_i, direction, couple), on_i, direction, couple, fn, ft, increment, ok


class _NoAliasCompiler(Compiler):
    """numba's compiler with its arrays declared not to overlap (LLVM's noalias on the
    array arguments), as numba declares them in the loops it compiles from prange:
    without it LLVM must assume a store to one array may change another, and a contact
    loop reading some twenty arrays needs more run-time overlap checks than it will
    emit, so it is not vectorised (measured: 34 ns a contact scalar, 7 ns in 8-wide
    AVX-512 code, the same bits)."""

    def define_pipelines(self):
        self.state.flags.noalias = True
        return super().define_pipelines()


# Rows of a tile of pair contacts (``evaluate_pair_tile``): what force_range gathers for
# each touching pair, and what the evaluation gives back
# (T_DV: v_i - v_j, whose difference is the contact velocity's first operation; T_END:
# the pair's to_end, END_VELOCITY only)
T_DX, T_DY, T_DZ, T_DISTANCE, T_OVERLAP, T_PREVIOUS, T_RI, T_RJ, T_MI, T_MJ, T_DV, T_WI, T_WJ, T_END = (
    0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 13, 16, 19)
TILE_INPUTS = 28 if END_VELOCITY else 19
R_ON_I, R_DIRECTION, R_COUPLE, R_FINITE = 0, 3, 6, 9
TILE_RESPONSES = 10
# contacts a tile holds (a compile-time constant: see history_column), and particles a
# group of them at most: the tile's arrays stay in the L1 and L2 caches. Not a power of
# two: rows 2 KiB apart fall into two sets of the L1 cache, and the 22 rows written for
# each gathered contact evicted each other
TILE_CONTACTS = 264
TILE_PARTICLES = 128


# Not inlined, without numba's reference counting (the arrays are the caller's; nothing
# here allocates) and with its arrays declared not to overlap: LLVM then compiles the
# loop over the tile to vector code, several contacts at a time, when the law has no
# branch it cannot turn into a select (hm, linear and their parts do; hmd and lth run
# one contact at a time). Each contact's operations are those of a scalar evaluation:
# the same bits either way.
@numba.njit(cache=True, error_model="numpy", fastmath=FAST, pipeline_class=_NoAliasCompiler, _nrt=False)
def evaluate_pair_tile(count, rows, constants, tile, tile_history, response, dt, stats):
    """The responses (``contact_response``) of the ``count`` pair contacts gathered in
    ``tile`` (rows T_*, a column a contact), with their law's constants row ``rows[k]``
    and history ``tile_history[:, k]`` (updated), to ``response`` (rows R_*)."""
    for k in range(count):
        overlap = tile[T_OVERLAP, k]
        inverse = 1.0 / tile[T_DISTANCE, k]
        ri, rj, mi, mj = tile[T_RI, k], tile[T_RJ, k], tile[T_MI, k], tile[T_MJ, k]
        reach = ri + rj
        wi, wj = ZERO, ZERO
        if SPIN:
            wi = (tile[T_WI, k], tile[T_WI + 1, k], tile[T_WI + 2, k])
            wj = (tile[T_WJ, k], tile[T_WJ + 1, k], tile[T_WJ + 2, k])
        to_end = NO_CHANGE
        if END_VELOCITY:
            to_end = (tile[T_END, k], tile[T_END + 1, k], tile[T_END + 2, k], tile[T_END + 3, k],
                      tile[T_END + 4, k], tile[T_END + 5, k], tile[T_END + 6, k], tile[T_END + 7, k],
                      tile[T_END + 8, k])
        # R* = ri rj / (ri + rj) and m* = mi mj / (mi + mj) through one reciprocal:
        # a division fewer per contact (divisions and square roots share one unit)
        mass_sum = mi + mj
        shared = 1.0 / (reach * mass_sum)
        nx, ny, nz = tile[T_DX, k] * inverse, tile[T_DY, k] * inverse, tile[T_DZ, k] * inverse
        dvx, dvy, dvz = tile[T_DV, k], tile[T_DV + 1, k], tile[T_DV + 2, k]
        # the last step's line of centres, one drift back (the drift moved i and j by the
        # velocities here times dt): d - dt dv, over its length along n, distance - dt
        # (dv . n), so that it is seen from n (primitives); dt dv . n is the step's approach,
        # a few 1e-4 of the distance: the bound only keeps a wild step finite
        back = dt * inverse
        seen = 1.0 / max(1.0 - back * (dvx * nx + dvy * ny + dvz * nz), 0.5)
        rolling_inertia = 0.0
        if COUPLES:  # each sphere's inertia about the contact point, in series (declarations.COUPLE_ARGUMENTS)
            about_contact_i, about_contact_j = 1.4 * mi * ri * ri, 1.4 * mj * rj * rj
            rolling_inertia = about_contact_i * about_contact_j / (about_contact_i + about_contact_j)
        on_i, direction, couple, _, _, _, ok = contact_response(
            law_force, constants[rows[k]], history_column(tile_history, k, TILE_CONTACTS), overlap, tile[T_PREVIOUS, k],
            (nx, ny, nz), ((nx - back * dvx) * seen, (ny - back * dvy) * seen, (nz - back * dvz) * seen), True,
            (dvx, dvy, dvz), wi, ZERO, wj, to_end,
            ri - 0.5 * overlap, rj - 0.5 * overlap, 0.25 * (overlap - max(tile[T_PREVIOUS, k], 0.0)),
            ri * rj * mass_sum * shared, mi * mj * reach * shared, rolling_inertia, dt, stats)
        response[R_ON_I, k], response[R_ON_I + 1, k], response[R_ON_I + 2, k] = on_i
        response[R_DIRECTION, k], response[R_DIRECTION + 1, k], response[R_DIRECTION + 2, k] = direction
        response[R_COUPLE, k], response[R_COUPLE + 1, k], response[R_COUPLE + 2, k] = couple
        response[R_FINITE, k] = 1.0 if ok else 0.0


@numba.njit(cache=True, inline="always")
def mesh_contact_geometry(px, py, pz, ri, triangles, t):
    """(overlap, normal, closest point, feature) of a sphere with triangle t."""
    cx, cy, cz, feature = triangle_closest_point(px, py, pz, triangles, t)
    dx, dy, dz = px - cx, py - cy, pz - cz
    distance = math.sqrt(dx * dx + dy * dy + dz * dz)
    if distance == 0.0:
        return ri, 0.0, 0.0, 1.0, cx, cy, cz, feature
    return ri - distance, dx / distance, dy / distance, dz / distance, cx, cy, cz, feature


# not inlined, as mesh_entry_overlap below
@numba.njit(cache=True)
def mesh_normal_at(px, py, pz, triangles, t):
    """The normal of a sphere centred at (px, py, pz) against triangle t (from its
    closest point to the centre)."""
    _, nx, ny, nz, _, _, _, _ = mesh_contact_geometry(px, py, pz, 1.0, triangles, t)
    return nx, ny, nz


# not inlined: it is called from four places of the MESHES block of force_range; inlining every copy of the
# closest-point search took the mesh kernel's cold compilation from 27 to 49 s of CPU for
# no gain (hopper scene, 250 beads, 0.3 s: 1.25 s of CPU either way; 2026-11-22)
@numba.njit(cache=True)
def mesh_entry_overlap(px, py, pz, ri, triangles, candidates, start, stop, k, touches_face, tolerance):
    """(overlap, normal, on a face's interior) of sphere i with candidate entry k, after
    the rule of one contact per feature region (see force_range); -1 for a contact
    another entry carries.

    An edge or vertex contact is shadowed by a deeper edge or vertex contact (or, at
    equal depth, an earlier one) when its point is not above that contact's tangent
    plane: on a flat or convex part of the mesh it is then no local minimum of the
    distance, only the same surface seen from another triangle. In a concave corner the
    point is above the plane and both contacts count.
    """
    overlap, nx, ny, nz, cx, cy, cz, feature = mesh_contact_geometry(px, py, pz, ri, triangles, candidates[k])
    if overlap > 0.0 and feature != FACE:
        if touches_face:
            overlap = -1.0
        else:
            for other in range(start, stop):
                if other == k:
                    continue
                o2, n2x, n2y, n2z, c2x, c2y, c2z, f2 = mesh_contact_geometry(
                    px, py, pz, ri, triangles, candidates[other])
                if f2 != FACE and (o2 > overlap or (o2 == overlap and other < k)) \
                        and (cx - c2x) * n2x + (cy - c2y) * n2y + (cz - c2z) * n2z <= tolerance:
                    overlap = -1.0
                    break
    return overlap, nx, ny, nz, feature == FACE


@numba.njit(cache=True, error_model="numpy", fastmath=FAST, _nrt=False)
def settle_group(group_first, group_stop, partial_at, first, last, particles, pairs, constants, scratch,
                 finishing, dt, stats, status, store_reactions):
    """Evaluate the tile's n_tile pair contacts (``evaluate_pair_tile``), then, for the
    particles group_first..group_stop-1 in order, add each one's contacts (tile_end) to
    its own force (own: gravity and walls) and give each partner its share, and finish
    the particle (``finish_range``), or leave it to finish_kick_drift with its force
    stored. The particle partial_at, when it is in the group (the last one), is not
    finished: its sum so far goes back to its row of own (its other contacts are in the
    next tile). Returns (contacts, particles finished that moved more than half the
    skin).

    Compiled once and called, not inlined: force_range calls it at two places (a group
    full of particles or the last one, and a tile full mid-particle); inlined, each call
    site had its own copy of it and of its finish_range, and the first run of
    scenarios/settle.toml on empty caches took 19 s instead of 12.8 s (whole process,
    2-core AMD EPYC). Called once a tile, and without reference counting (``_nrt=False``:
    nothing here allocates), so a call costs next to nothing."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material, last_force = particles
    (offsets, neighbours, pair_history, pair_overlap, reaction, reaction_slot, reverse_offsets, reaction_in_use,
     reaction_pending, partner_torque) = pairs
    tile, tile_history, response, tile_entry, tile_row, own, own_count, tile_end = scratch
    first_partner, drift_on, position_at_build, half_skin_squared, step_records = finishing
    # the tile's contacts: up to the group's last particle's end (read from the array,
    # not passed: a literal 0 at one call would compile this function twice)
    n_tile = tile_end[group_stop - 1 - group_first] if group_stop > group_first else 0
    if PAIRS and n_tile > 0:
        evaluate_pair_tile(n_tile, tile_row, constants, tile, tile_history, response, dt, stats)
    active, moved_too_far = 0, 0
    for i in range(group_first, group_stop):
        if i < 0:  # never (non_negative)
            continue
        g = i - group_first
        acc = (own[g, 0], own[g, 1], own[g, 2], own[g, 3], own[g, 4], own[g, 5], own_count[g])
        if PAIRS:
            for k in range(tile_end[g - 1] if g > 0 else 0, tile_end[g]):
                if k < 0:  # never (non_negative)
                    continue
                e = non_negative(tile_entry[k])
                j = non_negative(neighbours[e])
                if response[R_FINITE, k] == 0.0:
                    fault(status, NON_FINITE_FORCE, i, j, PARTICLE)
                    break
                for c in range(tile_history.shape[0]):
                    pair_history[e, c] = tile_history[c, k]
                overlap = tile[T_OVERLAP, k]
                lever_j = tile[T_RJ, k] - 0.5 * overlap
                on_i = (response[R_ON_I, k], response[R_ON_I + 1, k], response[R_ON_I + 2, k])
                direction = (response[R_DIRECTION, k], response[R_DIRECTION + 1, k], response[R_DIRECTION + 2, k])
                couple = (response[R_COUPLE, k], response[R_COUPLE + 1, k], response[R_COUPLE + 2, k])
                acc = add_contact(acc, tile[T_RI, k] - 0.5 * overlap, on_i, direction, couple)
                # j's share: the force on i (j gets its opposite) and the torque on j,
                # R_j' (n x ft) minus the couple on i
                tjx, tjy, tjz = 0.0, 0.0, 0.0
                if COUPLES:
                    tjx, tjy, tjz = (lever_j * direction[0] - couple[0], lever_j * direction[1] - couple[1],
                                     lever_j * direction[2] - couple[2])
                elif SPIN:
                    tjx, tjy, tjz = lever_j * direction[0], lever_j * direction[1], lever_j * direction[2]
                direct = j < last and first_partner[j] >= first
                if direct:
                    # j is in this block and finished in this pass, after every row that lists
                    # it (all in this block, in ascending i): its reactions are summed in its
                    # own force and torque rows, zero at the start of the pass (finish_range)
                    reaction_pending[j] = 1
                    force[j, 0] -= on_i[0]
                    force[j, 1] -= on_i[1]
                    force[j, 2] -= on_i[2]
                    if SPIN:
                        torque[j, 0] += tjx
                        torque[j, 1] += tjy
                        torque[j, 2] += tjz
                if store_reactions or not direct:
                    # at the slot of the entry in j's reverse row: read by finish_kick_drift
                    # for a j it finishes, and at a step whose state the run sees
                    # (State.contact_pairs)
                    r = non_negative(reaction_slot[e])
                    reaction_in_use[r] = 1
                    reaction[r, 0], reaction[r, 1], reaction[r, 2] = on_i
                    # j's torque only where finish_kick_drift reads it: State.contact_pairs
                    # reads the forces alone, so on one thread nothing writes these rows,
                    # and their pages (24 bytes an entry) are never resident
                    if SPIN and not direct:
                        partner_torque[r, 0], partner_torque[r, 1], partner_torque[r, 2] = tjx, tjy, tjz
        if i == partial_at:
            own[g, 0], own[g, 1], own[g, 2], own[g, 3], own[g, 4], own[g, 5], own_count[g] = acc
            # its row of own moves to the front: the next group starts at i
            own[0, 0], own[0, 1], own[0, 2], own[0, 3], own[0, 4], own[0, 5], own_count[0] = acc
            continue
        active += acc[6]
        moved_too_far += finish_range(i, i + 1, last, first_partner, particles, pairs, dt, drift_on,
                                      position_at_build, half_skin_squared, step_records, True, acc, first)
    return active, moved_too_far


@numba.njit(cache=True, error_model="numpy", fastmath=FAST, inline=INLINE)
def force_range(first, last, particles, law, planes, cylinders, meshes, pairs, gravity, dt, time, tracking,
                first_partner, drift_on, position_at_build, half_skin_squared, step_records):
    """Gravity and the contacts owned by particles first..last-1; returns (their count,
    particles moved more than half the skin, see ``finish_range``).

    Particle i owns its walls and the pairs (i, j > i) of its row of the Verlet half
    list; a pair's force on j and torque on j go to j's force and torque rows or to the
    pair's slot in j's transposed row (see the module docstring). Lever arms of a pair: R_i - d/2 and R_j - d/2 sum to the centre
    distance, so the pair's torques balance the moment of its force and angular
    momentum is conserved to round-off.

    Each particle p none of whose partners comes before ``first`` (first_partner[p] >=
    first, see ``minidem.engine.blocks``; on one thread every particle) is finished
    (``finish_range``) right after its own contacts. That is legal in ascending order:
    p's reactions come from the rows i < p, all in this block and done by then, and
    only rows i < p read p's position and velocity. The operations are the same, in
    the same order, as in the separate pass (the same bits), but p's force, velocity
    and reactions are still in cache: the separate pass is left with the particles
    that have a partner in an earlier block (on two threads, about a layer of the pile)
    and those ``defer_finishing`` leaves to it (first_partner -1).
    """
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material, last_force = particles
    pair_row, constants = law
    wall_point, wall_normal, wall_material, wall_history, wall_overlap, near_offsets, near_planes = planes
    # a kind of contact the scene does not have comes as an empty tuple (see advance), unpacked
    # only under its flag
    if CYLINDERS:
        base, axis, cylinder_radius, length, cylinder_material, cylinder_history, cylinder_overlap_prev = cylinders
    if MESHES:
        triangles, triangle_material, mesh_offsets, mesh_candidates, mesh_history, mesh_overlap = meshes
    probe_wall, probe, stats, status = tracking
    longest_row, history_width = 0, 0
    if PAIRS:
        (offsets, neighbours, pair_history, pair_overlap, reaction, reaction_slot, reverse_offsets, reaction_in_use,
         reaction_pending, partner_torque) = pairs
        history_width = pair_history.shape[1]
        for i in range(first, last):
            longest_row = max(longest_row, offsets[i + 1] - offsets[i])
    # Pair contacts are evaluated a tile at a time (evaluate_pair_tile: vector code): the
    # particles are taken in order, their walls evaluated and their touching pairs
    # gathered into the tile; when the tile is full, or holds TILE_PARTICLES particles,
    # it is evaluated and settle_group sums each particle's contacts and finishes it, in
    # order: the same operations in the same order as one particle at a time. A particle
    # whose contacts fill the tile is summed in parts and finished with the next tile.
    # A particle that ends with the tile empty (no pair of its own touches, and no earlier
    # particle waits in the group) is finished at once, as before tiles: its reactions are
    # all in (every earlier row is settled), and a sphere in free flight pays nothing for
    # the group (free fall, 200,000 spheres: 3.0 -> 2.7 s of kernel CPU, docs/benchmarks.md)
    touching_entries = np.empty(longest_row, dtype=np.int64)
    tile = np.empty((TILE_INPUTS, TILE_CONTACTS if PAIRS else 0))
    tile_history = np.empty((history_width, TILE_CONTACTS if PAIRS else 0))
    response = np.empty((TILE_RESPONSES, TILE_CONTACTS if PAIRS else 0))
    tile_entry = np.empty(TILE_CONTACTS if PAIRS else 0, dtype=np.int64)
    tile_row = np.empty(TILE_CONTACTS if PAIRS else 0, dtype=np.int64)
    own = np.empty((TILE_PARTICLES if PAIRS else 0, 6))  # gravity, walls and pairs summed so far
    own_count = np.empty(TILE_PARTICLES if PAIRS else 0, dtype=np.int64)
    tile_end = np.empty(TILE_PARTICLES if PAIRS else 0, dtype=np.int64)  # each particle's contacts end there
    scratch = (tile, tile_history, response, tile_entry, tile_row, own, own_count, tile_end)
    finishing = (first_partner, drift_on, position_at_build, half_skin_squared, step_records)
    # every pair's reaction also at its slot at a step whose state the run reads (a call's
    # last, when its caller asks: a frame, a copy, a checkpoint, the end): the contact
    # forces of the VTK frames and the files (State.contact_pairs)
    store_reactions = step_records[3]
    active, moved_too_far = 0, 0
    group_first = first
    n_tile = 0
    # one step past the last particle: the last group is settled there, at the same call
    # as the others (a call site fewer for the compiler)
    for i in range(first, last + 1):
        if i < 0:  # never: proves i >= 0 to the compiler (non_negative)
            continue
        if PAIRS and i > group_first and (i == last or i - group_first == TILE_PARTICLES):
            group_active, group_moved = settle_group(group_first, i, i, first, last, particles, pairs,
                                                     constants, scratch, finishing, dt, stats, status,
                                                     store_reactions)
            active += group_active
            moved_too_far += group_moved
            group_first, n_tile = i, 0
        if i == last:
            break
        # i's material is read where a contact needs it (pair_row[material[i], ...]), as its
        # spin below: a sphere in free flight reads neither
        px, py, pz, ri, mi = position[i, 0], position[i, 1], position[i, 2], radius[i], mass[i]
        vi = (velocity[i, 0], velocity[i, 1], velocity[i, 2])
        # i's spin is read where a contact of its own needs it, not here: a sphere in free
        # flight then touches no byte of it (finish_range)
        wi = ZERO
        acc = (mi * gravity[0], mi * gravity[1], mi * gravity[2], 0.0, 0.0, 0.0, 0)
        to_end = NO_CHANGE
        if END_VELOCITY:  # i's at its walls (which do not move); a pair's adds j's below
            kick_i = closing_kick(i, last_force, inverse_mass, inverse_inertia, dt)
            to_end = (kick_i[0], kick_i[1], kick_i[2], kick_i[3], kick_i[4], kick_i[5], 0.0, 0.0, 0.0)

        # Walls. Each kind has its own loop: binding the history rows of different
        # arrays to one variable would cost reference counting per contact (see above).
        # planes: those near i (State.list_near_planes; all of them in a tracked kernel),
        # each entry k with its own history and last overlap (carried over at list
        # builds); a plane's normal never turns, so its history needs no rotation
        probed = False  # the probed plane's contact was evaluated (TRACK, sphere 0)
        for k in range(near_offsets[i], near_offsets[i + 1]):
            if k < 0:  # never (non_negative)
                continue
            w = non_negative(near_planes[k])
            overlap = plane_overlap(px, py, pz, ri, wall_point, wall_normal, w)
            lives_above = engaged_above(constants, pair_row[material[i], wall_material[w]])
            touching_at_start = touches_at_start(dt, overlap, lives_above, ri, vi,
                                                 (wall_normal[w, 0], wall_normal[w, 1], wall_normal[w, 2]))
            if touching_at_start:
                overlap = lives_above  # the law sees the touch itself
            previous = wall_overlap[k]
            wall_overlap[k] = overlap
            if TRACK:
                note_transitions(stats, time, dt, overlap, previous)
            if overlap <= lives_above and not touching_at_start:
                # contact ends: its history is dropped (>=: also one that began touching at
                # the start, stored at lives_above, and went no further)
                if previous >= lives_above:
                    wall_history[k, :] = 0.0
                continue
            if overlap >= ri:
                fault(status, TUNNELLED, i, w, PLANE)
                break
            if SPIN:
                wi = (angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2])
            acc, _, _, _, fn, ft, increment, ok = evaluate_contact(
                acc, constants[pair_row[material[i], wall_material[w]]], history_row(wall_history, k), overlap, previous,
                (wall_normal[w, 0], wall_normal[w, 1], wall_normal[w, 2]), ZERO, False, vi, wi, to_end, ri, ri, mi, dt,
                stats)
            if not ok:
                fault(status, NON_FINITE_FORCE, i, w, PLANE)
                break
            if TRACK and i == 0 and w == probe_wall:
                probed = True
                probe[PROBE_OVERLAP] = overlap
                probe[PROBE_FN] = fn
                probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = ft
                probe[PROBE_DISPLACEMENT] += increment[0]
                probe[PROBE_DISPLACEMENT + 1] += increment[1]
                probe[PROBE_DISPLACEMENT + 2] += increment[2]
        # a tracked kernel lists every plane for every sphere, in order: sphere 0's entry
        # for plane w is w
        if TRACK and i == 0 and 0 <= probe_wall and not probed:
            probe[PROBE_OVERLAP], probe[PROBE_FN] = wall_overlap[probe_wall], 0.0
            probe[PROBE_FT], probe[PROBE_FT + 1], probe[PROBE_FT + 2] = 0.0, 0.0, 0.0

        if CYLINDERS:
            for c in range(base.shape[0]):
                overlap, nx, ny, nz = cylinder_overlap(px, py, pz, ri, base, axis, cylinder_radius, length, c)
                lives_above = engaged_above(constants, pair_row[material[i], cylinder_material[c]])
                touching_at_start = touches_at_start(dt, overlap, lives_above, ri, vi, (nx, ny, nz))
                if touching_at_start:
                    overlap = lives_above  # the law sees the touch itself (as at a plane)
                previous = cylinder_overlap_prev[i, c]
                cylinder_overlap_prev[i, c] = overlap
                if TRACK:
                    note_transitions(stats, time, dt, overlap, previous)
                if (overlap <= lives_above and not touching_at_start) or overlap >= ri:
                    if overlap >= ri:
                        fault(status, TUNNELLED, i, c, CYLINDER)
                        break
                    if previous >= lives_above:  # as at a plane: also a touch at the start that went no further
                        cylinder_history[i, c, :] = 0.0
                    continue
                if SPIN:
                    wi = (angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2])
                # the normal at i's position one drift back
                previous_normal = seen_from(cylinder_normal(px - dt * vi[0], py - dt * vi[1], pz - dt * vi[2], base,
                                                            axis, c, (nx, ny, nz)), (nx, ny, nz))
                acc, _, _, _, _, _, _, ok = evaluate_contact(
                    acc, constants[pair_row[material[i], cylinder_material[c]]], history_row_of(cylinder_history, i, c), overlap, previous,
                    (nx, ny, nz), previous_normal, True, vi, wi, to_end, ri, ri, mi, dt, stats)
                if not ok:
                    fault(status, NON_FINITE_FORCE, i, c, CYLINDER)
                    break

        if MESHES:
            # One contact per feature region: a face-interior contact always counts; an
            # edge or vertex contact counts only when the sphere touches no face interior
            # (else the face carries it, e.g. on a flat mesh split into triangles) and only
            # once however many triangles share that edge or vertex (mesh_entry_overlap).
            # A sphere moving across an edge or vertex passes from one triangle's entry to
            # the next: the contact with the first ends in the same step as the one with
            # the second starts. That is one contact moving on, so the new entry takes over
            # the old one's history and previous overlap (else the tangential force would
            # restart from zero at every edge). Entries that were touching are therefore
            # processed first, and an ending entry's history is kept until every entry of
            # the row has been seen.
            start, stop = mesh_offsets[i], mesh_offsets[i + 1]
            touches_face = False
            for k in range(start, stop):
                overlap, nx, ny, nz, cx, cy, cz, feature = mesh_contact_geometry(px, py, pz, ri, triangles,
                                                                                 mesh_candidates[k])
                if overlap > 0.0 and feature == FACE:
                    touches_face = True
                    break
            tolerance = _SAME_POINT * ri
            ending = 0  # contacts of the last step that end in this one, history not yet dropped
            for sweep in range(2):
                # sweep 0: the entries touching at the last step; sweep 1: the others
                for k in range(start, stop):
                    previous = mesh_overlap[k]
                    if (previous > 0.0) != (sweep == 0):
                        continue
                    t = mesh_candidates[k]
                    turned_from = t  # the triangle the contact touched at the last step
                    overlap, nx, ny, nz, on_face = mesh_entry_overlap(px, py, pz, ri, triangles, mesh_candidates,
                                                                      start, stop, k, touches_face, tolerance)
                    if sweep == 0 and overlap <= 0.0:
                        ending += 1  # left as it is (previous > 0 marks it) until the row is done
                        continue
                    if overlap > 0.0 and sweep == 1 and ending > 0:
                        # a new contact while another ends: the same contact moving on
                        for e in range(start, stop):
                            if mesh_overlap[e] > 0.0 and mesh_entry_overlap(
                                    px, py, pz, ri, triangles, mesh_candidates, start, stop, e, touches_face,
                                    tolerance)[0] <= 0.0:
                                mesh_history[k, :] = mesh_history[e, :]
                                previous = mesh_overlap[e]
                                turned_from = mesh_candidates[e]
                                mesh_overlap[e] = 0.0  # handed over: it ends without a separation
                                mesh_history[e, :] = 0.0
                                ending -= 1
                                break
                    # a touch at the start (as at a plane) counts on a face's interior only:
                    # an edge or vertex there is shared, and which entry carries it is decided
                    # on overlaps above zero
                    touching_at_start = on_face and touches_at_start(dt, overlap, 0.0, ri, vi, (nx, ny, nz))
                    if touching_at_start:
                        overlap = 0.0  # the law sees the touch itself
                    mesh_overlap[k] = overlap
                    if TRACK:
                        note_transitions(stats, time, dt, overlap, previous)
                    if overlap <= 0.0 and not touching_at_start:
                        if previous >= 0.0:  # as at a plane: also a touch at the start that went no further
                            mesh_history[k, :] = 0.0
                        continue
                    if overlap >= ri:
                        fault(status, TUNNELLED, i, t, TRIANGLE)
                        break
                    if SPIN:
                        wi = (angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2])
                    acc, _, _, _, _, _, _, ok = evaluate_contact(
                        acc, constants[pair_row[material[i], triangle_material[t]]], history_row(mesh_history, k), overlap, previous,
                        (nx, ny, nz), seen_from(mesh_normal_at(px - dt * vi[0], py - dt * vi[1], pz - dt * vi[2], triangles,
                                                               turned_from), (nx, ny, nz)),
                        True, vi, wi, to_end, ri, ri, mi, dt, stats)
                    if not ok:
                        fault(status, NON_FINITE_FORCE, i, t, TRIANGLE)
                        break
            if ending > 0:
                # the contacts that ended without a successor: their history is dropped
                for k in range(start, stop):
                    if mesh_overlap[k] > 0.0:
                        overlap = mesh_entry_overlap(px, py, pz, ri, triangles, mesh_candidates, start, stop, k,
                                                     touches_face, tolerance)[0]
                        if overlap <= 0.0:
                            if TRACK:
                                note_transitions(stats, time, dt, overlap, mesh_overlap[k])
                            mesh_overlap[k] = overlap
                            mesh_history[k, :] = 0.0



        g = i - group_first
        if PAIRS:
            # Two passes over the row. Whether a listed pair touches is unpredictable
            # (about a third do), and a mispredicted branch would flush the work in
            # flight: the first pass only collects the touching entries, without a
            # branch on it (and ends the rare contact that stops touching); the second
            # gathers them into the tile.
            n_touching = 0
            for e in range(offsets[i], offsets[i + 1]):
                if e < 0:  # never (non_negative)
                    continue
                j = non_negative(neighbours[e])
                dx, dy, dz = px - position[j, 0], py - position[j, 1], pz - position[j, 2]
                distance_squared = dx * dx + dy * dy + dz * dz
                reach = ri + radius[j]
                lives_above = 0.0
                if REACH:  # compile-time: a contact lives while the distance is below r_i + r_j + reach
                    lives_above = engaged_above(constants, pair_row[material[i], material[j]])
                    limit_squared = (reach - lives_above) * (reach - lives_above)
                else:
                    limit_squared = reach * reach
                touching = distance_squared < limit_squared
                if END_VELOCITY and dt == 0.0 and not touching:  # compile-time, then the first call only
                    touching = pair_touches_at_start(dt, reach, lives_above, (dx, dy, dz), vi, velocity, j)
                touching_entries[n_touching] = e
                n_touching += touching
                previous = pair_overlap[e]
                # The contact ends: apart now and touching at the last step (>=: also one
                # that began touching at the start, stored at lives_above, and went no
                # further; touches_at_start, as at a plane). Asked as one comparison of
                # the smaller of two differences (x - y >= 0 exactly when x >= y): as two,
                # the compiler branched first on whether the last step touched, as
                # unpredictable as whether this one does, for every listed pair; the
                # contact ending is rare.
                if TRACK:  # every apart entry's overlap, for the transitions
                    if not touching:
                        overlap = reach - math.sqrt(distance_squared)
                        pair_overlap[e] = overlap
                        note_transitions(stats, time, dt, overlap, previous)
                        if previous >= lives_above:
                            end_pair_contact(e, pair_history, reaction_slot, reaction, reaction_in_use)
                elif (min(previous - lives_above, distance_squared - limit_squared) >= 0.0
                      and not (END_VELOCITY and touching)):  # touching: at the start (dt = 0) only
                    pair_overlap[e] = reach - math.sqrt(distance_squared)
                    end_pair_contact(e, pair_history, reaction_slot, reaction, reaction_in_use)
            for k in range(n_touching):
                e = non_negative(touching_entries[k])
                j = non_negative(neighbours[e])
                dx, dy, dz = px - position[j, 0], py - position[j, 1], pz - position[j, 2]
                distance_squared = dx * dx + dy * dy + dz * dz
                rj = radius[j]
                reach = ri + rj
                previous = pair_overlap[e]
                distance = math.sqrt(distance_squared)
                overlap = reach - distance
                row = pair_row[material[i], material[j]]
                lives_above = engaged_above(constants, row)
                touching_at_start = (END_VELOCITY and dt == 0.0 and overlap <= lives_above
                                     and pair_touches_at_start(dt, reach, lives_above, (dx, dy, dz), vi, velocity, j))
                if touching_at_start:
                    overlap = lives_above  # the law sees the touch itself
                pair_overlap[e] = overlap
                if TRACK:
                    note_transitions(stats, time, dt, overlap, previous)
                if overlap <= lives_above and not touching_at_start:
                    # touching by the squared distance, not by its root (the distance within
                    # a rounding of the contact's reach): apart, as the next step's first
                    # pass will find it, and ended as there. Evaluated, its overlap 0 would
                    # keep the history and a stored reaction's flag for good (the end test
                    # is previous >= 0), a force on a partner finished by finish_kick_drift
                    if previous >= lives_above:
                        end_pair_contact(e, pair_history, reaction_slot, reaction, reaction_in_use)
                    continue
                if distance == 0.0:
                    fault(status, TUNNELLED, i, j, PARTICLE)
                    break
                if n_tile == TILE_CONTACTS:
                    # the tile is full: the particles before i are finished, i's contacts so
                    # far summed into its row of own, which moves to the front
                    own[g, 0], own[g, 1], own[g, 2], own[g, 3], own[g, 4], own[g, 5], own_count[g] = acc
                    tile_end[g] = n_tile
                    group_active, group_moved = settle_group(group_first, i + 1, i, first, last,
                                                             particles, pairs, constants, scratch, finishing, dt,
                                                             stats, status, store_reactions)
                    active += group_active
                    moved_too_far += group_moved
                    acc = (own[g, 0], own[g, 1], own[g, 2], own[g, 3], own[g, 4], own[g, 5], own_count[g])
                    group_first, n_tile, g = i, 0, 0
                tile_entry[n_tile] = e
                tile_row[n_tile] = row
                tile[T_DX, n_tile], tile[T_DY, n_tile], tile[T_DZ, n_tile] = dx, dy, dz
                tile[T_DISTANCE, n_tile], tile[T_OVERLAP, n_tile], tile[T_PREVIOUS, n_tile] = (
                    distance, overlap, previous)
                tile[T_RI, n_tile], tile[T_RJ, n_tile], tile[T_MI, n_tile], tile[T_MJ, n_tile] = ri, rj, mi, mass[j]
                # the contact velocity reads v_i - v_j only (pair_contact_velocity)
                tile[T_DV, n_tile], tile[T_DV + 1, n_tile], tile[T_DV + 2, n_tile] = (
                    vi[0] - velocity[j, 0], vi[1] - velocity[j, 1], vi[2] - velocity[j, 2])
                if SPIN:
                    tile[T_WI, n_tile], tile[T_WI + 1, n_tile], tile[T_WI + 2, n_tile] = (
                        angular_velocity[i, 0], angular_velocity[i, 1], angular_velocity[i, 2])
                    tile[T_WJ, n_tile], tile[T_WJ + 1, n_tile], tile[T_WJ + 2, n_tile] = (
                        angular_velocity[j, 0], angular_velocity[j, 1], angular_velocity[j, 2])
                if END_VELOCITY:
                    # j's last force is still its own: j is finished after i (ascending order)
                    kick_j = closing_kick(j, last_force, inverse_mass, inverse_inertia, dt)
                    tile[T_END, n_tile], tile[T_END + 1, n_tile], tile[T_END + 2, n_tile] = (
                        to_end[0] - kick_j[0], to_end[1] - kick_j[1], to_end[2] - kick_j[2])
                    tile[T_END + 3, n_tile], tile[T_END + 4, n_tile], tile[T_END + 5, n_tile] = (
                        to_end[3], to_end[4], to_end[5])
                    tile[T_END + 6, n_tile], tile[T_END + 7, n_tile], tile[T_END + 8, n_tile] = (
                        kick_j[3], kick_j[4], kick_j[5])
                for c in range(pair_history.shape[1]):
                    tile_history[c, n_tile] = pair_history[e, c]
                n_tile += 1
        if n_tile == 0:
            active += acc[6]
            moved_too_far += finish_range(i, i + 1, last, first_partner, particles, pairs, dt, drift_on,
                                          position_at_build, half_skin_squared, step_records, True, acc, first)
            group_first = i + 1
        else:
            own[g, 0], own[g, 1], own[g, 2], own[g, 3], own[g, 4], own[g, 5], own_count[g] = acc
            tile_end[g] = n_tile
    return active, moved_too_far


@numba.njit(cache=True, fastmath=FAST, inline="always")
def finish_range(first, last, finished_from, first_partner, particles, pairs, dt, drift_on, position_at_build,
                 half_skin_squared, step_records, own_given, own, block_first):
    """Particles first..last-1, except those whose first partner is at ``finished_from``
    or later (finished in the force pass): add the pair reactions and apply the closing
    kick; with ``drift_on`` also the next step's opening half kick and drift (the same
    operations in the same order, so the same bits as a closing kick then
    ``kick_drift``). Returns how many of them have moved more than half the skin since
    the neighbour list was built (0 without drift). ``step_records`` = (sampling,
    inertia, particle_energy, store_reactions; see ``advance``): when sampling, each particle's kinetic energy at the end of
    the step (after the closing kick) goes to particle_energy, fused here rather than a
    pass of its own (see ``advance``).

    ``own_given``: the force pass finishing its particle i (first = i, last = i + 1) hands
    over ``own`` = (fx, fy, fz, tx, ty, tz, contacts) of i's own contacts and gravity in
    registers, and its reactions are in its force and torque rows; if i has a partner
    before ``block_first`` (the force pass's first particle) it is not finished but its
    own force stored, for finish_kick_drift; else its own force is read from those
    rows and its reactions from its transposed row (see the module docstring). The total
    is stored when the drift is not fused (the call's last step, and every traced or
    stop-at-separation step: the next call's opening kick and the run between chunks read
    it), and always without pairs (END_VELOCITY: the next force pass predicts with it);
    with the drift fused, a pair kernel's rows that hold something (reactions, or the own
    force of a particle finish_kick_drift finishes) are zeroed for the next force pass
    instead."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material, last_force = particles
    sampling, inertia, particle_energy, _ = step_records
    if PAIRS:  # else an empty tuple (see advance)
        (offsets, neighbours, history, pair_overlap, reaction, reaction_slot, reverse_offsets, reaction_in_use,
         reaction_pending, partner_torque) = pairs
    moved_too_far = 0
    for p in range(first, last):
        if p < 0:  # never (non_negative)
            continue
        if first_partner[p] >= finished_from:
            continue
        if own_given:
            fx, fy, fz, tx, ty, tz, _ = own
            if first_partner[p] < block_first:
                force[p, 0], force[p, 1], force[p, 2] = fx, fy, fz
                torque[p, 0], torque[p, 1], torque[p, 2] = tx, ty, tz
                continue
        else:
            fx, fy, fz = force[p, 0], force[p, 1], force[p, 2]
            tx, ty, tz = torque[p, 0], torque[p, 1], torque[p, 2]
        if PAIRS:
            # the reactions of the pairs (i < p, p), summed from zero in ascending i, so the
            # same sum whatever the thread count
            rfx, rfy, rfz, rtx, rty, rtz = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            pending = False
            if own_given:
                # finished in the force pass: summed there in p's force and torque rows, if
                # a pair gave it one (reaction_pending, a byte a particle: a falling particle
                # reads that byte, not 48 bytes of zeros)
                pending = reaction_pending[p] != 0
                if pending:
                    reaction_pending[p] = 0
                    rfx, rfy, rfz = force[p, 0], force[p, 1], force[p, 2]
                    rtx, rty, rtz = torque[p, 0], torque[p, 1], torque[p, 2]
            else:
                # left to this pass (a partner in an earlier block, or defer_finishing's):
                # stored contiguously (the reverse rows).
                # Only the rows of touching pairs are read (reaction_in_use, a byte a row);
                # a branch: reading a zero row instead, chosen without one, was 10 % slower
                # in the falling phase of the settle scene (the loads wait for the flag)
                for k in range(reverse_offsets[p], reverse_offsets[p + 1]):
                    if k < 0:  # never (non_negative)
                        continue
                    if reaction_in_use[k]:
                        rfx -= reaction[k, 0]
                        rfy -= reaction[k, 1]
                        rfz -= reaction[k, 2]
                        if SPIN:
                            rtx += partner_torque[k, 0]
                            rty += partner_torque[k, 1]
                            rtz += partner_torque[k, 2]
            fx, fy, fz = fx + rfx, fy + rfy, fz + rfz
            if SPIN:
                tx, ty, tz = tx + rtx, ty + rty, tz + rtz
        if END_VELOCITY:  # read by the next force pass (closing_kick)
            last_force[p, 0], last_force[p, 1], last_force[p, 2] = fx, fy, fz
            last_force[p, 3], last_force[p, 4], last_force[p, 5] = tx, ty, tz
        if not drift_on or not PAIRS:  # a single sphere's: the run loop's checks read them
            force[p, 0], force[p, 1], force[p, 2] = fx, fy, fz
            torque[p, 0], torque[p, 1], torque[p, 2] = tx, ty, tz
        elif PAIRS and (pending or not own_given):
            # zero for the next force pass, which may sum p's reactions there (a call that
            # goes on after a list rebuild takes new blocks without an opening kick_drift);
            # nothing reads the total before that pass (the drift is fused). Rows no pair
            # wrote into are zero still
            force[p, 0], force[p, 1], force[p, 2] = 0.0, 0.0, 0.0
            torque[p, 0], torque[p, 1], torque[p, 2] = 0.0, 0.0, 0.0
        # the spin only under a torque (kick_spin): a falling sphere leaves it alone
        turning = SPIN and turns((tx, ty, tz))
        # the velocity in registers from the closing kick to the drift (integrate.kicked)
        velocity_of_p = (velocity[p, 0], velocity[p, 1], velocity[p, 2])
        if CLOSING_KICK > 0.0:
            velocity_of_p = kicked(velocity_of_p, (fx, fy, fz), inverse_mass[p], CLOSING_KICK * dt)
            if turning:
                kick_spin(p, angular_velocity, (tx, ty, tz), inverse_inertia, CLOSING_KICK * dt)
        if sampling:
            particle_energy[p] = kinetic_energy_of(mass[p], inertia[p], velocity_of_p, (
                angular_velocity[p, 0], angular_velocity[p, 1], angular_velocity[p, 2]))
        if drift_on and turning:
            kick_spin(p, angular_velocity, (tx, ty, tz), inverse_inertia, OPENING_KICK * dt)
        if CLOSING_KICK > 0.0 and not drift_on:
            velocity[p, 0], velocity[p, 1], velocity[p, 2] = velocity_of_p
        if drift_on and kick_drift_one(p, position, velocity, velocity_of_p, (fx, fy, fz), inverse_mass, dt,
                                        position_at_build, half_skin_squared):
            moved_too_far += 1
    return moved_too_far


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def compute_forces(particles, law, planes, cylinders, meshes, pairs, gravity, dt, time, tracking, threads, drift_on,
                   position_at_build, half_skin_squared, bounds, first_partner, block_cycles, step_records):
    """Gravity and every contact force on every particle; returns (the number of
    contacts, particles finished and moved too far). Finishes every particle that has
    no partner in an earlier block (``force_range``), on one thread all of them; the
    others are left to ``finish_kick_drift``.

    Parallel: one block of consecutive particles per thread (``bounds``, see
    ``minidem.engine.blocks.thread_blocks``). A call of force_range
    unpacks the argument tuples, an atomic reference-count update per array on headers
    the threads share, so it is made once per thread and step (blocks of 256 particles
    cost 48 of these per block, and the two threads' cache lines bounced between the
    cores). numba's default schedule gives each thread an equal share of a prange in
    one piece, so those smaller blocks did not balance the load either. Each block's
    cycles are added to ``block_cycles``, by which the next call's blocks are balanced
    (``minidem.engine.blocks.BlockTiming``)."""
    if PARALLEL:  # a compile-time constant: serial kernels compile (and inline) one force_range
        if threads > 1:
            active, moved_too_far = 0, 0
            for block in particle_range(threads):
                started = cycle_counter()
                block_active, block_moved = force_range(bounds[block], bounds[block + 1], particles, law, planes,
                                                        cylinders, meshes, pairs, gravity, dt, time, tracking,
                                                        first_partner, drift_on, position_at_build, half_skin_squared,
                                                        step_records)
                block_cycles[block] += cycle_counter() - started
                active += block_active
                moved_too_far += block_moved
            return active, moved_too_far
    # bounds[0] (= 0), not the literal 0: numba would compile force_range a second time for a
    # literal first argument, beside the prange loop's (11 of the 44 s of CPU of a first run
    # of scenarios/settle.toml)
    return force_range(bounds[0], bounds[1], particles, law, planes, cylinders, meshes, pairs, gravity, dt, time,
                       tracking, first_partner, drift_on, position_at_build, half_skin_squared, step_records)


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def finish_kick_drift(particles, pairs, dt, drift_on, position_at_build, half_skin_squared, threads, bounds,
                      first_partner, step_records):
    """``finish_range`` of the particles compute_forces left (a partner in an earlier
    block), in the same blocks."""
    moved_too_far = 0
    for block in particle_range(threads):
        moved_too_far += finish_range(bounds[block], bounds[block + 1], bounds[block], first_partner, particles,
                                      pairs, dt, drift_on, position_at_build, half_skin_squared, step_records, False,
                                      (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0), 0)
    return moved_too_far


@numba.njit(cache=True, inline="always")
def kick_drift_one(p, position, velocity, velocity_of_p, force_on_p, inverse_mass, dt, position_at_build,
                   half_skin_squared):
    """Opening kick of particle p's velocity ``velocity_of_p`` (a 3-tuple: its row of
    ``velocity`` is written here) by the force given (a 3-tuple; the spin's kick is the
    caller's, ``kick_spin``) and drift of p; True when it has moved more than half the
    skin since the neighbour list was built."""
    opened = kicked(velocity_of_p, force_on_p, inverse_mass[p], OPENING_KICK * dt)
    velocity[p, 0], velocity[p, 1], velocity[p, 2] = opened
    moved_to = drifted((position[p, 0], position[p, 1], position[p, 2]), opened, dt)
    position[p, 0], position[p, 1], position[p, 2] = moved_to
    if not CHECK_DISPLACEMENT:
        return False
    dx = moved_to[0] - position_at_build[p, 0]
    dy = moved_to[1] - position_at_build[p, 1]
    dz = moved_to[2] - position_at_build[p, 2]
    return dx * dx + dy * dy + dz * dz > half_skin_squared


@numba.njit(cache=True, parallel=PARALLEL, fastmath=FAST, inline=INLINE)
def kick_drift(particles, dt, position_at_build, half_skin_squared):
    """Opening half kick and drift; returns how many particles have moved more than
    half the skin since the neighbour list was built."""
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material, last_force = particles
    moved_too_far = 0
    for p in particle_range(position.shape[0]):
        if SPIN and turns((torque[p, 0], torque[p, 1], torque[p, 2])):
            kick_spin(p, angular_velocity, (torque[p, 0], torque[p, 1], torque[p, 2]), inverse_inertia,
                      OPENING_KICK * dt)
        moved = kick_drift_one(p, position, velocity, (velocity[p, 0], velocity[p, 1], velocity[p, 2]),
                               (force[p, 0], force[p, 1], force[p, 2]), inverse_mass, dt, position_at_build,
                               half_skin_squared)
        if END_VELOCITY:  # the rows hold the totals here (a call's start, a restored state)
            last_force[p, 0], last_force[p, 1], last_force[p, 2] = force[p, 0], force[p, 1], force[p, 2]
            last_force[p, 3], last_force[p, 4], last_force[p, 5] = torque[p, 0], torque[p, 1], torque[p, 2]
        if PAIRS:  # zero for the force pass, which sums p's pair reactions there (force_range)
            force[p, 0], force[p, 1], force[p, 2] = 0.0, 0.0, 0.0
            torque[p, 0], torque[p, 1], torque[p, 2] = 0.0, 0.0, 0.0
        if moved:
            moved_too_far += 1
    return moved_too_far


@numba.njit(cache=True, parallel=PARALLEL, inline=INLINE)
def total_energy(particle_energy, block_sums):
    """The sum of the particles' energies (J) by the blocks of
    ``minidem.engine.integrate.kinetic_energy`` (ENERGY_BLOCK particles each, summed in
    parallel, their sums added in order): the same bits on any number of threads, and as
    that function's."""
    for block in particle_range(block_sums.shape[0]):
        block_sums[block] = block_sum(block, particle_energy)
    total = 0.0
    for block in range(block_sums.shape[0]):
        total += block_sums[block]
    return total


@numba.njit(cache=True, error_model="numpy")
def advance(particles, law, planes, cylinders, meshes, pairs, gravity, position_at_build, half_skin_squared,
            dt, start_time, start_step, n_steps, resume, stop_at_separation, store_reactions, trace, tracking,
            threads, bounds, first_partner, block_cycles, energy):
    """Advance up to n_steps; return (steps completed, neighbour list needs a rebuild).

    Returns early
    * after a drift that took a particle more than half the skin from where the Verlet
      list was built: the caller rebuilds the list and calls again with ``resume``
      True, which continues from the force evaluation of the step that drift began
      (a pair kernel's force and torque rows are then zero, as every fused step leaves
      them, for the force pass to sum reactions into; a state holding totals, e.g.
      restored, is continued with ``resume`` False, whose opening kick_drift reads and
      zeroes them);
    * after the step in which the last contact ended (``stop_at_separation``, once a
      contact has occurred; tracked scenes only);
    * on a fault (status[0] != OK).
    ``trace`` (rows = steps, may have 0 rows) receives the probed contact each step.
    ``store_reactions``: every touching pair's force is also stored at its reaction slot
    at the steps that end on the closing kick (the call's last, and every traced or
    stop-at-separation step), for a caller that reads that state's contact forces
    (``State.contact_pairs``: a frame, a copy of the state, a checkpoint, the end of the
    run). Otherwise only the reactions finish_kick_drift needs are stored (none on one
    thread): a pile's reaction rows (24 bytes a list entry) are then not resident between
    list builds (docs/benchmarks.md, "Reactions stored where they are read"). Which
    steps store them changes no other value.
    ``energy`` = (sample_steps, inertia, samples, particle_energy, block_sums): at the end
    of every step whose number (start_step + 1, ...) is a multiple of sample_steps (> 0),
    the kinetic energy goes to the next element of ``samples`` (as many as fit): the run's
    samples, taken without returning to Python (at 200 samples a run, returning for each
    cost the falling phase of the settle scene at N = 200,000 18 % of its time, in the
    checks and the sample between chunks) and without a pass of their own (each
    particle's energy is taken as it is finished, ``finish_range``; a separate pass and
    the unfused drift after it cost as much as the returns).
    ``threads``: how many threads run the particle loops, at most numba's current
    number (numba.set_num_threads; not read here: numba.get_num_threads() in compiled
    code makes it uncacheable). ``bounds``, ``first_partner``: its blocks of particles
    (``minidem.engine.blocks.blocks``, for ``threads`` threads; one block, all particles,
    for a serial kernel): chosen outside the kernel, which therefore does not compile
    them anew for every law and scene shape; ``block_cycles``: each block's force pass
    adds the processor cycles it took (more than one thread), for the next call's blocks.
    ``cylinders``, ``meshes``, ``pairs``: an empty tuple when the kernel's flag is off
    (``Simulation.arguments``): each array of a tuple argument is unboxed, typed and
    lowered in a first compile, whether used or not.
    Times are start_time + k dt, not a running sum, so long runs do not drift.

    Two parallel passes a step: forces, then reactions + closing half kick fused with
    the next step's opening half kick and drift, for the particles the force pass could
    not finish itself (none on one thread: one pass a step; see the module docstring).
    The call's last step (and every traced or stop-at-separation step) ends on the
    closing half kick, so the velocities the caller sees are those at the end of a
    step. Either way the same operations in the same order.
    """
    position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia, radius, material, last_force = particles
    probe_wall, probe, stats, status = tracking
    sample_steps, inertia, samples, particle_energy, block_sums = energy
    sampled = 0
    if not PARALLEL:
        threads = 1
    drift_done = resume  # the opening half kick and drift of the current step are done
    for step in range(n_steps):
        if not drift_done:
            if kick_drift(particles, dt, position_at_build, half_skin_squared) > 0:
                return step, True
        time = start_time + (start_step + step + 1) * dt
        sampling = sample_steps > 0 and (start_step + step + 1) % sample_steps == 0 and sampled < samples.shape[0]
        drift_done = step + 1 < n_steps and step + 1 >= trace.shape[0] and not stop_at_separation
        step_records = (sampling, inertia, particle_energy, store_reactions and not drift_done)
        active, moved_too_far = compute_forces(particles, law, planes, cylinders, meshes, pairs, gravity, dt, time,
                                               tracking, threads, drift_done, position_at_build, half_skin_squared, bounds,
                                               first_partner, block_cycles, step_records)
        if status[0] != OK:
            return step + 1, False
        if PARALLEL:  # compile-time: a serial kernel has no second pass to compile
            if threads > 1:
                moved_too_far += finish_kick_drift(particles, pairs, dt, drift_done, position_at_build,
                                                   half_skin_squared, threads, bounds, first_partner, step_records)
        if sampling:
            samples[sampled] = total_energy(particle_energy, block_sums)
            sampled += 1
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
        if moved_too_far > 0:
            return step + 1, True
    return n_steps, False


TRACE_COLUMNS = (
    "time_s", "normal_overlap_m", "normal_force_n", "tangential_force_x_n", "tangential_force_y_n",
    "tangential_force_z_n", "tangential_displacement_x_m", "tangential_displacement_y_m",
    "tangential_displacement_z_m", "velocity_x_m_s", "velocity_y_m_s", "velocity_z_m_s",
    "angular_velocity_x_rad_s", "angular_velocity_y_rad_s", "angular_velocity_z_rad_s",
)
