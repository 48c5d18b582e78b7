"""Chung & Ooi (2011, Granular Matter 13:643) verification tests 1-8, from the scenario
files in scenarios/chung-ooi/ (one case of each sweep, the sweep's other keys as set).

Every expected value comes from theory, never from minidem's output:
- tests 1-3: the closed-form elastic Hertz impact (computed here from the formulas, and
  checked against the values tabulated in shared/reference/chung-ooi.md);
- test 3: the restitution requested (and the clipped spring-dashpot's closed form,
  Schwager & Poeschel 2007, against an independent integration);
- tests 4-8: rigid-body impulse theory in gross sliding at the test's own e (delta v_t = mu (1 + e) v_n,
  delta omega = 5/2 mu (1 + e) v_n / R on a wall; the general two-body form in
  analysis.rigid_body_impact, whose wall limit is checked here against those formulas),
  Coulomb's law on the computed normal force, and the conservation of linear and angular
  momentum (two spheres, no walls, no gravity).
Kernels are shared: one per law and scene shape (sphere-wall, sphere-sphere).
"""

from __future__ import annotations

import math
import tomllib
import warnings
from pathlib import Path

import numpy as np
import pytest

from minidem.engine import simulation
from minidem.results import analysis
from minidem.scene import scenario
from minidem.scene.scenario import ScenarioError
from minidem.studies import executors, sweep

FILES = Path(__file__).resolve().parent.parent / "scenarios" / "chung-ooi"


def _scene(test: int, *overrides: str):
    """The base scenario of test N (its [sweep] removed) with overrides."""
    path = FILES / f"test{test}.toml"
    data = tomllib.loads(path.read_text())
    data.pop("sweep")
    return scenario.build_scene(scenario.apply_overrides(data, list(overrides)), str(path))


def _run(test: int, *overrides: str, trace: bool = False):
    """Run one case with every warning an error (no stability or energy warning may pass)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = _scene(test, *overrides)
        scene.trace = trace
        result = simulation.Simulation(scene).run()
        summary = analysis.summary(result)
    assert summary["warnings"] == [], summary["warnings"]
    return result, summary


def _hertz(youngs, poisson, density, radius, speed, two_spheres):
    """Closed-form elastic Hertz impact (Johnson 1985): two identical spheres
    (R* = R/2, m* = m/2, E* = E/(2(1 - nu^2)), v the relative speed) or a sphere on a
    rigid plane (R* = R, m* = m, E* = E/(1 - nu^2))."""
    mass = density * 4.0 / 3.0 * math.pi * radius**3
    e_star = youngs / (1.0 - poisson**2) / (2.0 if two_spheres else 1.0)
    r_star, m_star = (radius / 2, mass / 2) if two_spheres else (radius, mass)
    overlap = (15.0 * m_star * speed**2 / (16.0 * e_star * math.sqrt(r_star))) ** 0.4
    force = 4.0 / 3.0 * e_star * math.sqrt(r_star) * overlap**1.5
    # t_c = 2 (alpha_max/v) int_0^1 dx / sqrt(1 - x^(5/2)) = 2.9432752 alpha_max / v
    duration = 0.8 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9) * overlap / speed
    return overlap, force, duration


# (test, overrides, material (E, nu, rho), R, v, two spheres, tabulated (alpha um, F N, tc us))
HERTZ_CASES = [
    (1, (), (48e9, 0.20, 2800.0), 0.010, 20.0, True, (274.1, 10.70e3, 40.3)),
    (1, ('particles.0.material="limestone"', 'particles.1.material="limestone"'), (20e9, 0.25, 2500.0), 0.010,
     20.0, True, (368.3, 7.108e3, 54.2)),
    (2, (), (70e9, 0.30, 2699.0), 0.1, 0.2, False, (49.72, 11.37e3, 731.7)),
    (2, ('impact.material="mg_alloy"',), (40e9, 0.35, 1800.0), 0.1, 0.2, False, (52.12, 7.233e3, 767.1)),
    (3, (), (380e9, 0.23, 4000.0), 0.0025, 3.9, False, (8.09, 615.0, 6.11)),
    (3, ('impact.material="cast_iron"',), (100e9, 0.25, 7000.0), 0.0025, 3.9, False, (17.19, 507.0, 12.97)),
]


@pytest.mark.parametrize("test, overrides, material, radius, speed, two_spheres, table", HERTZ_CASES)
def test_tests_1_to_3_elastic_impact_is_hertz_within_half_a_percent(test, overrides, material, radius, speed,
                                                                     two_spheres, table):
    overlap, force, duration = _hertz(*material, radius, speed, two_spheres)
    # the formulas reproduce the reference's tabulated values (to their 3-4 digits)
    for computed, tabulated in zip((overlap * 1e6, force, duration * 1e6), table):
        assert computed == pytest.approx(tabulated, rel=5e-3)
    _, summary = _run(test, *overrides)
    assert summary["max_overlap_m"] == pytest.approx(overlap, rel=5e-3)
    assert summary["peak_normal_force_n"] == pytest.approx(force, rel=5e-3)
    assert summary["contact_duration_s"] == pytest.approx(duration, rel=5e-3)
    assert summary["en"] == pytest.approx(1.0, abs=1e-6)  # e = 1: elastic
    # the summary's own Hertz limits are the same formulas (the "rigid" wall is 1e9 times stiffer)
    assert summary["hertz_max_overlap_m"] == pytest.approx(overlap, rel=1e-8)
    assert summary["hertz_peak_force_n"] == pytest.approx(force, rel=1e-8)
    assert summary["hertz_contact_time_s"] == pytest.approx(duration, rel=1e-8)


@pytest.mark.parametrize("law", ["hmd", "ls", "walton_braun"])
def test_test_3_requested_restitution_within_one_percent(law):
    # every damping model minidem has claims e exactly (docs/laws.md), the normal force
    # clipped at zero: the Hertz dashpot mapped by bisection on its dimensionless
    # equation, the linear dashpot by the clipped closed form, Walton-Braun's k2 = k1/e^2.
    # The tsuji and viscous parts share the laws' mappings and clipping
    # (tests/test_parts.py: hooke+viscous+linear_history is ls bit for bit at e = 0.8)
    for restitution in (0.01, 0.25, 0.5, 0.75, 1.0):
        _, summary = _run(3, f'contact.law="{law}"', f"contact.restitution={restitution}")
        assert summary["en"] == pytest.approx(restitution, rel=1e-2), (law, restitution)


def _clipped_restitution(force, step=1e-4):
    """Rebound speed of x'' = -max(force(x, x'), 0), x(0) = 0, x'(0) = 1: plain RK4, the
    body leaving where the force returns to zero in restitution (then no force acts),
    the exit speed interpolated linearly in the force. Independent of minidem's code."""
    def acceleration(x, v):
        return -max(force(x, v), 0.0)

    x, v, force_old = 0.0, 1.0, 0.0
    while True:
        k1 = (v, acceleration(x, v))
        k2 = (v + step / 2 * k1[1], acceleration(x + step / 2 * k1[0], v + step / 2 * k1[1]))
        k3 = (v + step / 2 * k2[1], acceleration(x + step / 2 * k2[0], v + step / 2 * k2[1]))
        k4 = (v + step * k3[1], acceleration(x + step * k3[0], v + step * k3[1]))
        x_new = x + step / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        v_new = v + step / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        force_new = force(x_new, v_new)
        if v_new < 0.0 and force_new <= 0.0:
            return -(v + force_old / (force_old - force_new) * (v_new - v))
        x, v, force_old = x_new, v_new, force_new


@pytest.mark.parametrize("restitution", [0.05, 0.5, 0.9])
def test_test_3_clipped_dashpot_mappings_solve_their_equations(restitution):
    # the damping minidem maps from e, put into the dimensionless clipped equations and
    # integrated here: linear x'' = -max(x + 2 zeta x', 0), Hertz (Tsuji) x'' =
    # -max(x^1.5 + alpha x^0.25 x', 0)
    from minidem.contact.builtin_laws.common import hertz_damping_factor, linear_damping_ratio

    zeta = linear_damping_ratio(restitution)
    alpha = hertz_damping_factor(restitution)
    assert _clipped_restitution(lambda x, v: x + 2.0 * zeta * v) == pytest.approx(restitution, rel=1e-6)
    assert _clipped_restitution(lambda x, v: max(x, 0.0) ** 1.5 + alpha * max(x, 0.0) ** 0.25 * v) == pytest.approx(
        restitution, rel=1e-5)
    # the closed form (Schwager & Poeschel 2007) below critical damping, e = exp(-zeta t_c)
    if zeta < 1.0:
        w = math.sqrt(1.0 - zeta**2)
        assert math.exp(-zeta * (math.pi - math.atan2(2 * zeta * w, 1 - 2 * zeta**2)) / w) == pytest.approx(
            restitution, rel=1e-12)


def test_test_3_zero_restitution_is_refused_with_the_bound():
    with pytest.raises(ScenarioError, match=r"restitution.*\(0, 1\]|restitution.*> 0"):
        _scene(3, "contact.restitution=0.0")


def test_rigid_body_theory_on_a_wall_is_the_closed_form():
    # delta v_t = mu (1 + e) v_n, delta omega = 5/2 mu (1 + e) v_n / R in gross sliding,
    # rolling (v_t + R omega = 0 about the contact, 5/7 v_t) below 3.5 mu (1 + e)
    radius, mass = 0.1, 2.0
    inertia = 0.4 * mass * radius**2
    n = np.array([0.0, 0.0, 1.0])
    for vt, sliding in ((3.0, True), (0.05, False)):
        v, w, slid = analysis.rigid_body_impact([mass], [inertia], [radius], [[vt, 0.0, -1.0]], [[0.0, 0.0, 0.0]],
                                                n, 0.5, 0.4)
        assert slid is sliding
        if sliding:
            assert v[0, 0] == pytest.approx(vt - 0.4 * 1.5 * 1.0, rel=1e-14)
            assert abs(w[0, 1]) == pytest.approx(2.5 * 0.4 * 1.5 / radius, rel=1e-14)
        else:
            assert v[0, 0] == pytest.approx(5.0 / 7.0 * vt, rel=1e-14)
            assert v[0, 0] - w[0, 1] * radius == pytest.approx(0.0, abs=1e-15)  # contact point at rest: rolling
        assert v[0, 2] == pytest.approx(0.5, rel=1e-14)


def _assert_rigid_body(summary, tolerance=1e-3):
    assert summary["rigid_sliding"]
    for measure in ("tangential_velocity_m_s", "spin_rad_s", "rebound_angle_deg"):
        assert summary[measure] == pytest.approx(summary[f"rigid_{measure}"], rel=tolerance), measure


@pytest.mark.parametrize("law", ["hmd", "hm", "ls"])
@pytest.mark.parametrize("angle", [45.0, 75.0])
def test_test_4_gross_sliding_follows_rigid_body_theory(law, angle):
    # the paper's e = 0.98, mu = 0.092: gross sliding from 32.5 deg
    _, summary = _run(4, f'contact.law="{law}"', f"impact.angle_deg={angle}")
    assert summary["en"] == pytest.approx(0.98, rel=1e-3)
    _assert_rigid_body(summary)
    # and the closed form itself: vt' = vt - mu (1 + e) vn
    theta = math.radians(angle)
    assert summary["rigid_tangential_velocity_m_s"] == pytest.approx(
        3.9 * math.sin(theta) - 0.092 * 1.98 * 3.9 * math.cos(theta), rel=1e-12)


@pytest.mark.parametrize("material", ["steel", "polyethylene"])
def test_test_5_extremes_run_at_the_default_step_and_slide_as_theory(material):
    # a 10-micrometre sphere at vt = 70 m/s, vn = 5 m/s: no warning (stability, energy)
    # at dt = "auto", and gross sliding within 1e-3 of theory
    result, summary = _run(5, f'impact.material="{material}"', "impact.tangential_speed=70.0")
    assert summary["dt_reason"].startswith("auto")
    _assert_rigid_body(summary)
    assert summary["tangential_velocity_m_s"] == pytest.approx(70.0 - 0.3 * 2.0 * 5.0, rel=1e-3)


# Gross sliding far above the onset: with a dashpot the Coulomb limit mu Fn rises at
# touch faster than the tangential spring builds up (the linear dashpot's force is c vn
# at once, Tsuji's grows as d^(1/4)), so the contact slides only after an onset that
# costs the fraction 2 zeta^2 mu vn / ((1 + e) kappa R omega) of the tangential impulse
# (linear spring, to first order; see the onset test). It falls as 1/omega: at
# omega = 200 rad/s (R omega = 100 vn) it is 4.3e-4 for ls (measured 4.4e-4), and the
# Hertz laws' is alike.
GROSS_SPIN = 200.0


@pytest.mark.parametrize("law", ["hmd", "hm", "ls"])
@pytest.mark.parametrize("material", ["al_alloy", "nylon"])
def test_test_6_pre_spun_sphere_slides_as_theory_at_e_half(law, material):
    # the paper's e = 0.5, mu = 0.4: the normal force never tensile, so the Coulomb limit
    # acts on the force whose impulse is (1 + e) m vn, and rigid-body theory holds
    result, summary = _run(6, f'contact.law="{law}"', f'impact.material="{material}"', f"impact.spin={GROSS_SPIN}",
                           trace=True)
    assert summary["en"] == pytest.approx(0.5, rel=1e-3)
    _assert_rigid_body(summary)
    trace = result.trace
    assert trace[:, 2].min() >= 0.0  # never tensile
    assert np.all(np.linalg.norm(trace[:, 3:6], axis=1) <= 0.4 * trace[:, 2] * (1 + 1e-12) + 1e-300)


@pytest.mark.parametrize("law", ["hmd", "ls"])
def test_test_6_elastic_pre_spun_sphere_slides_as_theory(law):
    # e = 1 (no dashpot, nothing clipped: the paper's laws as they were): sliding from touch
    _, summary = _run(6, f'contact.law="{law}"', "impact.spin=20.0", "contact.restitution=1.0")
    _assert_rigid_body(summary, tolerance=1e-6)


def test_test_6_onset_of_sliding_with_a_dashpot():
    # ls, e = 0.5: at touch the limit jumps to mu c vn (c = 2 zeta sqrt(m kn)) while the
    # tangential spring grows as kt R omega t; it reaches the limit at t* = mu c vn /
    # (kt R omega), having missed mu c vn t* / 2 of impulse: the fraction
    # 2 zeta^2 mu vn / ((1 + e) kappa R omega) of mu (1 + e) m vn (kappa = kt/kn). After
    # t* the contact slides to the end: |Ft| = mu Fn at every step.
    from minidem.contact.builtin_laws.common import linear_damping_ratio

    zeta = linear_damping_ratio(0.5)
    kappa = 2.0 * (1.0 - 0.33) / (2.0 - 0.33)  # eq 10, the Al alloy sphere on a rigid plane
    deficits = []
    for spin in (25.0, 50.0):
        result, summary = _run(6, 'contact.law="ls"', f"impact.spin={spin}", trace=True)
        trace, dt, mass = result.trace, result.dt, float(result.scene.mass[0])
        normal, tangential = trace[:, 2], np.linalg.norm(trace[:, 3:6], axis=1)
        normal_impulse, tangential_impulse = normal.sum() * dt, tangential.sum() * dt
        assert normal_impulse == pytest.approx(mass * 1.5 * 0.2, rel=1e-3)  # (1 + e) m vn
        assert mass * summary["tangential_velocity_m_s"] == pytest.approx(tangential_impulse, rel=1e-9)
        sliding = np.flatnonzero(tangential >= 0.4 * normal * (1 - 1e-9))
        first = sliding[0]
        assert np.all(tangential[first:] >= 0.4 * normal[first:] * (1 - 1e-9))  # slides from t* to the end
        deficit = 1.0 - tangential_impulse / (0.4 * normal_impulse)
        onset = 2.0 * zeta**2 * 0.4 * 0.2 / (1.5 * kappa * 0.1 * spin)
        assert deficit == pytest.approx(onset, rel=0.1), spin
        deficits.append(deficit)
    assert deficits[0] / deficits[1] == pytest.approx(2.0, rel=0.1)  # as 1/omega


def _momenta(scene, position, velocity, angular_velocity):
    linear = (scene.mass[:, None] * velocity).sum(axis=0)
    angular = (scene.inertia[:, None] * angular_velocity
               + scene.mass[:, None] * np.cross(position, velocity)).sum(axis=0)
    return linear, angular


@pytest.mark.parametrize("test", [7, 8])
def test_tests_7_and_8_conserve_momentum(test):
    # the paper's e = 0.5: linear and angular momentum (about the origin) to round-off
    result, summary = _run(test, "particles.0.angular_velocity.2=20.0",
                           *(["particles.1.angular_velocity.2=20.0"] if test == 7 else []))
    scene = result.scene
    before = _momenta(scene, scene.position, result.initial_velocity, result.initial_angular_velocity)
    after = _momenta(scene, result.position, result.velocity, result.angular_velocity)
    scale_p = float(np.sum(scene.mass * np.linalg.norm(result.initial_velocity, axis=1)))
    scale_l = float(np.sum(scene.inertia * np.linalg.norm(result.initial_angular_velocity, axis=1))
                    + np.sum(scene.mass * scene.radius * np.linalg.norm(result.initial_velocity, axis=1)))
    assert np.abs(after[0] - before[0]).max() <= 1e-12 * scale_p
    assert np.abs(after[1] - before[1]).max() <= 1e-12 * scale_l


@pytest.mark.parametrize("law", ["hmd", "hm", "ls"])
@pytest.mark.parametrize("test", [7, 8])
def test_tests_7_and_8_slide_as_theory_at_e_half(test, law):
    # the paper's e = 0.5, far above the onset (GROSS_SPIN): rigid-body theory of the
    # two bodies within 1e-3
    _, summary = _run(test, f'contact.law="{law}"', f"particles.0.angular_velocity.2={GROSS_SPIN}",
                      *([f"particles.1.angular_velocity.2={GROSS_SPIN}"] if test == 7 else []))
    assert summary["en"] == pytest.approx(0.5, rel=1e-3)
    _assert_rigid_body(summary)


# ---------------------------------------------------------------------------------
# the scenario features the tests use, and the sweep files
# ---------------------------------------------------------------------------------
def test_impact_by_normal_and_tangential_speed():
    scene = _scene(5, "impact.tangential_speed=5.0")
    assert scene.impact.speed == pytest.approx(math.hypot(5.0, 5.0))
    assert scene.impact.angle_deg == pytest.approx(45.0)
    assert scene.velocity[0] @ scene.impact.normal == pytest.approx(-5.0)


@pytest.mark.parametrize("overrides, where, says", [
    (("impact.speed=3.0",), "impact.normal_speed", "not both"),
    (('impact.normal_speed="fast"',), "impact.normal_speed", "expected a number"),
    (("impact.normal_speed=-1.0",), "impact.normal_speed", "must be > 0"),
])
def test_impact_velocity_errors_name_the_key(overrides, where, says):
    with pytest.raises(ScenarioError, match=rf"test5.toml: invalid scenario\n(.|\n)*{where}: .*{says}"):
        _scene(5, *overrides)


def test_impact_tangential_speed_needs_normal_speed():
    data = tomllib.loads((FILES / "test5.toml").read_text())
    data.pop("sweep")
    del data["impact"]["normal_speed"]
    with pytest.raises(ScenarioError, match=r"impact.normal_speed: missing: tangential_speed needs normal_speed"):
        scenario.build_scene(data, "test5.toml")


def test_sweep_together_and_abscissa_errors():
    data = tomllib.loads((FILES / "test7.toml").read_text())
    data["sweep"]["cases"]["particles.1.angular_velocity.2"] = [1.0, 2.0]
    data["sweep"]["abscissa"] = "impact.angle_deg"
    with pytest.raises(ScenarioError) as caught:
        sweep.plan(data, "test7.toml")
    message = str(caught.value)
    assert "sweep.together[1]: the keys of a group vary together" in message
    assert "sweep.abscissa: 'impact.angle_deg' is not a swept key" in message


@pytest.mark.parametrize("test", range(1, 9))
def test_every_sweep_file_plans(test):
    path = FILES / f"test{test}.toml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plan = sweep.plan(tomllib.loads(path.read_text()), str(path))
    assert plan.abscissa in plan.keys
    if test == 7:  # materials and spins vary together: 3 laws x 2 materials x 13 spins
        assert len(plan.cases) == 3 * 2 * 13
        for case in plan.cases:
            values = dict(zip(plan.keys, case))
            assert values["particles.0.material"] == values["particles.1.material"]
            assert values["particles.0.angular_velocity.2"] == values["particles.1.angular_velocity.2"]


def test_a_sweep_writes_its_chung_ooi_figure(tmp_path):
    # test 1 for HMD: the hertz figure and the collision columns of sweep.csv
    path = FILES / "test1.toml"
    data = tomllib.loads(path.read_text())
    data["sweep"]["cases"]["contact.law"] = ["hmd"]
    data["sweep"]["series_labels"] = ["HMD"]
    plan = sweep.plan(data, str(path))
    rows = sweep.run(plan, tmp_path, progress=False, executor=executors.LocalProcesses(1))
    from minidem.studies import figures

    written = figures.draw(plan, rows, tmp_path)
    assert [p.name for p in written] == ["hertz.png"] and written[0].stat().st_size > 10_000
    header = (tmp_path / "sweep.csv").read_text().splitlines()[0].split(",")
    assert "hertz_peak_force_n" in header and "rigid_spin_rad_s" in header
    for row in rows:
        assert row["max_overlap_m"] == pytest.approx(row["hertz_max_overlap_m"], rel=5e-3)


def test_force_time_figure_without_traces_is_refused():
    data = tomllib.loads((FILES / "test2.toml").read_text())
    data["sweep"]["keep_traces"] = False
    with pytest.raises(ScenarioError, match=r'sweep.figures: "force_time" plots the cases\' traces: it needs '
                                            r"sweep.keep_traces = true"):
        sweep.plan(data, "test2.toml")
