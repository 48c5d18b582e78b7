"""minidem from Python: the functions and classes at the package's face (``import minidem``).

A :class:`Scenario` is the scenario file's content as a dict, the one the TOML parser
produces: read from a file (:func:`load`, with overrides as ``--set`` takes them) or
built in code (materials, contact law, walls, particles from arrays). It becomes a
scene only through :func:`minidem.scene.scenario.build_scene`, the validator of
``minidem run``: the same checks, the same messages naming the key, the same
:class:`ScenarioError` (a :class:`MinidemError`). :func:`run` runs it as ``minidem run``
does and returns a :class:`Result` (arrays and the summary dict); :func:`sweep` runs a
sweep and returns its table; :func:`open_results` reads an output directory back.
See docs/python-api.md.
"""

from __future__ import annotations

import copy
import json
import math
import numbers
import os
import time
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from minidem.results.output import PARTICLE_ARRAYS, Output
from minidem.scene.scenario import ScenarioError

__all__ = ["Scenario", "Result", "SweepTable", "load", "run", "sweep", "open_results"]


def _plain(value):
    """numpy arrays and scalars as Python lists and numbers: the values a TOML file gives."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _toml_text(value) -> str:
    """A Python value as the TOML text ``--set KEY=VALUE`` would be given."""
    value = _plain(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, list):
        return "[" + ", ".join(_toml_text(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_text(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (int, float)):
        return repr(value)
    # None became the string 'None' in the validator's message (a robustness review)
    raise TypeError(f"{value!r:.60} ({type(value).__name__}) is no TOML value: give a number, a string, true or "
                    "false, a list or a dict")


def _override_texts(overrides) -> list[str]:
    """``{"impact.angle_deg": 10}`` or ``["impact.angle_deg=10"]`` -> ``--set`` texts."""
    if overrides is None:
        return []
    if isinstance(overrides, str):
        return [overrides]
    if isinstance(overrides, Mapping):
        texts = []
        for key, value in overrides.items():
            try:
                texts.append(f"{key}={_toml_text(value)}")
            except TypeError as exc:
                raise TypeError(f"overrides: {key}: {exc}") from None
        return texts
    if isinstance(overrides, (list, tuple)) and all(isinstance(text, str) for text in overrides):
        return list(overrides)
    raise TypeError(f"overrides: expected a dict of dotted keys ({{\"impact.angle_deg\": 10.0}}) or a list of "
                    f"'KEY=VALUE' texts, got {type(overrides).__name__} {overrides!r:.60}")


class Scenario:
    """A scenario (the content of a scenario file) to validate, run or sweep.

    Build one in code with the methods below (each returns the scenario, so they chain),
    or read one with :func:`load`. ``data`` is the dict a TOML file of the same content
    parses to; nothing is checked until :meth:`scene`, :meth:`run` or :func:`sweep`,
    which all validate it with the validator of scenario files.
    """

    def __init__(self, data: Mapping | None = None, source: str = "<python>"):
        self.data: dict = copy.deepcopy(_plain(dict(data))) if data else {}
        self.source = str(source)

    # -- reading -------------------------------------------------------------------
    @classmethod
    def from_file(cls, path: str | Path, overrides=None) -> "Scenario":
        """A scenario file, with ``overrides`` applied as ``minidem run --set`` does:
        a dict of dotted keys (``{"impact.angle_deg": 10.0}``) or ``KEY=VALUE`` texts."""
        from minidem.scene import scenario

        data = scenario.apply_overrides(scenario.read_toml(path), _override_texts(overrides))
        made = cls(source=str(path))
        made.data = data
        return made

    # -- building ------------------------------------------------------------------
    def set(self, overrides=None, **dotted) -> "Scenario":
        """Set values by dotted key, as ``--set`` does: ``set({"run.end_time": 0.1})``, or
        with ``__`` for the dots: ``set(run__end_time=0.1)``."""
        from minidem.scene import scenario

        texts = _override_texts(overrides) + _override_texts({k.replace("__", "."): v for k, v in dotted.items()})
        self.data = scenario.apply_overrides(self.data, texts)
        return self

    def material(self, name: str, **keys) -> "Scenario":
        """``[materials.NAME]``: youngs_modulus (Pa), poisson_ratio, density (kg/m^3); checked
        with the rest (a misspelt key is named, with the valid ones)."""
        self.data.setdefault("materials", {})[name] = _plain(keys)
        return self

    def contact(self, law: str, **parameters) -> "Scenario":
        """``[contact]``: the law (``minidem laws`` lists them) and its parameters, e.g. friction."""
        self.data["contact"] = _plain({"law": law, **parameters})
        return self

    def wall(self, type: str = "plane", **keys) -> "Scenario":
        """One ``[[walls]]`` table: ``wall(normal=[0, 0, 1], material="glass")``, ``wall("box",
        lower=..., upper=..., material=...)``, ``"cylinder"``, ``"mesh"`` (docs/scenario-reference.md)."""
        self.data.setdefault("walls", []).append(_plain({"type": type, **keys}))
        return self

    def fill(self, kind: str, **keys) -> "Scenario":
        """One ``[[fill]]`` generator: ``"lattice"``, ``"random"`` or ``"file"``."""
        self.data.setdefault("fill", []).append(_plain({"kind": kind, **keys}))
        return self

    def impact(self, **keys) -> "Scenario":
        """``[impact]``: the paper's sphere against a wall (material, radius, speed, angle_deg, ...)."""
        self.data["impact"] = _plain(keys)
        return self

    def particles(self, position, radius, material, velocity=None, angular_velocity=None) -> "Scenario":
        """Spheres from arrays, one ``[[particles]]`` table each (appended to any already there).

        ``position`` (N, 3) m; ``radius`` (N,) m or one value; ``material`` a name or N
        names; ``velocity`` (N, 3) m/s and ``angular_velocity`` (N, 3) rad/s, default zero.
        Values are checked by the scenario validator (``particles[K].radius: must be > 0 m``);
        only the shapes are checked here.
        """
        def as_numbers(name, value, dtype=np.float64):
            try:
                return np.asarray(value, dtype=dtype)
            except (TypeError, ValueError) as exc:  # "abc", a complex number: numpy's own error named no argument
                raise ScenarioError(f"{self.source}: particles({name}=...): expected numbers, got "
                                    f"{value!r:.60} ({exc})") from None

        position = as_numbers("position", position)
        if position.ndim != 2 or position.shape[1] != 3:
            raise ScenarioError(f"{self.source}: particles(position=...): expected an array of shape (N, 3), "
                                f"got shape {position.shape}")
        n = position.shape[0]

        def per_particle(name, value, shape):
            if value is None:
                return None
            array = as_numbers(name, value, object if name == "material" else np.float64)
            if array.ndim == 0:
                return np.broadcast_to(array, (n, *shape))
            if array.shape != (n, *shape):
                expected = ", ".join(str(d) for d in (n, *shape))
                raise ScenarioError(f"{self.source}: particles({name}=...): expected one value or an array of "
                                    f"shape ({expected}{',' if not shape else ''}) for {n} particle(s), "
                                    f"got shape {array.shape}")
            return array

        radius = per_particle("radius", radius, ())
        material = per_particle("material", material, ())
        velocity = per_particle("velocity", velocity, (3,))
        angular_velocity = per_particle("angular_velocity", angular_velocity, (3,))
        tables = self.data.setdefault("particles", [])
        for i in range(n):
            table = {"position": position[i].tolist(), "radius": float(radius[i]), "material": material[i]}
            if velocity is not None:
                table["velocity"] = velocity[i].tolist()
            if angular_velocity is not None:
                table["angular_velocity"] = angular_velocity[i].tolist()
            tables.append(table)
        return self

    def run_settings(self, **keys) -> "Scenario":
        """``[run]`` keys: dt, end_time, stop, gravity, integrator, ... (merged into the table)."""
        self.data.setdefault("run", {}).update(_plain(keys))
        return self

    def output(self, **keys) -> "Scenario":
        """``[output]`` keys: trace, vtk, interval, contacts, ... (merged into the table)."""
        self.data.setdefault("output", {}).update(_plain(keys))
        return self

    def sweep_cases(self, cases: Mapping[str, Sequence], **keys) -> "Scenario":
        """``[sweep]``: ``cases`` maps dotted keys to lists of values (their cartesian product
        is run); ``keys`` are the other [sweep] keys (keep_traces, figures, ...)."""
        self.data["sweep"] = _plain({**keys, "cases": dict(cases)})
        return self

    # -- using ---------------------------------------------------------------------
    def scene(self, out: str | Path | None = None):
        """The validated :class:`minidem.scene.scenario.Scene` (raises :class:`ScenarioError`)."""
        from minidem.scene import scenario

        if "sweep" in self.data:
            raise ScenarioError(f"{self.source}: has a [sweep] table: run it with minidem.sweep(), one of its "
                                "cases with minidem.run(..., case=N), or drop it (scenario.data.pop('sweep')) to "
                                "run the base scenario once")
        return scenario.build_scene(copy.deepcopy(self.data), self.source, out)

    def run(self, out: str | Path | None = None, progress: bool = False) -> "Result":
        """Run it: see :func:`run`."""
        return run(self, out=out, progress=progress)

    def to_toml(self) -> str:
        """The scenario as TOML text (a file ``minidem run`` reads to the same scene)."""
        lines = []
        for section, value in self.data.items():
            if isinstance(value, list):
                for table in value:
                    lines += [f"[[{section}]]", *(f"{k} = {_toml_text(v)}" for k, v in table.items()), ""]
            elif isinstance(value, dict) and section == "materials":
                for name, table in value.items():
                    lines += [f"[materials.{name}]", *(f"{k} = {_toml_text(v)}" for k, v in table.items()), ""]
            elif isinstance(value, dict):
                lines += [f"[{section}]", *(f"{k} = {_toml_text(v)}" for k, v in value.items()), ""]
        return "\n".join(lines)

    def __repr__(self) -> str:
        return f"<Scenario {self.source}: {', '.join(self.data) or 'empty'}>"


def _one_case(given: Scenario, case: int, overrides) -> Scenario:
    """Case ``case`` of a scenario's [sweep] (``overrides`` applied to it), as a scenario
    without it; an override of a swept key is refused: every case sets it again."""
    from minidem.studies import sweep as sweep_module

    if "sweep" not in given.data:
        raise ScenarioError(f"{given.source}: case={case!r}: the scenario has no [sweep] table, so no cases: run "
                            "it without case=")
    plan = sweep_module.plan(copy.deepcopy(given.data), given.source, check_cases=False)
    sweep_module.refuse_swept_overrides(plan, _override_texts(overrides), "overrides {}", "case=N")
    return Scenario(plan.base, given.source).set(sweep_module.case_values(plan, case, f"case={case!r}"))


def load(path: str | Path, overrides=None) -> Scenario:
    """Read a scenario file; ``overrides`` as ``minidem run --set`` takes them (a dict of
    dotted keys, or ``KEY=VALUE`` texts). Raises :class:`ScenarioError` for a missing or
    malformed file or a bad override."""
    return Scenario.from_file(path, overrides)


def _scenario(scenario, overrides) -> Scenario:
    if isinstance(scenario, Scenario):
        return Scenario(scenario.data, scenario.source).set(overrides) if overrides else scenario
    if isinstance(scenario, (str, Path)):
        return Scenario.from_file(scenario, overrides)
    if isinstance(scenario, Mapping):
        return Scenario(scenario).set(overrides)
    raise TypeError(f"expected a Scenario, a scenario file path or a dict, got {type(scenario).__name__}")


class Result:
    """A finished run: the final state as arrays, the summary as a dict.

    ``summary``: summary.json's content (docs/cli.md lists the stable keys);
    ``position``, ``velocity``, ``angular_velocity``, ``force``, ``torque``: (N, 3) at the
    end (m, m/s, rad/s, N, N m); ``radius`` (N,) m; ``initial_velocity``,
    ``initial_angular_velocity``; ``time`` (s) at the end; ``trace``: the probed contact
    per step as columns (``output.trace = true``) or None; ``energy``: (time s, kinetic
    energy J) samples; ``scene``: the validated scene; ``raw``: the engine's
    :class:`minidem.engine.run_loop.RunResult`; ``directory``: where the files went
    (``out=``), else None.
    """

    def __init__(self, raw, summary: dict, directory: Path | None = None):
        self.raw, self.summary, self.directory = raw, summary, directory
        self.scene = raw.scene
        for name in ("position", "velocity", "angular_velocity", "force", "torque", "initial_velocity",
                     "initial_angular_velocity", "time", "energy"):
            setattr(self, name, getattr(raw, name))
        self.radius = self.scene.radius

    @property
    def trace(self) -> dict[str, np.ndarray] | None:
        if self.raw.trace is None:
            return None
        from minidem.engine.kernel import TRACE_COLUMNS

        return {name: self.raw.trace[:, k] for k, name in enumerate(TRACE_COLUMNS)}

    def to_pyvista(self):
        """The particles at the end as a ``pyvista.PolyData`` of their centres, with the point
        arrays of a VTK frame (radius, velocity, angular_velocity, force, particle_id,
        material_id): ``result.to_pyvista().glyph(scale="radius", factor=2.0)`` draws spheres."""
        import pyvista

        cloud = pyvista.PolyData(np.ascontiguousarray(self.position))
        arrays = {"radius": self.radius, "velocity": self.velocity, "angular_velocity": self.angular_velocity,
                  "force": self.force, "particle_id": np.arange(self.scene.n_particles),
                  "material_id": self.scene.particle_material}
        for name in PARTICLE_ARRAYS:
            if arrays[name] is not None:
                cloud.point_data[name] = np.ascontiguousarray(arrays[name])
        return cloud

    def walls_pyvista(self):
        """The walls as one ``pyvista.PolyData`` (planes as the rectangles ParaView shows), or
        None; with walls.vtu's cell arrays ``wall_id`` (which wall) and ``wall_table`` (which
        ``[[walls]]`` table of the scenario), to threshold one wall."""
        import pyvista

        from minidem.geometry.walls import display_meshes

        scene = self.scene
        lower = (scene.position - scene.radius[:, None]).min(axis=0)
        upper = (scene.position + scene.radius[:, None]).max(axis=0)
        meshes = display_meshes(scene.walls, lower, upper)
        if not meshes:
            return None
        tables = scene.walls.display_tables()
        parts = []
        for wall, (vertices, faces) in enumerate(meshes):
            part = pyvista.PolyData(vertices, np.hstack([np.full((len(faces), 1), faces.shape[1]), faces]).ravel())
            part.cell_data["wall_id"] = np.full(len(faces), wall, dtype=np.int64)
            part.cell_data["wall_table"] = np.full(len(faces), int(tables[wall]), dtype=np.int64)
            parts.append(part)
        return parts[0].merge(parts[1:]) if len(parts) > 1 else parts[0]

    def __repr__(self) -> str:
        return (f"<Result law {self.summary['law']}: {self.scene.n_particles} particle(s), "
                f"{self.summary['steps']} steps, t = {self.time:.6g} s>")


def run(scenario, overrides=None, out: str | Path | None = None, progress: bool = False,
        case: int | None = None) -> Result:
    """Run a scenario (a :class:`Scenario`, a file path or a dict) as ``minidem run`` does.

    ``overrides``: as :func:`load`. ``out``: an output directory to write what ``minidem
    run`` writes there (summary.json, final_state.npz, trace.csv, the VTK series); None
    (default) writes no file. ``progress``: a tqdm bar for long runs. ``case``: of a
    scenario with a ``[sweep]``, run that case alone (as ``minidem run --case``; its
    number as in sweep.csv), after ``overrides``; ``out`` is then its directory itself
    (``minidem run --case`` makes OUT/case_NNN).
    Raises :class:`ScenarioError` (bad input), :class:`LawError` (a broken law),
    :class:`RunFailure` (a blow-up), all :class:`MinidemError`.
    """
    from minidem.engine import checkpoint, run_loop, simulation
    from minidem.results import analysis
    from minidem.files import OutputError
    from minidem.results.output import set_aside_earlier_results, write_run_files
    from minidem.scene import scenario as scenario_module

    if out is not None and not isinstance(out, (str, os.PathLike)):
        raise TypeError(f"out: expected a directory path (str or os.PathLike), got {type(out).__name__} {out!r:.40}")
    given = _scenario(scenario, overrides)
    if case is not None:
        given = _one_case(given, case, overrides)
    scene = given.scene(out)
    directory, policy, frames = None, None, None
    if out is not None:
        directory = scenario_module.prepare_output_directory(scene.output_directory, "out", given.source)
        policy = checkpoint.Policy(directory, scene.checkpoint_interval, scene.checkpoint_wall_interval)
        checkpoint.remove_stale_temporaries(directory)
    sim = simulation.Simulation(scene)
    if directory is not None and scene.vtk:
        from minidem.results.vtk import SimulationFrames

        frames = SimulationFrames(sim, directory)
    bar = _ProgressBar(scene.n_particles, sim.dt) if progress else None
    started = time.time()
    try:
        try:
            result = sim.run(progress=bar, on_frame=frames, checkpoints=policy)
        finally:
            if frames is not None:
                frames.close()
            if bar is not None:
                bar.close()
        summary = (write_run_files(directory, result, wrote_series=frames is not None and frames.frames > 0)
                   if directory is not None else analysis.summary(result))
        if frames is not None:
            frames.succeeded()
    except (run_loop.RunFailure, OutputError):
        # an earlier run's results in the directory must not read as this one's (as minidem run)
        told = set_aside_earlier_results(directory, started) if directory is not None else None
        if told:
            warnings.warn(told, stacklevel=2)
        raise
    return Result(result, summary, directory)


class _ProgressBar:
    def __init__(self, particles: int, dt: float):
        self.particles, self.dt, self.bar = particles, dt, None

    def __call__(self, steps, total, contacts):
        if self.bar is None:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, unit="step", delay=2.0)
        # the postfix first: update() draws the bar, with the postfix it holds then
        self.bar.set_postfix_str(f"t={steps * self.dt:.4g} s, {contacts} contacts", refresh=False)
        self.bar.update(steps - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


class SweepTable:
    """A sweep's table: the rows of sweep.csv (case order) and its columns.

    ``table["y1"]`` is a column as a numpy array (float64 for numbers, a missing value NaN;
    object for text such as ``law``, ``status``); ``table.rows`` the rows as dicts (None
    for a missing value); ``table.columns`` the names in sweep.csv's order; ``table.failed``
    the rows whose ``status`` is not ``ok``; ``table.traces`` (with ``keep_traces``) each
    case's per-step contact trace, {case: array}. ``len(table)`` is the number of cases.
    """

    def __init__(self, columns: list[str], rows: list[dict], traces: dict | None = None,
                 directory: Path | None = None):
        self.columns, self.rows, self.traces, self.directory = columns, rows, traces or {}, directory

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self.columns:
            raise KeyError(f"{name!r}: not a column of the sweep; columns: {', '.join(self.columns)}")
        values = [row.get(name) for row in self.rows]
        if all(v is None or (isinstance(v, (int, float)) and not isinstance(v, bool)) for v in values):
            return np.array([np.nan if v is None else v for v in values], dtype=np.float64)
        return np.array(values, dtype=object)

    @property
    def failed(self) -> list[dict]:
        return [row for row in self.rows if row.get("status") != "ok"]

    def __repr__(self) -> str:
        return f"<SweepTable {len(self)} case(s), {len(self.failed)} failed; columns {', '.join(self.columns)}>"


def sweep(scenario, cases: Mapping[str, Sequence] | None = None, overrides=None, workers: int | None = None,
          out: str | Path | None = None, progress: bool = False) -> SweepTable:
    """Run a sweep and return its table (the columns of sweep.csv).

    ``scenario``: a :class:`Scenario`, a file path or a dict; with a ``[sweep]`` table, or
    a base scenario and ``cases`` (dotted key -> list of values, as ``sweep.cases``; given,
    it replaces the scenario's, and with them ``sweep.series_labels``, ``sweep.together``
    and a ``sweep.abscissa`` it does not vary; the other [sweep] keys stay).
    ``overrides``: applied to the base scenario first, as ``--set`` (not to a key the
    sweep varies: refused, every case would set it again). Every case is validated before any runs (:class:`ScenarioError` names the
    case and the key). ``workers``: local processes (default ``sweep.workers``; 0: one per
    CPU; 1: in this process). ``out``: write what ``minidem run`` writes for a sweep
    (sweep.csv, sweep.json, the journal, figures) there, resuming a sweep it holds;
    None (default): no file. A failed case is a row with ``status = "failed"`` and the
    reason in ``error``; the others still run.
    """
    from minidem.studies import executors
    from minidem.studies import sweep as sweep_module

    given = _scenario(scenario, overrides)
    data = copy.deepcopy(given.data)
    if cases is not None:
        # the file's other [sweep] settings stay, but not those naming its cases' keys or
        # counting their series: they would not fit the cases given
        kept = {key: value for key, value in (data.get("sweep") or {}).items()
                if key not in ("cases", "series_labels", "together")
                and not (key == "abscissa" and value not in cases)}
        data["sweep"] = {**kept, "cases": _plain(dict(cases))}
    if "sweep" not in data:
        raise ScenarioError(f"{given.source}: no [sweep] table and no cases given: pass cases={{\"impact.angle_deg\": "
                            "[...], ...}} or use minidem.run() for a single run")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, numbers.Integral)):
        raise TypeError(f"workers: expected a whole number of processes (0: one per CPU), got "
                        f"{type(workers).__name__} {workers!r:.40}")
    if workers is not None and workers < 0:
        raise ScenarioError(f"workers={workers}: must be >= 0 (0: one per CPU)")
    plan = sweep_module.plan(data, given.source)
    sweep_module.refuse_swept_overrides(plan, _override_texts(overrides), "overrides {}", "minidem.run(..., case=N)")
    if out is not None:
        from minidem.scene import scenario as scenario_module
        from minidem.studies import figures

        directory = scenario_module.prepare_output_directory(out, "out", given.source)
        rows = sweep_module.run(plan, directory, progress=progress, workers=workers)
        figures.draw(plan, rows, directory)
        traces = {}
        if plan.keep_traces:
            from minidem.results.output import read_columns

            traces = {row["case"]: np.column_stack(list(read_columns(directory / row["trace_file"]).values()))
                      for row in rows if row.get("trace_file")}
        columns = sweep_module.table_columns(plan)
        return SweepTable(columns, [{c: row.get(c) for c in columns} for row in rows], traces, directory)
    executor = executors.LocalProcesses(workers if workers is not None else plan.workers)
    done, lost, traces = {}, {}, {}
    for index, row in sweep_module.execute(plan, list(range(len(plan.cases))), executor):
        if isinstance(row, executors.Lost):
            lost[index] = row.reason
            continue
        trace = row.pop("trace", None)
        if trace is not None:
            traces[index] = trace
        done[index] = row
    if lost:
        raise executors.BackendFailure(f"{len(lost)} of {len(plan.cases)} case(s) were not run by "
                                       f"{executor.description}: {'; '.join(sorted(set(lost.values())))[:500]}")
    rows = sweep_module.complete_rows(plan, [done[i] for i in range(len(plan.cases))])
    columns = sweep_module.table_columns(plan)
    return SweepTable(columns, [{c: row.get(c) for c in columns} for row in rows], traces)


def open_results(directory: str | Path) -> Output:
    """Read what ``minidem run`` (or :func:`run` with ``out=``) wrote in ``directory``:
    the summary, the final state, the trace, a sweep's table and the VTK series as
    pyvista data sets by time. See :class:`minidem.results.output.Output`."""
    return Output(directory)

