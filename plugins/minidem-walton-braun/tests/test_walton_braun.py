"""The Walton-Braun plugin against its theory (Walton & Braun 1986).

Expected values are analytic: a linear spring k on mass m is a harmonic oscillator, so
loading lasts a quarter period pi/2 sqrt(m/k1) and reaches delta_max = v sqrt(m/k1);
unloading on k2 returns the speed e v with e^2 = k1/k2 (energy k1 delta_max^2 / 2 in,
k2 (delta_max - delta_0)^2 / 2 out).
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from minidem.contact import laws
from minidem.results import analysis
from minidem.scene import scenario
from minidem.engine import simulation
from minidem.engine.kernel import TRACE_COLUMNS
from minidem_walton_braun.law import MAX_OVERLAP, WALTON_BRAUN, walton_braun_force

RADIUS, DENSITY, SPEED, MU = 0.025, 2650.0, 5.0, 0.1
MASS = 4.0 / 3.0 * math.pi * RADIUS**3 * DENSITY
K1 = 1.0e8  # N/m, given so that the theory below needs no calibration


def scene_data(angle_deg=0.0, restitution=0.7, friction=MU, speed=SPEED, **contact):
    """A sphere hitting a wall of the same material (Thornton et al. 2011's set-up)."""
    contact = {"loading_stiffness": K1, **contact}
    return {
        "materials": {"glass": {"youngs_modulus": 70e9, "poisson_ratio": 0.3, "density": DENSITY}},
        "contact": {"law": "walton_braun", "friction": friction, "restitution": restitution,
                    **{k: v for k, v in contact.items() if v is not None}},
        "walls": [{"normal": [0.0, 0.0, 1.0], "material": "glass"}],
        "impact": {"material": "glass", "radius": RADIUS, "speed": speed, "angle_deg": angle_deg},
    }


def impact(angle_deg=0.0, restitution=0.7, friction=MU, speed=SPEED, **contact):
    sim = simulation.Simulation(scenario.build_scene(scene_data(angle_deg, restitution, friction, speed, **contact),
                                                     "walton_braun_test.toml"))
    return sim, sim.run()


def test_registered_through_its_entry_point():
    entry = laws.load_registry().entry("walton_braun")
    assert entry.distribution == "minidem-walton-braun"
    assert entry.version == importlib.metadata.version("minidem-walton-braun")
    assert entry.plugin == "walton_braun"
    assert laws.load_registry().get("wb") is entry.law


def test_listed_by_minidem_laws_with_package_and_version():
    script = Path(sys.executable).with_name("minidem")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "minidem.cli"]
    done = subprocess.run(command + ["laws", "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    payload = json.loads(done.stdout)
    [law] = [law for law in payload["laws"] if law["name"] == "walton_braun"]
    assert (law["package"], law["version"]) == ("minidem-walton-braun", "0.1.0")
    assert {p["name"] for p in law["parameters"]} >= {"friction", "restitution", "loading_stiffness"}
    assert not [b for b in payload["broken"] if "walton" in b["plugin"]]


@pytest.mark.parametrize("restitution", [0.3, 0.7, 0.95, 1.0])
def test_normal_impact_reproduces_restitution_overlap_and_duration(restitution):
    sim, result = impact(0.0, restitution)
    s = analysis.summary(result)
    # e^2 = k1/k2 by construction of k2 (prepare); the run must return the speed e V
    assert s["en"] == pytest.approx(restitution, abs=1e-4)
    assert s["energy_ratio"] == pytest.approx(restitution**2, abs=2e-4)
    # quarter period on k1: delta_max = V sqrt(m/k1)
    assert s["max_overlap_m"] == pytest.approx(SPEED * math.sqrt(MASS / K1), rel=1e-4)
    # overlap lasts: loading pi/2 sqrt(m/k1), force-carrying unloading pi/2 sqrt(m/k2),
    # then free flight out of the dent delta_0 = (1 - e^2) delta_max at speed e V
    k2 = K1 / restitution**2
    dent_time = (1.0 - restitution**2) * math.sqrt(MASS / K1) / restitution
    expected = 0.5 * math.pi * (math.sqrt(MASS / K1) + math.sqrt(MASS / k2)) + dent_time
    assert s["contact_duration_s"] == pytest.approx(expected, rel=5e-3)
    # the law's own contact time is the force pulse and sets the automatic time step
    pulse = 0.5 * math.pi * (math.sqrt(MASS / K1) + math.sqrt(MASS / k2))
    assert sim.reference_contact_time == pytest.approx(pulse, rel=1e-12)


@pytest.mark.parametrize("speed", [0.1, 50.0])
def test_restitution_does_not_depend_on_speed(speed):
    # a linear hysteretic law dissipates the same fraction at every speed
    _, result = impact(0.0, 0.6, speed=speed)
    assert analysis.rebound(result)["en"] == pytest.approx(0.6, abs=1e-4)
    assert result.max_overlap == pytest.approx(speed * math.sqrt(MASS / K1), rel=1e-4)


ANGLES = [1.0, 3.0, 5.0, 10.0, 20.0, 30.0, 45.0, 60.0, 80.0]


@pytest.mark.parametrize("restitution", [0.5, 1.0])
def test_oblique_impacts_never_create_energy(restitution):
    for angle in ANGLES:
        _, result = impact(angle, restitution)
        ratio = analysis.energy_ratio(result)
        # the normal branch returns at most e^2 of the normal energy; the incremental
        # tangential spring can only store or dissipate
        assert ratio <= 1.0 + 1e-9, (angle, ratio)
        assert analysis.rebound(result)["en"] == pytest.approx(restitution, abs=1e-4)


def test_gross_sliding_matches_rigid_body_theory():
    # Thornton et al. 2011 eqs 6-8 with the law's own en
    theta, e = 60.0, 0.7
    _, result = impact(theta, e)
    r = analysis.rebound(result)
    assert r["y2"] == pytest.approx(-5.0 * MU, abs=1e-3)
    assert r["y1"] == pytest.approx(r["x"] - 7.0 * MU, abs=1e-3)
    assert r["et"] == pytest.approx(1.0 - MU * (1.0 + e) / math.tan(math.radians(theta)), abs=1e-3)


def test_sticking_contact_is_the_analytic_tangential_oscillator():
    # An oblique impact in partial slip (5 deg, e = 0.7): while the contact point sticks,
    # the incremental spring's force is kt s with m s'' = -(7/2) kt s for a solid sphere,
    # whatever the hysteretic normal force does, so from s(0) = 0, s'(0) = V sin(theta):
    # Ft = kt Vt sin(w t) / w, w = sqrt(7 kt / 2m), with kt = 2(1 - nu)/(2 - nu) k1 (the
    # paper's eq 10 ratio, the law's default) until Ft first meets mu Fn. Velocity Verlet's
    # error is O((w dt)^2): bound 20 (w dt)^2 of the peak (measured 2.6e-7 of it against
    # 2.6e-5); a spin term of the wrong sign or I = 1/2 m R^2 is off by 0.25 of it or more.
    data = scene_data(5.0)
    data["output"] = {"trace": True}
    sim = simulation.Simulation(scenario.build_scene(data, "walton_braun_test.toml"))
    result = sim.run()
    columns = {name: i for i, name in enumerate(TRACE_COLUMNS)}
    time, normal, force = (result.trace[:, columns[name]] for name in ("time_s", "normal_force_n",
                                                                        "tangential_force_x_n"))
    kt = 2.0 * (1.0 - 0.3) / (2.0 - 0.3) * K1
    omega = math.sqrt(3.5 * kt / MASS)
    capped = np.flatnonzero((normal > 0) & (np.abs(force) >= MU * normal * (1 - 1e-12)))
    assert capped.size and capped[0] > 100  # partial slip: a stretch of sticking first
    sticking = slice(0, capped[0])
    expected = kt * SPEED * math.sin(math.radians(5.0)) * np.sin(omega * time[sticking]) / omega
    scale = np.max(np.abs(expected))
    assert np.max(np.abs(force[sticking] - expected)) <= 20.0 * (omega * result.dt) ** 2 * scale


def test_frictionless_impact_keeps_tangential_velocity_and_never_spins():
    _, result = impact(45.0, 0.5, friction=0.0)
    r = analysis.rebound(result)
    assert r["et"] == pytest.approx(1.0, abs=1e-12)
    assert np.array_equal(result.angular_velocity, np.zeros((1, 3)))


def test_force_follows_loading_unloading_and_reloading_branches():
    """Drive the compiled force function directly through a load-unload-reload cycle."""
    k2 = 4.0 * K1  # e = 0.5
    constants = np.array([K1, k2, 0.5 * K1, 0.0])
    history = np.zeros(sum(slot.size for slot in WALTON_BRAUN.history))
    zero = (0.0, 0.0, 0.0)

    def force(overlap):
        return walton_braun_force(constants, RADIUS, MASS, overlap, 0.0, 0.0, zero, zero, history)[0]

    assert force(1e-4) == pytest.approx(K1 * 1e-4)  # loading line
    assert force(2e-4) == pytest.approx(K1 * 2e-4)
    assert history[MAX_OVERLAP] == 2e-4
    # unloading on k2 from (2e-4, k1 2e-4): zero at delta_0 = 2e-4 (1 - k1/k2) = 1.5e-4
    assert force(1.8e-4) == pytest.approx(K1 * 2e-4 - k2 * 0.2e-4)
    assert force(1.5e-4) == pytest.approx(0.0, abs=1e-6)
    assert force(1.0e-4) == 0.0  # inside the dent: no force, no tension
    # reloading retraces the unloading line, then continues on the loading line
    assert force(1.9e-4) == pytest.approx(K1 * 2e-4 - k2 * 0.1e-4)
    assert force(3e-4) == pytest.approx(K1 * 3e-4)
    assert history[MAX_OVERLAP] == 3e-4


def test_bad_parameters_are_refused_by_name():
    law = WALTON_BRAUN
    _, errors = law.resolve_parameters({"friction": 0.1, "restitution": 0.0})
    assert errors == ["'restitution' must be > 0, got 0 (unit -, bounds (0, 1])"]
    _, errors = law.resolve_parameters({"friction": 0.1})
    assert "law 'walton_braun' needs parameter 'restitution'" in errors[0]


def test_calibrated_loading_stiffness_is_the_paper_ls_stiffness():
    # with no loading_stiffness, k1 is LS's kn of Thornton et al. Table 1: 108 MN/m for nu = 0.3
    scene = scenario.build_scene(scene_data(0.0, 0.8, loading_stiffness=None), "t.toml")
    constants = simulation.Simulation(scene).constants_by_pair[(0, 0)]
    assert constants["loading_stiffness"] / 1e6 == pytest.approx(108.0, abs=1.0)
    assert constants["unloading_stiffness"] == pytest.approx(constants["loading_stiffness"] / 0.64)
    # kt = kappa k1 with kappa = 2(1-nu)/(2-nu) = 0.8235 (eq 10): Table 1's 89 MN/m
    assert constants["tangential_stiffness"] / 1e6 == pytest.approx(89.0, abs=1.0)
