"""Time-integration pieces of the compiled step, and the integrators a scenario can choose.

Every integrator is the same kick-drift-kick step with a different split of the
velocity update around the force evaluation (``OPENING_KICK``, a kernel specialisation
constant: the fraction of dt applied before the drift, the rest after the forces):

    velocity_verlet   0.5: v += F dt/2m, x += v dt, F(x), v += F dt/2m (second order)
    symplectic_euler  1.0: v += F dt/m, x += v dt, F(x) (the velocity it reports lags
                      half a step: first order in the velocity, same positions)
    analytic_flight   velocity Verlet in contact; the free flight before the first
                      contact (ballistic, under gravity) is solved in closed form up to
                      the exact touch time and the step grid starts there, so no step
                      straddles first touch and no step is spent in the approach
                      (``flight_to_first_touch``; one particle and plane walls)

The contact forces at step n+1 are evaluated from positions x(n+1) and the velocities
that carried the particles there, so the tangential displacement increment v_t dt is
exactly the relative motion of the contact points over the step (the LAMMPS
convention), and the overlap changes linearly within the step: the mid-step overlap
d - dd/2 the Hertz-Mindlin laws use for their stiffness is exact under every integrator.

The kick and drift act on one particle so the kernel can fuse them with its other
per-particle work in a single (parallel) loop.
"""

import math

import numba

INTEGRATORS = ("velocity_verlet", "symplectic_euler", "analytic_flight")
# fraction of the velocity update made before the drift, per integrator
OPENING_KICK = {"velocity_verlet": 0.5, "symplectic_euler": 1.0, "analytic_flight": 0.5}


@numba.njit(cache=True, inline="always")
def kicked(velocity_of_p, force_on_p, inverse_mass_of_p, duration):
    """v + F duration / m, v and F 3-tuples: the kernel keeps a particle's velocity in
    registers from its closing kick through its opening kick and drift, and stores it
    once. Stored and read back between them (numba cannot tell the velocity and position
    arrays apart), each particle waited on a chain of round trips through memory, which
    the processor could not overlap with the next particle's work in the kernel's long
    loop body: 4 % of the settle scene's step at N = 20,000, lattice (one thread, 11.52
    against 11.07 s, medians of three alternated runs; jitter unchanged). The same
    operations in the same order, so the same bits."""
    scale = duration * inverse_mass_of_p
    return (velocity_of_p[0] + scale * force_on_p[0], velocity_of_p[1] + scale * force_on_p[1],
            velocity_of_p[2] + scale * force_on_p[2])


@numba.njit(cache=True, inline="always")
def turns(torque_on_p):
    """Whether a torque (3-tuple) changes the spin: any component nonzero, or NaN (which
    compares unequal, so a non-finite torque still reaches the spin)."""
    return (torque_on_p[0] != 0.0) | (torque_on_p[1] != 0.0) | (torque_on_p[2] != 0.0)


@numba.njit(cache=True, inline="always")
def kick_spin(p, angular_velocity, torque_on_p, inverse_inertia, duration):
    """w += T duration / I, for a torque that ``turns``: w + 0 = w, so a sphere without a
    torque (in free flight) is left alone and neither its spin nor its inverse inertia is
    read, 56 of the ~270 bytes a falling sphere moves a step (docs/benchmarks.md). The
    caller tests, not this function: a branch on the arrays inside an inlined helper kept
    numba's reference counting in the kernel's particle loop (3x slower). A spin of -0.0
    stays -0.0 where adding +0.0 made it +0.0: no other bit differs from an unconditional
    update."""
    scale = duration * inverse_inertia[p]
    angular_velocity[p, 0] += scale * torque_on_p[0]
    angular_velocity[p, 1] += scale * torque_on_p[1]
    angular_velocity[p, 2] += scale * torque_on_p[2]


@numba.njit(cache=True, inline="always")
def drifted(position_of_p, velocity_of_p, dt):
    """x + v dt, x and v 3-tuples (see ``kicked``)."""
    return (position_of_p[0] + dt * velocity_of_p[0], position_of_p[1] + dt * velocity_of_p[1],
            position_of_p[2] + dt * velocity_of_p[2])


def time_to_touch(gap: float, approach_speed: float, approach_acceleration: float) -> float:
    """First t >= 0 at which gap - c t - b t^2/2 = 0 (c approach speed, b approach
    acceleration, both along the wall normal towards the wall), or inf. A gap of zero
    that is not closing (c < 0, or c = 0 and b <= 0) is no touch at t = 0: the next root.

    Each root in a form free of cancellation: 2 s / (c + sqrt(c^2 + 2 b s)) for a sphere
    approaching or at rest (c >= 0), (sqrt(c^2 + 2 b s) - c) / b for one moving away and
    pulled back (c < 0 < b). The first form for a sphere moving away (a rebound
    under gravity: c < 0, s tiny) divides by the difference of two nearly equal numbers:
    15 ms off for a 1.4 m/s rebound 1e-16 m from the wall, inf at 1e-18 m, and the
    flight planned from it passed through the floor.
    """
    if gap < 0.0 or (gap == 0.0 and (approach_speed > 0.0 or (approach_speed == 0.0 and approach_acceleration > 0.0))):
        return 0.0
    discriminant = approach_speed * approach_speed + 2.0 * approach_acceleration * gap
    if discriminant < 0.0:
        return math.inf  # turns back before reaching the wall
    root = math.sqrt(discriminant)
    if approach_speed >= 0.0 and approach_speed + root > 0.0:  # (c = 0: a fall from rest, sqrt(2 s / b))
        return 2.0 * gap / (approach_speed + root)
    if approach_acceleration > 0.0:
        return (root - approach_speed) / approach_acceleration
    return math.inf  # moving away or along the wall, never pulled back


def ballistic_position(position, velocity, gravity, elapsed: float):
    """Where free flight under gravity alone takes ``position`` in ``elapsed`` s, starting
    at ``velocity``: x + t (v + g t / 2), the position velocity Verlet reaches too (exact
    under a constant force). One expression, so that every flight's states have the same
    bits wherever they are computed (minidem.engine.run_loop.RunLoop.fly)."""
    return position + elapsed * (velocity + 0.5 * elapsed * gravity)


def flight_to_first_touch(position, velocity, radius, wall_point, wall_normal, gravity):
    """Closed-form ballistic flight of one sphere to its first touch of a plane.

    Returns (flight time, position, velocity, index of the wall touched) at the touch
    instant, or None when the sphere touches no plane (or already touches one). The
    position is corrected along the wall normal so the overlap there is exactly zero,
    not a rounding error either side of it.
    """
    best, wall = math.inf, -1
    for w in range(wall_normal.shape[0]):
        normal = wall_normal[w]
        gap = float((position - wall_point[w]) @ normal) - radius
        if gap <= 0.0:
            return None  # in contact at the start: nothing to skip
        t = time_to_touch(gap, -float(velocity @ normal), -float(gravity @ normal))
        if t < best:
            best, wall = t, w
    if wall < 0 or not math.isfinite(best):
        return None
    moved = position + velocity * best + 0.5 * gravity * best * best
    normal = wall_normal[wall]
    moved = moved + (radius - float((moved - wall_point[wall]) @ normal)) * normal
    return best, moved, velocity + gravity * best, wall


@numba.njit(cache=True, inline="always")
def particle_kinetic_energy(p, mass, inertia, velocity, angular_velocity):
    """Translational plus rotational kinetic energy of particle p (J)."""
    return kinetic_energy_of(mass[p], inertia[p], (velocity[p, 0], velocity[p, 1], velocity[p, 2]),
                             (angular_velocity[p, 0], angular_velocity[p, 1], angular_velocity[p, 2]))


@numba.njit(cache=True, inline="always")
def kinetic_energy_of(mass_of_p, inertia_of_p, velocity_of_p, angular_velocity_of_p):
    """Translational plus rotational kinetic energy (J) of a sphere of the given mass and
    moment of inertia, its velocity and spin 3-tuples. Products, not ``** 2``: numba
    compiles a float power into a call of the C library's pow (six a particle, 90 % of
    the cost of a kinetic-energy pass)."""
    vx, vy, vz = velocity_of_p
    wx, wy, wz = angular_velocity_of_p
    return 0.5 * (mass_of_p * (vx * vx + vy * vy + vz * vz) + inertia_of_p * (wx * wx + wy * wy + wz * wz))


# particles a block of the kinetic energy's sum: the sum is taken block by block and the
# blocks' sums in order, so the same bits whether the blocks are summed on one thread or
# several (minidem.engine.kernel.total_energy, the run's samples) or here
ENERGY_BLOCK = 4096


@numba.njit(cache=True, inline="always")
def energy_blocks(n_particles):
    """How many blocks of ENERGY_BLOCK particles (the last one may be short)."""
    return -(-n_particles // ENERGY_BLOCK)


@numba.njit(cache=True, inline="always")
def block_particles(block, n_particles):
    """The particles of block ``block``, as a range."""
    return range(block * ENERGY_BLOCK, min((block + 1) * ENERGY_BLOCK, n_particles))


@numba.njit(cache=True)
def block_sum(block, values):
    """values[p] summed in order over the particles p of block ``block``."""
    total = 0.0
    for p in block_particles(block, values.shape[0]):
        total += values[p]
    return total


@numba.njit(cache=True)
def kinetic_energy(mass, inertia, velocity, angular_velocity):
    """Kinetic energy of all particles (J): the particles' energies summed by blocks of
    ENERGY_BLOCK particles, the blocks' sums in order: the same bits as the samples the
    kernel takes during a run (minidem.engine.kernel.total_energy). One compiled pass
    (numpy's einsum and sums took 0.5 ms at N = 20,000; a BLAS dot would also start
    OpenBLAS threads that spin on the kernel's cores)."""
    total = 0.0
    for block in range(energy_blocks(mass.shape[0])):
        block_total = 0.0
        for p in block_particles(block, mass.shape[0]):
            block_total += particle_kinetic_energy(p, mass, inertia, velocity, angular_velocity)
        total += block_total
    return total
