"""`minidem verify` must tell a sound law from an unsound one.

The paper (section 5, Fig 12) is the oracle: the incremental linear spring conserves
energy and obeys the rigid-body limit, while the integral Hertz-Mindlin form (eq 38)
creates energy over its first force-displacement loop at 5 deg.
"""

import json
import subprocess
import sys

from minidem import verify


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
    unknown = subprocess.run([sys.executable, "-m", "minidem.cli", "verify", "hdm"], capture_output=True, text=True)
    assert unknown.returncode == 2 and "did you mean" in unknown.stderr.lower() and "hmd" in unknown.stderr
