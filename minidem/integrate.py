"""Time-integration pieces of the compiled step (velocity Verlet, kick-drift-kick).

The contact forces at step n+1 are evaluated from positions x(n+1) and the half-step
velocities v(n+1/2) that carried the particles there, so the tangential displacement
increment v_t(n+1/2) dt is exactly the relative motion of the contact points over the
step (the LAMMPS convention).
"""

import numba


@numba.njit(cache=True)
def half_kick(velocity, angular_velocity, force, torque, inverse_mass, inverse_inertia, dt, spin):
    half = 0.5 * dt
    for i in range(velocity.shape[0]):
        scale = half * inverse_mass[i]
        velocity[i, 0] += scale * force[i, 0]
        velocity[i, 1] += scale * force[i, 1]
        velocity[i, 2] += scale * force[i, 2]
        if spin:
            scale = half * inverse_inertia[i]
            angular_velocity[i, 0] += scale * torque[i, 0]
            angular_velocity[i, 1] += scale * torque[i, 1]
            angular_velocity[i, 2] += scale * torque[i, 2]


@numba.njit(cache=True)
def drift(position, velocity, dt):
    for i in range(position.shape[0]):
        position[i, 0] += dt * velocity[i, 0]
        position[i, 1] += dt * velocity[i, 1]
        position[i, 2] += dt * velocity[i, 2]
