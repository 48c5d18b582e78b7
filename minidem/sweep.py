"""Parameter sweeps: one scenario, many cases, one table.

A scenario with a ``[sweep]`` section is run once per case by ``minidem run``::

    [sweep]
    cases = {"contact.law" = ["hmd", "ls"], "impact.angle_deg" = [1.0, 5.0, 30.0]}
    figures = ["y1", "y2", "et"]

``cases`` maps dotted scenario keys (the ones ``--set`` takes) to lists of values; the
cases are their cartesian product, the first key varying slowest, and every case is the
base scenario with those values set. Cases run in worker processes; each worker reuses
the compiled kernel of a law across its cases (one ``Simulation`` per case, no
recompilation). Rows come back in case order whatever the completion order, so
``sweep.csv`` does not depend on the worker count. A case that fails is a row with its
``error`` column filled in; the other cases still run.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import itertools
import json
import math
import multiprocessing
import os
import time as wallclock
import warnings
from pathlib import Path
from typing import Any

from minidem import scenario
from minidem.scenario import ScenarioError

ROW_COLUMNS = ("case", "law", "angle_deg", "x", "y1", "y2", "et", "en", "contact_duration_s", "energy_ratio",
               "max_overlap_m", "steps", "dt_s", "wall_time_s")
FIGURES = ("y1", "y2", "et", "force_displacement")
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

    def overrides(self, index: int) -> list[str]:
        return [f"{key}={_toml_value(value)}" for key, value in zip(self.keys, self.cases[index])]

    @property
    def series_keys(self) -> list[str]:
        """The swept keys that tell the curves of a figure apart (all but the angle)."""
        return [k for k in self.keys if k != ANGLE_KEY]


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string for the names scenarios use
    return repr(value)


def has_sweep(data: dict) -> bool:
    return "sweep" in data


def plan(data: dict, source: str) -> SweepPlan:
    """Validate ``[sweep]`` (keys from scenario.SCHEMA) and every case's scenario."""
    errors = scenario._Errors(source)
    keys_declared = scenario.SCHEMA["sweep"][1]
    values = scenario._check_table(data["sweep"], keys_declared, "sweep", errors)
    errors.raise_if_any()
    cases_table = values["cases"]
    keys, columns = [], []
    for key, options in cases_table.items():
        where = f'sweep.cases."{key}"'
        if not isinstance(options, list) or not options:
            errors.add(where, f"expected a non-empty list of values, got {options!r}")
            continue
        if key.split(".")[0] == "sweep":
            errors.add(where, "a sweep cannot sweep its own settings")
            continue
        keys.append(key)
        columns.append(options)
    unknown = [f for f in values["figures"] if f not in FIGURES]
    if unknown:
        errors.add("sweep.figures", f"unknown figure(s) {unknown}; valid: {', '.join(FIGURES)}")
    if values["workers"] < 0:
        errors.add("sweep.workers", f"must be >= 0 (0: one per CPU), got {values['workers']}")
    errors.raise_if_any()
    base = {k: v for k, v in data.items() if k != "sweep"}
    cases = list(itertools.product(*columns))
    sweep = SweepPlan(source, base, keys, cases, values["workers"], values["keep_traces"],
                      list(values["figures"]), values.get("series_labels"), values.get("title"))
    if sweep.series_labels is not None and len(sweep.series_labels) != len(_series(sweep)):
        errors.add("sweep.series_labels", f"expected {len(_series(sweep))} labels (one per combination of "
                   f"{', '.join(sweep.series_keys) or 'nothing'}), got {len(sweep.series_labels)}")
    # every case must be a valid scenario before anything runs: bad input is exit 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for index in range(len(cases)):
            try:
                scenario.build_scene(scenario.apply_overrides(base, sweep.overrides(index)), source)
            except ScenarioError as exc:
                setting = ", ".join(f"{k} = {_toml_value(v)}" for k, v in zip(keys, cases[index]))
                errors.add(f"sweep case {index} ({setting})", str(exc).replace(f"{source}: ", "", 1))
                break
    for message in dict.fromkeys(str(w.message) for w in caught):
        warnings.warn(message, stacklevel=2)  # once each, not once per case
    errors.raise_if_any()
    return sweep


def _series(sweep: SweepPlan) -> list[tuple]:
    """Distinct values of the series keys, in first-seen order."""
    positions = [sweep.keys.index(k) for k in sweep.series_keys]
    seen: dict[tuple, None] = {}
    for case in sweep.cases:
        seen.setdefault(tuple(case[p] for p in positions), None)
    return list(seen)


# ---------------------------------------------------------------------------------
# running one case (in a worker process)
# ---------------------------------------------------------------------------------
def _run_case(task) -> dict:
    index, base, overrides, source, trace_path = task
    from minidem import analysis, output, simulation
    from minidem.kernel import TRACE_COLUMNS

    row: dict[str, Any] = {"case": index, "error": ""}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # plan() has shown them once already
            scene = scenario.build_scene(scenario.apply_overrides(base, overrides), source)
        if trace_path is not None:
            scene.trace = True
        result = simulation.Simulation(scene).run()
        summary = analysis.summary(result)
        row.update({k: summary.get(k) for k in ROW_COLUMNS if k != "case"})
        if not result.separated and scene.stop == "separation":
            row["error"] = f"contact had not ended by t = {result.time:.4g} s"
        if trace_path is not None and result.trace is not None:
            output.write_csv(trace_path, TRACE_COLUMNS, result.trace.tolist())
            row["trace_file"] = str(trace_path)
    except Exception as exc:  # noqa: BLE001 - a failed case is reported in its row
        row["error"] = f"{type(exc).__name__}: {exc}".replace("\n", " ")
    return row


def run(sweep: SweepPlan, directory: Path, progress: bool = True, workers: int | None = None) -> list[dict]:
    """Run every case; write ``sweep.csv`` (and traces) under ``directory``; return the rows."""
    from minidem import output

    directory = Path(directory)
    n = len(sweep.cases)
    workers = workers if workers is not None else sweep.workers
    workers = min(workers or os.cpu_count() or 1, n)
    tasks = []
    for index in range(n):
        trace_path = directory / "traces" / f"case_{index:03d}.csv" if sweep.keep_traces else None
        tasks.append((index, sweep.base, sweep.overrides(index), sweep.source, trace_path))

    rows: list[dict | None] = [None] * n
    bar = _progress_bar(n, progress)
    started = wallclock.perf_counter()
    # The first case of each law runs here first: its kernel is compiled (or loaded from
    # numba's cache) once, and forked workers inherit it instead of compiling it again.
    first_of_law: dict[Any, int] = {}
    for index in range(n):
        first_of_law.setdefault(_law_of(sweep, index), index)
    for index in first_of_law.values():
        rows[index] = _run_case(tasks[index])
        bar.update(1)
    rest = [t for t in tasks if rows[t[0]] is None]
    if workers <= 1 or len(rest) <= 1:
        for task in rest:
            rows[task[0]] = _run_case(task)
            bar.update(1)
    else:
        context = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else None)
        with concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context) as pool:
            # a few cases per task keeps the inter-process traffic below the run time
            chunk = max(1, len(rest) // (workers * 8))
            batches = [rest[i:i + chunk] for i in range(0, len(rest), chunk)]
            futures = {pool.submit(_run_batch, batch): batch for batch in batches}
            for future in concurrent.futures.as_completed(futures):
                for row in future.result():
                    rows[row["case"]] = row
                bar.update(len(futures[future]))
    bar.close()
    elapsed = wallclock.perf_counter() - started

    swept = [k for k in sweep.keys if k not in ("contact.law", ANGLE_KEY)]
    columns = list(ROW_COLUMNS) + swept + (["trace_file"] if sweep.keep_traces else []) + ["error"]
    table = []
    for row, case in zip(rows, sweep.cases):
        for key, value in zip(sweep.keys, case):
            if key not in ("contact.law", ANGLE_KEY):
                row[key] = value
        if row.get("law") is None and "contact.law" in sweep.keys:
            row["law"] = case[sweep.keys.index("contact.law")]
        if row.get("angle_deg") is None and ANGLE_KEY in sweep.keys:
            row["angle_deg"] = case[sweep.keys.index(ANGLE_KEY)]
        table.append(["" if row.get(c) is None else row.get(c) for c in columns])
    output.write_csv(directory / "sweep.csv", columns, table)
    failed = sum(1 for r in rows if r["error"])
    output.write_json(directory / "sweep.json", {
        "scenario": sweep.source, "cases": n, "failed": failed, "workers": workers,
        "wall_time_s": elapsed, "swept_keys": sweep.keys,
    })
    return rows


def _run_batch(batch) -> list[dict]:
    return [_run_case(task) for task in batch]


def _law_of(sweep: SweepPlan, index: int):
    if "contact.law" in sweep.keys:
        return sweep.cases[index][sweep.keys.index("contact.law")]
    return sweep.base.get("contact", {}).get("law")


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress_bar(total: int, enabled: bool):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="case", desc="sweep", leave=True)


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


def friction_of(sweep: SweepPlan) -> float:
    """The friction coefficient of the base scenario (for the rigid-body lines)."""
    value = sweep.base.get("contact", {}).get("friction")
    return float(value) if isinstance(value, (int, float)) else math.nan


def command(args, data: dict) -> int:
    """``minidem run`` of a scenario with a [sweep] section."""
    from minidem import figures

    data = scenario.apply_overrides(data, args.set)
    sweep = plan(data, str(args.file))
    directory = Path(args.out) if args.out else Path(
        sweep.base.get("output", {}).get("directory") or Path("out") / Path(args.file).stem)
    if not args.quiet:
        print(f"minidem: {sweep.source}: sweep of {len(sweep.cases)} case(s) over {', '.join(sweep.keys)}")
    rows = run(sweep, directory, progress=not args.quiet, workers=getattr(args, "workers", None))
    written = figures.draw(sweep, rows, directory)
    failed = [r for r in rows if r["error"]]
    if not args.quiet:
        print(f"  wrote {directory / 'sweep.csv'}" + "".join(f"\n  wrote {p}" for p in written))
        for r in failed:
            print(f"  case {r['case']} failed: {r['error']}")
    return 1 if failed and len(failed) == len(rows) else 0
