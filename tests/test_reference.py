"""The independent reference solution (minidem.studies.reference) and the engine against it.

Expected values come from closed forms: Hertz's normal impact (paper eqs 12-13, with the
exact duration coefficient), the linear spring's half period (eq 27), the constant force
obliquity of LS at kappa = 2/7 (section 4: et = 3/7), and rigid-body gross sliding
(eqs 6-8). The engine target (1e-4 absolute in y1, y2, et) is issue 5's.
"""

import math

import pytest

from minidem.studies import reference
from minidem.studies.reference import Impact, solve

PAPER = Impact()  # R = 25 mm, 2650 kg/m3, E = 70 GPa, nu = 0.3, mu = 0.1, V = 5 m/s


def test_hertz_normal_impact_duration_and_overlap():
    s = solve(Impact(law="hmd", angle_deg=0.0), 1e-12)
    m, v = PAPER.mass, PAPER.speed
    # delta_max = (15 m V^2 / (16 sqrt(R) E*))^(2/5)  (paper eq 12)
    delta_max = (15 * m * v**2 / (16 * math.sqrt(PAPER.radius) * PAPER.effective_modulus)) ** 0.4
    # tc = 2 delta_max / V * int_0^1 dx / sqrt(1 - x^(5/2)) = (4/5) B(2/5, 1/2) delta_max / V
    # (energy integral of m u^2/2 + (8/15) E* sqrt(R) d^(5/2); 2.9432 delta_max / V, eq 13's 2.868 form)
    tc = 0.8 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9) * delta_max / v
    assert s.max_overlap == pytest.approx(delta_max, rel=1e-9)
    assert s.contact_duration == pytest.approx(tc, rel=1e-9)
    assert s.en == pytest.approx(1.0, abs=1e-9)  # elastic
    assert s.y2 == 0.0 and s.y1 == 0.0  # no tangential motion, no spin


def test_linear_normal_impact_half_period():
    s = solve(Impact(law="ls", angle_deg=0.0), 1e-12)
    kn = PAPER.ls_normal_stiffness
    assert kn == pytest.approx(108e6, abs=1e6)  # Table 1, kappa = 0.8235 row
    assert s.contact_duration == pytest.approx(math.pi * math.sqrt(PAPER.mass / kn), rel=1e-9)  # eq 27
    assert s.max_overlap == pytest.approx(PAPER.speed * math.sqrt(PAPER.mass / kn), rel=1e-9)
    assert s.en == pytest.approx(1.0, abs=1e-9)


@pytest.mark.parametrize("angle", [2.0, 5.0, 10.0, 15.0])
def test_linear_spring_kappa_two_sevenths_gives_three_sevenths(angle):
    # kappa = 2/7: tangential and normal periods equal, Ft/Fn = (2/7) tan(theta) < mu
    # below ~19 deg, no sliding, et = 3/7 exactly (paper section 4, Fig 4)
    s = solve(Impact(law="ls", angle_deg=angle, stiffness_ratio=2.0 / 7.0), 1e-12)
    assert s.et == pytest.approx(3.0 / 7.0, abs=1e-9)


@pytest.mark.parametrize("law", reference.LAWS)
def test_gross_sliding_matches_rigid_body_theory(law):
    # sliding throughout at 60 deg for every law: eqs 6-8 hold exactly, not just approximately
    mu, angle = PAPER.friction, 60.0
    s = solve(Impact(law=law, angle_deg=angle), 1e-12)
    assert [e for _, e in s.events if e.startswith("start")] == ["start in slide"] or law == "hmdns_integral"
    assert s.y1 == pytest.approx(s.x - 7 * mu, abs=1e-9)
    assert s.y2 == pytest.approx(-5 * mu, abs=1e-9)
    assert s.et == pytest.approx(1 - mu * (1 + s.en) / math.tan(math.radians(angle)), abs=1e-9)


@pytest.mark.parametrize("law", reference.LAWS)
def test_two_tolerances_agree_far_below_the_reported_errors(law):
    # the engine errors reported in docs/benchmarks.md are >= 1e-8; the reference at
    # rtol 1e-10 and 1e-12 must agree far below that
    for angle in (1.0, 5.0, 20.0):
        coarse = solve(Impact(law=law, angle_deg=angle), 1e-10)
        fine = solve(Impact(law=law, angle_deg=angle), 1e-12)
        for k in ("en", "et", "y1", "y2"):
            assert abs(getattr(coarse, k) - getattr(fine, k)) < 2e-9, (law, angle, k)


def test_hmd_switches_are_events():
    # at 5 deg HMD starts in the eq 19 special case, unloads when the surface velocity
    # reverses and slides near the end (paper Fig 11): every switch is located, none straddled
    s = solve(Impact(law="hmd", angle_deg=5.0), 1e-12)
    labels = [e for _, e in s.events]
    assert labels[0] == "start in load" and labels[-1] == "end"
    assert "unload" in labels and ("slide+" in labels or "slide-" in labels)


# Measured with `minidem bench` (docs/benchmarks.md): the incremental Hertz-Mindlin laws
# updated with Ft += kt(a_new) dd were first order in dt; at 2000 steps per contact HMD was
# 2.5e-3 off in et at 1 deg and HM 3.8e-4 at 5 deg. The engine uses the stiffness averaged
# over the step (test_hm_and_hmd_converge_at_second_order below).
@pytest.mark.parametrize("law", reference.LAWS)
def test_engine_within_1e_4_of_reference_at_default_settings(law):
    from minidem.studies import bench

    for angle in (1.0, 5.0, 20.0, 45.0):
        summary, _ = bench.engine_case(law, angle)
        errors = bench.errors(summary, bench.reference_solution(law, angle))
        assert max(errors.values()) <= 1e-4, (law, angle, errors)


def test_hmd_engine_within_1e_4_of_reference_over_the_paper_sweep():
    # issue 13: at the default settings, every angle of the paper's sweep (0.5 deg
    # included), y1, y2 and et; measured worst 2.7e-7 (0.5 deg; 6.8e-6 at 12 deg before
    # the second-order integration of eq 21, docs/laws.md HMD choice 5)
    from minidem.studies import bench

    for angle in reference.PAPER_ANGLES_DEG:
        summary, _ = bench.engine_case("hmd", angle)
        errors = bench.errors(summary, bench.reference_solution("hmd", angle))
        assert max(errors[k] for k in ("et", "y1", "y2")) <= 1e-4, (angle, errors)


def test_previous_reading_of_partial_slip_reversal_engine_within_1e_4_of_reference():
    # partial_slip_reversal_check = 0 (a reversal the instant the increment reverses) is
    # the same law in the engine and the reference as the default reading
    from conftest import impact_summary

    for angle in (0.5, 1.0, 3.0, 5.0):
        summary = impact_summary("hmd", angle, contact__partial_slip_reversal_check=0)
        expected = solve(Impact(law="hmd", angle_deg=angle, partial_slip_reversal_check=0), 1e-10)
        for k in ("et", "y1", "y2"):
            assert abs(summary[k] - getattr(expected, k)) <= 1e-4, (angle, k)


# ../shared/paper/models.md, "The reading that gives the paper's 4 %": an independent
# event-driven solution (DOP853, rtol 1e-12) of the same rule, printed to 6 digits / 0.01 %
MODELS_MD_LS_OVER_HMD = {1.0: 0.0439, 2.0: 0.0329, 3.0: 0.0261, 5.0: 0.0167}


def test_reference_reproduces_the_independent_solution_of_models_md():
    hmd = solve(Impact(law="hmd", angle_deg=1.0), 1e-12)
    ls = solve(Impact(law="ls", angle_deg=1.0), 1e-12)
    assert hmd.et == pytest.approx(0.829444, abs=1e-6)
    assert ls.et == pytest.approx(0.865841, abs=1e-6)
    for angle, excess in MODELS_MD_LS_OVER_HMD.items():
        ratio = solve(Impact(law="ls", angle_deg=angle), 1e-10).et / solve(Impact(law="hmd", angle_deg=angle), 1e-10).et
        assert ratio - 1 == pytest.approx(excess, abs=5e-5), angle


@pytest.mark.parametrize("angle", [1.0, 5.0])
def test_reference_reversal_in_partial_slip_waits_until_admissible(angle):
    # After the full reversal (Masing, after maximum compression) the new loading branch is
    # in partial slip while Fn falls, and the surface velocity turns against it. The
    # reading before issue 13 unloads at that instant; with the admissibility test the
    # branch goes on past it (8 G* a |vs| stays below mu |Fn'|) until the Coulomb limit.
    def labels_and_times(check):
        s = solve(Impact(law="hmd", angle_deg=angle, partial_slip_reversal_check=check), 1e-12)
        return [e for _, e in s.events], [t for t, _ in s.events]

    instant, instant_times = labels_and_times(0)
    waits, waits_times = labels_and_times(1)
    velocity_reversal = instant_times[instant.index("unload", instant.index("reverse"))]
    after = waits[waits.index("reverse") + 1:]
    assert after[0] in ("slide+", "slide-") and after[1] == "end"
    assert waits_times[waits.index("reverse") + 1] > velocity_reversal


@pytest.mark.parametrize("law", ["ls", "hmd", "hm"])
def test_reference_sliding_throughout_threshold(law):
    # Sliding throughout iff the stick event never fires: kappa vs - mu u > 0 until the end
    # (u = -Vni, vs = Vti - 7 mu Vni in gross sliding), tan(theta) >= mu (7 - 1/kappa)
    # (docs/paper-reproduction.md, eq 36 derived): 30.0524 deg, models.md's 30.05.
    def throughout(angle):
        labels = [e for _, e in solve(Impact(law=law, angle_deg=angle), 1e-10).events]
        return labels[0] == "start in slide" and "stick" not in labels

    lo, hi = 29.0, 31.0
    assert throughout(hi) and not throughout(lo)
    while hi - lo > 1e-5:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if throughout(mid) else (mid, hi)
    critical = math.degrees(math.atan(PAPER.friction * (7 - 1 / PAPER.kappa)))
    assert lo == pytest.approx(critical, abs=2e-5)
    assert lo == pytest.approx(30.05, abs=0.005)


@pytest.mark.parametrize("reading", [1, 2, 3, 4, 5])
def test_engine_within_1e_4_of_reference_for_every_reading_of_eq_24(reading):
    # HMD's special_case (docs/laws.md "HMD implementation choices", item 9): the
    # reference locates where each reading's special state ends as an event; the engine
    # tests it per step. Same 1e-4 target as the default law (issue 5).
    import warnings

    from minidem.results import analysis
    from minidem.studies import bench
    from minidem.scene import scenario
    from minidem.engine import simulation

    for angle in (1.0, 5.0, 8.0, 20.0):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = scenario.load_scene(bench.SCENARIO, [f"impact.angle_deg={angle!r}", 'contact.law="hmd"',
                                                         f"contact.special_case={reading}"])
        summary = analysis.summary(simulation.Simulation(scene).run())
        expected = solve(Impact(law="hmd", angle_deg=angle, special_case=reading), 1e-10)
        for k in ("et", "y1", "y2"):
            assert abs(summary[k] - getattr(expected, k)) <= 1e-4, (reading, angle, k)


def _observed_order(steps, errors):
    """Least-squares slope of log(error) against log(dt), dt ~ 1/steps."""
    import numpy as np

    return float(-np.polyfit(np.log(steps), np.log(errors), 1)[0])


@pytest.mark.parametrize("law", ["hmd", "hm"])
def test_hm_and_hmd_converge_at_second_order(law):
    # Issue 13, "HMD at second order": worst error in y1, y2, et over 1, 5, 10, 20 deg
    # against the reference. Velocity Verlet is second order; HMD was first order (order
    # 1.01 in et, docs/benchmarks.md: its Coulomb-limit arrival, where theta ~ (t_c - t)^(1/2),
    # fell inside a step) and HM 1.57 (the stiffness at mid-step, while a ~ sqrt(t) after
    # first touch). Measured now: HMD 6.1e-6, 8.4e-7, 2.9e-7, 9.3e-8, 1.7e-8 at 500 ... 8000
    # steps per contact (slope 2.1), HM 7.9e-6 ... 1.7e-8 (2.2); the order is asked to be
    # at least 1.8, and 1e-6 to be reached by 2000 steps per contact (issue: <= 4000).
    from conftest import impact_summary

    angles, steps = (1.0, 5.0, 10.0, 20.0), (500, 1000, 2000, 4000, 8000)
    expected = {a: solve(Impact(law=law, angle_deg=a), 1e-12) for a in angles}
    worst = []
    for n in steps:
        worst.append(max(abs(impact_summary(law, a, run__steps_per_contact=n)[k] - getattr(expected[a], k))
                         for a in angles for k in ("et", "y1", "y2")))
    assert _observed_order(steps, worst) >= 1.8, worst
    assert max(worst[steps.index(2000):]) <= 1e-6, worst


def test_hmd_full_reversal_needs_a_positive_reversal_point():
    # At mu = 10 eq 23 drives Ft* far below zero after the maximum compression; -Ft* is
    # then no point of the mirrored virgin curve and no full reversal may happen there
    # (docs/laws.md, HMD choice 6). The reference used to take one at Ft = -Ft* > 0 (et
    # 0.629 at 5 deg against the engine's 0.734). Now no reversal happens at all in this
    # impact, and the engine agrees within its own step-to-step spread at mu = 10
    # (4e-4 between 2000 and 32000 steps per contact, docs/laws.md), taken as 1e-3.
    from minidem.results import analysis
    from minidem.studies import bench
    from minidem.scene import scenario
    from minidem.engine import simulation

    expected = solve(Impact(law="hmd", angle_deg=5.0, friction=10.0), 1e-10)
    assert "reverse" not in [e for _, e in expected.events]
    scene = scenario.load_scene(bench.SCENARIO, ["impact.angle_deg=5.0", 'contact.law="hmd"', "contact.friction=10.0"])
    summary = analysis.summary(simulation.Simulation(scene).run())
    assert abs(summary["et"] - expected.et) <= 1e-3


# HMD at large friction, where eq 23 moves Ft* by mu dFn a step: the engine and the
# reference used to take different branch switches at 1 deg for 0.5 <= mu <= 1.1 and at
# mu = 2, 3 deg (et 0.750 against 0.845 at mu = 1, 1 deg). The reference missed the full
# reversal at Ft = -Ft* (its event function jumped over it); the engine missed it from
# mu ~ 1.2, and set a reversal point up to mu dFn / 2 off depending on where in its step
# the displacement reversed (docs/laws.md, HMD choices 3 and 6). Tolerance: with both
# fixed, the engine's worst error on this grid (et, y1, y2) at the default 4000 steps per
# contact was 6.6e-5 (mu = 5, 0.5 deg), and over 3990..4010 steps per contact et moved by
# at most 5.2e-5 from the reference; before, that spread was 3.7e-3 at mu = 5, 0.5 deg.
# With issue 13's reversal rule and the second-order integration of eq 21 (choice 5) the
# worst error is 1.2e-5 (mu = 5, 0.5 deg) and the 3990..4010 spread 1.2e-5 (same case).
# So the 1e-4 holds here too. The reference at rtol 1e-10 is within 1e-6 of rtol
# 1e-12 on this grid (rtol 1e-8 is not good enough at mu = 5: 5.4e-5, because its force
# scale is mu times the peak normal force); about 40 ms a solve.
HIGH_FRICTION_GRID = [(mu, angle) for mu in (0.3, 0.5, 0.7, 1.0, 1.3, 2.0, 5.0) for angle in (0.5, 1.0, 3.0, 10.0)]


def test_hmd_engine_matches_reference_over_friction_and_angle():
    from conftest import impact_summary

    failures = []
    for mu, angle in HIGH_FRICTION_GRID:
        summary = impact_summary("hmd", angle, contact__friction=mu)
        expected = solve(Impact(law="hmd", angle_deg=angle, friction=mu), 1e-10)
        error = max(abs(summary[k] - getattr(expected, k)) for k in ("et", "y1", "y2"))
        if error > 1e-4:
            failures.append((mu, angle, summary["et"], expected.et, error))
    assert not failures, failures


@pytest.mark.parametrize("partial_slip_reversal_check", [1, 0])
def test_hmd_full_reversal_is_taken_where_both_conditions_hold(partial_slip_reversal_check):
    # mu = 1, 1 deg: Ft* falls through zero within about one reference step just after
    # Ft + Ft* crossed zero; the full reversal (Ft <= -Ft* with Ft* > 0) happens there.
    # The old event function found it only when the steps were small enough (rtol 1e-10
    # took the reversal, rtol 1e-9 and 1e-8 did not: et 0.8453 against 0.7504 in the
    # reading before issue 13): now at every tolerance, in both readings of a reversal in
    # partial slip, so every tolerance agrees with rtol 1e-12 (the solver's own accuracy,
    # test_two_tolerances_agree_far_below_the_reported_errors: 2e-9; 1e-6 here for 1e-8).
    # At mu = 1.3 Ft* reaches zero while Ft > 0: no full reversal. The reading before
    # issue 13 then reloads at the velocity reversal; with the admissibility test the
    # reload never becomes admissible before the unloading branch reaches the Coulomb limit.
    reading = dict(law="hmd", angle_deg=1.0, partial_slip_reversal_check=partial_slip_reversal_check)
    finest = solve(Impact(friction=1.0, **reading), 1e-12)
    for rtol in (1e-8, 1e-9, 1e-10):
        reverses = solve(Impact(friction=1.0, **reading), rtol)
        labels = [e for _, e in reverses.events]
        assert labels.index("reverse") > labels.index("max_overlap"), rtol
        assert reverses.et == pytest.approx(finest.et, abs=1e-6), rtol
    labels = [e for _, e in solve(Impact(friction=1.3, **reading), 1e-10).events]
    assert "reverse" not in labels and ("reload" in labels) == (partial_slip_reversal_check == 0)


def test_reference_dashpot_factors_match_the_engine_mappings():
    # The reference finds the dashpot's factor by bisection on its own event-located normal
    # impact (rtol 1e-12); the engine maps e by the closed form of the clipped linear
    # spring-dashpot (LS) and by RK4 on the dimensionless Hertz-dashpot equation (HM,
    # documented to reproduce e within 1e-6): alpha measured 1.6e-6 apart
    from minidem.contact.builtin_laws import common

    for e in (0.3, 0.5, 0.9):
        assert reference.damping_for(Impact(law="ls", restitution=e)) == pytest.approx(
            common.linear_damping_ratio(e), rel=1e-8)
        assert reference.damping_for(Impact(law="hm", restitution=e)) == pytest.approx(
            common.hertz_damping_factor(e), rel=1e-5)
        assert solve(Impact(law="hm", angle_deg=0.0, restitution=e)).en == pytest.approx(e, abs=1e-9)


@pytest.mark.parametrize("law", reference.DAMPED_LAWS)
def test_damped_oblique_impact_converges_to_the_reference(law):
    # e = 0.5, mu = 0.3: sticking at first touch (the dashpot's force outgrows every
    # elastic trial), then slip in both directions and release where the force returns to
    # zero. The engine hands the law the velocity at the end of the step (kernel
    # END_VELOCITY) and starts a contact at the exact touch of the paper's start (kernel
    # ``touches_at_start``): with the drift's half-step velocity and the touch's force left out, as
    # LAMMPS and LIGGGHTS do, every damped impact was first order, 1.4e-5 (HM's en) to
    # 1.9e-4 (LS's y1) off at 4000 steps per contact (docs/time-step.md).
    # LS: its force is smooth but for the jump c v at the touch, now in the first step:
    # second order, the error falls 16-fold from 2000 to 8000 steps where first order
    # gives 4 (measured: en 2.1e-7 -> 1.3e-8; everything else within 1.8e-7 at 2000 and
    # 3e-8 at 4000 steps, near the reference's own 3.5e-9).
    # HM: its dashpot c(d) v grows as d^(1/4) ~ t^(1/4) from the touch, whose first steps
    # no trapezoid integrates to better than dt^(5/4) (a property of the model): the order
    # is 1.25 at the limit, above it while the dt^2 terms weigh (measured: worst over the
    # components and angles 2.9e-5, 1.2e-5, 4.7e-6 at 2000, 4000, 8000 steps, ratios 2.4
    # and 2.5 a halving; first order gives 2).
    from conftest import impact_summary

    steps = (2000, 4000, 8000)
    worst = []
    for angle in (10.0, 30.0, 45.0):
        expected = solve(Impact(law=law, angle_deg=angle, restitution=0.5, friction=0.3), 1e-12)
        assert [e for _, e in expected.events][0] == "start in stick"
        runs = {n: impact_summary(law, angle, contact__restitution=0.5, contact__friction=0.3,
                                  run__steps_per_contact=n) for n in steps}
        errors = {n: {k: abs(runs[n][k] - getattr(expected, k)) for k in ("en", "et", "y1", "y2")} for n in steps}
        worst.append([max(errors[n].values()) for n in steps])
        if law == "ls":
            assert errors[2000]["en"] / errors[8000]["en"] > 8.0, (angle, errors)
            assert max(errors[4000].values()) < 1e-7, (angle, errors)
    worst = [max(w[k] for w in worst) for k in range(len(steps))]
    if law == "hm":
        assert worst[0] / worst[1] > 2.2 and worst[1] / worst[2] > 2.2, worst
        assert worst[1] < 3e-5, worst

def _damped_ls_impact(**changes):
    """The summary of LS at e = 0.5, mu = 0.3, 30 deg from oblique.toml, changed as given
    (keys of the scenario's tables: walls, impact, run)."""
    import tomllib

    from conftest import OBLIQUE
    from minidem.engine import simulation
    from minidem.results import analysis
    from minidem.scene import scenario

    data = tomllib.loads(OBLIQUE.read_text())
    data["contact"].update(law="ls", restitution=0.5, friction=0.3)
    data["impact"]["angle_deg"] = 30.0
    data["output"] = {"vtk": False}
    for table, values in changes.items():
        if table == "walls":
            data["walls"][0].update(values)
        else:
            data.setdefault(table, {}).update(values)
    return analysis.summary(simulation.Simulation(scenario.build_scene(data)).run())


@pytest.mark.parametrize("start", [{"run": {"integrator": "velocity_verlet"}},
                                   {"impact": {"gap": 1e-3}, "run": {"integrator": "analytic_flight"}}])
def test_a_touch_at_the_start_counts_on_a_tilted_plane_too(start):
    # The same impact on a plane tilted by 10 deg: the sphere's placement (touching, the
    # paper's start) or analytic flight's move to the touch leaves an overlap of a few
    # 1e-18 m either side of zero, and the touch at the start must count all the same
    # (kernel touches_at_start), or LS's jump c v at the touch is missed: a first-order
    # error, 1.0e-4 in en at 4,000 steps per contact (measured before the tolerance on
    # such a tilt; the flat plane and the tilted one now agree within 5e-13)
    tilt = math.radians(10.0)
    flat = _damped_ls_impact(**start)
    tilted = _damped_ls_impact(walls={"normal": [0.0, math.sin(tilt), math.cos(tilt)]}, **start)
    for k in ("en", "et", "y1", "y2"):
        assert tilted[k] == pytest.approx(flat[k], abs=1e-9), k
