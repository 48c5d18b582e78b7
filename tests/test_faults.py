"""Faults in runs: checkpoints and resume (bit for bit), blow-up detection, atomic
output after a kill, determinism; and a plugin written outside the repository, installed
with pip, listed, run and verified.

Kernel variants: the multi-particle runs use the scene of tests/test_multiparticle.py
(scenarios/bench/settle.toml, law hm, > 16 particles: the parallel variant it compiles) and
the single impacts scenarios/oblique.toml (hmd, compiled by the foundation tests), so
only the out-of-repo plugin compiles new kernels. One thread everywhere: results are
the same on any number (tests/test_multiparticle.py checks that), and a parallel region
on a busy 2-core machine only adds waiting.
"""

from __future__ import annotations

import io
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import OBLIQUE, REPO, minidem_command, run_cli
from minidem import cli
from minidem.engine import blowup
from minidem.scene import scenario
from minidem.engine import run_loop, simulation
from minidem.engine.state import State, StateCopy, on_memory_file_system
from minidem.engine import checkpoint

SETTLE = REPO / "scenarios" / "bench" / "settle.toml"
# 300 spheres in 4 layers falling into a 20 mm box (the scene of test_multiparticle.py)
SMALL_SETTLE = ["fill.0.jitter=0.0", "fill.0.count=300", "walls.0.upper=[0.02, 0.02, 1.0]",
                "fill.0.upper=[0.02, 0.02, 1.0]", "run.threads=1"]


def as_options(overrides):
    return [word for value in overrides for word in ("--set", value)]


def assert_same_state(got: dict, want: dict):
    assert sorted(got) == sorted(want)
    different = [name for name in want if not np.array_equal(got[name], want[name])]
    assert not different, f"arrays that differ: {different}"


def assert_ends_as_uninterrupted(out, path, overrides, tmp_path) -> tuple[dict, dict, dict]:
    """The final state a resumed run wrote in ``out`` is, array for array, the one an
    uninterrupted run of the same scene writes; returns (its arrays, its meta, the
    uninterrupted run's meta)."""
    reference = tmp_path / "reference"
    simulation.Simulation(scenario.load_scene(path, overrides, reference)).run(
        checkpoints=checkpoint.Policy(reference))
    got, got_meta = checkpoint.read(out / checkpoint.FINAL_STATE)
    want, want_meta = checkpoint.read(reference / checkpoint.FINAL_STATE)
    assert_same_state(got, want)
    return got, got_meta, want_meta


def assert_files_complete(directory, n_particles):
    """Every file under a final name is whole: the .pvd files parse and list only files
    that exist, every .vtu reads back with all its points, every .npz loads."""
    import vtk

    for path in sorted(directory.iterdir()):
        if path.name.startswith("."):
            continue  # an atomic write's temporary: never under a final name
        if path.suffix == ".pvd":
            for entry in ET.parse(path).getroot().iter("DataSet"):
                assert (directory / entry.get("file")).exists(), f"{path.name} lists a missing {entry.get('file')}"
        elif path.suffix == ".vtu":
            reader = vtk.vtkXMLUnstructuredGridReader()
            reader.SetFileName(str(path))
            reader.Update()
            expected = n_particles if path.name.startswith("particles") else None
            points = reader.GetOutput().GetNumberOfPoints()
            assert points > 0 and (expected is None or points == expected), f"{path.name}: {points} points"
        elif path.suffix == ".npz":
            arrays, meta = checkpoint.read(path)
            assert arrays["position"].shape == (n_particles, 3) and meta["format"] == checkpoint.FORMAT


# --------------------------------------------------------------------------------------
# checkpoints and --resume
# --------------------------------------------------------------------------------------
def test_killed_run_resumes_bit_for_bit(tmp_path):
    # A 10,000-step settling run with a checkpoint every 1,000 steps and a VTK frame with
    # the contact network every 1,000 steps, killed with SIGKILL once a checkpoint exists,
    # then resumed: the final state (every array a checkpoint holds, contact histories and
    # Verlet lists included) and every VTK file must equal, bit for bit, those of an
    # uninterrupted run in this process that writes no checkpoint on the way.
    overrides = SMALL_SETTLE + ["run.end_time=0.2", "output.interval=0.02", "output.contacts=true",
                                "output.checkpoint_interval=0.02"]
    out = tmp_path / "killed"
    command = ["run", SETTLE, "--out", out, "--quiet", *as_options(overrides)]
    process = subprocess.Popen(minidem_command() + [str(a) for a in command], cwd=REPO,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 600
    try:
        while not (out / checkpoint.CHECKPOINT).exists():
            assert process.poll() is None, f"the run ended before its first checkpoint: {process.stderr.read()}"
            assert time.monotonic() < deadline, "no checkpoint within 10 minutes"
            time.sleep(0.01)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert not (out / checkpoint.FINAL_STATE).exists(), "the run finished before the kill"
    assert_files_complete(out, 300)
    saved, meta = checkpoint.read(out / checkpoint.CHECKPOINT)
    assert 0 < meta["step"] < meta["total_steps"]
    # the kill came after contacts (with tangential history) and list rebuilds
    assert np.count_nonzero(saved["pair_overlap"] > 0) > 0 and int(saved["builds"]) > 1

    done = run_cli(*command, "--resume")
    assert done.returncode == 0, done.stderr
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")], "temporary files left behind"
    assert not (out / checkpoint.CHECKPOINT).exists()  # the run is complete

    reference = tmp_path / "uninterrupted"
    scene = scenario.load_scene(SETTLE, [o for o in overrides if "checkpoint" not in o], reference)
    sim = simulation.Simulation(scene)
    from minidem.results.vtk import SimulationFrames

    frames = SimulationFrames(sim, reference)
    sim.run(on_frame=frames, checkpoints=checkpoint.Policy(reference))
    frames.close()
    got, got_meta = checkpoint.read(out / checkpoint.FINAL_STATE)
    want, want_meta = checkpoint.read(reference / checkpoint.FINAL_STATE)
    assert_same_state(got, want)
    assert got_meta["loop"] == want_meta["loop"]
    vtk_files = sorted(p.name for p in reference.iterdir() if p.suffix in (".vtu", ".pvd"))
    assert len(vtk_files) == 2 * 11 + 3  # particles and contacts at t = 0, 0.02, ..., 0.2; 2 .pvd; walls
    assert sorted(p.name for p in out.iterdir() if p.suffix in (".vtu", ".pvd")) == vtk_files
    assert [name for name in vtk_files if (out / name).read_bytes() != (reference / name).read_bytes()] == []


def test_sigterm_writes_a_checkpoint_that_resumes_bit_for_bit(tmp_path):
    # SIGTERM (a job scheduler's stop) between chunks: exit code 130, a checkpoint of the
    # last copied state (not one written on schedule: no checkpoint interval is set), and
    # a message saying how to continue; the resumed run ends as an uninterrupted one.
    overrides = SMALL_SETTLE + ["run.end_time=0.2", "output.interval=0.02"]
    out = tmp_path / "out"
    command = ["run", SETTLE, "--out", out, "--quiet", *as_options(overrides)]
    process = subprocess.Popen(minidem_command() + [str(a) for a in command], cwd=REPO, text=True,
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # the third frame is written at step 2,000, past the first copy of the state (every
    # 666 steps of 300 particles)
    try:
        while not (out / "particles_000002.vtu").exists():
            assert process.poll() is None, f"the run ended before it was stopped: {process.stderr.read()}"
            time.sleep(0.01)
    finally:
        process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=300)
    assert process.returncode == 130, stderr
    assert "--resume" in stderr and "Traceback" not in stderr
    arrays, meta = checkpoint.read(out / checkpoint.CHECKPOINT)
    assert 0 < meta["step"] < meta["total_steps"]
    done = run_cli(*command, "--resume")
    assert done.returncode == 0, done.stderr

    assert_ends_as_uninterrupted(out, SETTLE, overrides, tmp_path)


def test_interrupted_impact_resumes_bit_for_bit_and_refuses_another_scenario(tmp_path, capsys):
    # Ctrl-C (a KeyboardInterrupt between chunks) writes a checkpoint; --resume refuses
    # it for a changed scenario or another engine build, and otherwise completes the run
    # with the trace and result of an uninterrupted run.
    out = tmp_path / "out"
    overrides = ["output.trace=true", "impact.angle_deg=45"]
    sim = simulation.Simulation(scenario.load_scene(OBLIQUE, overrides, out))
    calls = []

    def interrupt(steps, total, contacts):  # Ctrl-C in mid-contact (the contact lasts ~4,000 steps)
        calls.append(steps)
        if steps >= 2500:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sim.run(progress=interrupt, checkpoints=checkpoint.Policy(out, interval=1000 * sim.dt))
    stopped_at, path = sim.interrupted_at
    assert path == out / checkpoint.CHECKPOINT and stopped_at == 2000 * sim.dt  # the last checkpoint's step

    args = ["run", str(OBLIQUE), "--out", str(out), "--quiet", "--resume", *as_options(overrides)]
    assert cli.main(args[:-4] + as_options(["output.trace=true", "impact.angle_deg=40"])) == cli.EXIT_BAD_INPUT
    assert "was written for a different scenario" in capsys.readouterr().err
    arrays, meta = checkpoint.read(path)
    checkpoint.write(path, arrays, dict(meta, kernel="minidem_kernel_hmd_0000000000000000"))
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "another build of the engine or of law 'hmd'" in capsys.readouterr().err
    # a file of an older format (2: the plane contacts per sphere and plane, not per entry
    # of the list of planes near each sphere) is refused, naming both formats
    with open(path, "wb") as handle:
        np.savez(handle, **arrays, meta=np.frombuffer(json.dumps(dict(meta, format=2)).encode(), dtype=np.uint8))
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert f"has checkpoint format 2, this minidem writes format {checkpoint.FORMAT}" in capsys.readouterr().err
    checkpoint.write(path, arrays, meta)
    assert cli.main(args) == cli.EXIT_OK, capsys.readouterr().err

    got, got_meta, _ = assert_ends_as_uninterrupted(out, OBLIQUE, overrides, tmp_path)
    # one trace row per step: those before the interruption came from the checkpoint
    assert got["trace"].shape[0] == got_meta["step"] > 2500
    # and with nothing left to resume
    assert cli.main(args) == cli.EXIT_BAD_INPUT
    assert "has finished" in capsys.readouterr().err
    # and a --resume into a directory that holds no run creates nothing (it made the
    # directory before refusing; a new user's report, 2026-11-27)
    nowhere = tmp_path / "never_run"
    assert cli.main(["run", str(OBLIQUE), "--out", str(nowhere), "--resume", "--quiet"]) == cli.EXIT_BAD_INPUT
    assert "no checkpoint" in capsys.readouterr().err and not nowhere.exists()


# --------------------------------------------------------------------------------------
# blow-ups
# --------------------------------------------------------------------------------------
def test_a_ctrl_c_during_the_copy_of_the_last_good_state_waits_for_the_copy():
    """The last good state is one copy overwritten in place (not two alternating): a
    Ctrl-C must not tear it, so SIGINT is held while it is copied and raised after."""
    events = []
    with pytest.raises(KeyboardInterrupt):
        with run_loop._interrupts_deferred():
            signal.raise_signal(signal.SIGINT)
            time.sleep(0.01)  # Python would run its handler here if the signal were not held
            events.append("copy finished")
        events.append("after the block")  # never reached: the interrupt comes first
    assert events == ["copy finished"]


def test_a_ctrl_c_during_a_copy_checkpoints_a_whole_state(tmp_path, monkeypatch):
    """SIGINT arriving while the last good state is copied (held until the copy and its
    step count are both recorded): the checkpoint then written resumes to the
    uninterrupted result bit for bit. The diff review found the arrays of the new step
    saved with the step count of the previous copy."""
    def load():
        return scenario.load_scene(REPO / "scenarios" / "newtons_cradle.toml", ["run.end_time=2e-4"], "-")

    reference = simulation.Simulation(load()).run()
    original, copies = State.capture_items, []

    def capture_items(self):
        yield from original(self)
        copies.append(self.position.copy())
        if len(copies) == 3:  # a copy in the loop, overwriting the last good state
            signal.raise_signal(signal.SIGINT)

    monkeypatch.setattr(State, "capture_items", capture_items)
    with pytest.raises(KeyboardInterrupt):
        simulation.Simulation(load()).run(checkpoints=checkpoint.Policy(tmp_path, interval=2e-5), chunk_steps=100)
    monkeypatch.setattr(State, "capture_items", original)
    arrays, meta = checkpoint.read(tmp_path / checkpoint.CHECKPOINT)
    assert np.array_equal(arrays["position"], copies[2])  # the newest copy, with its own step count:
    sim = simulation.Simulation(load())
    loaded = checkpoint.load_for_resume(sim, tmp_path)
    resumed = sim.run(resume_from=loaded)
    assert resumed.steps == reference.steps
    assert np.array_equal(resumed.position, reference.position)
    assert np.array_equal(resumed.velocity, reference.velocity)
    # the file's arrays were released once restored (not held beside the live state for the
    # whole run); the meta, which the CLI reports from, is left
    assert loaded[0] == {} and loaded[1]["step"] == meta["step"]


def test_blow_up_stops_with_the_last_good_state_and_a_time_step_to_try(tmp_path):
    # The settling scene at 50 times its time step: dt = 1 ms against a Hertz contact
    # time of ~0.3 ms, so contacts inject energy at every step. The run must stop with
    # exit code 1 and no traceback, name the step, the particle and its contacts, suggest
    # a time step no larger than a tenth of the given one, and leave the last good state
    # (finite, before the failure) in last_good.npz and as the last VTK frame. Such a dt
    # is refused up front (docs/time-step.md) unless run.allow_unstable_dt says it is meant.
    done = run_cli("run", SETTLE, "--out", tmp_path, *as_options(
        SMALL_SETTLE + ["run.end_time=0.5", "run.dt=1e-3", "run.allow_unstable_dt=true"]))
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr and "allow_unstable_dt" in done.stderr  # the knowing override is echoed
    message = done.stderr[done.stderr.index("minidem: run failed: "):]
    assert message.startswith("minidem: run failed: blow-up (energy) at step ")
    failed_step = int(message.split("at step ")[1].split()[0])
    assert "times the scene's energy budget" in message and " touches " in message
    suggested = float(message.split("Try run.dt = ")[1].split()[0])
    assert 0 < suggested <= 1e-4
    arrays, meta = checkpoint.read(tmp_path / checkpoint.LAST_GOOD)
    assert meta["step"] < failed_step
    assert all(np.isfinite(arrays[name]).all() for name in ("position", "velocity", "angular_velocity", "force"))
    last_frame = ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")[-1]
    assert float(last_frame.get("timestep")) == meta["time"]
    assert_files_complete(tmp_path, 300)



def test_a_failed_run_does_not_leave_an_earlier_runs_results_looking_like_its_own(tmp_path):
    # A run into a directory where an earlier run succeeded, then a blow-up: the failed run
    # writes no summary, so the earlier summary.json and final_state.npz would read as its
    # result (a script checking summary.json saw success; a new user's report, 2026-11-27).
    # They are kept, renamed *.previous.*, and the run says so; its own last_good.npz is there.
    oblique = OBLIQUE
    assert run_cli("run", oblique, "--out", tmp_path, "--quiet").returncode == 0
    earlier = (tmp_path / "summary.json").read_bytes()
    done = run_cli("run", oblique, "--out", tmp_path, "--quiet", "--set", "run.dt=2e-4", "--set",
                   "run.allow_unstable_dt=true")
    assert done.returncode == 1 and "minidem: run failed: blow-up" in done.stderr, done.stderr
    assert "renamed summary.json -> summary.previous.json, final_state.npz -> final_state.previous.npz" in done.stderr
    assert not (tmp_path / "summary.json").exists() and not (tmp_path / checkpoint.FINAL_STATE).exists()
    assert (tmp_path / "summary.previous.json").read_bytes() == earlier
    assert (tmp_path / checkpoint.LAST_GOOD).exists()
    # the Python API does the same, and says so as a warning
    import minidem

    minidem.run(oblique, out=tmp_path)
    with pytest.warns(UserWarning) as caught:  # with the unstable time step's own warning
        with pytest.raises(minidem.RunFailure):
            minidem.run(oblique, {"run.dt": 2e-4, "run.allow_unstable_dt": True}, out=tmp_path)
    # the first set-aside summary is not overwritten: the second goes to the next free name
    assert any("renamed summary.json -> summary.previous.2.json" in str(w.message) for w in caught)
    assert not (tmp_path / "summary.json").exists() and (tmp_path / "summary.previous.2.json").exists()
    assert (tmp_path / "summary.previous.json").read_bytes() == earlier


def test_a_failed_run_keeps_the_earlier_runs_vtk_series_and_a_success_replaces_it(tmp_path):
    # The VTK series of an earlier run was deleted at a new run's first frame: a run that
    # then failed left summary.previous.json describing frames that were gone (a
    # robustness review, 2026-11-28). It is moved to previous_series/ at the first frame,
    # kept if the run fails, deleted once a run succeeds.
    small = [arg for o in SMALL_SETTLE + ["run.end_time=0.02"] for arg in ("--set", o)]
    assert run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small, "--set", "output.vtk=true").returncode == 0
    frames = ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")
    assert len(frames) >= 3
    failed = run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small, "--set", "output.vtk=true",
                     "--set", "run.dt=1e-3", "--set", "run.allow_unstable_dt=true")
    assert failed.returncode == 1 and "the VTK series to previous_series/" in failed.stderr, failed.stderr
    kept = ET.parse(tmp_path / "previous_series" / "particles.pvd").getroot().findall(".//DataSet")
    assert [f.get("file") for f in kept] == [f.get("file") for f in frames]
    assert all((tmp_path / "previous_series" / f.get("file")).is_file() for f in kept)
    again = run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small, "--set", "output.vtk=true")
    assert again.returncode == 0 and not (tmp_path / "previous_series").exists()
    assert len(ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")) == len(frames)


def test_a_run_without_frames_puts_an_earlier_runs_series_aside(tmp_path):
    # A run that writes no VTK series (output.vtk = false here) into a directory holding an
    # earlier run's series left that series beside its own summary: open_results and
    # ParaView read it as this run's (a user's audit, 2026-12-08: the oblique impact's
    # summary beside a Newton's cradle's five-ball frames). It goes to previous_series/ with
    # a warning, as a run with frames puts it at its first frame; walls.vtu goes with it,
    # and the next run with frames that succeeds empties the folder.
    import minidem

    with_frames = SMALL_SETTLE + ["run.end_time=0.01", "output.vtk=true"]
    minidem.run(SETTLE, with_frames, out=tmp_path)
    listed = [f.get("file") for f in ET.parse(tmp_path / "particles.pvd").getroot().findall(".//DataSet")]
    assert len(listed) >= 2 and (tmp_path / "walls.vtu").is_file()
    with pytest.warns(UserWarning, match="the VTK series there is an earlier run's"):
        minidem.run(SETTLE, with_frames + ["output.vtk=false"], out=tmp_path)
    assert not (tmp_path / "particles.pvd").exists() and not (tmp_path / "walls.vtu").exists()
    assert not any(tmp_path.glob("particles_*.vtu"))
    assert minidem.open_results(tmp_path).series is None
    aside = tmp_path / "previous_series"
    assert all((aside / name).is_file() for name in listed + ["particles.pvd", "walls.vtu"])
    minidem.run(SETTLE, with_frames, out=tmp_path)
    assert not aside.exists() and (tmp_path / "particles.pvd").is_file()


def test_the_last_good_state_of_a_blow_up_stays_until_a_run_succeeds(tmp_path, monkeypatch):
    # last_good.npz was deleted when the next run started (a user's audit, 2026-12-08: the
    # state before the blow-up gone while a smaller time step was being tried). It stays
    # while the next run goes on, a blow-up of that run writes its own, and a run that
    # succeeds deletes it (beside a successful summary it would read as that run's).
    import minidem

    with pytest.warns(UserWarning), pytest.raises(minidem.RunFailure):
        minidem.run(OBLIQUE, {"run.dt": 2e-4, "run.allow_unstable_dt": True}, out=tmp_path)
    assert (tmp_path / checkpoint.LAST_GOOD).exists()
    seen_while_running = []
    original = simulation.Simulation.run

    def run(self, *args, **kwargs):
        seen_while_running.append((tmp_path / checkpoint.LAST_GOOD).exists())
        return original(self, *args, **kwargs)

    monkeypatch.setattr(simulation.Simulation, "run", run)
    minidem.run(OBLIQUE, out=tmp_path)
    assert seen_while_running == [True]
    assert not (tmp_path / checkpoint.LAST_GOOD).exists() and (tmp_path / "summary.json").exists()


@pytest.fixture(scope="module")
def settle_guard():
    sim = simulation.Simulation(scenario.load_scene(SETTLE, SMALL_SETTLE + ["run.end_time=0.5"]))
    return sim, blowup.Guard(sim)


def test_guard_passes_free_fall_and_catches_nan_runaway_energy_and_escape(settle_guard):
    sim, guard = settle_guard
    state = State(sim)
    assert guard.check(state, 0.0, 0.0)[0] is None
    # every particle in free fall for 0.1 s: energy from gravity only, allowed
    t, g = 0.1, sim.scene.gravity
    state.position += 0.5 * g * t * t
    state.velocity[:] = g * t
    fault, work = guard.check(state, t, 0.0)
    assert fault is None and work == pytest.approx(float(sim.scene.mass.sum()) * 9.81 * 0.5 * 9.81 * t * t)
    # one particle 100 times faster than the whole energy budget allows (1e4 times the energy)
    fast = State(sim)
    budget = guard.budget(fast.position, 0.0)[0]
    fast.velocity[7] = [0.0, 100.0 * math.sqrt(2.0 * budget / sim.scene.mass[7]), 0.0]
    fault, _ = guard.check(fast, 1e-3, 0.0)
    assert (fault.what, fault.particle) == ("energy", 7)
    # a NaN spin
    broken = State(sim)
    broken.angular_velocity[12, 2] = math.nan
    fault, _ = guard.check(broken, 1e-3, 0.0)
    assert (fault.what, fault.particle) == ("non-finite state", 12) and "angular velocity" in fault.detail
    # a particle 1 km away after 1 ms, at rest: no energy could have carried it there
    escaped = State(sim)
    escaped.position[42, 0] += 1e3
    fault, _ = guard.check(escaped, 1e-3, 0.0)
    assert (fault.what, fault.particle) == ("domain", 42) and "left the domain" in fault.detail


# --------------------------------------------------------------------------------------
# determinism
# --------------------------------------------------------------------------------------
def final_arrays(result, sim):
    arrays = sim.state.capture()
    arrays["energy"] = result.energy
    arrays["trace"] = result.trace if result.trace is not None else np.zeros(0)
    arrays["stats"] = np.array([result.first_contact_time, result.last_separation_time, result.max_overlap,
                                result.peak_normal_force, result.peak_tangential_force])
    return arrays


@pytest.mark.parametrize("case", ["impact", "settle"])
def test_runs_are_deterministic(case):
    # Same input, same threads: identical bits in every result array, the sampled
    # kinetic energy and the per-step trace included (their schedule depends on the
    # step count alone, never on wall time).
    if case == "impact":
        load = lambda: scenario.load_scene(OBLIQUE, ["output.trace=true", "impact.angle_deg=20"])  # noqa: E731
    else:
        load = lambda: scenario.load_scene(SETTLE, SMALL_SETTLE + ["fill.0.count=100", "run.end_time=0.03",  # noqa: E731
                                                                   "output.vtk=false"])
    runs = []
    for _ in range(2):
        sim = simulation.Simulation(load())
        runs.append(final_arrays(sim.run(), sim))
    assert_same_state(runs[0], runs[1])


# --------------------------------------------------------------------------------------
# a plugin written outside the repository
# --------------------------------------------------------------------------------------
def install_plugin(tmp_path, distribution: str, version: str, entry_point: str, setuptools: str,
                   files: dict[str, str]):
    """Write a plugin's pyproject.toml and ``files`` (path -> source) into a folder and
    install it with pip into ``tmp_path/site`` (a folder for PYTHONPATH, so the test
    environment stays as it was); return that folder."""
    source = tmp_path / distribution
    (source / "pyproject.toml").parent.mkdir(parents=True)
    (source / "pyproject.toml").write_text(textwrap.dedent(f'''
        [build-system]
        requires = ["setuptools>=61"]
        build-backend = "setuptools.build_meta"

        [project]
        name = "{distribution}"
        version = "{version}"

        [project.entry-points.minidem]
        {entry_point}

        [tool.setuptools]
        {setuptools}
    '''))
    for name, text in files.items():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        (source / name).write_text(textwrap.dedent(text))
    site = tmp_path / "site"
    pip = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                          "--target", str(site), str(source)], capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr
    return site


PLUGIN_MODULE = '''
"""Linear normal spring, incremental linear tangential spring capped at mu Fn; no damping."""
import math
import os

import numba

from minidem import hookimpl
from minidem.contact import ContactLaw, HistorySlot, Parameter


def prepare(pair, params):
    return {"normal_stiffness": params["normal_stiffness"],
            "tangential_stiffness": params["stiffness_ratio"] * params["normal_stiffness"],
            "friction": params["friction"]}


def contact_time(pair, constants, effective_radius, effective_mass, normal_speed):
    return math.pi * math.sqrt(effective_mass / constants["normal_stiffness"])  # half a spring period


@numba.njit(cache=True)
def hooke_coulomb_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                        normal_velocity, tangential_increment, tangential_velocity, history):
    normal_force = constants[0] * normal_overlap
    fx = history[0] + constants[1] * tangential_increment[0]
    fy = history[1] + constants[1] * tangential_increment[1]
    fz = history[2] + constants[1] * tangential_increment[2]
    magnitude = math.sqrt(fx * fx + fy * fy + fz * fz)
    limit = constants[2] * normal_force
    if magnitude > limit:
        scale = limit / magnitude
        fx, fy, fz = fx * scale, fy * scale, fz * scale
    history[0], history[1], history[2] = fx, fy, fz
    return normal_force, fx, fy, fz


@hookimpl
def minidem_register_laws(registry):
    registry.add(ContactLaw(
        name="hooke_coulomb",
        description="linear spring, incremental tangential spring, Coulomb cap",
        parameters=(Parameter("friction", None, "-", "Coulomb friction coefficient", low=0.0, required=True),
                    Parameter("normal_stiffness", 1e8, "N/m", "kn", low=0.0, low_open=True),
                    Parameter("stiffness_ratio", 0.8, "-", "kt / kn", low=0.0, low_open=True)),
        constants=("normal_stiffness", "tangential_stiffness", "friction"),
        history=(HistorySlot("tangential_force", "spring force (N)", vector=True),),
        prepare=prepare, force=hooke_coulomb_force, contact_time=contact_time))
'''


def test_a_plugin_written_outside_the_repository_is_installed_listed_run_and_verified(tmp_path):
    # The third-party workflow of docs/writing-a-contact-law.md, for real: a folder with a
    # pyproject.toml and an entry point, installed with pip (into a folder on PYTHONPATH,
    # so the test environment stays as it was), then `minidem laws`, `minidem run` and
    # `minidem verify` in fresh processes, as a user would.
    site = install_plugin(tmp_path, "minidem-hooke-coulomb", "2.5.1", 'hooke = "minidem_hooke_coulomb"',
                          'py-modules = ["minidem_hooke_coulomb"]', {"minidem_hooke_coulomb.py": PLUGIN_MODULE})
    env = {"PYTHONPATH": str(site)}

    listed = run_cli("laws", env=env)
    assert listed.returncode == 0, listed.stderr
    assert "hooke_coulomb  [minidem-hooke-coulomb 2.5.1, plugin 'hooke']" in listed.stdout
    assert "BROKEN" not in listed.stdout

    # the paper's normal impact: an undamped linear spring returns en = 1 after half a
    # period, pi sqrt(m/k) (paper eq 27)
    ran = run_cli("run", OBLIQUE, "--out", tmp_path / "run", "--set", "contact.law=hooke_coulomb",
                  "--set", "impact.angle_deg=0", env=env)
    assert ran.returncode == 0, ran.stderr
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    mass = 4.0 / 3.0 * math.pi * 0.025**3 * 2650.0
    assert summary["law"] == "hooke_coulomb"
    assert summary["contact_duration_s"] == pytest.approx(math.pi * math.sqrt(mass / 1e8), rel=1e-3)
    assert summary["en"] == pytest.approx(1.0, abs=1e-6)

    judged = run_cli("verify", "hooke_coulomb", "--out", tmp_path / "verify", env=env)
    assert judged.returncode == 0, judged.stdout + judged.stderr
    assert "FAIL" not in judged.stdout
    for check in ("elastic impacts create no energy", "rigid-body sliding limit", "normal-impact duration",
                  "frame invariance (rotated collision)", "sphere-sphere forces equal and opposite"):
        assert f"PASS  {check}" in judged.stdout
    report = json.loads((tmp_path / "verify" / "verify.json").read_text())
    assert (report["package"], report["version"]) == ("minidem-hooke-coulomb", "2.5.1")


HELPER_PLUGIN_LAW = '''
"""A linear normal spring whose stiffness factor comes from a helper in a subpackage."""
import math
import os

import numba

from minidem import hookimpl
from minidem.contact import ContactLaw, Parameter
from minidem_scaled.helpers.factor import stiffness_factor


def prepare(pair, params):
    return {"normal_stiffness": params["normal_stiffness"]}


def contact_time(pair, constants, effective_radius, effective_mass, normal_speed):
    return math.pi * math.sqrt(effective_mass / constants["normal_stiffness"])


@numba.njit(cache=True)
def scaled_force(constants, effective_radius, effective_mass, normal_overlap, normal_overlap_increment,
                 normal_velocity, tangential_increment, tangential_velocity, history):
    return stiffness_factor() * constants[0] * normal_overlap, 0.0, 0.0, 0.0


@hookimpl
def minidem_register_laws(registry):
    registry.add(ContactLaw(
        name="scaled_spring", description="linear spring, stiffness factor from a helper",
        parameters=(Parameter("normal_stiffness", 1e8, "N/m", "kn", low=0.0, low_open=True),),
        constants=("normal_stiffness",), history=(), prepare=prepare, force=scaled_force,
        contact_time=contact_time, frictional=False))
'''


def test_an_edited_helper_of_a_plugin_law_rebuilds_its_kernel(tmp_path):
    """A helper two files away from the force function (a subpackage) is edited between two
    runs: the second run must use it. numba's cache checks only each function's own file,
    so without minidem following the force function's calls the first kernel (and the
    force function's own cached machine code) came back: found by review, max overlap
    2.08e-4 m twice instead of halving. Expected values from the spring alone: an
    undamped linear spring stops the sphere at v sqrt(m / k) (paper eq 27's oscillator)."""
    helper = "import numba\n\n\n@numba.njit(cache=True)\ndef stiffness_factor():\n    return {}\n"
    site = install_plugin(tmp_path, "minidem-scaled", "1.0.0", 'scaled = "minidem_scaled.law"',
                          'packages = ["minidem_scaled", "minidem_scaled.helpers"]',
                          {"minidem_scaled/__init__.py": "", "minidem_scaled/helpers/__init__.py": "",
                           "minidem_scaled/law.py": HELPER_PLUGIN_LAW,
                           "minidem_scaled/helpers/factor.py": helper.format(1.0)})
    installed_helper = site / "minidem_scaled" / "helpers" / "factor.py"
    # a cache of its own: what is tested is how this cache is reused
    env = {"PYTHONPATH": str(site), "MINIDEM_CACHE_DIR": str(tmp_path / "cache"),
           "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    mass = 4.0 / 3.0 * math.pi * 0.025**3 * 2650.0
    scene = tmp_path / "normal.toml"  # the paper's impact; this law has no friction parameter
    scene.write_text("\n".join(line for line in OBLIQUE.read_text().splitlines()
                               if not line.startswith("friction")))

    def max_overlap(factor: float, out: str) -> float:
        installed_helper.write_text(helper.format(factor))
        ran = run_cli("run", scene, "--out", tmp_path / out, "--quiet", "--set", "contact.law=scaled_spring",
                      "--set", "impact.angle_deg=0", env=env)
        assert ran.returncode == 0, ran.stderr
        overlap = json.loads((tmp_path / out / "summary.json").read_text())["max_overlap_m"]
        assert overlap == pytest.approx(5.0 * math.sqrt(mass / (factor * 1e8)), rel=1e-3)
        return overlap

    kernels = tmp_path / "cache" / "kernels"
    first = max_overlap(1.0, "one")
    second = max_overlap(4.0, "four")
    assert second == pytest.approx(first / 2.0, rel=1e-3)
    built = sorted(p.name for p in kernels.glob("*.py"))
    max_overlap(4.0, "again")  # nothing changed: the kernel is reused, not rebuilt
    assert sorted(p.name for p in kernels.glob("*.py")) == built


def test_an_earlier_trace_is_not_left_beside_a_later_runs_summary(tmp_path):
    # a run with output.trace, then one without into the same directory: the first run's
    # trace.csv stayed beside the second's summary and open_results returned it as the
    # second run's (a robustness review, 2026-11-28). It is renamed, and the run says so.
    import minidem

    assert run_cli("run", OBLIQUE, "--out", tmp_path, "--quiet", "--set", "output.trace=true").returncode == 0
    traced = (tmp_path / "trace.csv").read_bytes()
    later = run_cli("run", OBLIQUE, "--out", tmp_path, "--quiet", "--set", "impact.angle_deg=60")
    assert later.returncode == 0 and "trace.csv is an earlier run's" in later.stderr, later.stderr
    assert not (tmp_path / "trace.csv").exists() and (tmp_path / "trace.previous.csv").read_bytes() == traced
    assert minidem.open_results(tmp_path).trace is None


def test_a_file_in_the_way_of_the_set_aside_series_stops_the_run_naming_it(tmp_path):
    # a file named previous_series ended the run as "internal error: FileExistsError"; a
    # folder of that name the user made (no series in it) took the place of a set-aside
    # series, and the earlier run's frames were deleted (a review, 2026-11-28)
    small = [arg for o in SMALL_SETTLE + ["run.end_time=0.01", "output.vtk=true"] for arg in ("--set", o)]
    assert run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small).returncode == 0
    (tmp_path / "previous_series").write_text("mine")
    blocked = run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small)
    assert blocked.returncode == 1 and "internal error" not in blocked.stderr, blocked.stderr
    assert f"cannot write {tmp_path / 'previous_series'}: File exists" in blocked.stderr, blocked.stderr
    (tmp_path / "previous_series").unlink()
    (tmp_path / "previous_series").mkdir()
    (tmp_path / "previous_series" / "notes.txt").write_text("mine")
    failed = run_cli("run", SETTLE, "--out", tmp_path, "--quiet", *small, "--set", "run.dt=1e-3",
                     "--set", "run.allow_unstable_dt=true")
    assert failed.returncode == 1 and (tmp_path / "previous_series" / "particles.pvd").exists(), failed.stderr
    assert (tmp_path / "previous_series" / "notes.txt").read_text() == "mine"


def test_a_checkpoint_of_a_run_without_frames_resumes_with_a_series_from_there(tmp_path, capsys):
    """A checkpoint written by `Simulation.run` without on_frame (the Python API, no VTK
    output) holds no series; `minidem run --resume` of a scene that writes VTK frames
    went on to an internal error (TypeError in the series' restore; the review of
    2026-12-07). It now resumes: a warning says the series starts where the run resumes,
    every frame is at or after that time, and the final state is the uninterrupted
    run's, bit for bit. The bouncing ball: 0.5 s of its 1 s, frames every 0.01 s."""
    import xml.etree.ElementTree as ElementTree

    path = REPO / "scenarios" / "bouncing_ball.toml"
    out = tmp_path / "out"
    sim = simulation.Simulation(scenario.load_scene(path, [], out))

    def interrupt(steps, total, contacts):
        if steps * sim.dt > 0.5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        sim.run(progress=interrupt, checkpoints=checkpoint.Policy(out, interval=0.1))
    resumed_at, _ = sim.interrupted_at
    capsys.readouterr()
    assert cli.main(["run", str(path), "--out", str(out), "--resume", "--quiet"]) == cli.EXIT_OK
    err = capsys.readouterr().err
    assert "wrote no VTK frames: the series starts at t =" in err and "internal error" not in err, err
    times = [float(d.get("timestep")) for d in ElementTree.parse(out / "particles.pvd").getroot().iter("DataSet")]
    # a frame every 0.01 s from the resumed time (0.64 s) to the end (1 s), and the final state
    assert len(times) >= 36 and min(times) >= resumed_at - 1e-12 and times == sorted(times)
    # the state as an uninterrupted run's (its energy samples, taken at every frame too,
    # follow the frames, which differ by construction)
    reference = simulation.Simulation(scenario.load_scene(path, [], "-")).run()
    got, _ = checkpoint.read(out / checkpoint.FINAL_STATE)
    for name in ("position", "velocity", "angular_velocity"):
        assert np.array_equal(got[name], getattr(reference, name)), name


# -- the last good state in a file (minidem.engine.state.StateCopy) ----------------------
SMALL_BLOW_UP = SMALL_SETTLE + ["run.end_time=0.5", "run.dt=2e-4", "run.allow_unstable_dt=true"]  # fails at step 60


def copy_every_chunk(monkeypatch):
    # a copy of the last good state after every chunk that passed the checks, so that a
    # run of a few hundred steps makes many (a run copies at most every 200,000 particle-steps)
    monkeypatch.setattr(run_loop, "SNAPSHOT_STEPS", 1)
    monkeypatch.setattr(run_loop, "SNAPSHOT_PARTICLE_STEPS", 1)
    monkeypatch.setattr(run_loop, "SNAPSHOT_COST_RATIO", 0)


def unnamed_files_in(directory):
    """(descriptor, size) of this process's open files in ``directory`` that have no name."""
    found = []
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
            if target.startswith(str(directory) + "/") and target.endswith("(deleted)"):
                found.append((int(fd), os.fstat(int(fd)).st_size))
        except OSError:
            pass
    return found


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="reads the process's open files from /proc")
def test_the_last_good_state_is_an_unnamed_file_in_the_output_directory(tmp_path, monkeypatch):
    if on_memory_file_system(tmp_path):
        pytest.skip("the test directory is on tmpfs, where the copy stays in memory (the next test)")
    """The copy is written to the run's directory, not held in memory (30 % of a settled
    pile's memory, docs/benchmarks.md), has no name there while the run holds it, and is
    gone when the run ends."""
    copy_every_chunk(monkeypatch)
    sim = simulation.Simulation(scenario.load_scene(SETTLE, SMALL_SETTLE + ["run.end_time=0.02"], "-"))
    seen = []
    sim.run(checkpoints=checkpoint.Policy(tmp_path), chunk_steps=50,
            progress=lambda steps, total, contacts: seen.append(unnamed_files_in(tmp_path)))
    # the particle arrays alone (position, velocity, spin, force, torque, position at build)
    particle_bytes = 6 * sim.state.position.nbytes
    assert len(seen) > 5 and all(len(files) == 1 and files[0][1] > particle_bytes for files in seen), seen
    assert unnamed_files_in(tmp_path) == []
    assert sorted(path.name for path in tmp_path.iterdir()) == [checkpoint.FINAL_STATE]


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="needs a tmpfs (Linux's /dev/shm)")
def test_on_tmpfs_the_last_good_state_stays_in_memory(monkeypatch):
    """A file on tmpfs is memory the system cannot reclaim either (the review measured
    +200 MiB of shared memory for -184 MiB of the process's): the copy is kept where it
    is counted, in the process, and nothing is written there."""
    assert on_memory_file_system("/dev/shm") and on_memory_file_system("/dev/shm/not/made/yet")
    copy = StateCopy("/dev/shm")
    copy.write(lambda: iter([("position", np.arange(6.0).reshape(2, 3))]))
    assert isinstance(copy.handle, io.BytesIO)
    assert np.array_equal(copy.read()["position"], np.arange(6.0).reshape(2, 3))
    copy.close()


def test_a_copy_read_back_from_its_file_is_the_state_bit_for_bit(tmp_path, monkeypatch):
    from minidem.engine import state as state_module

    sim = simulation.Simulation(scenario.load_scene(SETTLE, SMALL_SETTLE + ["run.end_time=0.1"], "-"))
    sim.run()
    # the touching rows are written a block at a time (StateCopy, RowsTaken): blocks of 7
    # rows here, so that every array is many blocks and most end in a partial one
    monkeypatch.setattr(state_module, "_SPARSE_BLOCK", 7)
    copy = StateCopy(tmp_path)
    for _ in range(2):  # a second write replaces the first
        copy.write(sim.state.capture_items)
    got, want = copy.read(), sim.state.capture()
    copy.close()
    assert want["pair_reaction@rows"].size > 100  # a pile: the touching pairs are in the copy
    assert got.keys() == want.keys()
    for name in want:
        assert got[name].dtype == want[name].dtype and got[name].shape == want[name].shape, name
        assert got[name].tobytes() == want[name].tobytes(), name


class _FullDisk:
    """A temporary file whose writes fail (ENOSPC) from the ``fail_at``-th on, and whose
    close then fails too, as a buffered file's does when it flushes what it holds onto
    the full disk (the review's find: the fallback's close raised the same error, and the
    run stopped)."""

    def __init__(self, make_file, fail_at, writes):
        self.file, self.fail_at, self.writes = make_file(), fail_at, writes

    def write(self, data):
        self.writes.append(len(data))
        if len(self.writes) >= self.fail_at:
            raise OSError(28, "No space left on device")
        return self.file.write(data)

    def close(self):
        self.file.close()
        if len(self.writes) >= self.fail_at:
            raise OSError(28, "No space left on device")

    def __getattr__(self, name):
        return getattr(self.file, name)


def test_a_full_disk_keeps_the_last_good_state_in_memory_and_the_blow_up_restores_it(tmp_path, monkeypatch):
    """A copy whose file fails half-way (a full disk) is kept in memory from then on, with a
    warning; the run goes on, and the blow-up restores and writes the same last good state
    as with the file, bit for bit."""
    from minidem.engine import state as state_module

    copy_every_chunk(monkeypatch)

    def blow_up(out):
        # the scene's time step is unstable on purpose (SMALL_BLOW_UP), and said so
        with pytest.warns(UserWarning, match="allowed by run.allow_unstable_dt"):
            sim = simulation.Simulation(scenario.load_scene(SETTLE, SMALL_BLOW_UP, "-"))
        with pytest.raises(run_loop.RunFailure) as failure:
            sim.run(checkpoints=checkpoint.Policy(out), chunk_steps=20)
        return str(failure.value), sim.state.capture(), checkpoint.read(out / checkpoint.LAST_GOOD)[0]

    (tmp_path / "file").mkdir()
    message, state, written = blow_up(tmp_path / "file")
    assert int(message.split("Last good state: step ")[1].split()[0]) > 20  # copies in the loop
    writes = []
    make_file = state_module.tempfile.TemporaryFile
    monkeypatch.setattr(state_module.tempfile, "TemporaryFile", lambda **kw: _FullDisk(make_file, 70, writes))
    (tmp_path / "memory").mkdir()
    with pytest.warns(UserWarning, match="cannot keep the last good state in a temporary file in .*memory "
                                          r"\(No space left on device\): it is kept in memory instead"):
        got_message, got_state, got_written = blow_up(tmp_path / "memory")
    assert len(writes) == 70  # the file failed once, in the middle of a copy after the first
    assert got_message == message.replace(str(tmp_path / "file"), str(tmp_path / "memory"))
    for name in state:
        assert got_state[name].tobytes() == state[name].tobytes(), name
    for name in written:
        assert got_written[name].tobytes() == written[name].tobytes(), name
