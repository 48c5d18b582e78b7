"""The Python API (docs/python-api.md): the same runs, validation and files as `minidem run`.

Expected values: the CLI's own output on the same input (the API must give the same bits:
it is the same code path, and a difference would be a second, drifting implementation),
conservation laws (momentum in a Newton's cradle without walls or gravity), and the
paper's rigid-body limit in gross sliding, y2 = -5 mu (Thornton, Cummins & Cleary 2011, eq 8).
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest

import minidem
from conftest import OBLIQUE, REPO, run_cli

TWO_SPHERES = REPO / "scenarios" / "two_spheres_oblique.toml"
CRADLE = REPO / "scenarios" / "newtons_cradle.toml"
DOC = REPO / "docs" / "python-api.md"
MU = 0.1  # friction of scenarios/oblique.toml


def test_api_run_of_the_paper_impact_is_minidem_run_bit_for_bit(tmp_path):
    cli = run_cli("run", OBLIQUE, "--set", "impact.angle_deg=10", "--out", tmp_path / "cli", "--quiet")
    assert cli.returncode == 0, cli.stderr
    by_cli = json.loads((tmp_path / "cli" / "summary.json").read_text())
    result = minidem.run(OBLIQUE, {"impact.angle_deg": 10.0}, out=tmp_path / "api")
    for key in ("en", "et", "x", "y1", "y2", "contact_duration_s", "max_overlap_m", "energy_ratio", "steps", "dt_s"):
        assert result.summary[key] == by_cli[key], key
    # the files the API wrote are those of `minidem run` (wall time aside)
    written = json.loads((tmp_path / "api" / "summary.json").read_text())
    assert {k: v for k, v in written.items() if k != "wall_time_s"} == \
        {k: v for k, v in by_cli.items() if k not in ("wall_time_s",)}
    state = minidem.open_results(tmp_path / "cli").final_state
    for name in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(state[name], getattr(result, name)), name
    # and it is the paper's elastic impact: en = 1 (HMD without damping), rebound along +z
    assert abs(result.summary["en"] - 1.0) < 1e-6
    assert result.velocity[0, 2] > 0.0


def _two_spheres_in_code() -> minidem.Scenario:
    half = 2.1650635094610966, 1.25  # 2.5 m/s (cos 30, sin 30): the values of the scenario file
    return (minidem.Scenario()
            .material("glass", youngs_modulus=70e9, poisson_ratio=0.3, density=2650.0)
            .contact("hmd", friction=0.1)
            .particles(np.array([[-0.025, 0.0, 0.0], [0.025, 0.0, 0.0]]), np.array([0.025, 0.025]), "glass",
                       velocity=np.array([[half[0], half[1], 0.0], [-half[0], -half[1], 0.0]]))
            .run_settings(dt="auto", stop="separation")
            .output(vtk=False))


def test_scene_built_from_arrays_is_the_scene_of_the_toml_file(tmp_path):
    built = _two_spheres_in_code()
    from_file = minidem.load(TWO_SPHERES)
    a, b = built.scene(), from_file.scene()
    for name in ("position", "velocity", "angular_velocity", "radius", "particle_material", "wall_point",
                 "gravity"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert (a.materials, a.law_name, a.law_parameters, a.stop, a.integrator) == \
        (b.materials, b.law_name, b.law_parameters, b.stop, b.integrator)
    # its TOML text is a file `minidem run` reads to the same scene
    path = tmp_path / "pair.toml"
    path.write_text(built.to_toml())
    again = minidem.load(path).scene()
    assert np.array_equal(again.position, a.position) and np.array_equal(again.velocity, a.velocity)
    # and the collision comes out the same, bit for bit: the sphere-sphere en, et
    ran, ran_file = built.run(), from_file.run()
    assert (ran.summary["en"], ran.summary["et"]) == (ran_file.summary["en"], ran_file.summary["et"])
    assert abs(ran.summary["en"] - 1.0) < 5e-3  # elastic Hertz: en = 1 to the integration error (0.9977)


def test_a_bad_key_is_named_and_caught_as_minidem_error(tmp_path):
    scenario = (minidem.Scenario().material("glass", youngs_modulus=70e9, poisson_ratio=0.3, density=2650.0)
                .contact("hmd", friction=0.1).wall(normal=[0, 0, 1], material="glass")
                .impact(material="glass", radius=0.025, sped=5.0))
    with pytest.raises(minidem.MinidemError) as caught:
        scenario.run()
    assert isinstance(caught.value, minidem.ScenarioError)
    assert "impact.sped: unknown key (did you mean 'speed'?)" in str(caught.value)
    assert "impact.speed: missing required key" in str(caught.value)
    # the same message, word for word, as `minidem run` on the same file (one validator)
    path = tmp_path / "typo.toml"
    path.write_text(scenario.to_toml())
    with pytest.raises(minidem.ScenarioError) as from_file:
        minidem.run(path)
    cli = run_cli("run", path, "--out", tmp_path / "out")
    assert cli.returncode == 2
    assert cli.stderr.strip() == f"minidem: error: {from_file.value}"
    # the array shapes particles() takes are checked before the validator
    with pytest.raises(minidem.ScenarioError, match=r"particles\(velocity=\.\.\.\): expected .*shape \(2, 3\)"):
        minidem.Scenario().particles(np.zeros((2, 3)), 0.01, "glass", velocity=np.zeros((3, 3)))
    # a material's keys too, and overrides of another type than a dict or a list of texts
    # (before: Python's own "unexpected keyword argument" and "'float' object is not
    # iterable", a review, 2026-11-28)
    with pytest.raises(minidem.ScenarioError, match=r"materials\.g\.young: unknown key; valid keys: youngs_modulus"):
        minidem.Scenario().material("g", young=1.0, poisson_ratio=0.3, density=2500.0).scene()
    with pytest.raises(TypeError, match=r"overrides: expected a dict of dotted keys .* got float 10\.0"):
        minidem.run(OBLIQUE, 10.0)
    # arguments of the wrong type name the argument (a robustness review, 2026-11-28: numpy's
    # "could not convert string to float", "expected str, bytes or os.PathLike", a None
    # validated as the string 'None', "'<' not supported")
    with pytest.raises(minidem.ScenarioError, match=r"particles\(position=\.\.\.\): expected numbers, got 'abc'"):
        minidem.Scenario().particles("abc", 0.01, "glass")
    with pytest.raises(minidem.ScenarioError, match=r"particles\(position=\.\.\.\): expected numbers"):
        minidem.Scenario().particles([[0.0, 0.0, 1j]], 0.01, "glass")
    with pytest.raises(TypeError, match=r"^out: expected a directory path"):
        minidem.run(OBLIQUE, out=5)
    with pytest.raises(TypeError, match=r"^overrides: impact.angle_deg: None \(NoneType\) is no TOML value"):
        minidem.run(OBLIQUE, {"impact.angle_deg": None})
    with pytest.raises(TypeError, match=r"^workers: expected a whole number of processes"):
        minidem.sweep(OBLIQUE, cases={"impact.angle_deg": [1.0]}, workers="2")
    for error in (minidem.ScenarioError, minidem.LawError, minidem.RunFailure, minidem.OutputError):
        assert issubclass(error, minidem.MinidemError)
    assert issubclass(minidem.OutputError, OSError)  # code catching OSError for a full disk still does


def test_a_sweep_from_python_returns_the_table_of_sweep_csv(tmp_path):
    cases = {"contact.law": ["hmd"], "impact.angle_deg": [5.0, 60.0], "contact.friction": [0.1, 0.2]}
    table = minidem.sweep(OBLIQUE, cases=cases, workers=1)
    assert len(table) == 4 and not table.failed
    assert table.columns[:3] == ["case", "law", "angle_deg"] and "contact.friction" in table.columns
    sliding = table["angle_deg"] == 60.0
    # gross sliding at 60 deg (tan 60 > 7 mu (1 + en) / 2 for mu <= 0.2): y2 = -5 mu (paper eq 8)
    assert np.allclose(table["y2"][sliding], -5.0 * table["contact.friction"][sliding], rtol=0, atol=1e-6)
    # the same sweep through files: sweep.csv holds the same numbers, bit for bit
    written = minidem.sweep(OBLIQUE, cases=cases, workers=1, out=tmp_path / "sweep")
    columns = minidem.open_results(tmp_path / "sweep").sweep
    for name in ("x", "y1", "y2", "et", "en", "steps", "contact.friction"):
        assert np.array_equal(columns[name], table[name]), name
        assert np.array_equal(written[name], table[name]), name
    assert list(columns["law"]) == ["hmd"] * 4
    with pytest.raises(KeyError, match="'y3': not a column"):
        table["y3"]
    # every case is validated before any runs, the bad one named
    with pytest.raises(minidem.ScenarioError, match=r"(?s)sweep case 1 \(impact.angle_deg = 95.0\).*impact.angle_deg: must be < 90 deg, got 95"):
        minidem.sweep(OBLIQUE, cases={"impact.angle_deg": [10.0, 95.0]}, workers=1)


@pytest.fixture(scope="module")
def cradle_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("cradle")
    result = minidem.run(CRADLE, {"run.end_time": 2e-4, "output.interval": 2e-5}, out=out)
    return out, result


def test_open_results_reads_back_the_series_and_the_final_state(cradle_run):
    out, result = cradle_run
    output = minidem.open_results(out)
    assert output.summary == json.loads((out / "summary.json").read_text())
    series = output.series
    # a frame every output.interval from t = 0 (to the step), and the final state (docs/scenario-reference.md)
    dt = result.summary["dt_s"]
    assert np.all(np.abs(series.times[:11] - 2e-5 * np.arange(11)) <= dt)
    assert series.times[-1] == pytest.approx(result.time, rel=1e-12)
    last = series[-1]
    # VTK frames are raw Float64: the last frame is the final state to the bit
    assert np.array_equal(np.asarray(last.points), result.position)
    assert np.array_equal(output.final_state["position"], result.position)
    assert np.array_equal(series.at(series.times[3] + 1e-9).points, series[3].points)
    # no walls, no gravity: the chain's momentum is that of the first ball, 1 m/s, in every frame
    mass = 7850.0 * 4.0 / 3.0 * np.pi * 0.01**3
    for time_s, frame in series:
        momentum = mass * np.asarray(frame.point_data["velocity"]).sum(axis=0)
        assert np.allclose(momentum, [mass * 1.0, 0.0, 0.0], rtol=1e-12, atol=1e-15), time_s
    with pytest.raises(minidem.MinidemError, match="not a minidem output directory"):
        minidem.open_results(out / ".." / "..")


def test_minidem_render_writes_a_png_and_a_gif_of_the_series(cradle_run, tmp_path):
    from PIL import Image

    out, _ = cradle_run
    done = run_cli("render", out, "--array", "velocity", "--out", tmp_path / "cradle.png",
                   "--animation", tmp_path / "cradle.gif")
    assert done.returncode == 0, done.stderr
    assert "bad X server" not in done.stderr  # off-screen through EGL, no X attempted
    # one line says what is read and drawn before the wait (review: 30 s of silence)
    assert f"reading and drawing {len(minidem.open_results(out).series)} frame(s)" in done.stderr
    picture = np.asarray(Image.open(tmp_path / "cradle.png").convert("RGB"))
    assert picture.shape == (768, 1024, 3)
    # the five balls (and the colour bar) are drawn on the white background
    assert np.mean(np.all(picture > 250, axis=2)) < 0.97
    assert Image.open(tmp_path / "cradle.gif").n_frames == len(minidem.open_results(out).series)
    bad = run_cli("render", out, "--array", "speed")
    assert bad.returncode == 2 and "not a particle array; arrays: radius, velocity" in bad.stderr
    assert "reading and drawing" not in bad.stderr  # refused before the read (a user's audit)
    # refused before anything is drawn (review: --fps 0 drew the PNG for 30 s, then died
    # dividing by zero, an internal error)
    for fps in ("0", "-5", "nan"):
        slow = run_cli("render", out, "--fps", fps, "--out", tmp_path / f"fps{fps}.png")
        assert slow.returncode == 2 and "expected frames per second in (0, 50]" in slow.stderr, slow.stderr
        assert not (tmp_path / f"fps{fps}.png").exists()
    impact = run_cli("run", OBLIQUE, "--out", tmp_path / "impact", "--quiet")
    assert impact.returncode == 0
    nothing = run_cli("render", tmp_path / "impact")
    assert nothing.returncode == 2 and "no particle series (particles.pvd)" in nothing.stderr


def test_a_shorter_run_into_the_same_directory_leaves_only_its_own_frames(cradle_run, tmp_path):
    # review: a second, shorter run into a used directory listed its 3 frames in
    # particles.pvd and left the first run's later .vtu files beside them; ParaView's file
    # dialog groups every particles_*.vtu into one series, mixing the two runs
    import shutil

    out = tmp_path / "again"
    shutil.copytree(cradle_run[0], out)
    before = sorted(p.name for p in out.glob("particles_*.vtu"))
    assert len(before) > 5
    (out / "notes_000001.vtu").write_text("a file of the user's: kept")
    minidem.run(CRADLE, {"run.end_time": 4e-5, "output.interval": 2e-5}, out=out)
    listed = [Path(entry.get("file")).name for entry in
              ElementTree.parse(out / "particles.pvd").getroot().iter("DataSet")]
    assert sorted(p.name for p in out.glob("particles_*.vtu")) == sorted(listed) and len(listed) < len(before)
    assert (out / "notes_000001.vtu").read_text() == "a file of the user's: kept"
    # a resumed run continues its own series instead, every frame kept (test_faults.py,
    # the killed settle run resumed)


def test_an_impact_with_vtk_on_has_frames_inside_its_contact(tmp_path):
    # review: the default interval, run.end_time / 50, is 2 contact times for a run to
    # separation (whose end_time is a cap of 100 contact times): t = 0 and the end only.
    # Now 1/50 of the flight and one contact time: ~50 frames, most inside the contact
    result = minidem.run(OBLIQUE, {"output.vtk": True}, out=tmp_path)
    times = minidem.open_results(tmp_path).series.times
    # the paper's start: in contact from t = 0 to the separation
    inside = [t for t in times if 0.0 < t < result.summary["contact_duration_s"]]
    assert len(inside) >= 40, times


def _python_blocks(text: str) -> list[str]:
    return re.findall(r"```python\n(.*?)```", text, re.S)


def _printed_lines(block: str) -> list[str]:
    """The output a block shows: its trailing comment lines ('# ...' stands for lines left out)."""
    lines = block.rstrip("\n").split("\n")
    shown = []
    while lines and lines[-1].startswith("# "):
        shown.insert(0, lines.pop()[2:])
    return [line for line in shown if line != "..."]


def test_every_example_of_the_python_api_page_runs_and_prints_what_it_shows(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scenarios").symlink_to(REPO / "scenarios")
    namespace: dict = {}
    blocks = _python_blocks(DOC.read_text())
    assert len(blocks) >= 7
    for k, block in enumerate(blocks):
        printed = io.StringIO()
        with redirect_stdout(printed):
            exec(compile(block, f"{DOC.name} block {k}", "exec"), namespace)
        output = printed.getvalue().splitlines()
        for line in _printed_lines(block):
            assert line in output, f"block {k}: the page shows {line!r}, the run printed {output}"
    assert (tmp_path / "cradle.png").exists() and (tmp_path / "out" / "cradle" / "render.gif").exists()
    for k, block in enumerate(_python_blocks((REPO / "README.md").read_text())):  # the README's taste of it
        with redirect_stdout(io.StringIO()):
            exec(compile(block, f"README.md block {k}", "exec"), {})


def _example(name: str, *args, cwd) -> str:
    done = subprocess.run([sys.executable, str(REPO / "docs" / "examples" / name), *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_example_paper_sweep(tmp_path):
    printed = _example("paper_sweep.py", tmp_path / "fig6.png", cwd=tmp_path)
    rows = [line.split() for line in printed.splitlines() if line.startswith(("hmd", "ls "))]
    assert len(rows) == 10
    # 45 deg is gross sliding for mu = 0.1: y2 = -5 mu (eq 8), for both laws
    assert [float(r[4]) for r in rows if r[1] == "45.0"] == [-5 * MU, -5 * MU]
    assert (tmp_path / "fig6.png").stat().st_size > 10_000


def test_example_multi_particle_scene(tmp_path):
    printed = _example("multi_particle.py", tmp_path / "out", cwd=tmp_path)
    lowest = float(re.search(r"lowest centre ([\d.]+) mm", printed).group(1))
    # at rest on the floor: the lowest centre one radius up, less the small Hertz overlap under the load
    assert 0.99 < lowest <= 1.0
    assert (tmp_path / "out" / "render.png").exists() and (tmp_path / "out" / "render.gif").exists()
    # free fall before the bed lands: the mean speed at t = 0.012 s is g t
    speed = float(re.search(r"t = 0\.012 s: mean speed ([\d.]+) m/s", printed).group(1))
    assert speed == pytest.approx(9.81 * 0.012, abs=1e-4)
