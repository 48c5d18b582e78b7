"""Time-integration pieces of the compiled step (velocity Verlet, kick-drift-kick).

The contact forces at step n+1 are evaluated from positions x(n+1) and the half-step
velocities v(n+1/2) that carried the particles there, so the tangential displacement
increment v_t(n+1/2) dt is exactly the relative motion of the contact points over the
step (the LAMMPS convention).

Both functions act on one particle so the kernel can fuse them with its other
per-particle work in a single (parallel) loop.
"""

import numba


@numba.njit(cache=True, inline="always")
def half_kick(p, velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, dt, spin):
    half = 0.5 * dt
    scale = half * inverse_mass[p]
    velocity[p, 0] += scale * force[p, 0]
    velocity[p, 1] += scale * force[p, 1]
    velocity[p, 2] += scale * force[p, 2]
    if spin:
        scale = half * inverse_inertia[p]
        angular_velocity[p, 0] += scale * torque[p, 0]
        angular_velocity[p, 1] += scale * torque[p, 1]
        angular_velocity[p, 2] += scale * torque[p, 2]


@numba.njit(cache=True, inline="always")
def drift(p, position, velocity, dt):
    position[p, 0] += dt * velocity[p, 0]
    position[p, 1] += dt * velocity[p, 1]
    position[p, 2] += dt * velocity[p, 2]
