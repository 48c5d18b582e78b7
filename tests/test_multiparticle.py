"""Multi-particle physics: sphere-sphere contacts against the sphere-wall impact they
reduce to, conservation laws, restitution, a settling pile, VTK output, and the
per-contact history across neighbour-list rebuilds and thread counts."""

import copy
import ctypes
import math
import mmap
import platform
import sys
import xml.etree.ElementTree as ET

import numba
import numpy as np
import pytest

from conftest import contact_count, rk4_step
from minidem.results import analysis
from minidem.scene import scenario
from minidem.engine import blocks, integrate, simulation
from minidem.engine.run_loop import LoopThreads
from minidem.engine.state import _full_array, full_arrays

GLASS = {"youngs_modulus": 70e9, "poisson_ratio": 0.3, "density": 2650.0}
RADIUS, SPEED = 0.025, 5.0


def run(data):
    return simulation.Simulation(scenario.build_scene(copy.deepcopy(data))).run()


def two_spheres(law, angle_deg=0.0, extra=None, radii=(RADIUS, RADIUS), materials=("glass", "glass"),
                spin=((0, 0, 0), (0, 0, 0)), dt="auto"):
    """Spheres touching at t = 0 on the x axis, relative speed SPEED at angle_deg from -x,
    each carrying the share of it that leaves the centre of mass at rest."""
    theta = math.radians(angle_deg)
    relative = SPEED * np.array([math.cos(theta), math.sin(theta), 0.0])
    mass = [r**3 for r in radii]  # same density: mass ratio
    share = [mass[1] / sum(mass), -mass[0] / sum(mass)]
    return {
        "materials": {"glass": GLASS, "steel": {"youngs_modulus": 200e9, "poisson_ratio": 0.28, "density": 7800.0}},
        "contact": {"law": law, "friction": 0.3, **(extra or {})},
        "particles": [
            {"position": [-radii[0], 0.0, 0.0], "velocity": (share[0] * relative).tolist(), "radius": radii[0],
             "material": materials[0], "angular_velocity": list(spin[0])},
            {"position": [radii[1], 0.0, 0.0], "velocity": (share[1] * relative).tolist(), "radius": radii[1],
             "material": materials[1], "angular_velocity": list(spin[1])},
        ],
        "run": {"stop": "separation", "dt": dt},
        "output": {"vtk": False},
    }


def equivalent_wall_impact(law, angle_deg=0.0, extra=None, dt="auto"):
    """The sphere-wall impact with the pair's reduced radius R* = R/2 and mass m* = m/2:
    a sphere of radius R/2 and density 4x (so its inertia is that of a solid sphere
    too), on a wall of the same elastic constants, at the pair's relative velocity."""
    dense = dict(GLASS, density=4.0 * GLASS["density"])
    return {
        "materials": {"dense": dense},
        "contact": {"law": law, "friction": 0.3, **(extra or {})},
        "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "dense"}],
        "impact": {"material": "dense", "radius": RADIUS / 2, "speed": SPEED, "angle_deg": angle_deg},
        "run": {"dt": dt},
        "output": {"vtk": False},
    }


def test_head_on_collision_equals_the_reduced_wall_impact():
    # Normal impact: the relative motion obeys m* d'' = -F(d, d'; R*, m*) exactly, as the
    # wall impact of a sphere of radius R*, mass m* does. Elastic, both runs see the same
    # forces at the same steps, so en and the duration agree to round-off (measured
    # 4e-13 and 2e-13).
    pair = run(two_spheres("hm", 0.0, dt=1e-7))
    wall = run(equivalent_wall_impact("hm", 0.0, dt=1e-7))
    assert analysis.pair_rebound(pair)["en"] == pytest.approx(analysis.rebound(wall)["en"], rel=1e-9)
    duration_pair = pair.last_separation_time - pair.first_contact_time
    duration_wall = wall.last_separation_time - wall.first_contact_time
    assert duration_pair == pytest.approx(duration_wall, rel=1e-9)
    # and the Hertz duration itself (eq 13) with R*, m*
    elastic = run(two_spheres("hm", 0.0))
    mass = 4.0 / 3.0 * math.pi * RADIUS**3 * GLASS["density"]
    e_star = GLASS["youngs_modulus"] / (2 * (1 - GLASS["poisson_ratio"] ** 2))
    tc = 2.868 * ((mass / 2) ** 2 / (RADIUS / 2 * e_star**2 * SPEED)) ** 0.2
    assert elastic.last_separation_time - elastic.first_contact_time == pytest.approx(tc, rel=2e-3)


def test_a_pair_touching_at_the_start_that_parts_at_once_is_ended():
    # review: two spheres 2e-14 m apart (within the round-off of touch, 1e-9 of R_i + R_j)
    # and closing count as touching at t = 0 (touches_at_start); at 2e-9 m/s they are still
    # apart a step later, and the contact must end there: its overlap was stored at exactly
    # 0, and the end test read previous > 0, keeping its history and stored reaction (the
    # plane's test is >= for the same case)
    data = two_spheres("ls", 0.0, {"restitution": 0.5, "friction": 0.1, "calibration_speed": 1.0}, dt=1e-6)
    for sphere, sign in zip(data["particles"], (-1.0, 1.0)):
        sphere["position"][0] = sign * (RADIUS + 1e-14)
        sphere["velocity"] = [-sign * 1e-9, 0.0, 0.0]
    data["run"].update(stop="time", end_time=3e-6)
    sim = simulation.Simulation(scenario.build_scene(data))
    result = sim.run()
    # counted at the start: its dashpot's c v at zero overlap slowed the approach
    assert result.velocity[0, 0] < 1e-9
    offsets, partners, history, overlap, reaction, slot, reverse, in_use = sim.state.pairs[:8]
    assert overlap[0] < 0.0 and not history.any() and not in_use.any() and not reaction.any()


@pytest.mark.parametrize("law, within", [("hm", 1e-4), ("ls", 1e-5)])
def test_damped_head_on_collision_equals_the_reduced_wall_impact(law, within):
    # With a dashpot (e = 0.7) too: both laws are handed the velocity predicted at the
    # end of the step (kernel END_VELOCITY, the pair's from both spheres' last forces:
    # dv + dt F (1/m_i + 1/m_j) / 2 = dv + dt F / 2m*), and both contacts count from the
    # touch at t = 0 (touches_at_start: LS's dashpot force jumps to c v there), so the
    # same sums up to round-off (measured 3e-13 apart in en, 5e-13 of the duration, both
    # laws). Before the pair's prediction they were 3.4e-5 apart (hm), the pair's
    # first-order error. en itself is within its discretisation error of the requested
    # 0.7 (measured at 1,100 steps a contact: hm 4.0e-5, HM's dashpot, ~overlap^(1/4) at
    # the touch, converging at order ~1.25; ls 3.7e-7, its separation's kink)
    extra = {"restitution": 0.7}
    pair = run(two_spheres(law, 0.0, extra, dt=1e-7))
    wall = run(equivalent_wall_impact(law, 0.0, extra, dt=1e-7))
    assert analysis.pair_rebound(pair)["en"] == pytest.approx(analysis.rebound(wall)["en"], rel=1e-9)
    assert analysis.pair_rebound(pair)["en"] == pytest.approx(0.7, abs=within)
    duration_pair = pair.last_separation_time - pair.first_contact_time
    duration_wall = wall.last_separation_time - wall.first_contact_time
    assert duration_pair == pytest.approx(duration_wall, rel=1e-9)


def test_head_on_collision_of_unlike_spheres_lasts_the_hertz_time_of_their_effective_values():
    # Glass (R = 20 mm) on steel (R = 30 mm): Hertz between two finite moduli, E* =
    # 1 / ((1 - nu1^2)/E1 + (1 - nu2^2)/E2), R* = R1 R2 / (R1 + R2), m* = m1 m2 / (m1 + m2)
    # (the paper's eq 13 with these): every other pair test has like spheres or a rigid
    # wall, where one term of each sum is the other or zero. A mixed-up combination moves
    # tc by 4-23 % (E* of glass alone +17 %, of steel alone -23 %, R* = R1/2 +4 %, m* =
    # m1/2 -21 %); measured 9e-5 from the closed form, whose constant 2.868 is rounded
    # (the bound is the like-sphere test's); elastic, so en = 1.
    steel = {"youngs_modulus": 200e9, "poisson_ratio": 0.28, "density": 7800.0}
    radii = (0.02, 0.03)
    pair = run(two_spheres("hm", 0.0, radii=radii, materials=("glass", "steel")))
    e_star = 1.0 / ((1 - GLASS["poisson_ratio"] ** 2) / GLASS["youngs_modulus"]
                    + (1 - steel["poisson_ratio"] ** 2) / steel["youngs_modulus"])
    r_star = radii[0] * radii[1] / sum(radii)
    masses = [4.0 / 3.0 * math.pi * r**3 * m["density"] for r, m in zip(radii, (GLASS, steel))]
    m_star = masses[0] * masses[1] / sum(masses)
    tc = 2.868 * (m_star**2 / (r_star * e_star**2 * SPEED)) ** 0.2
    assert pair.last_separation_time - pair.first_contact_time == pytest.approx(tc, rel=2e-3)
    assert analysis.pair_rebound(pair)["en"] == pytest.approx(1.0, abs=1e-6)
    # the dashpot mapped from e with the pair's m* and its E*, R* (eq 13's variables):
    # the requested restitution within the 1 % of Chung & Ooi's test 3 (the wall tests;
    # measured 2e-6 to 1.5e-4 here; a dashpot coefficient with m1/2 for m* (0.55 of it)
    # would give en about 10-40 % high)
    for law in ("hm", "ls"):
        for restitution in (0.3, 0.7):
            damped = run(two_spheres(law, 0.0, {"restitution": restitution}, radii=radii, materials=("glass", "steel")))
            assert analysis.pair_rebound(damped)["en"] == pytest.approx(restitution, rel=1e-2), (law, restitution)


@pytest.mark.parametrize("angle_deg", [20.0, 45.0])
def test_oblique_collision_equals_the_reduced_wall_impact(angle_deg):
    # Tangentially the pair is the wall impact too (compliance 1/m1 + 1/m2 + R1^2/I1 +
    # R2^2/I2 = 7/(2 m*)), except that the line of centres turns during contact by about
    # Vt tc / (2R) and the pair's lever arms are R - d/2 instead of R: tolerances from
    # those two effects. The turning mixes the normal and tangential rebounds by at most
    # its angle (the mean normal lies within turn/2 of the first and of the last), the
    # shorter arms change the tangential compliance by d / 2R: tolerance turn + d / 2R,
    # 7.3e-3 at 20 deg and 1.1e-2 at 45 deg against gaps measured at 2.6e-3 and 5.4e-3
    # (it was 2 turn + d / R, loose enough at 45 deg for a friction of 0.2 in the pair
    # instead of 0.3 to pass).
    pair = run(two_spheres("hm", angle_deg, dt=1e-7))
    wall = run(equivalent_wall_impact("hm", angle_deg, dt=1e-7))
    tc = wall.last_separation_time - wall.first_contact_time
    turn = SPEED * math.sin(math.radians(angle_deg)) * tc / (2 * RADIUS)
    tolerance = turn + wall.max_overlap / (2 * RADIUS)
    got, want = analysis.pair_rebound(pair), analysis.rebound(wall)
    assert got["et"] == pytest.approx(want["et"], abs=tolerance)
    assert got["en"] == pytest.approx(want["en"], abs=tolerance)
    assert pair.last_separation_time - pair.first_contact_time == pytest.approx(tc, rel=1e-3)


def momenta(result, velocity, angular_velocity, position):
    scene = result.scene
    mass, inertia = scene.mass, scene.inertia
    linear = (mass[:, None] * velocity).sum(axis=0)
    angular = (np.cross(position, mass[:, None] * velocity) + inertia[:, None] * angular_velocity).sum(axis=0)
    return linear, angular


@pytest.mark.parametrize("law", ["hmd", "ls"])
def test_frictional_pair_conserves_momentum_and_angular_momentum(law):
    # Different radii, materials and spins, gross sliding then sticking: equal and
    # opposite forces, and lever arms summing to the centre distance, make both momenta
    # exact invariants of velocity Verlet; only round-off may change them.
    data = two_spheres(law, 35.0, {"normal_stiffness": 1e7} if law == "ls" else None, radii=(0.02, 0.03),
                       materials=("glass", "steel"), spin=((0.0, 50.0, 20.0), (10.0, 0.0, -30.0)))
    result = run(data)
    scene = result.scene
    assert result.first_contact_time >= 0 and result.separated
    p0, l0 = momenta(result, scene.velocity, scene.angular_velocity, scene.position)
    p1, l1 = momenta(result, result.velocity, result.angular_velocity, result.position)
    p_scale = np.sum(scene.mass * np.linalg.norm(scene.velocity, axis=1))
    l_scale = p_scale * 0.05 + np.sum(scene.inertia * np.linalg.norm(scene.angular_velocity, axis=1))
    assert np.all(np.abs(p1 - p0) <= 1e-13 * p_scale * result.steps ** 0.5)
    assert np.all(np.abs(l1 - l0) <= 1e-13 * l_scale * result.steps ** 0.5)
    # the collision did change each sphere's spin: the test is not trivially satisfied
    assert np.linalg.norm(result.angular_velocity - scene.angular_velocity) > 1.0


# Kernel variants (law, flags) are the test suite's main cost (~10-30 s of compilation
# each, cold): every impact here is frictional (mu = 0.3) so that it shares the SPIN
# variant of the collision tests and of the paper's tests, even at normal incidence,
# where the tangential force is zero and e is that of the normal law alone.
DAMPED_LAWS = ["ls", "hm", "hmd", "lth", "hmdns_integral", "hmdns_integral_reset"]


@pytest.mark.parametrize("law", DAMPED_LAWS)
def test_requested_restitution_is_reproduced_at_a_wall(law):
    # The dashpot is mapped from e (exactly for the linear spring, zeta = -ln e /
    # sqrt(pi^2 + ln^2 e); by the dimensionless Hertz-dashpot solution for the Hertz laws,
    # docs/laws.md): a normal impact must return e = 0.5 within 1 % (the figure).
    en = analysis.rebound(run(equivalent_wall_impact(law, 0.0, {"restitution": 0.5})))["en"]
    assert en == pytest.approx(0.5, rel=0.01)


@pytest.mark.parametrize("law", ["ls", "hm", "hmd"])
def test_requested_restitution_is_reproduced_between_two_spheres(law):
    # The same mapping with the pair's m* and R*. (The other Hertz laws share hm's normal
    # force function, hertz_normal_force, and the pair path is law-independent and equal
    # to the wall impact to round-off: test_head_on_collision_equals_the_reduced_wall_impact;
    # their pair kernels are not compiled here to save ~25 s each.)
    extra = {"restitution": 0.5}
    if law == "ls":
        extra["calibration_speed"] = SPEED  # eq 28 needs a speed; a pair has no [impact]
    en = analysis.pair_rebound(run(two_spheres(law, 0.0, extra)))["en"]
    assert en == pytest.approx(0.5, rel=0.01)


def test_an_unequal_pair_gives_the_mirrored_collision_when_mirrored_and_relabelled():
    # Physics is invariant under a reflection and under relabelling the bodies: the
    # oblique collision of a 10 mm and a 30 mm sphere, both spinning (sticking then
    # sliding), mirrored in x (positions and velocities x -> -x, spins, pseudovectors,
    # (wx, wy, wz) -> (wx, -wy, -wz)) and listed in the other order, must end in the
    # mirrored state. The engine evaluates a pair as (i, j > i), so the two runs hand the
    # small sphere the first role and then the second: a lever arm taken from the wrong
    # sphere (j's contact velocity with i's radius, R_i - d/2) gave 17 % in the velocities
    # and 150 % in the spins (a physics review's mutation, 2026-11-28, which no test
    # caught); the engine's evaluation is antisymmetric to the bit (measured 0.0).
    data = two_spheres("hm", 20.0, {"friction": 0.3, "restitution": 0.8}, radii=(0.01, 0.03),
                       spin=((0, 30, 200), (10, -50, -100)))
    mirror = np.array([-1.0, 1.0, 1.0])
    mirrored = copy.deepcopy(data)
    mirrored["particles"] = [dict(p, position=(np.array(p["position"]) * mirror).tolist(),
                                  velocity=(np.array(p["velocity"]) * mirror).tolist(),
                                  angular_velocity=(-np.array(p["angular_velocity"]) * mirror).tolist())
                             for p in reversed(data["particles"])]
    first, second = run(data), run(mirrored)
    assert first.contacts == 0 and first.steps > 1000  # a collision, run to separation
    velocity, spin = second.velocity[::-1] * mirror, -second.angular_velocity[::-1] * mirror
    assert np.abs(first.velocity - velocity).max() <= 1e-12 * np.abs(first.velocity).max()
    assert np.abs(first.angular_velocity - spin).max() <= 1e-12 * np.abs(first.angular_velocity).max()
    # and the collision did exchange spin (the sphere's 200 rad/s about z lost ~40)
    assert np.abs(first.angular_velocity[0] - data["particles"][0]["angular_velocity"]).max() > 10.0


# ---------------------------------------------------------------------------------
# History carried into the current tangent plane (docs/laws.md, "How history follows a
# contact"): exercised with the engine's own geometry and the law's force function.
# ---------------------------------------------------------------------------------
def _rotate(vector, axis, angle):
    """Rodrigues' rotation of vector about the unit axis."""
    return (vector * math.cos(angle) + np.cross(axis, vector) * math.sin(angle)
            + axis * np.dot(axis, vector) * (1.0 - math.cos(angle)))


@pytest.mark.parametrize("law_name", DAMPED_LAWS)
def test_rigidly_rotating_contact_keeps_its_tangential_force(law_name):
    # Two touching spheres are first sheared (sphere i slides along t under a fixed
    # overlap), then turned as one rigid body through 90 deg about an axis normal to the
    # line of centres: every contact point then moves with the pair, the relative
    # tangential velocity is zero, and an objective law must return the same tangential
    # force magnitude, turned with the pair. The normal (line of centres) turns, so a
    # history left in the old tangent plane would tilt out of the new one.
    from minidem.geometry import primitives as contact

    extra = {"friction": 1.0, **({"calibration_speed": SPEED} if law_name == "ls" else {})}
    sim = simulation.Simulation(scenario.build_scene(two_spheres(law_name, extra=extra)))
    law = sim.law
    constants = sim.constants[sim.pair_row[0, 0]]
    offsets = np.array(law.vector_history_offsets, dtype=np.int64)
    history = np.zeros(law.history_size)
    radius, mass = RADIUS, float(sim.scene.mass[0])
    effective_radius, effective_mass = radius / 2, mass / 2
    overlap = 2e-5  # m: a 1 kN contact for these glass spheres
    lever = radius - overlap / 2
    dt = 1e-7
    normal, tangent = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])

    def contact_force(normal, previous_normal, v_i, w_i, v_j, w_j, overlap_increment):
        # as the kernel evaluates a pair contact (contact_response)
        approach, vt = contact.pair_contact_velocity(*v_i, *w_i, *v_j, *w_j, lever, lever, *normal)
        seen = contact.seen_from(tuple(previous_normal), tuple(normal))
        for offset in offsets:
            contact.turn_slot(history, offset, seen, tuple(normal))
        increment = contact.turned_increment(vt, approach, seen, tuple(normal), tuple(lever * (w_i + w_j)), dt)
        fn, ftx, fty, ftz = law.force(constants, effective_radius, effective_mass, overlap, overlap_increment,
                                      approach, increment, vt, history)
        return fn, np.array([ftx, fty, ftz])

    zero = np.zeros(3)
    contact_force(normal, normal, zero, zero, zero, zero, overlap)  # first touch at the final overlap
    for _ in range(200):  # shear: 200 steps at 1 mm/s, well inside the Coulomb limit
        fn, ft = contact_force(normal, normal, 1e-3 * tangent, zero, zero, zero, 0.0)
    loaded = ft.copy()
    assert 0 < np.linalg.norm(loaded) < 0.5 * fn, "the spring must be loaded and sticking"
    axis = np.cross(normal, tangent) + tangent  # normal to the line of centres, tilted
    axis /= np.linalg.norm(axis)
    steps = 1000  # 90 deg in 1000 steps of dt
    angle_step = (math.pi / 2) / steps
    spin = axis * angle_step / dt
    for k in range(1, steps + 1):
        n = _rotate(normal, axis, k * angle_step)
        centre_i, centre_j = (radius - overlap / 2) * n, -(radius - overlap / 2) * n
        fn, ft = contact_force(n, _rotate(normal, axis, (k - 1) * angle_step), np.cross(spin, centre_i), spin,
                               np.cross(spin, centre_j), spin, 0.0)
    magnitude = np.linalg.norm(loaded)
    assert abs(np.dot(ft, n)) <= 1e-9 * magnitude  # in the current tangent plane
    # turned with the pair, its length kept: the history's turn (turn_slot) is off by the
    # fourth power of the step's angle over 8, 1000 (pi/2 / 1000)^4 / 8 = 8e-10 of the
    # force at most over the turn; measured 2.7e-10 (the projection and rescale the engine
    # used before, off by the square a step: 6.2e-4)
    assert np.linalg.norm(ft) == pytest.approx(magnitude, rel=1e-8)
    assert np.linalg.norm(ft - _rotate(loaded, axis, math.pi / 2)) <= 1e-8 * magnitude


def _passing_displacement(steps, turn_exactly=True):
    """Sphere i approaching a fixed sphere j along a straight line, (x, p, 0) with x from
    -p to 0 at speed V, without spin: its contact normal turns through 45 deg while its
    distance falls. The tangential displacement stored at the end when
    every step is evaluated as the kernel evaluates a pair contact (the drift moves i
    along the line exactly, so nothing else is discretised), and its exact value.
    ``turn_exactly`` False: the projection and the end-of-step increment the engine used
    before (LAMMPS' and LIGGGHTS' convention)."""
    from minidem.geometry import primitives as contact

    offset, speed = 0.02, 5.0
    dt = offset / speed / steps
    velocity = np.array([speed, 0.0, 0.0])
    history = np.zeros(3)
    for k in range(1, steps + 1):
        before = np.array([-offset + speed * dt * (k - 1), offset, 0.0])
        now = np.array([-offset + speed * dt * k, offset, 0.0])
        n, previous_n = now / np.linalg.norm(now), before / np.linalg.norm(before)
        approach, vt = contact.pair_contact_velocity(*velocity, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                                     0.0, 0.0, *n)
        if turn_exactly:
            seen = contact.seen_from(tuple(previous_n), tuple(n))
            contact.turn_slot(history, 0, seen, tuple(n))
            history += contact.turned_increment(vt, approach, seen, tuple(n), (0.0, 0.0, 0.0), dt)
        else:
            length = np.linalg.norm(history)
            history -= np.dot(history, n) * n
            if length > 0.0:
                history *= length / np.linalg.norm(history)
            history += np.array(vt) * dt
    # A displacement kept in the tangent plane and turned with it (minimally: about z)
    # is s t, t = z x n = (-p, x, 0) / |r|, with ds/dt = v . t = -V p / |r|:
    # s = -p integral of dx / sqrt(x^2 + p^2) = -p asinh(1) from x = -p to 0, where t
    # is (-1, 0, 0)
    return history, np.array([offset * math.asinh(1.0), 0.0, 0.0])


def test_turning_pair_contact_stores_its_displacement_at_second_order_in_the_step():
    # The kernel's turn of the history and its mid-step increment converge to the exact
    # displacement at second order (the error falls 4x a halving of the step); the
    # end-of-step increment they replaced converges at first (its error, in proportion to
    # the normal velocity, cancels only where an approach is followed by as fast a
    # recession: why the rebound of an elastic oblique pair collision converged at
    # 1.4-1.5 with it, docs/time-step.md)
    errors, old_errors = [], []
    for steps in (100, 200, 400, 800):
        stored, exact = _passing_displacement(steps)
        errors.append(np.linalg.norm(stored - exact) / np.linalg.norm(exact))
        stored, _ = _passing_displacement(steps, turn_exactly=False)
        old_errors.append(np.linalg.norm(stored - exact) / np.linalg.norm(exact))
    orders = [math.log2(errors[k] / errors[k + 1]) for k in range(len(errors) - 1)]
    old_orders = [math.log2(old_errors[k] / old_errors[k + 1]) for k in range(len(old_errors) - 1)]
    assert all(1.9 < order < 2.1 for order in orders), orders
    assert all(0.9 < order < 1.1 for order in old_orders), old_orders
    assert errors[-1] < 0.01 * old_errors[-1]  # measured: 2.1e-7 against 2.1e-4 at 800 steps


def test_spinning_pair_in_compression_converges_at_second_order_with_its_growing_lever_arms():
    # Head-on pair, both spheres spinning at 20 rad/s about y, sticking (mu = 10): the
    # contact point slips at (R_i - d/2) w_i + (R_j - d/2) w_j, and the arms shrink as
    # the overlap d grows. The kernel takes the step's increment with the arms of the
    # step's middle (a quarter of the step's overlap increment longer than at its end);
    # taken with the end's arms, the increment is off by n x (dd/4)(w_i + w_j) dt, an
    # error of first order. Stopped at 60 us, inside the contact (tc ~ 130 us), so that
    # no separation straddled by a step adds its own error: the differences between
    # halvings of the step must fall 4x. Measured 1.99 and 1.99; with the end's arms
    # (a mutation of the kernel, 2026-11-28) 1.48 and 1.32, falling towards 1.
    end_time = 6.0e-5
    finals = []
    for steps in (600, 1200, 2400, 4800):
        data = two_spheres("hm", 0.0, {"friction": 10.0}, spin=((0.0, 20.0, 0.0), (0.0, 20.0, 0.0)),
                           dt=end_time / steps)
        data["run"].update(stop="time", end_time=end_time)
        result = run(data)
        assert result.steps == steps and result.contacts == 1  # still in contact
        finals.append(np.concatenate([result.angular_velocity[:, 1], result.velocity[:, 2]]))
    # the spins (rad/s) and the velocities along z (m/s) each
    for columns in (slice(0, 2), slice(2, 4)):
        differences = [np.abs(finals[k][columns] - finals[k + 1][columns]).max() for k in range(len(finals) - 1)]
        orders = [math.log2(differences[k] / differences[k + 1]) for k in range(len(differences) - 1)]
        assert all(1.9 < order < 2.1 for order in orders), (columns, orders)
    # the tangential force was not negligible: the spins fell (20 -> ~19 rad/s) and the
    # spheres moved apart along z
    assert abs(finals[-1][0] - 20.0) > 0.1 and abs(finals[-1][2]) > 1e-3


# ---------------------------------------------------------------------------------
# The settle scene (the benchmark of /work/shared/bench/settle.md)
# ---------------------------------------------------------------------------------
# run.threads = 1: the PARALLEL kernel variant on one thread (no barrier between two
# threads per loop, which on a loaded 2-core machine can cost more than the loop).
ONE_THREAD = ["run.threads=1", "output.vtk=false"]


def test_settle_benchmark_scene_comes_to_rest_inside_the_box():
    # The scene exactly as benchmarked (N = 2,000, jitter, 10,000 steps of 2e-5 s):
    # kinetic energy below 1e-6 of its peak at the end, nobody below the floor or outside
    # the walls (overlaps a small fraction of the radius).
    scene = scenario.load_scene("scenarios/bench/settle.toml", ONE_THREAD)
    settled = simulation.Simulation(scene).run()
    assert settled.steps == 10_000 and scene.n_particles == 2000
    peak = settled.energy[:, 1].max()
    assert peak > 0
    assert settled.energy[-1, 1] < 1e-6 * peak
    radius, position = scene.radius, settled.position
    tolerance = 0.05 * radius
    assert np.all(position[:, 2] - radius > -tolerance), "below the floor"
    for axis in (0, 1):
        assert np.all(position[:, axis] - radius > -tolerance)
        assert np.all(position[:, axis] + radius < 0.1 + tolerance)


# A deeper pile: 300 spheres (9 x 9 per layer, ~4 layers) in a 20 mm box, with jitter,
# so the layers land off-centre on each other and the pile collapses sideways.
DEEP_PILE = ["fill.0.count=300", "walls.0.upper=[0.02, 0.02, 1.0]", "fill.0.upper=[0.02, 0.02, 1.0]"]


def test_deep_pile_comes_to_rest_except_its_loose_spheres():
    # The built-in laws (the paper's) have no rolling or twisting resistance and, apart
    # from the normal dashpot, no tangential damping: a sphere rolling without slip on the
    # floor, or round a neighbour, or rocking on its undamped tangential spring,
    # dissipates nothing, and the pile's kinetic energy levels off (measured: ~1e-4 of
    # the peak after 0.5 s, 99.9 % of it in 8 of the 300 spheres, each on the floor with
    # at most one neighbour; docs/multi-particle.md). What must hold: the energy falls by
    # more than 1e3, the spheres held by three or more contacts (the pile itself) are at
    # rest to 1e-6 of the peak, and what is left is in the loose ones.
    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE + ["run.end_time=0.5"] + ONE_THREAD)
    sim = simulation.Simulation(scene)
    result = sim.run()
    peak = result.energy[:, 1].max()
    assert result.energy[-1, 1] < 1e-3 * peak
    energy = 0.5 * scene.mass * (result.velocity ** 2).sum(axis=1) \
        + 0.5 * scene.inertia * (result.angular_velocity ** 2).sum(axis=1)
    held = contact_count(sim.state) >= 3
    assert held.sum() > 0.8 * scene.n_particles
    assert energy[held].sum() < 1e-6 * peak
    assert energy[~held].sum() > 0.9 * energy.sum()
    radius, position = scene.radius, result.position
    assert np.all(position[:, 2] - radius > -0.05 * radius), "below the floor"
    for axis in (0, 1):
        assert np.all(position[:, axis] - radius > -0.05 * radius)
        assert np.all(position[:, axis] + radius < 0.02 + 0.05 * radius)


def test_settle_pile_with_rolling_and_twisting_resistance_comes_to_rest():
    # scenarios/settle.toml, the pile a newcomer runs, at 300 spheres (the deep pile's
    # size, ~4 layers) for 0.4 s: with rolling (EPSD) and twisting (SDS) resistance the
    # modes the test above leaves alive (rolling on the floor or round a neighbour,
    # spinning about the normal) are dissipated too, and the kinetic energy falls below
    # 1e-8 of its peak (issue 14; measured 8.8e-20 at 0.375 s, where the paper's laws alone
    # stay near 1e-4). Nobody below the floor or outside the box.
    scene = scenario.load_scene("scenarios/settle.toml", ["fill.0.count=300", "run.end_time=0.4"] + ONE_THREAD)
    sim = simulation.Simulation(scene)
    result = sim.run()
    # the combination is inlined into the kernel's tile of pair contacts (vector code) and
    # called at walls as its force_alone: its inlined force is never compiled as a call
    # (minidem.contact.compose)
    assert sim.law.force_alone is not None and sim.law.force.signatures == []
    peak = result.energy[:, 1].max()
    assert peak > 0
    assert result.energy[-1, 1] < 1e-8 * peak
    radius, position = scene.radius, result.position
    assert position[:, 2].max() > 6 * radius[0]  # a pile of several layers, not a floor
    assert np.all(position[:, 2] - radius > -0.05 * radius), "below the floor"
    for axis in (0, 1):
        assert np.all(position[:, axis] - radius > -0.05 * radius)
        assert np.all(position[:, axis] + radius < 0.02 + 0.05 * radius)


def test_history_survives_neighbour_list_rebuilds_bit_for_bit():
    # A skin of 10 um rebuilds the list every few steps while spheres are in sustained
    # frictional contact; with a 20 mm skin it is built once. Contacts, their order of
    # summation and their carried history are identical, so are the trajectories.
    base = DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.06"] + ONE_THREAD
    results = {}
    for skin in (1e-5, 2e-2):
        scene = scenario.load_scene("scenarios/bench/settle.toml", base + [f"run.skin={skin}"])
        results[skin] = simulation.Simulation(scene).run()
    many, once = results[1e-5], results[2e-2]
    assert many.neighbour_builds > 100 and once.neighbour_builds == 1
    assert many.contacts > 100  # sustained contacts, with tangential history
    assert np.array_equal(many.position, once.position)
    assert np.array_equal(many.angular_velocity, once.angular_velocity)


def sliding_row(skin):
    """20 spheres (enough for the parallel kernel, 3 R apart: no pair touches) resting on
    the floor z = 0 and sliding along +x at V0 without spin, a plane x = 0 behind them."""
    radius = 1e-3
    return {
        "materials": {"beads": {"youngs_modulus": 5e6, "poisson_ratio": 0.3, "density": 2500.0}},
        "contact": {"law": "hm", "friction": 0.5, "restitution": 0.5},
        "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "beads"},
                  {"point": [0.0, 0.0, 0.0], "normal": [1.0, 0.0, 0.0], "material": "beads"}],
        "particles": [{"position": [0.01, 3 * radius * k, radius], "velocity": [SLIDE_SPEED, 0.0, 0.0],
                       "radius": radius, "material": "beads"} for k in range(20)],
        "run": {"dt": 2e-5, "stop": "time", "end_time": 0.02, "gravity": [0.0, 0.0, -9.81], "skin": skin,
                "threads": 1},
        "output": {"vtk": False},
    }


SLIDE_SPEED = 0.05  # m/s


def test_sliding_sphere_keeps_its_wall_contact_history_across_list_builds():
    # Plane contacts are kept per entry of the list of planes near each sphere, made anew
    # at every list build; the entry for the same (sphere, plane) takes over the old one's
    # tangential history and last overlap (State.list_near_planes). Spheres sliding on the
    # floor turn to rolling within 2 V0 / (7 mu g) = 3 ms and roll on, their Mindlin
    # springs loaded: a skin of 10 um rebuilds the lists ~140 times meanwhile. Against a
    # list built once (20 mm skin) and the tracked serial kernel (every plane of every
    # sphere every step, no list of near planes; its dashpots reading the drift's
    # velocity, as the multi-particle path's do): the same bits. A history lost or
    # mismatched at a build would change the friction force at once.
    results, states = {}, {}
    tracked = {"PARALLEL": False, "END_VELOCITY": False}
    for name, skin, flags in (("rebuilt", 1e-5, None), ("once", 2e-2, None), ("tracked", 1e-5, tracked)):
        sim = simulation.Simulation(scenario.build_scene(copy.deepcopy(sliding_row(skin))), kernel_flags=flags)
        results[name], states[name] = sim.run(), sim.state
    rebuilt = results["rebuilt"]
    assert rebuilt.neighbour_builds > 100 and results["once"].neighbour_builds == 1
    # the parallel kernel lists the floor alone; the tracked one both planes for every sphere
    assert states["rebuilt"].planes[3].shape[0] == 20 and states["tracked"].planes[3].shape[0] == 40
    assert np.count_nonzero(states["rebuilt"].planes[3].any(axis=1)) == 20  # every floor contact holds history
    for other in ("once", "tracked"):
        for quantity in ("position", "velocity", "angular_velocity"):
            assert np.array_equal(getattr(rebuilt, quantity), getattr(results[other], quantity)), (other, quantity)
    # physics: friction, the only horizontal force, acts at the contact point with the
    # lever arm R (the kernel's, paper eqs 3-8), so m v + I w / R is conserved: for a solid
    # sphere v + 2/5 w R = V0, to round-off
    radius = 1e-3
    v, spin = rebuilt.velocity[:, 0], rebuilt.angular_velocity[:, 1] * radius
    assert v + 0.4 * spin == pytest.approx(SLIDE_SPEED, rel=1e-9)
    # and rolling (v = w R) at the rigid-body result 5/7 V0, up to the oscillation of the
    # elastic tangential spring about it (0.4 % measured)
    assert v == pytest.approx(5.0 / 7.0 * SLIDE_SPEED, rel=1e-2)
    assert spin == pytest.approx(5.0 / 7.0 * SLIDE_SPEED, rel=2e-2)


def test_spheres_far_from_a_plane_skip_it_and_nothing_changes(monkeypatch):
    # Between list builds the kernel checks only the planes within radius + skin (+ reach)
    # of each sphere at the last build (neighbours.near_planes): a sphere moves less than
    # half the skin before the next build, so a skipped plane exerts no force. Against
    # every plane for every sphere: the same bits, and most checks skipped.
    from minidem.geometry import neighbours

    base = DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.03"] + ONE_THREAD
    listed = []
    real = neighbours.near_planes

    def counted(positions, radii, point, normal, margin):
        offsets, planes = real(positions, radii, point, normal, margin)
        listed.append((planes.shape[0], positions.shape[0] * point.shape[0]))
        # brute force: every listed plane is within radius + margin, every other is not
        distance = np.einsum("iwk,wk->iw", positions[:, None, :] - point[None], normal)
        near = distance < radii[:, None] + (np.inf if margin is None else margin)
        rows = np.repeat(np.arange(positions.shape[0]), np.diff(offsets))
        assert np.array_equal(np.argwhere(near), np.column_stack([rows, planes]))
        return offsets, planes

    monkeypatch.setattr(neighbours, "near_planes", counted)
    scene = scenario.load_scene("scenarios/bench/settle.toml", base)
    skipping = simulation.Simulation(scene).run()
    assert skipping.contacts > 50 and skipping.neighbour_builds > 1
    assert max(n for n, _ in listed[1:]) < 0.5 * listed[0][1]  # after the first build: half the checks or fewer
    monkeypatch.setattr(neighbours, "near_planes", lambda p, r, point, normal, margin: counted(p, r, point, normal,
                                                                                              None))
    every = simulation.Simulation(scenario.load_scene("scenarios/bench/settle.toml", base)).run()
    assert np.array_equal(skipping.position, every.position)
    assert np.array_equal(skipping.velocity, every.velocity)
    assert np.array_equal(skipping.angular_velocity, every.angular_velocity)


def small_pile():
    """The simulation of a pile of 100 spheres, run on one thread to 0.03 s (pair and
    wall contacts touching, some sheared, some ended)."""
    sim = simulation.Simulation(scenario.load_scene(
        "scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.03"] + ONE_THREAD))
    sim.run()
    return sim


def test_last_good_copy_keeps_the_touching_contacts_rows_and_gives_every_bit_back():
    # The last good state (State.capture) keeps, of the per-contact histories and
    # reactions, only the rows that are not all zero. A contact that ends drops its
    # history and its reaction, and one that never touched has none: so the rows kept
    # must be touching contacts (overlap > 0; this law has no reach), and expanding the
    # copy must give the live arrays back bit for bit (-0.0 included), also after the
    # live state has been overwritten (State.restore, as a failure does).
    sim = small_pile()
    state = sim.state
    copy_ = state.capture()
    live = {"pair_history": state.pairs[2], "pair_reaction": state.pairs[4], "plane_history": state.planes[3]}
    pair_touching = state.pairs[3] > 0.0
    reaction_touching = np.zeros_like(pair_touching)  # reactions are stored at each entry's slot
    reaction_touching[state.pairs[5]] = pair_touching
    touching = {"pair_history": pair_touching, "pair_reaction": reaction_touching,
                "plane_history": state.planes[4] > 0.0}
    for name, array in live.items():
        rows = copy_[name + "@rows"]
        assert name not in copy_ and 0 < len(rows) <= touching[name].sum()
        assert touching[name][rows].all(), f"{name}: a row kept for a contact that does not touch"
        assert copy_[name + "@values"].nbytes < array.nbytes
    saved = {name: array.copy() for name, array in full_arrays(copy_).items() if name != "builds"}
    state.pairs[2][...] = -0.0
    state.planes[3][...] = np.nan
    state.restore(copy_)
    restored = {name: _full_array(state.capture(), name) for name in saved}
    for name, array in saved.items():
        assert np.array_equal(array.view(np.uint8), restored[name].view(np.uint8)), name


@pytest.mark.parametrize("fails_in", ["build_lists", "rows_in_use"])
def test_a_list_build_that_fails_leaves_a_state_the_last_good_copy_restores(monkeypatch, fails_in):
    # Simulation.rebuild puts the old list back when the build fails (out of memory, an
    # interrupt), for the restore a failure does: also when it fails taking the old
    # histories' rows in use (the review's find: the list was gone then). The rest of the
    # pair tuple is gone then; State.restore must make it again, the same bits as a
    # restore of the intact state, and the run must go on from there as from the copy.
    sim = small_pile()
    state = sim.state
    copy_ = state.capture()
    intact = copy.deepcopy(state)
    intact.restore(copy_)

    def out_of_memory(*args, **kwargs):
        raise MemoryError
    monkeypatch.setattr(*((state, "build_lists") if fails_in == "build_lists" else (simulation, "rows_in_use")),
                        out_of_memory)
    with pytest.raises(MemoryError):
        sim.rebuild(state)
    monkeypatch.undo()
    for left, expected in zip(state.pairs[:4], intact.pairs[:4]):  # the old list, its histories bit for bit
        assert left.dtype == expected.dtype and left.tobytes() == expected.tobytes()
    state.restore(copy_)
    assert len(state.pairs) == len(intact.pairs)
    for restored, expected in zip(state.pairs, intact.pairs):
        assert restored.dtype == expected.dtype and np.array_equal(restored, expected)
    # and a list build from there gives what it gives from the intact state
    sim.rebuild(state)
    sim.rebuild(intact)
    assert state.pairs[1].shape[0] > 0
    for built, expected in zip(state.pairs, intact.pairs):
        assert np.array_equal(built, expected)


def resident_pages(array):
    """How many of the memory pages under ``array`` are resident (mincore, Linux)."""
    start = array.__array_interface__["data"][0] // mmap.PAGESIZE * mmap.PAGESIZE
    length = array.__array_interface__["data"][0] + array.nbytes - start
    flags = (ctypes.c_ubyte * -(-length // mmap.PAGESIZE))()
    assert ctypes.CDLL(None).mincore(ctypes.c_void_p(start), ctypes.c_size_t(length), flags) == 0
    return sum(flag & 1 for flag in flags)


def test_a_one_thread_run_stores_the_pairs_forces_and_never_the_partners_torques():
    # finish_kick_drift alone reads the torque a pair gives its partner (State.pair_arrays:
    # kept apart from the force). On one thread every particle is finished in the force
    # pass, so nothing writes those rows and their pages are never resident (24 bytes a
    # list entry of a pile, docs/multi-particle.md "Memory"); the forces are stored at the
    # call's last step, for the contact forces of the state the run sees. Two threads
    # read the torques they store: test_same_bits_on_one_and_two_threads.
    sim = small_pile()
    offsets, partners, history, overlap, reaction, slot = sim.state.pairs[:6]
    partner_torque = sim.state.pairs[9]
    touching = overlap > 0.0
    assert touching.sum() > 20 and np.abs(history[touching]).max() > 0.0  # sheared contacts: torques on both
    if sys.platform == "linux":  # on pages of their own (State.untouched_zeros), none resident
        assert resident_pages(partner_torque) == 0
    assert partner_torque.shape == (partners.shape[0], 3) and not partner_torque.any()
    assert (reaction[slot[touching]] != 0.0).any(axis=1).all()
    assert not reaction[slot[~touching]].any()


def test_one_thread_stores_the_pairs_forces_only_where_the_run_reads_the_state():
    # The contact forces of touching pairs are stored (kernel.advance's store_reactions)
    # only at a state the run reads: a frame, a copy of the last good state, a checkpoint,
    # the end. Between a list build and such a state, on one thread, no reaction row is
    # written and (on a mapping of their own, State.untouched_zeros) none of their pages is
    # resident: 116 bytes a particle of the settled pile at 200,000 (docs/benchmarks.md,
    # "Reactions stored where they are read"). Frames every 0.01 s: their states hold
    # every touching pair's force.
    sim = simulation.Simulation(scenario.load_scene(
        "scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.03", "run.threads=1"]))
    unread, frames = [], []

    def progress(steps, total, contacts):
        offsets, partners, history, overlap, reaction, slot, _, in_use = sim.state.pairs[:8]
        touching = overlap > 0.0
        if touching.sum() > 5 and not in_use.any():
            unread.append(resident_pages(reaction) if sys.platform == "linux" else 0)

    def on_frame(time, state):
        overlap, reaction, slot = state.pairs[3], state.pairs[4], state.pairs[5]
        touching = overlap > 0.0
        frames.append((touching.sum(), bool((reaction[slot[touching]] != 0.0).any(axis=1).all())))

    sim.run(progress=progress, on_frame=on_frame)
    assert len(unread) >= 3 and max(unread) == 0, unread
    assert len(frames) == 4 and frames[-1][0] > 20 and all(stored for _, stored in frames), frames


def test_same_bits_on_one_and_two_threads(monkeypatch):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs two threads")
    # 0.012 s: the pile's first impacts (pair and wall contacts, rebuilds), kept short
    # because two threads meet at a barrier twice a step
    base = DEEP_PILE[1:] + ["fill.0.count=200", "run.end_time=0.012", "output.vtk=false"]

    def run(threads):
        return simulation.Simulation(scenario.load_scene("scenarios/bench/settle.toml",
                                                         base + [f"run.threads={threads}"])).run()

    # a scene this small runs its loops on one thread (one fused pass) whatever run.threads says
    small = run(2)
    assert small.threads == 1
    # lowered, so that 200 particles run the two-thread loops (blocks, separate finish
    # pass), and no chunk tries one thread instead (LoopThreads)
    monkeypatch.setattr(simulation, "PARALLEL_MIN_PARTICLES", 0)
    monkeypatch.setattr(LoopThreads, "PROBE_FIRST", 10**9)
    measured = []
    plain_measure = blocks.BlockTiming.measure
    monkeypatch.setattr(blocks.BlockTiming, "measure",
                        lambda timing, *args: measured.append(plain_measure(timing, *args)) or measured[-1])
    runs = [run(t) for t in (1, 2)]
    assert runs[0].threads == 1 and runs[1].threads == 2
    assert runs[1].contacts > 50
    if platform.machine() in ("x86_64", "AMD64"):
        # each block's force pass counted its cycles (the next call's blocks weigh them)
        assert len(measured) > 3 and all((cycles > 0).all() for cycles in measured[1:])
    for other in (runs[1], small):
        assert np.array_equal(runs[0].position, other.position)
        assert np.array_equal(runs[0].velocity, other.velocity)
        assert np.array_equal(runs[0].angular_velocity, other.angular_velocity)
        # the kinetic-energy samples the compiled loop takes (blocked sums) too
        assert np.array_equal(runs[0].energy, other.energy)


def test_a_threaded_run_keeps_its_freed_pages_between_list_builds_whatever_its_chunks_run_on(monkeypatch):
    # Simulation.rebuild gives the heap's free pages back (malloc_trim) in a run on one
    # thread only: a threaded run would fault them in again on both threads at the next
    # build (docs/multi-particle.md, "Memory"). The decision follows run.threads, not the
    # chunk: a threaded run's probes (LoopThreads) run some chunks on one thread.
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs two threads")
    trims = []
    monkeypatch.setattr(simulation, "release_free_memory", lambda: trims.append(1))
    monkeypatch.setattr(simulation, "PARALLEL_MIN_PARTICLES", 0)  # the scene and kernel of the test above
    monkeypatch.setattr(LoopThreads, "PROBE_FIRST", 1)
    base = DEEP_PILE[1:] + ["fill.0.count=200", "run.end_time=0.012", "output.vtk=false"]
    results = {}
    for threads in (1, 2):
        trims.clear()
        result = simulation.Simulation(scenario.load_scene("scenarios/bench/settle.toml",
                                                           base + [f"run.threads={threads}"])).run()
        results[threads] = (len(trims), result)
    one, two = results[1], results[2]
    assert one[0] == one[1].neighbour_builds >= 3
    assert two[0] == 0 and two[1].neighbour_builds >= 3
    assert set(two[1].thread_steps) == {1, 2}  # chunks on one thread and on two
    assert np.array_equal(one[1].position, two[1].position)


def test_a_sphere_with_more_contacts_than_a_tile_gets_all_their_reactions():
    # One large sphere (index 0: it owns every pair of its row) touching 600 small ones
    # spread evenly over its surface (a Fibonacci lattice), each just apart from it and
    # moving in at 1 m/s while sliding sideways: from the first step on, its row holds more than two tiles' worth of
    # contacts (kernel.TILE_CONTACTS), so its force is summed over three tiles
    # (settle_group's partial path). No gravity, no walls: the forces of the last step
    # must cancel (each pair's force on j is minus its force on i) to round-off, and the
    # torques balance the moments of the forces (lever arms sum to the centre distance),
    # so the momenta stay as they were. A tile's contacts lost or counted twice would
    # leave the large sphere hundreds of contact forces off.
    from minidem.engine import kernel

    n_small = 600
    assert n_small > 2 * kernel.TILE_CONTACTS
    big, small = 0.05, 0.002
    index = np.arange(n_small) + 0.5
    polar = np.arccos(1.0 - 2.0 * index / n_small)
    azimuth = math.pi * (1.0 + 5.0**0.5) * index
    direction = np.stack([np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1)
    centres = direction * (big + small) * (1.0 + 1e-12)
    tangent = np.cross(direction, [0.3, 0.5, 0.8])
    sliding = 0.1 * tangent / np.linalg.norm(tangent, axis=1)[:, None] - 1.0 * direction
    particles = [{"position": [0.0, 0.0, 0.0], "radius": big, "material": "glass",
                  "angular_velocity": [0.0, 0.0, 5.0]}]
    particles += [{"position": c.tolist(), "radius": small, "material": "glass", "velocity": v.tolist()}
                  for c, v in zip(centres, sliding)]
    data = {"materials": {"glass": GLASS}, "contact": {"law": "hm", "friction": 0.3},
            "particles": particles, "run": {"stop": "time", "end_time": 2e-6, "dt": 1e-7, "threads": 1},
            "output": {"vtk": False}}
    result = run(data)
    scene = result.scene
    assert result.steps == 20
    assert result.contacts == n_small  # every small sphere still touches the large one
    force, torque = result.force, result.torque
    # every contact pushes: the large sphere's share is large, and it is the whole sum
    scale = np.abs(force[1:]).sum()
    assert np.linalg.norm(force[1:], axis=1).min() > 0
    assert np.all(np.abs(force.sum(axis=0)) <= 1e-12 * scale)
    moments = np.cross(result.position, force).sum(axis=0) + torque.sum(axis=0)
    assert np.all(np.abs(moments) <= 1e-12 * scale * (big + small))
    p0, l0 = momenta(result, scene.velocity, scene.angular_velocity, scene.position)
    p1, l1 = momenta(result, result.velocity, result.angular_velocity, result.position)
    p_scale = np.sum(scene.mass * np.linalg.norm(scene.velocity, axis=1))
    assert np.all(np.abs(p1 - p0) <= 1e-13 * p_scale * result.steps)
    l_scale = p_scale * (big + small) + scene.inertia[0] * 5.0
    assert np.all(np.abs(l1 - l0) <= 1e-13 * l_scale * result.steps)


def test_energy_samples_taken_in_the_loop_are_the_kinetic_energy_at_their_step():
    # The kernel takes the run's kinetic-energy samples without returning to Python: each
    # particle's energy as it is finished (closing kick, before the next step's drift),
    # summed by fixed blocks. Reference: the state's kinetic energy computed from its
    # velocities after the step (integrate.kinetic_energy, the same block order), read
    # between chunks of one step each. The samples must be those values at those steps,
    # bit for bit, and a run cut into chunks differently must give the same series.
    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=60", "run.end_time=0.004"]
                                + ONE_THREAD)
    sim = simulation.Simulation(scene)
    after_step = {}

    def read(steps, total, contacts):
        after_step[steps] = integrate.kinetic_energy(scene.mass, scene.inertia, sim.state.velocity,
                                                     sim.state.angular_velocity)

    stepwise = sim.run(chunk_steps=1, progress=read)
    whole = simulation.Simulation(scene).run()
    assert np.array_equal(stepwise.energy, whole.energy)
    dt = sim.dt
    sampled = 0
    for time, energy in stepwise.energy[1:]:
        step = int(round(time / dt))
        assert energy == after_step[step], (step, energy, after_step[step])
        sampled += 1
    assert sampled >= 200 and stepwise.energy[:, 1].max() > 0.0


def test_touching_flags_follow_the_contacts():
    # The reaction gather reads only the rows flagged touching (reaction_in_use, in the
    # transposed order). After a run into the pile the flag of every listed pair must be
    # whether it touches (overlap > 0: hm has no reach), and a pair apart holds no reaction.
    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.03"]
                                + ONE_THREAD)
    sim = simulation.Simulation(scene)
    sim.run()
    offsets, partners, history, overlap, reaction, slot, reverse_offsets, in_use = sim.state.pairs[:8]
    touching = overlap > 0.0
    assert touching.sum() > 20 and (~touching).sum() > 20
    assert np.array_equal(in_use[slot] == 1, touching)
    assert not reaction[slot[~touching]].any()


def test_a_pair_whose_root_rounds_to_touch_is_apart(monkeypatch):
    # Whether a listed pair touches is decided on the squared distance; its overlap is
    # reach - sqrt(d^2). Within a rounding of touch the first says touching and the second
    # gives an overlap of exactly 0: such a pair must be apart (no force, its history and
    # stored reaction dropped), or its contact's end is never seen (the end test is
    # previous > 0) and the stored reaction stays flagged: a force on the partner alone
    # whenever finish_kick_drift finishes it (two threads), breaking momentum conservation
    # and the same bits on one and two threads (found by review; the case below has
    # d^2 < (2R)^2 and sqrt(d^2) == 2R at the first step; law ls, whose dashpot acts at
    # zero overlap). Expected: momentum conserved to round-off (no gravity, no walls) and
    # the same bits on 1 and 2 threads.
    radius, x, y = 0.0004288, 0.0008575999999999999, 1.0289757937229989e-11
    assert math.sqrt(x * x + y * y) == 2 * radius and x * x + y * y < (2 * radius) ** 2
    particles = [{"position": [0.0, 0.0, 0.0], "velocity": [0.0, 0.0, 0.0], "radius": radius, "material": "beads"}]
    particles += [{"position": [0.05 + 0.01 * k, 0.05, 0.0], "velocity": [0.0, 0.0, 0.0], "radius": radius,
                   "material": "beads"} for k in range(20)]
    particles += [{"position": [x, y, 0.0], "velocity": [-1e-5, 1.0, 0.0], "radius": radius, "material": "beads"}]
    monkeypatch.setattr(simulation, "PARALLEL_MIN_PARTICLES", 0)
    monkeypatch.setattr(LoopThreads, "PROBE_FIRST", 10**9)
    runs = []
    for threads in (1, 2):
        scene = scenario.build_scene({
            "materials": {"beads": {"youngs_modulus": 5e6, "poisson_ratio": 0.3, "density": 2500.0}},
            "contact": {"law": "ls", "friction": 0.5, "restitution": 0.5, "calibration_speed": 1.0},
            "particles": copy.deepcopy(particles),
            "run": {"dt": 1e-6, "stop": "time", "end_time": 60e-6, "gravity": [0.0, 0.0, 0.0], "threads": threads},
            "output": {"vtk": False}})
        sim = simulation.Simulation(scene)
        runs.append(sim.run(chunk_steps=20))
        in_use = sim.state.pairs[7]
        assert not in_use.any() and not sim.state.pairs[2].any()
        momentum = (scene.mass[:, None] * runs[-1].velocity).sum(axis=0)
        start = (scene.mass[:, None] * scene.velocity).sum(axis=0)
        # round-off: ~1e-16 of it a step, 60 steps; the phantom force was 5e-6 of it
        assert np.abs(momentum - start).max() < 1e-12 * np.abs(start).max()
    assert runs[1].threads == 2
    assert np.array_equal(runs[0].velocity, runs[1].velocity) and np.array_equal(runs[0].position, runs[1].position)


def test_second_pass_is_shared_evenly_between_the_threads():
    """The particles with a partner in an earlier block must wait for the second pass;
    each other block leaves as many of its last particles to it, so no thread waits
    alone there (kernel.defer_finishing). Which pass finishes a particle changes no bit:
    test_same_bits_on_one_and_two_threads runs it."""
    kernel = simulation.Simulation(scenario.load_scene(
        "scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=200", "output.vtk=false"])).kernel
    # three blocks of 6: block 1 has 3 particles listed by a row of block 0, block 2 has 1
    first_partner = np.arange(18)
    first_partner[[6, 7, 8]] = 2
    first_partner[13] = 9
    bounds = np.array([0, 6, 12, 18])
    kernel.defer_finishing(bounds, first_partner)
    second_pass = [[p for p in range(bounds[b], bounds[b + 1]) if first_partner[p] < bounds[b]] for b in range(3)]
    assert second_pass == [[3, 4, 5], [6, 7, 8], [13, 16, 17]]
    assert np.array_equal(first_partner[[6, 7, 8, 13]], [2, 2, 2, 9])  # the cross-block ones untouched


def test_a_scene_below_the_thread_threshold_gets_the_serial_untracked_kernel():
    """A scene too small for a second thread (PARALLEL_MIN_PARTICLES) runs on one thread
    whatever run.threads says, so it is given the serial kernel, without numba's
    parallel pipeline (a third of the CPU time of the first run of settle.toml), and
    without contact statistics (TRACK: the same output as the parallel kernel). The
    result is the same bits as the parallel kernel's on one thread: the same operations
    in the same order, only compiled differently."""
    base = DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.01", "output.vtk=false", "run.threads=2"]
    scene = scenario.load_scene("scenarios/bench/settle.toml", base)
    assert simulation.PARALLEL_ABOVE < scene.n_particles < simulation.PARALLEL_MIN_PARTICLES
    serial = simulation.Simulation(scene)
    assert serial.parallel and not serial.threaded  # the multi-particle path, serial loops
    assert serial.kernel.PARALLEL is False and serial.kernel.TRACK is False
    threaded = simulation.Simulation(scenario.load_scene("scenarios/bench/settle.toml", base),
                                     kernel_flags={"PARALLEL": True})
    assert threaded.kernel.PARALLEL is True and threaded.kernel.TRACK is False
    results = [sim.run() for sim in (serial, threaded)]
    assert results[0].contacts > 50 and results[0].threads == results[1].threads == 1
    assert not results[0].contact_statistics and not results[1].contact_statistics
    for name in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(getattr(results[0], name), getattr(results[1], name))


def test_one_thread_is_one_block_of_all_particles():
    # the blocks advance is given on one thread, chosen without compiled code; on two,
    # thread_blocks balances the work (test_same_bits_on_one_and_two_threads)
    list_first_partner = np.array([0, 1, 0, 3, 1, 2, 6])  # the list's (State.first_partner)
    bounds, first_partner, block_cycles = blocks.blocks(1, None, None, list_first_partner)
    assert bounds.tolist() == [0, 7] and first_partner is list_first_partner  # used as it is, not copied
    assert block_cycles.tolist() == [0]  # nothing to balance
    assert bounds.dtype == first_partner.dtype == np.int64


def test_loop_threads_keep_the_faster_count():
    # two threads allowed; one thread is measured faster (a loaded machine): the run
    # switches to it at the first probe, and probes two threads again later, ever more
    # rarely while they keep losing; when two win again it goes back to two
    chooser = LoopThreads(2)
    speed = {1: 1.0, 2: 3.0}  # seconds per 100 steps
    used = []
    for _ in range(200):
        threads = chooser.choose()
        used.append(threads)
        chooser.record(threads, 100, speed[threads])
    # the first probe right after the first chunk: on a loaded machine two threads can be
    # thirty times slower than one, and four chunks before it cost a review's run 3.9 of
    # its 14.3 s (docs/multi-particle.md, "Threads")
    assert used[:2] == [2, 1] and used[2:6] == [1] * 4
    probes = [k for k in range(10, 200) if used[k] == 2]
    assert 2 <= len(probes) <= 6 and probes[-1] - probes[-2] >= 32  # backing off
    assert chooser.most_used() == 1 and chooser.steps == {1: 100 * used.count(1), 2: 100 * used.count(2)}
    speed = {1: 1.0, 2: 0.6}
    for _ in range(2 * LoopThreads.PROBE_MAX + 2):
        threads = chooser.choose()
        chooser.record(threads, 100, speed[threads])
    assert chooser.current == 2
    # chunks cut short by a rebuild count their steps but decide nothing
    chooser.record(1, LoopThreads.MIN_STEPS - 1, 1e-9)
    assert chooser.current == 2
    assert LoopThreads(1).choose() == 1


def test_vtk_series_reads_back_with_meshio_and_vtk(tmp_path):
    # Every frame of particles.pvd holds all points with every array the issue lists
    # (checked with meshio and with VTK's own XML reader, ParaView's), walls.vtu the
    # box's 5 faces, and the contact network lines with a compressive normal force.
    import meshio
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from minidem.results.vtk import SimulationFrames

    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE[1:] + [
        "fill.0.count=100", "run.end_time=0.03", "output.interval=0.006", "output.contacts=true", "run.threads=1"])
    sim = simulation.Simulation(scene)
    frames = SimulationFrames(sim, tmp_path)
    sim.run(on_frame=frames)
    frames.close()
    datasets = ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")
    assert len(datasets) == 6  # t = 0 and 5 intervals
    assert [float(d.get("timestep")) for d in datasets] == pytest.approx([0.0, 0.006, 0.012, 0.018, 0.024, 0.03])
    arrays = {"radius": 1, "velocity": 3, "angular_velocity": 3, "force": 3, "particle_id": 1, "material_id": 1}
    for entry in datasets:
        path = tmp_path / entry.get("file")
        mesh = meshio.read(path)
        assert mesh.points.shape == (100, 3)
        for name, components in arrays.items():
            data = np.asarray(mesh.point_data[name])
            assert data.shape[0] == 100 and (data.size // 100) == components
        reader = vtk.vtkXMLUnstructuredGridReader()
        reader.SetFileName(str(path))
        reader.Update()
        grid = reader.GetOutput()
        assert grid.GetNumberOfPoints() == 100
        for name in arrays:
            assert grid.GetPointData().GetArray(name) is not None
        assert np.allclose(vtk_to_numpy(grid.GetPointData().GetArray("radius")), scene.radius)
    walls = meshio.read(tmp_path / "walls.vtu")
    wall_ids = np.concatenate(walls.cell_data["wall_id"])
    assert sorted(set(wall_ids.tolist())) == [0, 1, 2, 3, 4]  # the open box: 5 faces (triangle fans)
    contacts = sorted(tmp_path.glob("particles_contacts_*.vtu"))
    assert len(contacts) == 6
    # (meshio cannot read a grid with zero cells, such as the t = 0 network: last frame)
    last = meshio.read(contacts[-1])
    normal_force = np.concatenate(last.cell_data["normal_force"])
    # compressive on the whole (the damped Hertz force may pull slightly at unloading)
    assert len(normal_force) > 0 and np.all(np.isfinite(normal_force)) and normal_force.sum() > 0


def test_the_state_a_run_ends_in_is_always_a_frame(tmp_path):
    # review: with output.interval > run.end_time only t = 0 was written; and an interval
    # that does not divide the run lost its end. Frames: every interval, then the end.
    from minidem.results.vtk import SimulationFrames

    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE[1:] + [
        "fill.0.count=100", "run.end_time=0.01", "output.interval=0.006", "run.threads=1"])
    sim = simulation.Simulation(scene)
    frames = SimulationFrames(sim, tmp_path)
    result = sim.run(on_frame=frames)
    frames.close()
    datasets = ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")
    assert [float(d.get("timestep")) for d in datasets] == pytest.approx([0.0, 0.006, result.time])
    assert result.time == pytest.approx(0.01, abs=scene.dt if scene.dt else 1e-6)
    import meshio

    last = meshio.read(tmp_path / datasets[-1].get("file"))
    assert np.array_equal(last.points, result.position)



def test_a_parallel_run_reports_unrecorded_contact_peaks_as_null():
    # review: summary.json said max_overlap_m = 0 and peak_normal_force_n = 0 for a
    # 200-particle settle whose final state had overlaps; the parallel loop does not
    # record peaks (a race between threads), so they are unknown, not zero
    from minidem.results import analysis

    scene = scenario.load_scene("scenarios/bench/settle.toml", DEEP_PILE[1:] + ["fill.0.count=100", "run.end_time=0.02"])
    result = simulation.Simulation(scene, kernel_flags={"PARALLEL": True}).run()  # whatever the size threshold
    summary = analysis.summary(result)
    assert not result.contact_statistics and result.contacts > 0
    assert summary["max_overlap_m"] is None and summary["peak_normal_force_n"] is None
    assert summary["peak_tangential_force_n"] is None


def _deepest_now(position, radius, box):
    """(the deepest overlap m, the largest overlap over a contact's smaller radius, the
    deepest contact's own ratio) in a state, by brute force: every pair and the open box's
    five planes (x, y = 0 and box, z = 0), each maximum over all contacts."""
    separation = np.linalg.norm(position[:, None, :] - position[None, :, :], axis=2)
    pair = radius[:, None] + radius[None, :] - separation
    np.fill_diagonal(pair, -np.inf)
    smaller = np.minimum(radius[:, None], radius[None, :])
    walls = np.stack([radius - position[:, 0], radius - position[:, 1], radius - position[:, 2],
                      radius - (box - position[:, 0]), radius - (box - position[:, 1])], axis=1)
    deepest = max(pair.max(), walls.max(), 0.0)
    ratio = max((pair / smaller).max(), (walls / radius[:, None]).max(), 0.0)
    if pair.max() >= walls.max():
        own = pair.max() / smaller.flat[np.argmax(pair)]
    else:
        own = walls.max() / radius[np.unravel_index(np.argmax(walls), walls.shape)[0]]
    return deepest, ratio, max(own, 0.0)


def test_a_pile_of_unlike_spheres_reports_its_deepest_overlaps_at_the_checks():
    # A pile the parallel loop runs records no every-step peak (above): its summary gives
    # the deepest overlap and the largest overlap over a contact's smaller radius at the
    # run's checks. Spheres of 0.5 to 1.5 mm, so that the two maxima are other contacts
    # (a small sphere pressed less deep than a large one can be the more compressed), and
    # the radii of both spheres of a pair and of a wall contact's sphere must be the right
    # ones. Reference: the same maxima by brute force from the positions at every check
    # (the progress callback: after every chunk, and with one thread and no frames or
    # checkpoints every chunk ends on the checks' grid), which the kernel's stored
    # overlaps must give to round-off.
    box = 0.012
    data = {
        "materials": {"beads": {"youngs_modulus": 5e6, "poisson_ratio": 0.3, "density": 2500.0}},
        "contact": {"law": "hm", "friction": 0.5, "restitution": 0.5},
        "walls": [{"type": "box", "lower": [0.0, 0.0, 0.0], "upper": [box, box, 1.0], "open_top": True,
                   "material": "beads"}],
        "fill": [{"kind": "random", "material": "beads", "radius": 5e-4, "radius_max": 1.5e-3,
                  "lower": [0.0, 0.0, 0.0], "upper": [box, box, 0.02], "count": 60, "seed": 7}],
        "run": {"dt": 2e-5, "stop": "time", "end_time": 0.06, "gravity": [0.0, 0.0, -9.81], "skin": 5e-4,
                "threads": 1},
        "output": {"vtk": False},
    }
    sim = simulation.Simulation(scenario.build_scene(data), kernel_flags={"PARALLEL": True})
    seen, last_step = [], []

    def progress(steps, total, contacts):
        seen.append(_deepest_now(sim.state.position, sim.state.radius, box))
        last_step.append(steps)

    result = sim.run(progress=progress)
    summary = analysis.summary(result)
    assert not result.contact_statistics and last_step[-1] == result.steps and len(seen) > 10
    deepest, ratio, _ = (max(values) for values in zip(*seen))
    assert deepest > 0.0
    assert summary["sampled_max_overlap_m"] == pytest.approx(deepest, rel=1e-9)
    assert summary["sampled_max_overlap_ratio"] == pytest.approx(ratio, rel=1e-9)
    # the largest ratio is not the deepest contact's at some checks: the ratio is
    # searched for, not read off the deepest contact
    assert any(check_ratio > 1.05 * own for _, check_ratio, own in seen)


def test_deepest_contact_finds_each_kind_of_contacts_spheres():
    # State.deepest_contact's index arithmetic for every kind of contact, on arrays laid
    # out as the kernel's: a CSR pair list (row i, partner j), CSR lists of near planes
    # and triangle candidates, and an (N, cylinders) array. Radii 1, 2, 3, 4 mm; each
    # case puts the one touching contact in another kind and row.
    from types import SimpleNamespace

    from minidem.engine.state import State

    radius = np.array([1e-3, 2e-3, 3e-3, 4e-3])
    none = np.zeros(0)

    def state(pairs=(np.zeros(5, dtype=np.int64), np.zeros(0, dtype=np.int32), none),
              planes=(none, np.zeros(5, dtype=np.int64)), meshes=(np.zeros(5, dtype=np.int64), none),
              cylinders=np.full((4, 0), -1.0)):
        return SimpleNamespace(particles=(None,) * 8 + (radius,),
                               pairs=(pairs[0], pairs[1], None, pairs[2]),
                               planes=(None, None, None, None, planes[0], planes[1]),
                               meshes=(None, None, meshes[0], None, None, meshes[1]),
                               cylinders=(None,) * 6 + (cylinders,))

    # pairs: row 0 lists 1 and 2, row 1 lists 3 (entry 2), rows 2 and 3 none
    pair_list = (np.array([0, 2, 3, 3, 3]), np.array([1, 2, 3], dtype=np.int32))
    got = State.deepest_contact(state(pairs=(*pair_list, np.array([-1.0, 1e-4, 3e-4]))))
    assert got == pytest.approx((3e-4, 3e-4 / 2e-3))  # 1-3: the smaller radius is sphere 1's
    got = State.deepest_contact(state(pairs=(*pair_list, np.array([2e-5, -1.0, 3e-5]))))
    assert got == pytest.approx((3e-5, 2e-5 / 1e-3))  # deepest 1-3, most compressed 0-1
    # near planes: sphere 0 one plane, sphere 1 none, sphere 2 two (entries 1, 2), sphere 3 one
    got = State.deepest_contact(state(planes=(np.array([-1.0, -1.0, 6e-4, 5e-4]), np.array([0, 1, 1, 3, 4]))))
    assert got == pytest.approx((6e-4, 6e-4 / 3e-3))
    # triangles: sphere 3's only candidate is entry 0
    got = State.deepest_contact(state(meshes=(np.array([0, 0, 0, 0, 1]), np.array([8e-4]))))
    assert got == pytest.approx((8e-4, 8e-4 / 4e-3))
    # cylinders: two of them, sphere 1 in the second
    cylinders = np.full((4, 2), -1.0)
    cylinders[1, 1] = 1e-4
    assert State.deepest_contact(state(cylinders=cylinders)) == pytest.approx((1e-4, 1e-4 / 2e-3))
    assert State.deepest_contact(state()) == (0.0, 0.0)


def test_a_two_sphere_scene_reports_the_pairs_restitution():
    """summary.json's en and et for a two-sphere scene are the pair's (the review found
    them always null, and the printed summary of any scene almost all '-'): the head-on
    scene (restitution 0.5 requested through the law's mapping) gives en = 0.5 within the
    mapping's 1 % (docs/laws.md) and no et; the printed table shows what a DEM user
    checks."""
    import io

    from minidem import cli

    scene = scenario.load_scene("scenarios/two_spheres_head_on.toml", ["contact.restitution=0.5"], "-")
    summary = analysis.summary(simulation.Simulation(scene).run())
    assert summary["en"] == pytest.approx(0.5, rel=0.01) and summary["et"] is None
    printed = io.StringIO()
    cli.print_summary(summary, printed)
    text = printed.getvalue()
    assert "normal restitution of the pair" in text and "contacts at end" in text and "particles" in text


def _frictionless_relative_rebound(kn, effective_mass, reach, velocity, step=1e-9):
    """The relative velocity after a frictionless linear-spring collision of two spheres
    touching at t = 0 (relative position (-reach, 0), force kn (reach - |r|) along r on
    the relative motion of mass m*): RK4 with ``step``, the separation located to within
    a step (the kink there costs RK4 ~ (kn/m*) step^2 of the speed: 1e-9 here)."""
    def acceleration(r):
        distance = math.hypot(r[0], r[1])
        overlap = reach - distance
        return np.zeros(2) if overlap <= 0.0 else kn * overlap / effective_mass * r / distance

    r, v, t = np.array([-reach, 0.0]), np.array(velocity[:2], dtype=float), 0.0
    while t < 1e-6 or math.hypot(*r) <= reach:
        r, v = rk4_step(acceleration, r, v, step)
        t += step
    return v


def test_linear_spring_pair_error_is_that_of_its_straddled_separation():
    # LS's force kn d ends with a kink; the step that straddles separation at a fraction
    # theta of the step leaves the rebound off by (pi^2 / 2) theta (1 - theta) / N^2 of
    # the speed at N steps per contact (velocity Verlet's trapezoid over a force falling
    # linearly to zero inside the step; docs/time-step.md). The frictionless oblique pair
    # (20 deg) against an independent integration of its relative motion: measured
    # within 6 % of the formula at 250 and 1000 steps (theta 0.93 and 0.72); asked 15 %
    errors, predicted = [], []
    for steps in (250, 1000):
        data = two_spheres("ls", 20.0, extra={"friction": 0.0})
        data["run"]["steps_per_contact"] = steps
        sim = simulation.Simulation(scenario.build_scene(data))
        result = sim.run()
        if steps == 250:
            masses = sim.scene.mass
            kn = float(sim.constants[sim.pair_row[0, 0]][0])
            start = np.asarray(result.initial_velocity[0] - result.initial_velocity[1])
            exact = _frictionless_relative_rebound(kn, masses[0] * masses[1] / (masses[0] + masses[1]), 2 * RADIUS,
                                                   start)
        got = np.asarray(result.velocity[0] - result.velocity[1])[:2]
        errors.append(np.max(np.abs(got - exact)) / SPEED)
        theta = result.last_separation_time / sim.dt % 1.0
        predicted.append(math.pi**2 / 2 * theta * (1 - theta) / steps**2)
    for error, expected in zip(errors, predicted):
        assert error == pytest.approx(expected, rel=0.15), (errors, predicted)
