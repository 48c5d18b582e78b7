"""Blow-up detection between chunks of the compiled loop.

The kernel itself stops at the step where a law returns a non-finite force or a sphere
passes through a wall (status codes in ``minidem.engine.kernel``). What it cannot see from
one contact, :class:`Guard` checks once per chunk and before every neighbour-list
rebuild, with a few vectorised passes over the particle arrays (no Python per step):

* non-finite state: a NaN or infinity in a position, velocity, angular velocity,
  force or torque;
* energy: a contact stores and dissipates energy and, when one of its parts declares
  the energy role "supply" (adhesion), gives at most that part's ``supply_bound`` (the
  depth of its potential well) per contact. So the kinetic energy can never exceed the
  initial kinetic energy plus the work gravity has done, W = sum m_i g.(x_i - x_i(0))
  (the scene starts with no stored elastic energy: initial overlaps are refused), plus
  the adhesion budget (the bound per contact times the most contacts the scene can
  hold, ``Simulation.supply_budget``). A run whose kinetic energy exceeds
  ``ENERGY_FACTOR`` times that budget is unstable;
* the domain: no particle can be farther from the box spanned by the initial
  particles and the finite walls than a particle carrying the whole energy budget
  could travel, with a margin of ``REACH_FACTOR``. This also keeps a runaway particle
  from stretching the neighbour grid.

The budget has a floor, 1/2 M v_c^2 with v_c the scene's characteristic speed (its
fastest initial approach or free-fall speed over its height, at least 1 mm/s), so
round-off in a scene at rest is never taken for a blow-up.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from minidem.engine.integrate import block_particles, energy_blocks, particle_kinetic_energy

# A blow-up grows by orders of magnitude within a few contact times, so generous
# factors cost almost nothing in detection time and rule out false alarms (velocity
# Verlet's energy error is O(dt^2), and the integral-form laws create ~1e-3 of the
# impact energy per loop, paper Fig 12). The energy factor is 2 on a budget that
# already includes the floor: a stable run stays below KE(0) + W, so twice the budget
# means the contacts created at least KE(0) + W + 2 x 1/2 M v_c^2 out of nothing, an
# unstable time step whatever run.allow_unstable_dt says (1000 let an allowed dt of 7
# times the stability limit finish with 3,200 times the energy the scene could supply).
ENERGY_FACTOR = 2.0
REACH_FACTOR = 10.0


@dataclasses.dataclass
class Fault:
    what: str  # "non-finite state", "energy", "domain"
    particle: int
    detail: str


class Guard:
    def __init__(self, sim):
        scene = sim.scene
        self.sim = sim
        self.follow(scene)
        self.gravity = np.asarray(scene.gravity, dtype=np.float64)
        self.gravity_magnitude = float(np.linalg.norm(self.gravity))
        initial_kinetic = 0.5 * float(np.dot(self.mass, np.einsum("ik,ik->i", scene.velocity, scene.velocity))
                                      + np.dot(self.inertia, np.einsum("ik,ik->i", scene.angular_velocity,
                                                                       scene.angular_velocity)))
        self.floor = 0.5 * float(self.mass.sum()) * sim.characteristic_speed() ** 2
        self.base_budget = initial_kinetic + self.floor + sim.supply_budget
        self.supply_budget = sim.supply_budget
        self.lightest = float(self.mass.min()) if self.mass.size else 1.0
        # a threaded run's checks share the survey between its threads; the same bits
        self.survey = survey_threads if sim.threaded else survey
        lower = (scene.position - scene.radius[:, None]).min(axis=0)
        upper = (scene.position + scene.radius[:, None]).max(axis=0)
        walls = scene.walls
        finite_points = [walls.triangles.reshape(-1, 3)]
        for c in range(walls.cylinder_base.shape[0]):
            ends = walls.cylinder_base[c] + np.outer([0.0, walls.cylinder_length[c]], walls.cylinder_axis[c])
            finite_points.append(np.concatenate([ends - walls.cylinder_radius[c], ends + walls.cylinder_radius[c]]))
        points = np.concatenate(finite_points)
        if points.size:
            lower, upper = np.minimum(lower, points.min(axis=0)), np.maximum(upper, points.max(axis=0))
        self.lower, self.upper = lower, upper
        self.extent = float(np.linalg.norm(upper - lower))

    def follow(self, scene) -> None:
        """The scene's per-particle arrays in the order it stores the particles (a run may
        sort them again, Simulation.sort_in_space)."""
        self.scene = scene
        self.mass, self.inertia = scene.mass, scene.inertia
        # the scene's own positions (a run advances a copy of them), not another copy
        self.initial_position = scene.position

    def budget(self, position, gravity_work_max: float) -> tuple[float, float]:
        """(energy budget J, the largest work of gravity so far J, to carry to the next check)."""
        work = float(np.dot(self.mass, (position - self.initial_position) @ self.gravity))
        gravity_work_max = max(gravity_work_max, work)
        return self.base_budget + gravity_work_max, gravity_work_max

    def check(self, state, time: float, gravity_work_max: float) -> tuple[Fault | None, float]:
        """(the first fault found or None, updated largest work of gravity). The fault's
        particle is the row it is stored in; the messages name the scenario's index."""
        if self.sim.scene is not self.scene:
            self.follow(self.sim.scene)
        name_of = self.scene.scenario_index
        bad, kinetic, top, gravity_work, far, distance = self.survey(
            state.position, state.velocity, state.angular_velocity, state.force, state.torque, self.mass,
            self.inertia, self.initial_position, self.gravity, self.lower, self.upper)
        if bad >= 0:
            arrays = {"position": state.position, "velocity": state.velocity,
                      "angular velocity": state.angular_velocity, "force": state.force, "torque": state.torque}
            name = next(name for name, array in arrays.items() if not np.isfinite(array[bad]).all())
            return Fault("non-finite state", bad, f"particle {name_of(bad)} has {name} {arrays[name][bad].tolist()}"), \
                gravity_work_max
        gravity_work_max = max(gravity_work_max, gravity_work)
        budget = self.base_budget + gravity_work_max
        if kinetic > ENERGY_FACTOR * budget:
            allowed = math.sqrt(2.0 * budget / self.mass[top])
            speed = float(np.linalg.norm(state.velocity[top]))
            spin = float(np.linalg.norm(state.angular_velocity[top]))
            rotational = 0.5 * float(self.inertia[top]) * spin * spin
            own = 0.5 * float(self.mass[top]) * speed * speed + rotational
            # a couple gone wrong shows in the spin, not the speed (a plugin author's review)
            spinning = (f" and spins at {spin:.3g} rad/s ({100.0 * rotational / own:.3g} % of its kinetic energy "
                        f"{own:.3g} J rotational)" if own > 0.0 and rotational > 0.01 * own else "")
            return Fault("energy", top, (
                f"the kinetic energy {kinetic:.3g} J is {kinetic / budget:.3g} times the scene's energy budget "
                f"{budget:.3g} J (initial kinetic energy + work of gravity so far"
                + (f" + what adhesion can supply, {self.supply_budget:.3g} J" if self.supply_budget else
                   "; passive contacts cannot add energy") + f"); particle {name_of(top)} moves at {speed:.3g} m/s{spinning}, where "
                f"the budget allows at most {allowed:.3g} m/s")), gravity_work_max
        reach = (self.extent + REACH_FACTOR * math.sqrt(2.0 * budget / self.lightest) * time
                 + 0.5 * self.gravity_magnitude * time * time)
        if distance > reach:
            return Fault("domain", far, (
                f"particle {name_of(far)} left the domain: it is at {state.position[far].tolist()} m, {distance:.3g} m "
                f"outside the box spanned by the initial particles and the finite walls ({self.lower.tolist()} "
                f"to {self.upper.tolist()} m), farther than the scene's energy could carry any particle by "
                f"t = {time:.6g} s ({reach:.3g} m)")), gravity_work_max
        return None, gravity_work_max


@numba.njit(cache=True)
def survey_block(block, position, velocity, angular_velocity, force, torque, mass, inertia, initial_position,
                 gravity, lower, upper):
    """The particles of one block (``minidem.engine.integrate.block_particles``): (first
    particle with a non-finite value or -1, their kinetic energy J, the particle with the
    most of it and that energy, their work of gravity J, the particle farthest outside
    the box lower-upper and its distance m (<= 0 inside))."""
    kinetic, top, top_energy, work, far, distance = 0.0, -1, -1.0, 0.0, -1, -math.inf
    for p in block_particles(block, position.shape[0]):
        for k in range(3):
            if not (math.isfinite(position[p, k]) and math.isfinite(velocity[p, k])
                    and math.isfinite(angular_velocity[p, k]) and math.isfinite(force[p, k])
                    and math.isfinite(torque[p, k])):
                return p, kinetic, top, top_energy, work, far, distance
        energy = particle_kinetic_energy(p, mass, inertia, velocity, angular_velocity)
        kinetic += energy
        if energy > top_energy:
            top, top_energy = p, energy
        outside = -math.inf
        for k in range(3):
            work += mass[p] * gravity[k] * (position[p, k] - initial_position[p, k])
            outside = max(outside, lower[k] - position[p, k], position[p, k] - upper[k])
        if outside > distance:
            far, distance = p, outside
    return -1, kinetic, top, top_energy, work, far, distance


@numba.njit(cache=True)
def survey(position, velocity, angular_velocity, force, torque, mass, inertia, initial_position, gravity,
           lower, upper):
    """One pass over the particles: (first particle with a non-finite value or -1,
    kinetic energy J, the particle with the most of it, work of gravity J, the particle
    farthest outside the box lower-upper and its distance m (<= 0 inside)).

    Block by block (``survey_block``), the blocks' results combined in order, as
    ``survey_threads`` combines them: the same bits on one thread or several."""
    blocks = energy_blocks(position.shape[0])
    found = np.empty((blocks, 7))
    for block in range(blocks):
        _store(found, block, survey_block(block, position, velocity, angular_velocity, force, torque, mass,
                                          inertia, initial_position, gravity, lower, upper))
        if found[block, 0] >= 0.0:  # a non-finite value: _combine stops at this block
            break
    return _combine(found)


@numba.njit(cache=True, parallel=True)
def survey_threads(position, velocity, angular_velocity, force, torque, mass, inertia, initial_position, gravity,
                   lower, upper):
    """``survey`` with the blocks shared between the run's threads (the check between
    chunks of a threaded run: 9 ms serial at N = 1,000,000); the same result, bit for bit."""
    blocks = energy_blocks(position.shape[0])
    found = np.empty((blocks, 7))
    for block in numba.prange(blocks):
        _store(found, block, survey_block(block, position, velocity, angular_velocity, force, torque, mass,
                                          inertia, initial_position, gravity, lower, upper))
    return _combine(found)


@numba.njit(cache=True, inline="always")
def _store(found, block, result):
    # particle indices as float64: exact below 2^53
    bad, kinetic, top, top_energy, work, far, distance = result
    found[block, 0], found[block, 1], found[block, 2], found[block, 3] = bad, kinetic, top, top_energy
    found[block, 4], found[block, 5], found[block, 6] = work, far, distance


@numba.njit(cache=True)
def _combine(found):
    """The blocks' results in block order: the first non-finite particle, the sums in
    order, the first particle with the most energy and the first farthest out."""
    kinetic, top, top_energy, work, far, distance = 0.0, 0, -1.0, 0.0, 0, -math.inf
    for block in range(found.shape[0]):
        if found[block, 0] >= 0.0:
            return int(found[block, 0]), kinetic, top, work, far, distance
        kinetic += found[block, 1]
        if found[block, 3] > top_energy:
            top, top_energy = int(found[block, 2]), found[block, 3]
        work += found[block, 4]
        if found[block, 6] > distance:
            far, distance = int(found[block, 5]), found[block, 6]
    return -1, kinetic, top, work, far, distance


def contacts_of(state, particle: int, scenario_index=int) -> list[str]:
    """The partners particle ``particle`` touches (overlap > 0) in ``state``; other
    particles named by ``scenario_index`` of the row they are stored in (Scene.scenario_index)."""
    found = []
    plane_overlap, near_offsets, near_planes = state.planes[4:7]  # per near-plane entry
    row = slice(near_offsets[particle], near_offsets[particle + 1])
    found += [f"plane wall {w}" for w in near_planes[row][plane_overlap[row] > 0]]
    cylinder_overlap = state.cylinders[6]
    if cylinder_overlap.shape[1]:
        found += [f"cylinder wall {c}" for c in np.flatnonzero(cylinder_overlap[particle] > 0)]
    offsets, candidates, overlap = state.meshes[2], state.meshes[3], state.meshes[5]
    if candidates.shape[0]:
        row = slice(offsets[particle], offsets[particle + 1])
        found += [f"mesh triangle {t}" for t in candidates[row][overlap[row] > 0]]
    offsets, neighbours, _, overlap = state.pairs[:4]
    if neighbours.shape[0]:
        first = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        touching = overlap > 0
        partners = np.concatenate([neighbours[touching & (first == particle)],
                                   first[touching & (neighbours == particle)]])
        found += [f"particle {scenario_index(int(j))}" for j in np.sort(partners)]
    return found
