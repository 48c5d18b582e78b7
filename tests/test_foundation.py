"""Issue 2's "Must show": the paper's impact end to end, checked against the paper.

Expected values come from Thornton, Cummins & Cleary (2011) (restated with equation
numbers in ../shared/paper/models.md) or from analytic limits, never from minidem's
own output.
"""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import (OBLIQUE, PAPER, impact_summary, minidem_command, paper_effective_modulus, paper_mass,
                      run_cli)
from minidem.results import analysis
from minidem.scene import scenario
from minidem.engine import simulation

MU = PAPER["friction"]


def hertz_duration(mass, radius, effective_modulus, speed):
    """Paper eq 13 (coefficient 2.868, the exact value of the Hertz integral)."""
    return 2.868 * (mass**2 / (radius * effective_modulus**2 * speed)) ** 0.2


# --------------------------------------------------------------------------------------
# normal impact
# --------------------------------------------------------------------------------------
def test_hmd_normal_impact_lasts_the_hertz_time_and_is_elastic():
    s = impact_summary("hmd", 0.0)
    expected = hertz_duration(paper_mass(), PAPER["radius"], paper_effective_modulus(), PAPER["speed"])
    # eq 13; 0.5 % leaves room for the time-step resolution of contact start and end
    assert s["contact_duration_s"] == pytest.approx(expected, rel=5e-3)
    # Hertz is elastic and the normal force not damped: Vnr = Vni
    assert s["en"] == pytest.approx(1.0, abs=1e-6)
    # eq 16: maximum overlap (15 m V^2 / (16 sqrt(R) E*))^(2/5)
    overlap = (15 * paper_mass() * PAPER["speed"] ** 2 / (16 * math.sqrt(PAPER["radius"]) * paper_effective_modulus())) ** 0.4
    assert s["max_overlap_m"] == pytest.approx(overlap, rel=1e-3)


# Table 1 of the paper: nu -> (kn, kt) in MN/m for E = 70 GPa, R = 25 mm, Vni = 5 m/s
TABLE_1 = [
    (0.0, 100.0, 100.0),
    (0.5, 126.0, 84.0),
    (2.0 / 3.0, 160.0, 80.0),
    (5.0 / 6.0, 259.0, 74.0),
    (0.3, 108.0, 89.0),
]


@pytest.mark.parametrize("nu, kn_table, kt_table", TABLE_1)
def test_ls_calibrated_stiffness_reproduces_table_1(nu, kn_table, kt_table):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # nu > 0.5 warns (tested in test_scenario_errors)
        scene = scenario.load_scene(OBLIQUE, ['contact.law="ls"', f"materials.glass.poisson_ratio={nu!r}"])
    constants = simulation.Simulation(scene).constants_by_pair[(0, 0)]
    assert constants["normal_stiffness"] / 1e6 == pytest.approx(kn_table, abs=1.0)
    # kt = kappa kn with kappa = 2 (1 - nu) / (2 - nu) (eq 10): the table's last column
    assert constants["tangential_stiffness"] / 1e6 == pytest.approx(kt_table, abs=1.0)


def test_ls_normal_impact_lasts_half_a_spring_period():
    scene = scenario.load_scene(OBLIQUE, ['contact.law="ls"', "impact.angle_deg=0.0"])
    sim = simulation.Simulation(scene)
    s = analysis.summary(sim.run())
    kn = sim.constants_by_pair[(0, 0)]["normal_stiffness"]
    # eq 27: a linear spring's contact lasts pi sqrt(m/kn) at any speed
    assert s["contact_duration_s"] == pytest.approx(math.pi * math.sqrt(paper_mass() / kn), rel=5e-3)
    # ...which the calibration (eq 28) makes equal to the Hertz duration (eq 13)
    hertz = hertz_duration(paper_mass(), PAPER["radius"], paper_effective_modulus(), PAPER["speed"])
    assert s["contact_duration_s"] == pytest.approx(hertz, rel=5e-3)
    assert s["en"] == pytest.approx(1.0, abs=1e-6)


# --------------------------------------------------------------------------------------
# gross sliding: the rigid-body limit (eqs 3-8)
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("law", ["hmd", "ls"])
def test_gross_sliding_at_60_degrees_matches_rigid_body_theory(law):
    theta = 60.0
    s = impact_summary(law, theta)
    # the paper's sphere is elastic (no dashpot): en = 1, and its normalised impact angle
    # x = 2 tan(theta) / (1 + en) is tan(theta), to the integrator's error
    en = 1.0
    x = 2.0 * math.tan(math.radians(theta)) / (1.0 + en)
    assert s["en"] == pytest.approx(en, abs=1e-6)
    assert s["x"] == pytest.approx(x, rel=1e-6)
    assert s["y1"] == pytest.approx(x - 7.0 * MU, abs=1e-3)  # eq 7
    assert s["y2"] == pytest.approx(-5.0 * MU, abs=1e-3)  # eq 8
    assert s["et"] == pytest.approx(1.0 - MU * (1.0 + en) / math.tan(math.radians(theta)), abs=1e-3)  # eq 6


# --------------------------------------------------------------------------------------
# energy
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("law", ["hmd", "ls"])
@pytest.mark.parametrize("angle", [0.0, 30.0, 60.0])
def test_frictionless_impact_conserves_energy_and_never_spins(law, angle):
    scene = scenario.load_scene(OBLIQUE, [f'contact.law="{law}"', f"impact.angle_deg={angle}",
                                          "contact.friction=0.0"])
    result = simulation.Simulation(scene).run()
    # no tangential force: the elastic normal impact returns all its energy (velocity
    # Verlet is symplectic, the residual is the O(dt^2) error at the last contact step)
    assert analysis.energy_ratio(result) == pytest.approx(1.0, abs=1e-6)
    # and the tangential velocity is untouched, the sphere cannot start spinning
    assert np.array_equal(result.angular_velocity, np.zeros((1, 3)))
    if angle:
        assert analysis.rebound(result)["et"] == pytest.approx(1.0, abs=1e-12)


ANGLES = [0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 25.0, 30.0, 35.0, 40.0, 50.0, 60.0,
          70.0, 80.0, 85.0]


@pytest.mark.parametrize("law", ["hmd", "ls"])
def test_incremental_laws_never_create_energy(law):
    # Incremental laws only ever store or dissipate tangential work (paper section 5);
    # 1e-9 is far above the round-off of the energy sums.
    ratios = {angle: impact_summary(law, angle)["energy_ratio"] for angle in ANGLES}
    created = {a: r for a, r in ratios.items() if r > 1.0 + 1e-9}
    assert not created, f"{law} created energy at {created}"
    # friction must actually dissipate something at oblique angles, else the test is void
    assert min(ratios.values()) < 0.99


# --------------------------------------------------------------------------------------
# summary.json and the command line
# --------------------------------------------------------------------------------------
# issue 2: "OUT/summary.json keys (stable, other tools will read them)"
STABLE_KEYS = ("law", "angle_deg", "speed", "en", "et", "x", "y1", "y2", "contact_duration_s", "max_overlap_m",
               "energy_ratio", "steps", "dt_s", "wall_time_s", "warnings")


def test_summary_stable_keys():
    assert analysis.SUMMARY_KEYS == STABLE_KEYS
    s = impact_summary("hmd", 30.0)
    assert list(s)[:len(STABLE_KEYS)] == list(STABLE_KEYS)
    assert s["law"] == "hmd" and s["angle_deg"] == 30.0 and s["speed"] == PAPER["speed"]
    for key in STABLE_KEYS[3:-1]:
        assert isinstance(s[key], (int, float)) and math.isfinite(s[key]), key
    assert s["warnings"] == []  # HMD at the paper's friction gains no energy
    assert isinstance(s["steps"], int) and s["steps"] > 0
    assert s["steps"] * s["dt_s"] >= s["contact_duration_s"]


def test_minidem_run_end_to_end(tmp_path):
    out = tmp_path / "out"
    done = run_cli("run", OBLIQUE, "--out", out)
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    for row in ("en", "et", "y1", "y2", "contact duration", "max overlap", "peak normal force", "energy ratio"):
        assert row in done.stdout
    written = json.loads((out / "summary.json").read_text())
    assert set(STABLE_KEYS) <= set(written)
    assert written["law"] == "hmd" and written["angle_deg"] == 30.0  # the scenario file's values


def test_minidem_run_set_overrides(tmp_path):
    out = tmp_path / "out"
    done = run_cli("run", OBLIQUE, "--out", out, "--set", "contact.law=ls", "--set", "impact.angle_deg=60",
                   "--set", "contact.friction=0.2", "--quiet")
    assert done.returncode == 0, done.stderr
    assert done.stdout == ""  # --quiet
    written = json.loads((out / "summary.json").read_text())
    assert written["law"] == "ls" and written["angle_deg"] == 60.0
    assert written["law_parameters"]["friction"] == 0.2
    # gross sliding with the overridden friction (eq 8): the override reached the physics
    assert written["y2"] == pytest.approx(-5.0 * 0.2, abs=1e-3)


def test_set_takes_a_key_part_in_quotes_as_toml_writes_it():
    """scenario-reference.md writes a pair's table [contact.pairs."beads/steel"]: --set takes
    that key as written (a new user's report, 2026-12-08: the quotes became part of the
    material's name), the same as the bare form; a quoted part may hold a dot or an '='."""
    bare = scenario.load_scene(OBLIQUE, ["contact.pairs.glass/glass.friction=0.3"])
    quoted = scenario.load_scene(OBLIQUE, ['contact.pairs."glass/glass".friction=0.3'])
    single = scenario.load_scene(OBLIQUE, ["contact.pairs.'glass/glass'.friction = 0.3"])
    assert bare.pair_parameters == quoted.pair_parameters == single.pair_parameters
    assert list(bare.pair_parameters.values())[0]["friction"] == 0.3
    assert scenario.parse_override('a."x.y=z".b=2') == (["a", "x.y=z", "b"], 2)
    # a quote opens a quoted part only where a part starts, as in TOML: o'brien is a bare
    # name, as before quoted parts were read (a review, 2026-12-08)
    assert scenario.parse_override("materials.o'brien.density=3000") == (["materials", "o'brien", "density"], 3000)
    assert scenario.canonical_key('"impact"."angle_deg"', "-") == "impact.angle_deg"
    assert scenario.canonical_key('materials."a.b".density', "-") == 'materials."a.b".density'
    for text, message in (('contact.pairs."glass/glass.friction=0.3', "no '=' outside the key's quotes"),
                          ('contact.pairs."glass"/glass.friction=0.3', "expected '.' or '='"),

                          ('contact."".law=hm', "empty key part")):
        with pytest.raises(scenario.ScenarioError, match=re.escape(message)):
            scenario.parse_override(text)


def test_second_run_reuses_the_compile_cache(tmp_path):
    done = run_cli("run", OBLIQUE, "--out", tmp_path, "--quiet", "--set", "contact.law=hmd")
    assert done.returncode == 0, done.stderr
    # The run compiled (or found) a kernel specialised for hmd and numba wrote its cache
    # index beside it: the next process loads machine code instead of compiling.
    scene = scenario.load_scene(OBLIQUE, ['contact.law="hmd"'])
    kernel = simulation.Simulation(scene).kernel  # imports the specialised module, compiles nothing
    # (a serial kernel inlines its step functions into advance: advance is the one entry point)
    for function in (kernel.advance,):
        cache = function._cache
        index = list(Path(cache._cache_path).glob(f"{kernel.__name__}.{function.__name__}-*.nbi"))
        assert index, f"no numba cache index for {kernel.__name__}.{function.__name__} in {cache._cache_path}"
        assert list(index[0].parent.glob(index[0].name.replace(".nbi", ".*.nbc")))


# --------------------------------------------------------------------------------------
# the docs cannot drift from the code
# --------------------------------------------------------------------------------------
DOCS = Path(__file__).resolve().parents[1] / "docs"


def test_committed_scenario_reference_is_the_generated_one():
    committed = (DOCS / "scenario-reference.md").read_text()
    assert committed == scenario.reference_markdown(), (
        "docs/scenario-reference.md is stale: run `minidem docs --write docs/scenario-reference.md`")


def test_cli_doc_names_every_command_and_option():
    import argparse

    from minidem import cli

    text = (DOCS / "cli.md").read_text()
    parser = cli.build_parser()
    missing = [o for a in parser._actions for o in a.option_strings if o.startswith("--") and o not in text]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                if f"## `minidem {name}" not in text:
                    missing.append(f"minidem {name}")
                missing += [f"{name} {o}" for a in sub._actions for o in a.option_strings
                            if o.startswith("--") and o != "--help" and f"`{o}" not in text]
    assert not missing, f"docs/cli.md does not describe: {missing}"


def test_cli_doc_sample_error_is_the_real_message(tmp_path, monkeypatch):
    """docs/cli.md shows the error for a misspelt key in the oblique scenario: it must be
    what minidem prints (the valid keys of [impact] change when the schema does)."""
    text = (DOCS / "cli.md").read_text()
    start = text.index("```\nminidem: error: my.toml: invalid scenario") + 4
    sample = text[start:text.index("```", start)].rstrip("\n")
    (tmp_path / "my.toml").write_text(OBLIQUE.read_text().replace("speed = 5.0", "sped = 5.0"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(scenario.ScenarioError) as info:
        scenario.load_scene("my.toml")
    assert sample == f"minidem: error: {info.value}"


def _guide_block(text: str, marker: str, lang: str) -> str:
    start = text.index(f"```{lang}\n", text.index(marker)) + len(lang) + 4
    return text[start:text.index("```", start)]


def _code_without_docstrings(source: str) -> str:
    import ast

    tree = ast.parse(source)
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (isinstance(body, list) and body and isinstance(body[0], ast.Expr)
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return ast.dump(tree)


def test_contact_law_guide_shows_the_example_plugin_as_it_is():
    """The guide's pyproject.toml, hook and law.py, copied as written, are the example
    plugin (comments and docstrings aside): a reader who follows it gets a working law."""
    import ast
    import tomllib

    text = (DOCS / "writing-a-contact-law.md").read_text()
    plugin = DOCS.parent / "plugins" / "minidem-walton-braun"
    package = plugin / "src" / "minidem_walton_braun"
    law = _guide_block(text, "**The law**", "python")
    assert _code_without_docstrings(law) == _code_without_docstrings((package / "law.py").read_text())
    hook = ast.parse(_guide_block(text, "**The hook**", "python")).body
    shipped = ast.parse((package / "__init__.py").read_text()).body
    assert [ast.dump(n) for n in hook] == [ast.dump(n) for n in shipped
                                           if isinstance(n, (ast.ImportFrom, ast.FunctionDef))]
    guide_toml = tomllib.loads(_guide_block(text, "**pyproject.toml.**", "toml"))
    shipped_toml = tomllib.loads((plugin / "pyproject.toml").read_text())

    def subset(small, big, where="pyproject.toml"):
        for key, value in small.items():
            assert key in big, f"{where}.{key} is in the guide but not in the plugin"
            if isinstance(value, dict):
                subset(value, big[key], f"{where}.{key}")
            else:
                assert value == big[key], f"{where}.{key}: guide {value!r}, plugin {big[key]!r}"

    subset(guide_toml, shipped_toml)


def test_run_piped_into_a_closed_reader_still_writes_its_results(tmp_path):
    # `minidem run ... | head -1`: once the reader has gone, every print raises
    # BrokenPipeError; the run must not die of it ("internal error", found by hand) but
    # finish and write its files. `| true` makes the reader go before the first line.
    import shlex

    command = " ".join(shlex.quote(str(part)) for part in
                       minidem_command() + ["run", OBLIQUE, "--out", tmp_path / "out"])
    piped = subprocess.run(["bash", "-c", f"{command} | true; exit ${{PIPESTATUS[0]}}"], capture_output=True,
                           text=True, timeout=300)
    assert piped.returncode == 0, piped.stderr
    assert "Error" not in piped.stderr
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["law"] == "hmd"


_CONSOLE = """
import atexit, sys
atexit.register(print, "exit handler ran")
sys.argv = ["minidem", *sys.argv[1:]]
from minidem.cli import console
console()
"""


@pytest.mark.parametrize("argv, code", [(["laws"], 0), (["run", "nowhere.toml"], 2)])
def test_the_command_ends_after_its_exit_handlers_with_its_output_and_exit_code(tmp_path, argv, code):
    # the console command leaves without Python's teardown (minidem.cli.console): what an
    # exit must do is still done. Output into a pipe is block-buffered: everything printed
    # arrives, then what the exit handlers print, and the exit code is main's (2 for a
    # scenario file that does not exist).
    done = subprocess.run([sys.executable, "-c", _CONSOLE, *argv], cwd=tmp_path, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == code, done.stderr
    lines = done.stdout.splitlines()
    assert lines[-1] == "exit handler ran", done.stdout[-500:]
    if code == 0:  # `minidem laws`: every built-in law listed before it
        assert {"hmd", "hm", "ls"} <= {word.strip(":") for line in lines for word in line.split()}
    else:
        assert "nowhere.toml" in done.stderr


def test_bench_sizes_are_checked_and_the_million_sphere_variant_fits_its_box():
    # `minidem bench --sizes`: a bad list is refused with exit 2 and a valid example,
    # before anything runs
    done = run_cli("bench", "--only", "multi-particle", "--sizes", "2000,lots")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "--sizes" in done.stderr and "2000,20000,200000,1000000" in done.stderr
    for option, value, valid in (("--steps", "0", "e.g. 400"), ("--variants", "grid", "lattice,jitter")):
        done = run_cli("bench", "--only", "multi-particle-scale", option, value)
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert option in done.stderr and valid in done.stderr
    # settle.md's largest variant: 1,000,000 spheres are 494 layers of 45 x 45 at 2.2 mm,
    # 1.088 m of centres, more than the scene file's 1 m box; the bench raises box and
    # fill as make_lattice.py does, and runs 2,000 steps (settle.md: "e.g. 2,000")
    from minidem.studies import bench_multi

    n = 1_000_000
    height = bench_multi.box_height(n)
    scene = scenario.load_scene(bench_multi.SETTLE, [f"fill.0.count={n}", f"fill.0.upper=[0.1, 0.1, {height!r}]",
                                                     f"walls.0.upper=[0.1, 0.1, {height!r}]"], "-")
    assert scene.n_particles == n
    assert scene.position[:, 2].max() == pytest.approx(1.1e-3 + 493 * 2.2e-3)
    assert scene.position[:, 2].max() + scene.radius.max() < height
    assert bench_multi.box_height(20_000) is None  # the shipped box holds the default sizes
    assert (bench_multi.steps_for(20_000), bench_multi.steps_for(200_000), bench_multi.steps_for(n)) == (
        10_000, 10_000, 2_000)


def test_bench_finds_the_clone_it_measures_or_says_where_it_looked(tmp_path):
    # `pip install .` copies the package alone into site-packages: `minidem bench` then
    # finds the clone (scenarios/, docs/) from the working directory or a folder above it,
    # and refuses with the folders it searched when there is none (a new user's report,
    # 2026-11-27: it stopped with "no such scenario file .../site-packages/scenarios/...")
    from minidem.studies import checkout

    installed = tmp_path / "site-packages"
    (installed / "minidem").mkdir(parents=True)
    clone = tmp_path / "clone"
    (clone / "scenarios").mkdir(parents=True)
    (clone / "pyproject.toml").write_text("")
    (clone / "scenarios" / "oblique.toml").write_text("")
    (clone / "out" / "deep").mkdir(parents=True)
    assert checkout.find_root(installed, clone) == clone
    assert checkout.find_root(installed, clone / "out" / "deep") == clone
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    lost = checkout.find_root(installed, elsewhere)
    with pytest.raises(checkout.NoCheckout, match="clone of minidem"):
        checkout.require(lost)
    # this test runs from a clone (or an editable install of one)
    assert checkout.require() == checkout.ROOT
    assert (checkout.ROOT / "scenarios" / "bench" / "settle.toml").is_file()
