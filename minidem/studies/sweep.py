"""Parameter sweeps: one scenario, many cases, one table.

A scenario with a ``[sweep]`` section is run once per case by ``minidem run``::

    [sweep]
    cases = {"contact.law" = ["hmd", "ls"], "impact.angle_deg" = [1.0, 5.0, 30.0]}
    figures = ["y1", "y2", "et"]

``cases`` maps dotted scenario keys (the ones ``--set`` takes) to lists of values; the
cases are their cartesian product, the first key varying slowest, and every case is the
base scenario with those values set.

Cases run through an executor (``minidem.studies.executors``): local processes by default, or
the workers of a Dask scheduler (``--scheduler``). The worker function
:func:`run_case` is pure and deterministic: it compiles or loads the law's kernel from
the worker's own cache, runs one case and returns its row (and trace); only this process
writes files. Rows go to ``sweep.csv`` in case order whatever the completion order, with
floats written so that they read back to the same bits, so ``sweep.csv`` is the same file
for any back end and worker count.

Every finished case is appended at once to ``OUT/sweep.journal`` (JSON lines after a
header holding the hash of the plan), so an interrupted sweep (Ctrl-C, kill, a lost
cluster) resumes: ``minidem run`` on the same output directory runs only the cases the
journal lacks. A case that fails is a row with ``status = failed`` and the reason in
``error``; the other cases still run.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import hashlib
import itertools
import json
import math
import operator
import os
import time as wallclock
import warnings
from pathlib import Path
from typing import Any

from minidem.studies import executors
from minidem.scene import scenario
from minidem.scene.scenario import ScenarioError

# Every column is a function of the case alone (no wall time: that goes to the journal
# and sweep.json), so that sweep.csv is the same file wherever the cases ran.
ROW_COLUMNS = ("case", "law", "angle_deg", "x", "y1", "y2", "et", "en", "contact_duration_s", "energy_ratio",
               "max_overlap_m", "steps", "dt_s", "peak_normal_force_n")
# One collision's rebound beside rigid-body impulse theory and the Hertz limits
# (analysis.collision_measures; Chung & Ooi 2011): written only by sweeps whose figures
# need them, so other sweeps' tables keep their columns.
COLLISION_COLUMNS = ("tangential_velocity_m_s", "spin_rad_s", "rebound_angle_deg", "recoil_ratio",
                     "rigid_tangential_velocity_m_s", "rigid_spin_rad_s", "rigid_rebound_angle_deg",
                     "rigid_recoil_ratio", "rigid_sliding", "hertz_max_overlap_m", "hertz_peak_force_n",
                     "hertz_contact_time_s")
JOURNAL = "sweep.journal"
JOURNAL_FORMAT = 1
FIGURES = ("y1", "y2", "et", "force_displacement", "hertz", "restitution", "rebound", "force_time")
COLLISION_FIGURES = ("hertz", "restitution", "rebound")
ANGLE_KEY = "impact.angle_deg"


@dataclasses.dataclass
class SweepPlan:
    source: str
    base: dict  # the scenario without [sweep]
    keys: list[str]  # swept dotted keys, in order
    cases: list[tuple]  # one tuple of values per case
    workers: int
    keep_traces: bool
    figures: list[str]
    series_labels: list[str] | None
    title: str | None
    abscissa: str = ANGLE_KEY  # the swept key on the x axis of the Chung & Ooi figures
    together: tuple = ()  # groups of keys that vary together (one axis of the product)

    def overrides(self, index: int) -> list[str]:
        return [f"{key}={_toml_value(value)}" for key, value in zip(self.keys, self.cases[index])]

    @property
    def series_keys(self) -> list[str]:
        """The swept keys that tell the curves of a figure apart: all but the abscissa
        (default the angle) and the keys that vary together with it."""
        along = next((group for group in self.together if self.abscissa in group), (self.abscissa,))
        return [k for k in self.keys if k not in along]

    @property
    def collision_columns(self) -> bool:
        return any(f in COLLISION_FIGURES for f in self.figures)

    def series(self) -> list[tuple]:
        """Distinct values of the series keys, in first-seen order."""
        seen: dict[tuple, None] = {}
        for case in self.cases:
            seen.setdefault(self.series_of(case), None)
        return list(seen)

    def series_of(self, case: tuple) -> tuple:
        """The series a case belongs to: its values of the series keys (a swept table,
        which is not hashable, as its TOML text)."""
        return tuple(_toml_value(case[p]) if isinstance(case[p], (dict, list)) else case[p]
                     for p in (self.keys.index(k) for k in self.series_keys))

    @property
    def friction(self) -> float:
        """The friction coefficient of the base scenario (for the rigid-body lines)."""
        value = self.base.get("contact", {}).get("friction")
        return float(value) if isinstance(value, (int, float)) else math.nan


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string for the names scenarios use
    if isinstance(value, dict):  # a whole table, e.g. "contact" = [{law = "ls", ...}, ...]: an inline table
        return "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return repr(value)


def has_sweep(data: dict) -> bool:
    return "sweep" in data


def plan(data: dict, source: str, check_cases: bool = True) -> SweepPlan:
    """Validate ``[sweep]`` (keys from scenario.SCHEMA) and every case's scenario
    (``check_cases`` False: not the cases, for one case run alone, which is checked as
    any single run is)."""
    errors = scenario._Errors(source)
    keys_declared = scenario.SCHEMA["sweep"][1]
    values = scenario._check_table(data["sweep"], keys_declared, "sweep", errors)
    errors.raise_if_any()
    cases_table = values["cases"]
    if not cases_table:
        errors.add("sweep.cases", 'is empty: give at least one key and its values, e.g. {"impact.angle_deg" = '
                   "[1.0, 5.0]} (a single run needs no [sweep] table)")
    keys, columns = [], []
    for given, options in cases_table.items():
        where = f'sweep.cases."{given}"'
        # compared as paths: '"impact".angle_deg' is impact.angle_deg everywhere below
        key = _canonical(given, where, errors)
        if key is None:
            continue
        if key in keys:
            errors.add(where, f"is {key}, swept already")
            continue
        if not isinstance(options, list) or not options:
            errors.add(where, f"expected a non-empty list of values, got {options!r}")
            continue
        if key.split(".")[0] == "sweep":
            errors.add(where, "a sweep cannot sweep its own settings")
            continue
        keys.append(key)
        columns.append(options)
    def spelled(key, where):  # a key as the cases are keyed; anything else is left to _axes to refuse
        return (_canonical(key, where, errors) or key) if isinstance(key, str) else key

    together = [[spelled(k, f"sweep.together[{i}]") for k in group] if isinstance(group, list) else group
                for i, group in enumerate(values["together"] or [])]
    if isinstance(values["abscissa"], str):
        values["abscissa"] = spelled(values["abscissa"], "sweep.abscissa")
    axes, grouped = _axes(keys, columns, together, values["abscissa"], errors)
    unknown = [f for f in values["figures"] if not isinstance(f, str) or f not in FIGURES]
    if unknown:
        errors.add("sweep.figures", f"unknown figure(s) {unknown}; valid: {', '.join(FIGURES)}")
    # a figure that cannot be drawn is refused now, not skipped silently after the run
    for traced in ("force_displacement", "force_time"):
        if traced in values["figures"] and not values["keep_traces"]:
            errors.add("sweep.figures", f'"{traced}" plots the cases\' traces: it needs sweep.keep_traces = true')
    paper = [f for f in values["figures"] if f in ("y1", "y2", "et", "force_displacement")]
    no_impact = "impact" not in data and not any(k.split(".")[0] == "impact" for k in keys)
    if paper and no_impact and "figures" not in data["sweep"]:
        values["figures"] = []  # the default figures are an impact's: a scene sweep draws none
    elif paper and no_impact:
        errors.add("sweep.figures", f"{paper} are the rebound measures of an [impact] scene, which this "
                   'scenario has none of; give figures = [] (sweep.csv is written anyway)')
    labels = values.get("series_labels")
    if labels is not None and not all(isinstance(label, str) for label in labels):
        errors.add("sweep.series_labels", f"expected a list of strings, got {labels!r}")
    figures = values["figures"]
    if not all(isinstance(f, str) for f in figures):
        errors.add("sweep.figures", f"expected a list of figure names (strings), got {figures!r}")
    if values["workers"] < 0:
        errors.add("sweep.workers", f"must be >= 0 (0: one per CPU), got {values['workers']}")
    errors.raise_if_any()
    base = {k: v for k, v in data.items() if k != "sweep"}
    # one axis per key, or per group of keys that vary together; the keys of a case in
    # axis order
    keys = [k for axis in axes for k in axis[0]]
    cases = [tuple(v for picked in product for v in picked)
             for product in itertools.product(*[list(zip(*axis[1])) for axis in axes])]
    sweep = SweepPlan(source, base, keys, cases, values["workers"], values["keep_traces"],
                      list(values["figures"]), values.get("series_labels"), values.get("title"),
                      values["abscissa"] or ANGLE_KEY, grouped)
    if sweep.series_labels is not None and len(sweep.series_labels) != len(sweep.series()):
        errors.add("sweep.series_labels", f"expected {len(sweep.series())} labels (one per combination of "
                   f"{', '.join(sweep.series_keys) or 'nothing'}), got {len(sweep.series_labels)}")
    # every case must be a valid scenario before anything runs: bad input is exit 2
    from minidem.contact import laws
    from minidem.engine import simulation

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for index in range(len(cases) if check_cases else 0):
            try:
                scene = scenario.build_scene(scenario.apply_overrides(base, sweep.overrides(index)), source)
                # what the values imply (constants, time step, steps), without compiling
                simulation.Simulation(scene, compile=False)
            except (ScenarioError, laws.LawError) as exc:
                setting = ", ".join(f"{k} = {_toml_value(v)}" for k, v in zip(keys, cases[index]))
                errors.add(f"sweep case {index} ({setting})", str(exc).replace(f"{source}: ", "", 1))
                break
    for message in dict.fromkeys(str(w.message) for w in caught):
        warnings.warn(message, stacklevel=2)  # once each, not once per case
    errors.raise_if_any()
    return sweep


def _canonical(key: str, where: str, errors) -> str | None:
    """``scenario.canonical_key``, a key it cannot read reported at ``where`` (None)."""
    try:
        return scenario.canonical_key(key, where)
    except ScenarioError as exc:
        errors.add(where, str(exc).removeprefix(f"{where}: "))
        return None


def _axes(keys, columns, together, abscissa, errors) -> tuple[list, tuple]:
    """[(keys, value lists)] per axis of the product: a key alone, or a [sweep].together
    group (its keys' lists must be as long as each other) at the place of its first key."""
    grouped, seen = [], set()
    for index, group in enumerate(together or []):
        where = f"sweep.together[{index}]"
        if not isinstance(group, list) or len(group) < 2 or not all(isinstance(k, str) for k in group):
            errors.add(where, f"expected a list of two or more swept keys, got {group!r}")
            continue
        missing = [k for k in group if k not in keys]
        if missing:
            errors.add(where, f"{', '.join(missing)} not in sweep.cases (swept keys: {', '.join(keys)})")
            continue
        if seen.intersection(group):
            errors.add(where, f"{', '.join(sorted(seen.intersection(group)))} already in another group")
            continue
        lengths = {k: len(columns[keys.index(k)]) for k in group}
        if len(set(lengths.values())) > 1:
            errors.add(where, "the keys of a group vary together, so their lists must be as long as each "
                       f"other; got {', '.join(f'{k}: {n}' for k, n in lengths.items())}")
            continue
        seen.update(group)
        grouped.append(tuple(group))
    if abscissa is not None and abscissa not in keys:
        errors.add("sweep.abscissa", f"{abscissa!r} is not a swept key (swept keys: {', '.join(keys)})")
    axes, placed = [], set()
    for key, column in zip(keys, columns):
        if key in placed:
            continue
        group = next((g for g in grouped if key in g), (key,))
        axes.append((list(group), [columns[keys.index(k)] for k in group]))
        placed.update(group)
    return axes, tuple(grouped)


# ---------------------------------------------------------------------------------
# what a plan computes: its hash decides whether a journal can be resumed
# ---------------------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def code_fingerprint(law_names: tuple[str, ...]) -> str:
    """Hash of what decides a case's numbers besides its scenario: minidem's own sources,
    the sources, package and version of the laws used, numba and numpy. Computed once per
    process; a worker whose fingerprint differs from the client's refuses to run cases."""
    import numba
    import numpy

    import minidem
    from minidem.contact import laws
    from minidem.engine import simulation

    digest = hashlib.sha256()
    package = Path(minidem.__file__).parent
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    registry = laws.registry()
    for name in law_names:
        entry = registry.entry(name)
        digest.update(f"|{entry.law.name}|{entry.distribution}|{entry.version}|"
                      f"{simulation._law_source_hash(entry.law)}".encode())
    digest.update(f"|numba {numba.__version__}|numpy {numpy.__version__}|minidem {minidem.__version__}".encode())
    return digest.hexdigest()


def _laws_of(sweep: SweepPlan) -> tuple[str, ...]:
    return tuple(dict.fromkeys(str(_law_of(sweep, index)) for index in range(len(sweep.cases))))


def plan_hash(sweep: SweepPlan) -> str:
    """Hash of everything that decides the rows: the base scenario, the swept keys and
    values, keep_traces and the code fingerprint (not figures, titles or workers)."""
    payload = {"format": JOURNAL_FORMAT, "base": sweep.base, "keys": sweep.keys, "cases": sweep.cases,
               "keep_traces": sweep.keep_traces, "code": code_fingerprint(_laws_of(sweep))}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()


# ---------------------------------------------------------------------------------
# one case: the worker function (pure, deterministic, importable as minidem.studies.sweep.run_case)
# ---------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Case:
    """Everything a worker needs to run one case; small, picklable, no file paths."""

    index: int
    base: dict
    overrides: tuple[str, ...]
    source: str
    trace: bool
    laws: tuple[str, ...]
    fingerprint: str


class CodeMismatch(RuntimeError):
    """The worker's minidem, laws, numba or numpy differ from the client's."""


def run_case(case: Case) -> dict:
    """Run one case; return its row (plain Python values) and, when asked, its trace
    (``row["trace"]``, an array the caller writes). A failure of the case itself is
    reported in the row (``status``, ``error``), never raised."""
    if code_fingerprint(case.laws) != case.fingerprint:
        # an infrastructure fault, not a result: raised, so the case is not journalled
        raise CodeMismatch(f"worker pid {os.getpid()} runs other minidem/law/numba/numpy code than the client "
                           "(install the same versions on every worker)")
    from minidem.results import analysis
    from minidem.engine import simulation

    row: dict[str, Any] = {"case": case.index, "status": "ok", "error": ""}
    started = wallclock.perf_counter()
    try:
        with warnings.catch_warnings():
            # plan() has shown the scene's and its Simulation's own warnings once already (the
            # stability warning of run.allow_unstable_dt was printed twice); minidem's are
            # UserWarnings, numba's (from the kernel's compile, which plan() does not do) are not
            warnings.simplefilter("ignore", UserWarning)
            scene = scenario.build_scene(scenario.apply_overrides(case.base, list(case.overrides)), case.source)
            scene.trace = case.trace
            sim = simulation.Simulation(scene)
        result = sim.run()
        summary = analysis.summary(result)
        row.update({k: _plain(summary.get(k)) for k in ROW_COLUMNS + COLLISION_COLUMNS if k != "case"})
        # a rebound measured from a contact of a few steps is no result either
        incomplete = (analysis.incomplete_contact(result)
                      or analysis.resolution_warning(result, summary["contact_duration_s"]))
        if incomplete:
            row["status"], row["error"] = "failed", incomplete
        if case.trace and result.trace is not None:
            row["trace"] = result.trace
    except Exception as exc:  # noqa: BLE001 - a failed case is reported in its row
        row["status"], row["error"] = "failed", f"{type(exc).__name__}: {exc}".replace("\n", " ")
    row["wall_time_s"] = wallclock.perf_counter() - started
    return row


def _plain(value):
    """numpy scalars as Python ones: the same row whether it crossed a pipe or the journal."""
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    return value


# ---------------------------------------------------------------------------------
# the journal: one JSON line per finished case, after a header with the plan's hash
# ---------------------------------------------------------------------------------
def _complete_row(row: dict) -> bool:
    """Whether a journalled row is one run_case wrote: its status, error and time, and an
    ok row's columns (a line of valid JSON missing them, edited or from elsewhere, ended
    the resumed sweep in a KeyError: a robustness review); another is a case not done."""
    if row.get("status") not in ("ok", "failed") or not isinstance(row.get("error"), str) \
            or "wall_time_s" not in row:
        return False
    return row["status"] == "failed" or all(k in row for k in ROW_COLUMNS)


class Journal:
    """Append-only record of finished cases. Each row is one ``write`` of one line,
    flushed at once (a killed process loses nothing it has written) and synced to disk at
    least once a second; a torn last line (power loss) is dropped on reading, so that
    case runs again."""

    def __init__(self, path: Path):
        self.path = path
        self.handle = None
        self.synced = 0.0

    def read(self) -> tuple[dict | None, dict[int, dict]]:
        """(header, {case: row}); (None, {}) when there is no readable journal."""
        try:
            lines = self.path.read_bytes().split(b"\n")
        except FileNotFoundError:
            return None, {}
        try:
            header = json.loads(lines[0])
        except ValueError:
            return None, {}
        if (not isinstance(header, dict) or header.get("minidem_sweep_journal") != JOURNAL_FORMAT
                or not isinstance(header.get("cases"), int)):
            return None, {}
        rows: dict[int, dict] = {}
        for line in lines[1:]:
            try:
                row = json.loads(line)
            except ValueError:
                continue  # empty, or torn by a crash: that case is simply not done
            if isinstance(row, dict) and isinstance(row.get("case"), int) and 0 <= row["case"] < header["cases"] \
                    and _complete_row(row):
                rows[row["case"]] = row
        return header, rows

    def start(self, header: dict) -> None:
        from minidem.files import atomic_write

        atomic_write(self.path, json.dumps(header) + "\n")
        self._open()

    def resume(self) -> None:
        # cut a torn last line so the next row starts on a line of its own
        data = self.path.read_bytes()
        if not data.endswith(b"\n"):
            with open(self.path, "r+b") as handle:
                handle.truncate(data.rfind(b"\n") + 1)
        self._open()

    def _open(self) -> None:
        self.handle = open(self.path, "ab", buffering=0)
        self.synced = wallclock.monotonic()

    def append(self, row: dict) -> None:
        from minidem.files import output_error

        line = (json.dumps(row, default=_plain) + "\n").encode()
        try:
            self.handle.write(line)
            if wallclock.monotonic() - self.synced > 1.0:
                os.fsync(self.handle.fileno())
                self.synced = wallclock.monotonic()
        except OSError as exc:
            # a torn last line is cut on resume: the rows before it are kept
            raise output_error(self.path, exc) from exc

    def close(self) -> None:
        if self.handle is not None:
            os.fsync(self.handle.fileno())
            self.handle.close()
            self.handle = None


# ---------------------------------------------------------------------------------
# running a sweep
# ---------------------------------------------------------------------------------
def run(sweep: SweepPlan, directory: Path, progress: bool = True, workers: int | None = None,
        executor: executors.Executor | None = None, restart: bool = False, echo=None) -> list[dict]:
    """Run the cases the journal in ``directory`` lacks (all of them for a new sweep or
    with ``restart``); write ``sweep.csv``, ``sweep.json`` (and traces) under
    ``directory``; return the rows in case order.

    ``executor``: where the cases run (default: local processes, ``workers`` of them,
    else ``sweep.workers``; 0 is one per CPU). ``echo(text)``: where notes go.
    Raises ScenarioError if the directory holds an unfinished sweep of another plan
    (unless ``restart``), BackendFailure if cases were lost by the back end (the
    finished ones stay in the journal: running again runs the rest).
    """
    echo = echo or (lambda text: None)
    directory = Path(directory)
    with _directory_lock(directory):
        return _run_locked(sweep, directory, progress, workers, executor, restart, echo)


class _directory_lock:
    """One sweep per output directory at a time: a second `minidem run` on the same
    directory would run the same cases again and interleave its rows with the first's.
    A POSIX record lock: the system releases it when its process dies, however it dies,
    and forked worker processes do not inherit it."""

    def __init__(self, directory: Path):
        self.path = directory / ".sweep.lock"
        self.handle = None

    def __enter__(self):
        try:
            import fcntl
        except ImportError:  # not a POSIX system: no lock
            return self
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.handle = open(self.path, "a+")
        try:
            fcntl.lockf(self.handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self.handle.seek(0)
            holder = self.handle.read().strip() or "another process"
            self.handle.close()
            raise ScenarioError(f"{self.path.parent}: another minidem sweep ({holder}) is running in this output "
                                "directory; wait for it to end, or choose another --out") from None
        self.handle.seek(0)
        self.handle.truncate()
        self.handle.write(f"pid {os.getpid()}\n")
        self.handle.flush()
        return self

    def __exit__(self, *exc):
        if self.handle is not None:
            self.handle.close()


def _run_locked(sweep, directory, progress, workers, executor, restart, echo) -> list[dict]:
    from minidem import files

    n = len(sweep.cases)
    digest = plan_hash(sweep)
    journal = Journal(directory / JOURNAL)
    header, done = journal.read()
    if header is not None and header.get("plan") == digest and not restart:
        if done:
            echo(f"resuming: {len(done)} of {n} case(s) already done in {journal.path}")
        journal.resume()
    else:
        if header is not None and not restart:
            previous_done = len(done)
            if 0 < previous_done < header.get("cases", 0):  # work would be lost: the user decides
                raise ScenarioError(
                    f"{directory}: holds an unfinished sweep of a different plan ({previous_done} of "
                    f"{header.get('cases')} case(s) done, from {header.get('source')}): the scenario, its [sweep] "
                    "cases, a --set value or minidem's code changed since. Run with --restart to discard it and "
                    "start over, or choose another --out")
            echo(f"starting over: {directory} held a sweep of a different plan ({previous_done} of "
                 f"{header.get('cases')} case(s) done)")
        done = {}
        for stale in [directory / "sweep.csv", directory / "sweep.json", *directory.glob("traces/case_*.csv")]:
            stale.unlink(missing_ok=True)
        journal.start({"minidem_sweep_journal": JOURNAL_FORMAT, "plan": digest, "cases": n,
                       "source": sweep.source, "keys": sweep.keys})

    pending = [i for i in range(n) if i not in done]
    owned = executor is None
    if executor is None:
        executor = executors.LocalProcesses(workers if workers is not None else sweep.workers)
    lost: dict[int, str] = {}
    bar = _NoBar()
    started = wallclock.perf_counter()
    try:
        bar = _progress_bar(n, len(done), progress)
        for index, row in execute(sweep, pending, executor):
            if isinstance(row, executors.Lost):
                lost[index] = row.reason
                continue
            trace = row.pop("trace", None)
            if trace is not None:
                relative = f"traces/case_{index:03d}.csv"
                from minidem.engine.kernel import TRACE_COLUMNS

                files.write_csv(directory / relative, TRACE_COLUMNS, trace.tolist())
                row["trace_file"] = relative  # relative to the sweep directory: the same file anywhere
            journal.append(row)  # after its trace: a journalled case is complete on disk
            done[index] = row
            bar.update(1)
    finally:
        bar.close()
        journal.close()
        if owned:
            executor.close()
    elapsed = wallclock.perf_counter() - started
    if lost:
        reasons = sorted(set(lost.values()))
        raise executors.BackendFailure(
            f"{len(lost)} of {n} case(s) were not run by {executor.description}: {'; '.join(reasons)[:500]}. "
            f"The {len(done)} finished case(s) are in {journal.path}: run the same command again to run the rest")

    rows = [dict(done[i]) for i in range(n)]
    columns = table_columns(sweep)
    table = [["" if row.get(c) is None else row.get(c) for c in columns] for row in complete_rows(sweep, rows)]
    files.write_csv(directory / "sweep.csv", columns, table)
    files.write_json(directory / "sweep.json", {
        "scenario": sweep.source, "cases": n, "failed": sum(1 for r in rows if r["status"] != "ok"),
        "ran_now": len(pending), "resumed_from": n - len(pending), "backend": executor.description,
        "wall_time_s": elapsed, "cases_wall_time_s": sum(r.get("wall_time_s") or 0.0 for r in rows),
        "swept_keys": sweep.keys, "plan": digest,
    })
    return rows


def execute(sweep: SweepPlan, pending: list[int], executor: executors.Executor):
    """Run the cases ``pending`` (indices into ``sweep.cases``) on ``executor``; yield
    (case index, row or :class:`executors.Lost`) as they finish, in any order."""
    laws = _laws_of(sweep)
    fingerprint = code_fingerprint(laws)
    tasks = [Case(i, sweep.base, tuple(sweep.overrides(i)), sweep.source, sweep.keep_traces, laws, fingerprint)
             for i in pending]
    # the first case of each law first and on its own: the workers compile the kernels in parallel
    first_of_law: dict[Any, int] = {}
    for position, index in enumerate(pending):
        first_of_law.setdefault(_law_of(sweep, index), position)
    for position, row in executor.run(run_case, tasks, warm=list(first_of_law.values())):
        yield pending[position], row


def table_columns(sweep: SweepPlan) -> list[str]:
    """The columns of sweep.csv: ROW_COLUMNS, COLLISION_COLUMNS (when the figures need
    them), the swept keys other than the law and the angle, trace_file (with
    keep_traces), status, error."""
    swept = [k for k in sweep.keys if k not in ("contact.law", ANGLE_KEY)]
    return (list(ROW_COLUMNS) + (list(COLLISION_COLUMNS) if sweep.collision_columns else []) + swept
            + (["trace_file"] if sweep.keep_traces else []) + ["status", "error"])


def complete_rows(sweep: SweepPlan, rows: list[dict]) -> list[dict]:
    """The rows (in case order) with the swept values set, and a failed case's law and
    angle taken from the plan (it has no summary): the rows of sweep.csv. Changes ``rows``."""
    for row, case in zip(rows, sweep.cases):
        for key, value in zip(sweep.keys, case):
            if key not in ("contact.law", ANGLE_KEY):
                # a swept table (a whole [contact]) or list is one cell, in TOML
                row[key] = _toml_value(value) if isinstance(value, (dict, list)) else value
        if row.get("law") is None:
            row["law"] = _law_of(sweep, row["case"])
        if row.get("angle_deg") is None:
            row["angle_deg"] = (case[sweep.keys.index(ANGLE_KEY)] if ANGLE_KEY in sweep.keys
                                else sweep.base.get("impact", {}).get("angle_deg"))
    return rows


def _law_of(sweep: SweepPlan, index: int):
    if "contact.law" in sweep.keys:
        return sweep.cases[index][sweep.keys.index("contact.law")]
    if "contact" in sweep.keys:  # whole [contact] tables swept (laws with parameters of their own)
        return sweep.cases[index][sweep.keys.index("contact")].get("law")
    return sweep.base.get("contact", {}).get("law")


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress_bar(total: int, initial: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, initial=initial, unit="case", desc="sweep", leave=True)

def load_rows(path: str | Path) -> list[dict]:
    """Read a sweep.csv back, numbers as floats (empty cells as None)."""
    import csv

    rows = []
    with open(path, newline="") as handle:
        for raw in csv.DictReader(handle):
            row = {}
            for key, text in raw.items():
                if text == "":
                    row[key] = None
                    continue
                try:
                    row[key] = float(text)
                except ValueError:
                    row[key] = text
            rows.append(row)
    return rows


def _energy_gain_notes(rows: list[dict]) -> list[str]:
    """One line per law whose impacts gained kinetic energy beyond integration error
    (analysis.energy_creation_warning), with the swept cases where it happened."""
    from minidem.results import analysis

    gained: dict[str, list[dict]] = {}
    for r in rows:
        if r["status"] == "ok" and analysis.energy_creation_warning(
                r["law"], r["energy_ratio"], r["dt_s"], r["contact_duration_s"]):
            gained.setdefault(r["law"], []).append(r)
    return [f"law '{law}' created energy in {len(cases)} case(s) (energy_ratio up to "
            f"{max(c['energy_ratio'] for c in cases):.6g}; cases {', '.join(str(c['case']) for c in cases[:8])}"
            f"{', ...' if len(cases) > 8 else ''}): docs/laws.md, 'Laws that create energy'"
            for law, cases in gained.items()]


def _directory(args, sweep: SweepPlan) -> Path:
    """Where ``minidem run`` writes a sweep: --out, output.directory, or out/<file stem>."""
    return Path(args.out) if args.out else Path(
        sweep.base.get("output", {}).get("directory") or Path("out") / Path(args.file).stem)


def _is_prefix(one: list[str], other: list[str]) -> bool:
    """One path leads into the other (or they are the same)."""
    shorter = min(len(one), len(other))
    return one[:shorter] == other[:shorter]


def refuse_swept_overrides(sweep: SweepPlan, texts, named: str = "--set {}", one_case: str = "--case N") -> None:
    """An override of a key the sweep varies (or of a value inside a swept table, or of a
    table holding a swept key) would be set again by every case: refused. ``named``
    formats an override as the caller was given it, ``one_case`` says how to run one case."""
    for text in texts or []:
        path = scenario.parse_override(text)[0]
        # as paths, not strings: 'contact.pairs."a/b".friction' is 'contact.pairs.a/b.friction'
        swept = next((k for k in sweep.keys
                      if _is_prefix(path, scenario.key_path(k, f"{sweep.source}: sweep.cases key {k!r}"))), None)
        if swept is not None:
            raise ScenarioError(
                f"{sweep.source}: {named.format(text)}: '{swept}' is varied by the [sweep] (sweep.cases), which "
                f"sets it in every case. To run one case alone: {one_case} (N from sweep.csv's case column, 0 to "
                f"{len(sweep.cases) - 1}); to sweep other values: change sweep.cases")


def case_alone(args, data: dict):
    """``minidem run FILE --case N``: the arguments of a single run of case N (its values
    after the other --set values, its files in OUT/case_NNN)."""
    sweep = plan(scenario.apply_overrides(data, args.set), str(args.file), check_cases=False)
    refuse_swept_overrides(sweep, args.set)
    values = case_values(sweep, args.case, f"--case {args.case}")
    one = copy.copy(args)
    one.set = [*(args.set or []), *values]
    one.out = str(_directory(args, sweep) / f"case_{args.case:03d}")
    if not args.quiet:
        print(f"minidem: {sweep.source}: case {args.case} of {len(sweep.cases)} alone: " + ", ".join(values))
    return one


def case_values(sweep: SweepPlan, case: int, named: str) -> list[str]:
    """Case ``case``'s values as --set texts; ``named``: how the caller was given it
    (``--case 3``, ``case=3``), for the error of a case the sweep does not have."""
    try:
        number = operator.index(case)  # an int, or numpy's (sweep.csv's case column read back)
    except TypeError:
        raise ScenarioError(f"{sweep.source}: {named}: expected a case number (an integer), got "
                            f"{type(case).__name__}") from None
    if isinstance(case, bool) or not 0 <= number < len(sweep.cases):
        raise ScenarioError(f"{sweep.source}: {named}: the sweep has {len(sweep.cases)} case(s), 0 to "
                            f"{len(sweep.cases) - 1} (sweep.csv's case column)")
    return sweep.overrides(number)


def command(args, data: dict) -> int:
    """``minidem run`` of a scenario with a [sweep] section."""
    import sys

    from minidem.studies import figures

    data = scenario.apply_overrides(data, args.set)
    sweep = plan(data, str(args.file))
    refuse_swept_overrides(sweep, args.set)
    directory = _directory(args, sweep)
    workers = getattr(args, "workers", None)
    if workers is not None and workers < 0:
        raise ScenarioError(f"--workers {workers}: must be >= 0 (0: one per CPU)")
    scenario.prepare_output_directory(directory, scenario.output_origin(args.out, sweep.base), str(args.file))
    executor = executors.from_options(getattr(args, "scheduler", None), workers if workers is not None
                                      else sweep.workers)
    echo = (lambda text: None) if args.quiet else (lambda text: print(f"  {text}"))
    try:
        if workers is not None and not isinstance(executor, executors.LocalProcesses):
            warnings.warn(f"--workers {workers} ignored: the cases run on the workers of {executor.description}")
        if sweep.base.get("output", {}).get("vtk") or sweep.base.get("output", {}).get("contacts"):
            warnings.warn(f"{sweep.source}: output.vtk and output.contacts are ignored in a sweep (a case writes "
                          "only its row, and with sweep.keep_traces its trace): run one case alone for its "
                          "series, `minidem run FILE --case N`")
        if not args.quiet:
            print(f"minidem: {sweep.source}: sweep of {len(sweep.cases)} case(s) over {', '.join(sweep.keys)} "
                  f"on {executor.description}")
        rows = run(sweep, directory, progress=not args.quiet, executor=executor,
                   restart=getattr(args, "restart", False), echo=echo)
    except KeyboardInterrupt:
        print(f"minidem: sweep interrupted; finished cases are in {directory / JOURNAL}: run the same command "
              "again to run only the rest", file=sys.stderr)
        raise
    finally:
        executor.close()
    written = figures.draw(sweep, rows, directory)
    failed = [r for r in rows if r["status"] != "ok"]
    if not args.quiet:
        print(f"  wrote {directory / 'sweep.csv'}" + "".join(f"\n  wrote {p}" for p in written))
        for r in failed:
            print(f"  case {r['case']} failed: {r['error']}")
        for line in _energy_gain_notes(rows):
            print(f"  warning: {line}")
    else:  # --quiet keeps the warnings (docs/cli.md), on standard error
        for line in _energy_gain_notes(rows):
            print(f"minidem: warning: {line}", file=sys.stderr)
    if failed:
        print(f"minidem: {len(failed)} of {len(rows)} sweep case(s) failed (status and error columns of "
              f"{directory / 'sweep.csv'}); the other cases ran", file=sys.stderr)
        return 1
    return 0
