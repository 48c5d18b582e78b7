"""Sweep execution: one executor interface, local processes and Dask.

Behaviour asserted (issue 7): sweep.csv is the same file, byte for byte, for any back
end and worker count; a failed case is a row with its reason and the sweep goes on (exit
code 1); an interrupted or killed sweep resumes and runs only the missing cases; a
changed plan is refused unless --restart; a sweep on a real Dask scheduler with two
worker processes, one of them SIGKILLed part way, gives the same sweep.csv as a local run.

Every case is the paper's single-sphere oblique impact with law hmd (friction on, so the
spin kernel): the kernel variant the paper tests compile, loaded here from the cache.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from minidem import cli
from minidem.studies import executors
from minidem.scene import scenario
from minidem.studies import sweep

from conftest import OBLIQUE, impact_summary, minidem_command

ANGLES = [5.0, 15.0, 25.0, 35.0, 45.0, 60.0]


def _plan(angles=ANGLES, keep_traces=True):
    data = scenario.read_toml(OBLIQUE)
    data["sweep"] = {"cases": {"impact.angle_deg": list(angles)}, "keep_traces": keep_traces, "figures": []}
    return sweep.plan(data, str(OBLIQUE))


def _journal_rows(directory: Path) -> list[dict]:
    lines = (directory / sweep.JOURNAL).read_text().splitlines()[1:]
    return [json.loads(line) for line in lines if line.strip()]


class Recording:
    """An executor around another that records the cases it was given and can stop
    (as Ctrl-C does) after a number of results."""

    def __init__(self, inner, stop_after=None):
        self.inner, self.stop_after, self.cases = inner, stop_after, []
        self.description = f"recording {inner.description}"

    def run(self, function, tasks, warm=()):
        self.cases = [task.index for task in tasks]
        for count, item in enumerate(self.inner.run(function, tasks, warm)):
            if count == self.stop_after:
                raise KeyboardInterrupt
            yield item

    def close(self):
        self.inner.close()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The sweep on one local process: the file every other way of running must equal."""
    directory = tmp_path_factory.mktemp("reference")
    rows = sweep.run(_plan(), directory, progress=False, executor=executors.LocalProcesses(1))
    return directory, rows


def test_rows_are_the_single_runs_and_read_back_to_the_same_bits(reference):
    """Each row is the summary of a single run of that case (not a copy of the sweep's own
    output: impact_summary runs the scene directly), and the CSV text of every float
    parses back to the same float."""
    directory, rows = reference
    table = sweep.load_rows(directory / "sweep.csv")
    for angle, row, read in zip(ANGLES, rows, table):
        single = impact_summary("hmd", angle)
        for key in ("x", "y1", "y2", "et", "en", "energy_ratio", "max_overlap_m"):
            assert row[key] == single[key] and read[key] == single[key], key
        assert read["status"] == "ok" and read["error"] is None
        assert (directory / read["trace_file"]).is_file()


def test_sweep_csv_is_identical_for_any_worker_count(reference, tmp_path):
    directory, _ = reference
    sweep.run(_plan(), tmp_path, progress=False, executor=executors.LocalProcesses(2))
    assert (tmp_path / "sweep.csv").read_bytes() == (directory / "sweep.csv").read_bytes()
    for trace in sorted((directory / "traces").glob("*.csv")):
        assert (tmp_path / "traces" / trace.name).read_bytes() == trace.read_bytes()


def test_a_sweep_after_parallel_loops_in_the_same_process_does_not_fork(reference, tmp_path):
    # Forking once numba's threading layer has started its threads can hang the workers
    # (a lock held by a thread that does not exist in the child: seen after the parallel
    # multi-particle tests). The pool must then start its workers from a fork server,
    # and give the same file.
    import numba

    @numba.njit(parallel=True)
    def total(values):
        result = 0.0
        for i in numba.prange(values.shape[0]):
            result += values[i]
        return result

    assert total(np.ones(1000)) == 1000.0
    assert not executors._fork_is_safe()
    directory, _ = reference
    sweep.run(_plan(), tmp_path, progress=False, executor=executors.LocalProcesses(2))
    assert (tmp_path / "sweep.csv").read_bytes() == (directory / "sweep.csv").read_bytes()


def test_a_single_impact_starts_no_threads_so_a_sweep_after_it_still_forks():
    # A user's script ran the impact, then a sweep with workers=2, without a __main__
    # guard: the impact's run had started numba's threads (numba.get_num_threads), so
    # the pool started fresh Pythons, which ran the script again, and every case was
    # lost (a user's audit, 2026-12-08). A serial kernel now leaves the threads alone.
    code = ("import minidem; from minidem.studies import executors; "
            f"minidem.run({str(OBLIQUE)!r}); print(executors._fork_is_safe())")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and done.stdout.split()[-1] == "True", done.stderr


def test_workers_that_could_not_fork_and_died_say_why(monkeypatch):
    # After a parallel run the workers start fresh Pythons, which run the main script
    # again: a script without the __main__ guard starts the sweep again in each, and
    # multiprocessing kills them. The lost cases say so and what to do.
    from concurrent.futures.process import BrokenProcessPool

    monkeypatch.setattr(sys.modules["__main__"], "__file__", "/home/user/loop.py", raising=False)
    hint = executors._not_forked_hint(BrokenProcessPool("terminated abruptly"))
    assert "runs /home/user/loop.py again" in hint and "if __name__ == \"__main__\":" in hint and "workers=1" in hint
    monkeypatch.setattr(sys.modules["__main__"], "__file__", "/venv/bin/minidem")  # the CLI's own: no advice
    assert executors._not_forked_hint(BrokenProcessPool("terminated abruptly")) == ""
    monkeypatch.delattr(sys.modules["__main__"], "__file__")  # a notebook's main: no script to run again
    assert executors._not_forked_hint(BrokenProcessPool("terminated abruptly")) == ""
    assert executors._not_forked_hint(ValueError("a case's own error")) == ""


def test_interrupted_sweep_resumes_with_only_the_missing_cases(reference, tmp_path):
    directory, _ = reference
    with pytest.raises(KeyboardInterrupt):
        sweep.run(_plan(), tmp_path, progress=False, executor=Recording(executors.LocalProcesses(2), stop_after=2))
    assert not (tmp_path / "sweep.csv").exists()  # never a partial table
    first = _journal_rows(tmp_path)
    assert 2 <= len(first) < len(ANGLES)  # the yielded rows are journalled before the interruption
    # a crash in the middle of a write leaves a torn last line: that case just runs again
    with open(tmp_path / sweep.JOURNAL, "ab") as handle:
        handle.write(b'{"case": 5, "status": "o')
    # and a line of valid JSON that is no row run_case wrote (edited by hand) is a case not
    # done either: it ended the resumed sweep in a KeyError (a robustness review, 2026-11-28)
    lines = (tmp_path / sweep.JOURNAL).read_bytes().split(b"\n")
    edited = json.loads(lines[1])["case"]
    lines[1] = json.dumps({"case": edited, "bogus": 1}).encode()
    (tmp_path / sweep.JOURNAL).write_bytes(b"\n".join(lines))
    done = {row["case"] for row in first} - {edited}
    again = Recording(executors.LocalProcesses(2))
    sweep.run(_plan(), tmp_path, progress=False, executor=again)
    assert sorted(again.cases) == sorted(set(range(len(ANGLES))) - done)
    assert sorted({row["case"] for row in _journal_rows(tmp_path)}) == list(range(len(ANGLES)))
    assert (tmp_path / "sweep.csv").read_bytes() == (directory / "sweep.csv").read_bytes()
    # a finished sweep run again runs nothing and writes the same table
    nothing = Recording(executors.LocalProcesses(2))
    sweep.run(_plan(), tmp_path, progress=False, executor=nothing)
    assert nothing.cases == []
    assert (tmp_path / "sweep.csv").read_bytes() == (directory / "sweep.csv").read_bytes()


def test_changed_plan_is_refused_until_restart(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        sweep.run(_plan(keep_traces=False), tmp_path, progress=False,
                  executor=Recording(executors.LocalProcesses(1), stop_after=1))
    changed = _plan([5.0, 16.0, 25.0, 35.0, 45.0, 60.0], keep_traces=False)
    with pytest.raises(scenario.ScenarioError, match="--restart"):
        sweep.run(changed, tmp_path, progress=False, executor=executors.LocalProcesses(1))
    fresh = Recording(executors.LocalProcesses(1))
    sweep.run(changed, tmp_path, progress=False, executor=fresh, restart=True)
    assert fresh.cases == list(range(6))
    assert [row["angle_deg"] for row in sweep.load_rows(tmp_path / "sweep.csv")] == [case[0] for case in changed.cases]


def test_a_second_sweep_in_the_same_directory_is_refused(tmp_path):
    """Two runs appending to one journal would run cases twice and interleave rows."""
    import sys

    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from minidem.studies import sweep; "
                               f"lock = sweep._directory_lock(__import__('pathlib').Path({str(tmp_path)!r})); "
                               "lock.__enter__(); print('locked', flush=True); time.sleep(60)"],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(scenario.ScenarioError, match=f"another minidem sweep \\(pid {holder.pid}\\)"):
            sweep.run(_plan([5.0], keep_traces=False), tmp_path, progress=False,
                      executor=executors.LocalProcesses(1))
    finally:
        holder.kill()
        holder.wait()
    # the lock dies with its process
    sweep.run(_plan([5.0], keep_traces=False), tmp_path, progress=False, executor=executors.LocalProcesses(1))


def test_failed_case_is_reported_in_its_row_and_the_sweep_goes_on(tmp_path):
    """dt = 1 us is fine (the contact lasts ~0.13 ms), but 0.2 ms, allowed although above the
    stability limit, blows up in the contact's second step: the engine's guard stops that
    case. (The case used to be an impact at 1e5 m/s, which passed through the wall in a
    step; its overlap, beyond the radius, is now refused before any case runs.)"""
    scenario_file = tmp_path / "sweep.toml"
    text = OBLIQUE.read_text().replace('dt = "auto"', "dt = 1e-6\nallow_unstable_dt = true")
    scenario_file.write_text(text + '\n[sweep]\ncases = {"run.dt" = [1e-6, 2e-4, 1.5e-6]}\nfigures = []\n')
    code = cli.main(["run", str(scenario_file), "--out", str(tmp_path / "out"), "--quiet", "--workers", "1"])
    assert code == 1  # some cases failed
    rows = sweep.load_rows(tmp_path / "out" / "sweep.csv")
    assert [r["status"] for r in rows] == ["ok", "failed", "ok"]
    assert "RunFailure: blow-up (energy)" in rows[1]["error"] and rows[1]["law"] == "hmd"
    assert rows[1]["et"] is None  # no number where there is no result, never a NaN
    for row in (rows[0], rows[2]):
        assert row["error"] is None and 0.0 < row["et"] < 1.0 and row["energy_ratio"] <= 1.0 + 1e-9



def test_sweep_keys_given_with_set_make_a_sweep_of_a_single_run_file(tmp_path, capsys):
    """`--set` overrides any scenario value (docs/cli.md), [sweep] too: on a file without
    [sweep] a single run used to ignore `--set sweep.cases=...` (one run at the file's
    angle, no sweep.csv, exit 0) and accept `--set sweep.bogus=1` (a new user's report,
    2026-11-27). The sweep is now made and checked as one written in the file."""
    bad = cli.main(["run", str(OBLIQUE), "--out", str(tmp_path / "bad"), "--quiet", "--set", "sweep.bogus=1"])
    assert bad == 2 and "sweep.bogus: unknown key" in capsys.readouterr().err
    code = cli.main(["run", str(OBLIQUE), "--out", str(tmp_path / "out"), "--quiet", "--workers", "1",
                     "--set", 'sweep.cases={"impact.angle_deg"=[10.0, 45.0]}', "--set", "sweep.figures=[]"])
    assert code == 0
    rows = sweep.load_rows(tmp_path / "out" / "sweep.csv")
    assert [r["angle_deg"] for r in rows] == [10.0, 45.0] and all(r["status"] == "ok" for r in rows)

def _sweep_file(directory: Path, extra: str = "") -> Path:
    path = directory / "angles.toml"
    path.write_text(OBLIQUE.read_text() + f'\n[sweep]\ncases = {{"impact.angle_deg" = {ANGLES!r}}}\nfigures = []\n'
                    + extra)
    return path


def test_one_case_of_a_sweep_runs_alone_with_its_own_files(reference, tmp_path, capsys):
    """`minidem run FILE --case N` runs case N as a single run (summary.json,
    final_state.npz, a VTK series when asked) in OUT/case_NNN: the row of sweep.csv to
    the bit, since a row is that single run. Before, docs/cli.md said to look at a case
    with `--set KEY=VALUE`, which on a sweep file ran the whole sweep with the value
    thrown away by every case (a review, 2026-11-28): that is now refused, naming the
    key and --case."""
    path = _sweep_file(tmp_path)
    out = tmp_path / "out"
    assert cli.main(["run", str(path), "--out", str(out), "--case", "3", "--quiet", "--set", "output.vtk=true"]) == 0
    summary = json.loads((out / "case_003" / "summary.json").read_text())
    row = reference[1][3]
    assert summary["angle_deg"] == ANGLES[3] == row["angle_deg"]
    assert all(summary[key] == row[key] for key in ("en", "et", "y1", "y2", "steps")), (summary, row)
    assert (out / "case_003" / "particles.pvd").exists() and not (out / "sweep.csv").exists()
    capsys.readouterr()
    assert cli.main(["run", str(path), "--out", str(out), "--case", "6", "--quiet"]) == 2
    assert "--case 6: the sweep has 6 case(s), 0 to 5" in capsys.readouterr().err
    assert cli.main(["run", str(path), "--out", str(out), "--quiet", "--set", "impact.angle_deg=30"]) == 2
    err = capsys.readouterr().err
    assert "--set impact.angle_deg=30: 'impact.angle_deg' is varied by the [sweep]" in err and "--case N" in err
    assert not (out / "sweep.csv").exists()
    assert cli.main(["run", str(OBLIQUE), "--out", str(out), "--case", "0", "--quiet"]) == 2
    assert "has no [sweep] table" in capsys.readouterr().err
    # the same from Python: minidem.run(..., case=N)
    import minidem

    assert minidem.run(path, case=3).summary["y2"] == row["y2"]
    assert minidem.run(path, case=np.int64(3)).summary["y2"] == row["y2"]  # a number read from sweep.csv
    # overrides of a swept key, or of the table holding one, are refused from Python too
    with pytest.raises(minidem.ScenarioError, match=r"overrides impact.angle_deg=45.0: 'impact.angle_deg' is varied"):
        minidem.run(path, {"impact.angle_deg": 45.0}, case=0)
    with pytest.raises(minidem.ScenarioError, match=r"'impact.angle_deg' is varied by the \[sweep\]"):
        minidem.sweep(path, overrides=['impact={material="glass", radius=0.025, speed=5.0}'], workers=1)
    capsys.readouterr()
    assert cli.main(["run", str(path), "--case", "1", "--quiet", "--set",
                     'impact={material="glass", radius=0.025, speed=5.0}']) == 2
    assert "'impact.angle_deg' is varied by the [sweep]" in capsys.readouterr().err
    with pytest.raises(minidem.ScenarioError, match=r"case=6: the sweep has 6 case\(s\), 0 to 5"):
        minidem.run(path, case=6)
    with pytest.raises(minidem.ScenarioError, match=r"one of its cases with minidem.run\(\.\.\., case=N\)"):
        minidem.run(path)


def test_cases_given_to_sweep_replace_the_settings_that_name_the_files_cases(tmp_path):
    """minidem.sweep(file, cases=...) replaces the file's cases; its series labels (one
    per law here) and an abscissa it no longer varies would not fit the new cases: they
    go with them (before: 'sweep.series_labels: expected 1 labels, got 2', a review,
    2026-11-28), and its other settings stay."""
    import minidem

    path = tmp_path / "laws.toml"
    path.write_text(OBLIQUE.read_text() + '\n[sweep]\ncases = {"contact.law" = ["hmd", "ls"], "impact.spin" = [1.0]}\n'
                    'series_labels = ["HMD", "LS"]\nabscissa = "impact.spin"\nfigures = []\n')
    table = minidem.sweep(path, cases={"impact.angle_deg": [5.0, 45.0]}, workers=1)
    assert list(table["angle_deg"]) == [5.0, 45.0] and not table.failed
    assert table["y2"][1] == pytest.approx(-0.5, abs=1e-12)  # gross sliding at 45 deg: -5 mu (paper eq 8)


# ---------------------------------------------------------------------------------
# separate processes: a killed `minidem run`, and a real Dask cluster
# ---------------------------------------------------------------------------------
# Cases of ~0.2 s (200000 steps per contact) so that a kill lands part way.
SLOW = ["run.steps_per_contact=200000"]
SLOW_ANGLES = [5.0, 15.0, 25.0, 35.0, 45.0, 60.0]


def _slow_scenario(directory: Path) -> Path:
    path = directory / "slow.toml"
    path.write_text(OBLIQUE.read_text() + f'\n[sweep]\ncases = {{"impact.angle_deg" = {SLOW_ANGLES!r}}}\n'
                    'figures = []\n')
    return path


def _cli(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(minidem_command() + [str(a) for a in args], capture_output=True, text=True, timeout=600,
                          env=env)


def _start(*args) -> subprocess.Popen:
    return subprocess.Popen(minidem_command() + [str(a) for a in args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def _wait_for_journal_rows(directory: Path, process: subprocess.Popen, timeout_s: float = 300.0) -> int:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if (directory / sweep.JOURNAL).exists() and _journal_rows(directory):
            return len(_journal_rows(directory))
        if process.poll() is not None:
            raise AssertionError(f"minidem run ended before any case was done: {process.communicate()}")
        time.sleep(0.02)
    raise AssertionError("no case finished in time")


@pytest.fixture(scope="module")
def slow_reference(tmp_path_factory):
    directory = tmp_path_factory.mktemp("slow")
    path = _slow_scenario(directory)
    done = _cli("run", path, "--out", directory / "reference", "--workers", "1", "--quiet",
                *[f"--set={s}" for s in SLOW])
    assert done.returncode == 0, done.stderr
    return path, (directory / "reference" / "sweep.csv").read_bytes()


def test_killed_sweep_command_resumes_with_only_the_missing_cases(slow_reference, tmp_path):
    path, expected = slow_reference
    out = tmp_path / "out"
    process = _start("run", path, "--out", out, "--workers", "2", "--quiet", *[f"--set={s}" for s in SLOW])
    try:
        _wait_for_journal_rows(out, process)
    finally:
        os.killpg(process.pid, signal.SIGKILL)  # the command and its worker processes, as `kill -9` would
        process.communicate()
    before = _journal_rows(out)
    assert 1 <= len(before) < len(SLOW_ANGLES), "the kill should land part way"
    again = _cli("run", path, "--out", out, "--workers", "2", *[f"--set={s}" for s in SLOW])
    assert again.returncode == 0, again.stderr
    assert f"resuming: {len(before)} of {len(SLOW_ANGLES)} case(s) already done" in again.stdout
    after = _journal_rows(out)
    assert after[:len(before)] == before and sorted(r["case"] for r in after) == list(range(len(SLOW_ANGLES)))
    assert (out / "sweep.csv").read_bytes() == expected


@pytest.mark.skipif(not executors.dask_available(), reason="dask[distributed] is not installed "
                    "(pip install 'minidem[dask]'; .ci/run installs it)")
def test_dask_sweep_survives_a_killed_worker_with_identical_results(slow_reference, tmp_path):
    """`dask scheduler` and two `dask worker` processes (one thread each) on 127.0.0.1;
    one worker is SIGKILLed while a case is on it: the scheduler reruns its task on the
    other and sweep.csv equals the local run's, byte for byte.

    The kill waits for a task on that worker (the scheduler's own record), not for the
    first row of the journal: on CI's loaded two cores the client once wrote its first
    row when all six cases were done, and the kill landed after the sweep."""
    from distributed import Client

    path, expected = slow_reference
    out = tmp_path / "out"
    env = dict(os.environ)  # MINIDEM_CACHE_DIR / NUMBA_CACHE_DIR: the workers load the kernel from the cache
    with executors.LocalDaskProcesses(2, env=env) as cluster, \
            Client(cluster.address, set_as_default=False) as watcher:
        # the worker killed: the one in the process group of cluster.workers[0]
        victim = next(address for address, group in watcher.run(os.getpgrp).items()
                      if group == cluster.workers[0].pid)
        process = _start("run", path, "--out", out, "--scheduler", cluster.address, "--quiet",
                         *[f"--set={s}" for s in SLOW])
        try:
            deadline = time.monotonic() + 300
            while not watcher.processing(workers=[victim]).get(victim):
                assert process.poll() is None and time.monotonic() < deadline, "no case reached the worker"
                time.sleep(0.005)
            done_at_kill = len(_journal_rows(out)) if (out / sweep.JOURNAL).exists() else 0
            assert cluster.kill_worker(0) == -signal.SIGKILL
            stdout, stderr = process.communicate(timeout=600)
        finally:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.communicate()
        assert process.returncode == 0, f"{stderr}\n{cluster.logs()}"
    assert done_at_kill < len(SLOW_ANGLES), "the kill should land part way"
    assert (out / "sweep.csv").read_bytes() == expected
    assert "Dask scheduler" in json.loads((out / "sweep.json").read_text())["backend"]


@pytest.mark.skipif(not executors.dask_available(), reason="dask[distributed] is not installed")
def test_a_result_lost_with_its_worker_before_it_is_fetched_is_computed_again():
    """The race behind a flaky failure seen in CI: a batch finishes on a worker that is
    killed before the client fetches the result; the scheduler starts it again, and the
    client sees the future no longer finished. That is no failure of the cases, so the
    batch must be waited for again, not come back as Lost. Made deterministic here: the
    second batch takes 1.5 s, the first result is taken, the worker holding the second
    is SIGKILLed, and the generator resumes while the batch is being recomputed."""
    from distributed import Future

    def negate(x):  # a local function: cloudpickle sends it by value
        time.sleep(1.5 if x > 2 else 0.0)
        return -x

    with executors.LocalDaskProcesses(2) as cluster:
        dask = executors.DaskCluster(cluster.address)
        try:
            results = executors.collect(dask.client, negate, [[1, 2], [3, 4]], [[0, 1], [2, 3]], max_attempts=4)
            first = [next(results), next(results)]  # the quick batch
            deadline = time.monotonic() + 60
            while True:  # until the slow batch is done and sits in a worker's memory
                done = [key for key, state in dask.client.futures.items()
                        if state.status == "finished" and Future(key, dask.client).result() == [-3, -4]]
                holders = dask.client.who_has().get(done[0], ()) if done else ()
                if holders:
                    break
                assert time.monotonic() < deadline, "the slow batch did not finish"
                time.sleep(0.05)
            pids = dask.client.run(os.getpid)
            group = os.getpgid(pids[holders[0]])
            index = next(i for i, w in enumerate(cluster.workers) if w.pid == group)
            assert cluster.kill_worker(index) == -signal.SIGKILL
            while dask.client.futures[done[0]].status == "finished":  # until the client hears of the loss
                assert time.monotonic() < deadline, "the scheduler did not notice the killed worker"
                time.sleep(0.05)
            rest = list(results)
        finally:
            dask.close()
    got = dict(first + rest)
    assert not [r for r in got.values() if isinstance(r, executors.Lost)], got
    assert got == {0: -1, 1: -2, 2: -3, 3: -4}


def test_a_worker_with_other_code_refuses_the_case():
    """A worker whose minidem/law/numba/numpy fingerprint differs from the client's raises
    (the back end reports the case as not run) instead of computing another result."""
    plan = _plan([5.0], keep_traces=False)
    case = sweep.Case(0, plan.base, tuple(plan.overrides(0)), plan.source, False, ("hmd",), "0" * 64)
    with pytest.raises(sweep.CodeMismatch):
        sweep.run_case(case)


def test_backend_choice_follows_the_dask_convention(monkeypatch):
    monkeypatch.setenv(executors.DASK_ADDRESS_VARIABLE, "not-an-address")
    assert isinstance(executors.from_options("local", 1), executors.LocalProcesses)
    with pytest.raises(executors.BackendUnavailable, match=executors.DASK_ADDRESS_VARIABLE):
        executors.from_options(None, 1)
    monkeypatch.delenv(executors.DASK_ADDRESS_VARIABLE)
    assert isinstance(executors.from_options(None, 1), executors.LocalProcesses)


def test_scheduler_errors_are_clear(tmp_path, capsys):
    path = _slow_scenario(tmp_path)
    code = cli.main(["run", str(path), "--out", str(tmp_path / "o"), "--scheduler", "not-an-address"])
    expected = "tcp://HOST:PORT" if executors.dask_available() else "pip install 'minidem[dask]'"
    assert code == 2 and expected in capsys.readouterr().err
    assert not (tmp_path / "o" / "sweep.csv").exists()


def test_sweep_names_the_laws_that_created_energy():
    # the paper's LTH gains up to 1.25 % at 16 deg (docs/paper-reproduction.md); a gain of
    # 1e-9 is round-off (docs/laws.md, 'Laws that create energy'); a failed case has none
    row = {"status": "ok", "dt_s": 3.1e-8, "contact_duration_s": 1.26e-4}
    rows = [dict(row, case=0, law="lth", energy_ratio=1.0125), dict(row, case=1, law="lth", energy_ratio=1.0 + 1e-9),
            dict(row, case=2, law="hm", energy_ratio=0.99998),
            {"status": "failed", "case": 3, "law": "hmd", "energy_ratio": None, "dt_s": None,
             "contact_duration_s": None}]
    notes = sweep._energy_gain_notes(rows)
    assert len(notes) == 1 and "'lth'" in notes[0] and "1 case(s)" in notes[0] and "1.0125" in notes[0]


def test_a_warning_of_the_plan_is_printed_once_not_again_by_its_case(tmp_path, capsys):
    # run.allow_unstable_dt's warning comes from the case's Simulation: plan() shows it,
    # and the case's own run printed it a second time (a new user's report, 2026-11-27)
    code = cli.main(["run", str(OBLIQUE), "--out", str(tmp_path / "out"), "--quiet", "--workers", "1",
                     "--set", 'sweep.cases={"impact.angle_deg"=[10.0]}', "--set", "sweep.figures=[]",
                     "--set", "run.dt=5e-5", "--set", "run.allow_unstable_dt=true"])
    assert code == 0
    assert capsys.readouterr().err.count("allowed by run.allow_unstable_dt") == 1


def test_swept_keys_are_compared_as_paths_whatever_their_quotes():
    """A key of sweep.cases may quote its parts as TOML allows: '"sweep".workers' is still
    the sweep's own setting (it ran, twice alike, once --set read quoted parts: a review,
    2026-12-08), and '"impact"."angle_deg"' is the angle that together and the abscissa
    name, and the same key as its bare spelling."""
    data = scenario.read_toml(OBLIQUE)
    data["sweep"] = {"cases": {'"sweep".workers': [1, 2]}, "figures": []}
    with pytest.raises(scenario.ScenarioError, match="a sweep cannot sweep its own settings"):
        sweep.plan(data, str(OBLIQUE))
    data["sweep"] = {"cases": {'"impact"."angle_deg"': [5.0, 45.0], "contact.friction": [0.1, 0.3]},
                     "together": [["impact.angle_deg", "contact.friction"]], "figures": []}
    plan = sweep.plan(data, str(OBLIQUE))
    assert plan.keys == ["impact.angle_deg", "contact.friction"] and plan.abscissa == "impact.angle_deg"
    assert plan.cases == [(5.0, 0.1), (45.0, 0.3)]
    data["sweep"] = {"cases": {'"impact".angle_deg': [5.0], "impact.angle_deg": [45.0]}, "figures": []}
    with pytest.raises(scenario.ScenarioError, match="is impact.angle_deg, swept already"):
        sweep.plan(data, str(OBLIQUE))
