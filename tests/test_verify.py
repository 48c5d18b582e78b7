"""`minidem verify` must tell a sound law from an unsound one.

The paper (section 5, Fig 12) is the oracle: the incremental linear spring conserves
energy and obeys the rigid-body limit, while the integral Hertz-Mindlin form (eq 38)
creates energy over its first force-displacement loop at 5 deg.
"""

import json
import subprocess
import sys
from pathlib import Path

from minidem.studies import verify


def by_name(checks):
    return {c.name: c for c in checks}


def test_linear_spring_passes_every_check(tmp_path):
    checks = by_name(verify.run_battery("ls", [], tmp_path))
    failed = [c for c in checks.values() if c.passed is False]
    assert not failed, verify.format_table(failed)
    report = json.loads((tmp_path / "verify.json").read_text())
    assert report["law"] == "ls" and len(report["checks"]) == len(checks)
    assert (tmp_path / "verify.png").stat().st_size > 10_000


def test_integral_law_is_caught_creating_energy(tmp_path):
    checks = by_name(verify.run_battery("hmdns_integral", []))
    assert checks["5 deg force-displacement loop creates no energy"].passed is False
    assert checks["elastic impacts create no energy"].passed is False
    # ...while the checks it should pass still pass: it is Hertz in the normal direction
    # and Coulomb-limited in gross sliding
    assert checks["rigid-body sliding limit"].passed is True
    assert checks["normal-impact duration"].passed is True


def test_cli_exit_code_reports_failure(tmp_path):
    bad = subprocess.run([sys.executable, "-m", "minidem.cli", "verify", "hmdns_integral", "--out", str(tmp_path)],
                         capture_output=True, text=True)
    assert bad.returncode == 1, bad.stderr
    assert "FAIL" in bad.stdout and "PASS" in bad.stdout
    # each group of checks announced as it starts (review: tens of silent seconds)
    assert "minidem: verify hmdns_integral: the history slots" in bad.stderr
    unknown = subprocess.run([sys.executable, "-m", "minidem.cli", "verify", "hdm"], capture_output=True, text=True)
    assert unknown.returncode == 2 and "did you mean" in unknown.stderr.lower() and "hmd" in unknown.stderr


OVERRUN_PLUGIN = '''
import numba

from minidem import hookimpl
from minidem.contact.builtin_laws.common import incremental_spring
from minidem.contact.laws import ContactLaw, HistorySlot, Parameter


@numba.njit
def overrun_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                  normal_velocity, tangential_increment, tangential_velocity, history):
    normal_force = constants[0] * normal_overlap
    # incremental_spring keeps a vector in history[0:3], but the law declares one slot
    ftx, fty, ftz = incremental_spring(history, constants[1], tangential_increment, constants[2] * normal_force)
    return normal_force, ftx, fty, ftz


def prepare(pair, params):
    return {"kn": 1e8, "kt": 1e8, "mu": params["friction"]}


@hookimpl
def minidem_register_laws(registry):
    registry.add(ContactLaw(
        name="fake_overrun", description="declares 1 history slot, writes 3", constants=("kn", "kt", "mu"),
        parameters=(Parameter("friction", None, "-", "Coulomb friction", low=0.0, required=True),),
        history=(HistorySlot("tangential_force_x", "x component of the tangential force (N)"),), prepare=prepare, force=overrun_force))
'''


def test_a_force_writing_past_its_declared_history_is_caught(tmp_path, monkeypatch):
    """numba does not check bounds: without this check the write would corrupt the next
    contact's history silently (a plugin author's mistake found in review)."""
    import importlib

    from minidem.contact import laws

    (tmp_path / "fake_overrun_plugin.py").write_text(OVERRUN_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = laws.load_registry(extra_plugins=(importlib.import_module("fake_overrun_plugin"),))
    assert not registry.broken, registry.broken
    monkeypatch.setattr(laws, "_REGISTRY", registry)
    [check] = verify.Battery("fake_overrun").history_bounds()
    assert check.passed is False and "wrote history[1]" in check.value and "declares 1 slot" in check.value
    [sound] = verify.Battery("hm").history_bounds()
    assert sound.passed is True
    # the whole battery ends there, its report written: the engine's checks would run the
    # force on the engine's history rows, and the process died of the overrun (free():
    # invalid next size) before it printed anything (found by a plugin author's walk-through)
    [ended] = verify.run_checks(verify.Battery("fake_overrun"), tmp_path / "report")
    assert ended.passed is False and ended.name == check.name
    assert json.loads((tmp_path / "report" / "verify.json").read_text())["checks"][0]["passed"] is False
    assert verify.report_files(tmp_path / "report", [ended]) == [tmp_path / "report" / "verify.json"]
    assert not (tmp_path / "report" / "verify.png").exists()


def test_a_run_of_a_plugin_law_writing_past_its_history_is_refused_before_it_steps(tmp_path, monkeypatch, capsys):
    """The same check guards `minidem run` (Simulation.check_history_bounds), for a law
    or part from a plugin, once per kernel: a plugin author who never ran `minidem
    verify` gets exit 2 naming the law, not another contact's history overwritten (or
    the heap: the process died of it in the verify battery before the check existed)."""
    import importlib

    from conftest import OBLIQUE
    from minidem import cli
    from minidem.contact import laws
    from minidem.engine.run_loop import RunLoop

    (tmp_path / "fake_overrun_plugin.py").write_text(OVERRUN_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = laws.load_registry(extra_plugins=(importlib.import_module("fake_overrun_plugin"),))
    monkeypatch.setattr(laws, "_REGISTRY", registry)
    stepped = []
    monkeypatch.setattr(RunLoop, "first_call", lambda loop: stepped.append(loop))
    code = cli.main(["run", str(OBLIQUE), "--set", 'contact.law="fake_overrun"', "--out", str(tmp_path / "out")])
    assert code == 2 and not stepped
    err = capsys.readouterr().err
    assert "law 'fake_overrun' from plugin 'fake_overrun_plugin'" in err and "writes past the history it declares" in err
    assert "wrote history[1]; the law declares 1 slot(s)" in err


SPRING_PLUGIN = '''
import numba

from minidem import hookimpl
from minidem.contact.laws import ContactLaw, Parameter


@numba.njit
def spring_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                 normal_velocity, tangential_increment, tangential_velocity, history):
    return constants[0] * normal_overlap, 0.0, 0.0, 0.0


def prepare(pair, params):
    return {"kn": params["normal_stiffness"]}


@hookimpl
def minidem_register_laws(registry):
    registry.add(ContactLaw(
        name="plain_spring", description="frictionless linear spring, no contact_time declared",
        constants=("kn",), parameters=(Parameter("normal_stiffness", None, "N/m", "kn", low=0.0, required=True),),
        history=(), prepare=prepare, force=spring_force, frictional=False))
'''


def test_a_frictionless_law_without_contact_time_is_checked_not_refused(tmp_path, monkeypatch):
    """A plugin author's first law (a new user's report, 2026-11-27): a frictionless linear
    spring that declares no contact_time. The battery must not add the paper's friction to
    a law that has none (it refused the scene, or stopped on a KeyError with the contact
    table given whole), must skip the sliding limit (Coulomb's), and must not call the
    spring's energy gain at separation (velocity Verlet's ~1e-7 when dt, chosen for the
    Hertz duration, does not divide its contact into whole steps) energy creation: the
    bound is the engine's, 10 (dt/tc)^2 and at least 1e-6 (analysis.energy_gain_bound),
    which the integral law's 1.2e-2 exceeds (test_integral_law_is_caught_creating_energy)."""
    import importlib

    from minidem.contact import laws

    (tmp_path / "plain_spring_plugin.py").write_text(SPRING_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = laws.load_registry(extra_plugins=(importlib.import_module("plain_spring_plugin"),))
    assert not registry.broken, registry.broken
    monkeypatch.setattr(laws, "_REGISTRY", registry)
    for overrides in (["contact.normal_stiffness=1e8"], ['contact={law="plain_spring", normal_stiffness=1e8}']):
        battery = verify.Battery("plain_spring", overrides)
        checks = by_name(battery.energy() + battery.sliding_limit())
        energy = checks["elastic impacts create no energy"]
        assert energy.passed is True, energy.value
        # it does gain a little: the bound is what lets it pass, not a gain of zero
        assert "1.00000" in energy.value
        assert checks["rigid-body sliding limit"].passed is None
    # the same spring a million times stiffer lasts 4 steps of the Hertz-based dt: its
    # impacts gain up to 7 %, inside the integration bound of so coarse a step, so the
    # check must not judge it passed but say the contact was not resolved
    [stiff] = verify.Battery("plain_spring", ["contact.normal_stiffness=1e14"]).energy()
    assert stiff.passed is False and "under-resolved" in stiff.value, stiff.value


def test_a_contact_far_shorter_than_the_automatic_time_step_assumed_is_reported(tmp_path, monkeypatch):
    """run.dt = "auto" takes steps_per_contact steps of the law's contact_time, or of the
    Hertz duration when the law declares none. A stiff linear spring without contact_time
    (kn = 1e14 N/m at the paper's impact: pi sqrt(m*/kn) = 1.3e-7 s, a thousandth of Hertz's
    1.3e-4 s) then lasted 4 steps, and the run reported en = 1.02 with no warning (a new
    user's report, 2026-11-27). The summary must say the rebound is under-resolved and
    why; the same law at kn = 1e8 (its contact about as long as Hertz's) gets no such
    warning, nor does a built-in law."""
    import importlib

    from minidem import api
    from minidem.contact import laws

    (tmp_path / "plain_spring_plugin.py").write_text(SPRING_PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = laws.load_registry(extra_plugins=(importlib.import_module("plain_spring_plugin"),))
    monkeypatch.setattr(laws, "_REGISTRY", registry)
    scenario_file = Path(__file__).resolve().parents[1] / "scenarios" / "oblique.toml"

    def warnings_of(**overrides):
        return api.run(scenario_file, overrides).summary["warnings"]

    stiff = warnings_of(**{"contact": {"law": "plain_spring", "normal_stiffness": 1e14}})
    assert any("under-resolved" in w and "declares no contact_time" in w for w in stiff), stiff
    assert not any("under-resolved" in w for w in warnings_of(**{"contact": {"law": "plain_spring",
                                                                             "normal_stiffness": 1e8}}))
    assert warnings_of() == []


def test_an_impact_without_a_rebound_ends_the_battery_with_the_reason():
    # The checks measure rebounds: an impact still in contact at its end has none (its
    # rebound keys are null), and the arithmetic on them was a TypeError traceback (a
    # review, 2026-12-08). It is a LawError naming the law, the angle and the reason.
    import pytest

    from minidem.contact.laws import LawError

    with pytest.raises(LawError, match=r"law 'hm': the impact at 0 deg has no rebound to measure: the contacts "
                                       r"had not ended by t = "):
        verify.Battery("hm").run("impact.angle_deg=0.0", "run.end_time=5e-5")
