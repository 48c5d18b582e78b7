"""Every free flight of one sphere among plane walls in closed form (run.integrator =
"analytic_flight", the default there): a ball bouncing on a floor under gravity.

The scene: the paper's glass sphere (R = 25 mm, 2650 kg/m3, E = 70 GPa, nu = 0.3) touching
a glass floor at t = 0 and moving into it at 0.5 m/s under g = 9.81 m/s^2, elastic Hertz
(law hm, restitution 1), for 0.25 s: three contacts and the two flights between them, and
the run ends in a third flight. Touching at t = 0, analytic flight and velocity Verlet are
the same bits up to the first separation (docs/time-step.md), so run.integrator =
"velocity_verlet", which steps every flight, is the stepped reference.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import OBLIQUE
from minidem import api, cli
from minidem.engine import checkpoint, run_loop, simulation
from minidem.scene import scenario
from test_faults import as_options, assert_ends_as_uninterrupted

G = 9.81
BOUNCE = ['contact.law="hm"', "impact.angle_deg=0", "impact.speed=0.5",
          f"run.gravity=[0, 0, {-G}]", 'run.stop="time"', "run.end_time=0.25"]


@pytest.fixture(scope="module")
def flown_and_stepped():
    """The bounce run twice: its flights flown (the default, analytic flight) and stepped
    (velocity Verlet)."""
    return api.run(OBLIQUE, BOUNCE).raw, api.run(OBLIQUE, BOUNCE + ['run.integrator="velocity_verlet"']).raw


def test_the_flights_between_bounces_are_flown_and_equal_the_stepped_ones(flown_and_stepped):
    """Velocity Verlet under gravity alone is exact (x + v dt + g dt^2/2 a step), so flying
    a flight in closed form changes only rounding: over the run's 5 million steps the
    stepped one's rounding grows to about N eps = 5e6 x 1.1e-16 = 6e-10 of a value, so
    the two agree to 1e-8 relative. The contacts start and end at the same instants (the
    kernel's touch and separation times interpolated within a step) to that difference
    over the touch speed, and every energy sample is the same sample. Almost every step out of contact is flown:
    those stepped are the contacts' (3 x ~4000) and two steps before each later touch."""
    flown, stepped = flown_and_stepped
    assert flown.steps == stepped.steps and stepped.flown_steps == 0
    scale = float(np.abs(stepped.position).max())
    np.testing.assert_allclose(flown.position, stepped.position, rtol=0, atol=1e-8 * scale)
    np.testing.assert_allclose(flown.velocity, stepped.velocity, rtol=0,
                               atol=1e-8 * float(np.abs(stepped.velocity).max()))
    # a touch's instant moves by a position's difference over the touch speed (0.52 m/s)
    for name in ("first_contact_time", "last_separation_time"):
        assert getattr(flown, name) == pytest.approx(getattr(stepped, name), abs=1e-8 * scale / 0.5)
    assert flown.energy.shape == stepped.energy.shape
    np.testing.assert_allclose(flown.energy[:, 0], stepped.energy[:, 0], rtol=0, atol=1e-6 * flown.dt)
    # a velocity's difference (1e-8 of the largest) gives m v dv: 1e-8 of the largest energy at most
    np.testing.assert_allclose(flown.energy[:, 1], stepped.energy[:, 1], rtol=0,
                               atol=2e-8 * float(stepped.energy[:, 1].max()))
    in_contact = 3 * 4000 * 1.05  # three contacts of ~steps_per_contact steps
    assert flown.flown_steps >= flown.steps - in_contact - 2 * 3


def test_the_bouncing_ball_keeps_its_energy_and_bounces_on_time(flown_and_stepped):
    """Physics of the flown run. Elastic Hertz: the mechanical energy (kinetic plus m g z)
    at the end, in flight after three contacts, is the initial one to within velocity
    Verlet's energy error in a contact, of order (pi / steps_per_contact)^2 = 6e-7.

    The contacts' instants: each flight lasts 2 v0 / g (an elastic rebound leaves at the
    speed it came, v0); each contact lasts the Hertz duration tc = 2.868 (m^2 / (R E*^2
    v0))^(1/5) (the paper's eq 13). The third separation is then 3 tc + 2 (2 v0 / g). Gravity
    during a contact changes its duration by about m g / Fmax of it (Fmax, Hertz's peak
    force at v0, 1.6 kN against m g = 1.7 N): the tolerance is three contacts' worth,
    3 tc m g / Fmax (6e-7 s), and a step."""
    flown, _ = flown_and_stepped
    scene = flown.scene
    radius, mass = float(scene.radius[0]), float(scene.mass[0])
    effective_modulus = 70e9 / (2.0 * (1.0 - 0.3 ** 2))  # sphere and wall of one material
    energy = [0.5 * mass * float(v @ v) + mass * G * float(x[2])
              for x, v in ((scene.position[0], scene.velocity[0]), (flown.position[0], flown.velocity[0]))]
    assert energy[1] == pytest.approx(energy[0], rel=(math.pi / scene.steps_per_contact) ** 2)
    # in flight at the end, rising or falling at the speed its height gives
    assert float(flown.position[0, 2]) > radius
    assert abs(float(flown.velocity[0, 2])) == pytest.approx(
        math.sqrt(2.0 * energy[0] / mass - 2.0 * G * float(flown.position[0, 2])), rel=1e-6)

    touch_speed = 0.5
    contact_time = 2.868 * (mass * mass / (radius * effective_modulus ** 2 * touch_speed)) ** 0.2
    peak_force = 4.0 / 3.0 * effective_modulus * math.sqrt(radius) * (
        15.0 * mass * touch_speed ** 2 / (16.0 * effective_modulus * math.sqrt(radius))) ** 0.6
    assert flown.first_contact_time == 0.0
    third_separation = 3.0 * contact_time + 2.0 * (2.0 * touch_speed / G)
    assert flown.last_separation_time == pytest.approx(
        third_separation, abs=3.0 * contact_time * mass * G / peak_force + flown.dt)


def test_a_run_stopped_in_flight_resumes_bit_for_bit(tmp_path, capsys):
    """The flight is planned once and every state in it computed from its start (saved
    in the checkpoint), so a run interrupted in mid-flight and resumed ends with the bits
    of one that was not, though its chunks cut the flight elsewhere. The resumed
    command's last line counts the steps it took and, of them, those it flew: its part of
    the run's free_flight_steps (the rest were flown before the checkpoint)."""
    out = tmp_path / "out"
    sim = simulation.Simulation(scenario.load_scene(OBLIQUE, BOUNCE, out))

    def interrupt(steps, total, contacts):  # in the second flight (contacts at 0 and ~0.102 s)
        if steps * sim.dt > 0.16:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sim.run(progress=interrupt, checkpoints=checkpoint.Policy(out, interval=0.013))
    stopped_at, path = sim.interrupted_at
    arrays, meta = checkpoint.read(path)
    assert 0.11 < stopped_at < 0.2 and meta["loop"]["flight"] is not None  # stopped in a planned flight
    capsys.readouterr()
    assert cli.main(["run", str(OBLIQUE), "--out", str(out), "--resume", *as_options(BOUNCE)]) == cli.EXIT_OK
    last = capsys.readouterr().out.strip().splitlines()[-1].strip()

    _, got_meta, want_meta = assert_ends_as_uninterrupted(out, OBLIQUE, BOUNCE, tmp_path)
    assert got_meta["loop"]["flown_steps"] == want_meta["loop"]["flown_steps"] > 0.99 * want_meta["step"]
    here = got_meta["step"] - meta["step"]
    flown_here = got_meta["loop"]["flown_steps"] - meta["loop"]["flown_steps"]
    assert 0 < flown_here < here
    assert last.startswith(f"{here} steps in ") and f": {here - flown_here} stepped, {flown_here} flown in closed form" \
        in last, last
    assert f"(resumed at step {meta['step']})" in last, last


def test_a_failure_in_flight_writes_the_last_checked_state_bit_for_bit(tmp_path, monkeypatch):
    """A blow-up stop goes back to the last copy of the state and replays the steps to the
    last check that passed (RunLoop.fail): the replay flies the flights as the run did,
    so the state written is the one a run ending at that step ends in, to the bit. The
    guard is made to fail the first check after t = 0.21 s, at the end of the third
    flight (contacts at 0, 0.102 and 0.204 s). VTK frames every 0.013 s cut the flights;
    the one copy of the state, the first (later copies are held off), is taken at a
    frame in the first flight, and the replay goes from there, with that flight's plan
    (re-planned from the copy, its states differ in the last bits), through the second
    contact, the second flight and the third contact."""
    from minidem.results.vtk import SimulationFrames
    from minidem.engine import blowup

    real_check, real_fly, replayed = blowup.Guard.check, run_loop.RunLoop.fly, []

    def failing_check(self, state, time, gravity_work_max):
        if time > 0.21:
            return blowup.Fault("energy", 0, "made to fail by the test"), gravity_work_max
        return real_check(self, state, time, gravity_work_max)

    def counted_fly(self, start_step, n_steps, sampled=True):
        taken = real_fly(self, start_step, n_steps, sampled)
        if not sampled:
            replayed.append(taken)
        return taken

    monkeypatch.setattr(blowup.Guard, "check", failing_check)
    monkeypatch.setattr(run_loop.RunLoop, "fly", counted_fly)
    out = tmp_path / "out"
    # no copy of the state after the first: the replay then runs from t = 0 through the
    # flights (the copies' schedule otherwise follows wall time)
    monkeypatch.setattr(run_loop, "SNAPSHOT_COST_RATIO", 1e12)
    copies = []
    real_snapshot = run_loop.RunLoop.snapshot

    def noted_snapshot(self, reuse=None, live=False):
        copy = real_snapshot(self, reuse, live)
        copies.append(copy["loop"]["flight"])
        return copy

    monkeypatch.setattr(run_loop.RunLoop, "snapshot", noted_snapshot)
    sim = simulation.Simulation(scenario.load_scene(OBLIQUE, BOUNCE + ["output.vtk=true", "output.interval=0.013"],
                                                    out))
    with pytest.raises(run_loop.RunFailure):
        sim.run(checkpoints=checkpoint.Policy(out), on_frame=SimulationFrames(sim, out))
    assert sum(replayed) > 0  # the replay flew
    assert copies[1] is not None  # the copy replayed from (the first is t = 0's) was taken in a flight
    arrays, meta = checkpoint.read(out / checkpoint.LAST_GOOD)
    monkeypatch.setattr(blowup.Guard, "check", real_check)
    reference = api.run(OBLIQUE, BOUNCE[:-1] + [f"run.end_time={meta['time']!r}"]).raw
    assert reference.steps == meta["step"]
    for name in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(arrays[name], getattr(reference, name)), name


def one_sphere(walls, position, velocity, radius, run):
    """A scene of scenarios/oblique.toml's glass and law (hm here) with one sphere of its
    own among ``walls`` (analytic flight, the default there)."""
    data = scenario.read_toml(OBLIQUE)
    data.pop("impact")
    data["contact"]["law"] = "hm"
    data.update(walls=walls, run=run, output={"vtk": False},
                particles=[{"position": position, "velocity": velocity, "radius": radius, "material": "glass"}])
    scene = scenario.build_scene(data, str(OBLIQUE), "-")
    assert scene.integrator == "analytic_flight"
    return scene


def test_the_time_to_a_touch_is_exact_for_a_sphere_moving_away():
    """integrate.time_to_touch solves s - c t - b t^2/2 = 0. A sphere that has just left a
    floor (c < 0, s a rounding error) and falls back under gravity touches again after
    2 |c| / b whatever s is (to s / |c|). The form 2 s / (c + sqrt(c^2 + 2 b s)) it used
    for every sign divides by a difference of nearly equal numbers then: 15 ms off at
    s = 1e-16 m, inf at 1e-18 m (the review of the flown flights). A gap of zero that is
    not closing is no touch at t = 0."""
    from minidem.engine.integrate import time_to_touch

    from decimal import Decimal, getcontext

    getcontext().prec = 50  # the root in 50 digits: the reference
    c, b = -1.4, 9.81
    for gap in (0.0, 1e-18, 1e-16, 1e-10):
        dc, db, ds = Decimal(c), Decimal(b), Decimal(gap)
        exact = float(((dc * dc + 2 * db * ds).sqrt() - dc) / db)
        assert time_to_touch(gap, c, b) == pytest.approx(exact, rel=4e-16)
    assert time_to_touch(0.0, 0.0, 0.0) == math.inf and time_to_touch(0.0, -1.0, 0.0) == math.inf
    assert time_to_touch(0.0, 0.0, b) == 0.0 and time_to_touch(0.0, 1.0, 0.0) == 0.0
    # a fall from rest: the approaching form, the bits of the flights planned before the review
    assert time_to_touch(0.1, 0.0, b) == 2.0 * 0.1 / math.sqrt(2.0 * b * 0.1)
    assert time_to_touch(0.1, 5.0, 0.0) == pytest.approx(0.02, rel=1e-15)
    assert time_to_touch(0.1, 1.0, -100.0) == math.inf  # pushed back before it arrives


def test_a_ball_thrown_up_from_the_floor_comes_back_at_its_speed():
    """The paper's sphere touching a floor at t = 0, thrown straight up at 5 m/s under
    g = 9.81 m/s^2 (law hm, elastic): it leaves at once and touches again at T = 2 v / g
    (the first flight, solved before the steps start), rebounds at 5 m/s, flies again
    (flown: it leaves the floor by a rounding error and falls back) and touches a second
    time at 2 T + tc. Each touch is at 5 m/s, so the deepest overlap is the paper's
    normal impact's, Hertz's (15 m v^2 / (16 E* sqrt(R)))^(2/5) (eq 12), and tc is the
    Hertz duration (eq 13). Elastic contact and gravity conserve energy, so the rebound
    leaves at the speed it came and the flight lasts 2 v / g exactly; gravity during the
    contact changes its duration by about m g / Fmax of it (8e-5: 1e-8 s), and the
    kernel times touch and separation within a step: the tolerance is two steps. With the
    time to a touch of a sphere moving away computed by cancellation, both flights were
    planned wrong: the sphere never touched and passed through the floor (z = -3.2 m at
    1.5 s in the review's case)."""
    speed, radius = 5.0, 0.025
    flight = 2.0 * speed / G
    # a floor at z = 0.3: the start's overlap is a rounding residue (-1.7e-17 m)
    scene = one_sphere([{"point": [0.0, 0.0, 0.3], "normal": [0.0, 0.0, 1.0], "material": "glass"}],
                       [0.0, 0.0, 0.3 + radius], [0.0, 0.0, speed], radius,
                       {"gravity": [0.0, 0.0, -G], "stop": "time", "end_time": 2.5 * flight})
    result = simulation.Simulation(scene).run()
    mass = float(scene.mass[0])
    effective_modulus = 70e9 / (2.0 * (1.0 - 0.3 ** 2))
    hertz = (15.0 * mass * speed ** 2 / (16.0 * effective_modulus * math.sqrt(radius))) ** 0.4
    contact_time = 2.868 * (mass * mass / (radius * effective_modulus ** 2 * speed)) ** 0.2
    assert result.first_contact_time == pytest.approx(flight, rel=1e-12)
    assert result.last_separation_time == pytest.approx(2.0 * flight + 2.0 * contact_time, abs=2.0 * result.dt)
    assert result.max_overlap == pytest.approx(hertz, rel=1e-3)
    assert float(result.position[0, 2]) > 0.3 + radius
    assert result.flown_steps >= result.steps - 2.2 * contact_time / result.dt - 3 * 2


def test_a_sphere_gliding_on_a_floor_at_zero_overlap_is_flown():
    """No gravity; a sphere lying on the floor of a box at zero overlap (no contact: a
    contact lives above zero overlap) glides at 1 m/s to a side wall 0.03 m away,
    rebounds and glides back. Every glide is flown (none of the floor's force acts), and
    the side wall is touched at t = 0.03 s. Before, the zero overlap counted as a contact
    to step to its end, and the kernel, stopping at every step that ends one, was called
    once a step: 60 times slower than stepping it."""
    scene = one_sphere([{"type": "box", "lower": [0.0, 0.0, 0.0], "upper": [0.1, 1.0, 1.0], "material": "glass"}],
                       [0.05, 0.5, 0.02], [1.0, 0.0, 0.0], 0.02, {"stop": "time", "end_time": 0.06})
    result = simulation.Simulation(scene).run()
    assert result.first_contact_time == pytest.approx(0.03, abs=result.dt)
    contact_steps = 1.1 * (result.last_separation_time - result.first_contact_time) / result.dt
    assert result.flown_steps >= result.steps - contact_steps - 3
    assert float(result.position[0, 2]) == 0.02 and result.velocity[0, 0] < 0.0


def test_the_frames_of_flown_flights_are_the_stepped_ones(tmp_path):
    """A ParaView series of the bounce (a frame every 0.01 s): frames fall in flights and
    are written from flown states. Each frame is at the same time as the stepped run's
    (velocity Verlet: the same grid) with the same position and velocity but for the
    stepped run's rounding (1e-8 of the largest, as above)."""
    runs = {}
    for name, extra in (("flown", []), ("stepped", ['run.integrator="velocity_verlet"'])):
        api.run(OBLIQUE, BOUNCE + ["output.vtk=true", "output.interval=0.01", *extra], out=tmp_path / name)
        runs[name] = api.open_results(tmp_path / name).series
    flown, stepped = runs["flown"], runs["stepped"]
    assert len(flown.times) == len(stepped.times) >= 26
    np.testing.assert_array_equal(flown.times, stepped.times)
    for (_, frame), (_, reference) in zip(flown, stepped):
        # scales: the sphere's height (~0.03 m) and its launch speed (0.5 m/s)
        for got, want, scale in ((frame.points, reference.points, 0.03),
                                 (frame.point_data["velocity"], reference.point_data["velocity"], 0.5)):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-8 * scale)


def test_the_guard_weighs_a_flight_against_the_work_gravity_did_in_it():
    """The energy guard allows the kinetic energy the initial energy plus the largest work
    of gravity recorded at the run's check grid. A sphere touching a side wall at t = 0,
    0.1 m above a floor, falls: most of its fall is one flown chunk, which passes the grid
    without a check. The record is kept there in closed form, so it is the stepped run's
    (velocity Verlet: every grid step checked) to the rounding of their states (1e-8),
    and no warning is given. Before, the record missed the fall (1.1e-4 J against
    1.08e-2 J) and the summary warned that the time step was too large."""
    scene = one_sphere([{"point": [0.0, 0.0, 0.0], "normal": [1.0, 0.0, 0.0], "material": "glass"},
                        {"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "glass"}],
                       [0.01, 0.0, 0.11], [-0.5, 0.0, 0.0], 0.01,
                       {"gravity": [0.0, 0.0, -G], "stop": "time", "end_time": 0.3})
    from minidem.results import analysis

    flown = simulation.Simulation(scene).run()
    scene.integrator = "velocity_verlet"
    stepped = simulation.Simulation(scene).run()
    assert flown.flown_steps > 0.99 * flown.steps - 3 * 4000 and stepped.flown_steps == 0
    # the sphere falls 0.1 m: m g h
    assert stepped.gravity_work_max == pytest.approx(float(scene.mass[0]) * G * 0.1, rel=0.01)
    assert flown.gravity_work_max == pytest.approx(stepped.gravity_work_max, rel=1e-8)
    assert analysis.summary(flown)["warnings"] == []
