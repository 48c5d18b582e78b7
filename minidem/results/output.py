"""A run's output directory: the files ``minidem run`` writes there, and reading them back.

Writing: :func:`write_run_files` (``summary.json``, ``trace.csv``; the engine writes
``final_state.npz`` and :class:`minidem.results.vtk.SimulationFrames` the ParaView series).

Reading: :class:`Output` (``minidem.open_results(path)``) gives the summary as a dict,
the final state as arrays, the trace and a sweep's table as columns, and the VTK series
as pyvista data sets by time (:class:`Series`), so a notebook can plot or render what
``minidem run`` wrote without ParaView.
"""

from __future__ import annotations

import csv
import json
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import numpy as np

from minidem.errors import MinidemError

# the arrays of a particle frame (minidem.results.vtk.VTKSeriesWriter.write_frame) and their units
PARTICLE_ARRAYS = {"radius": "m", "velocity": "m/s", "angular_velocity": "rad/s", "force": "N",
                   "particle_id": "", "material_id": ""}


def write_run_files(directory: Path, result, wrote_series: bool) -> dict:
    """Write ``summary.json`` (and ``trace.csv`` when the run traced its contact) of a
    finished run into ``directory``; return the summary. What ``minidem run`` and
    ``minidem.run(..., out=DIR)`` write, through this one function. An earlier run's
    trace and, when this run wrote no VTK series (``wrote_series`` False), its series are
    put aside: beside this run's summary they read as this run's (open_results, and
    ParaView's file dialog)."""
    import warnings

    from minidem import files
    from minidem.engine.checkpoint import LAST_GOOD
    from minidem.results import analysis

    summary = analysis.summary(result)
    files.write_json(Path(directory) / "summary.json", summary)
    if result.trace is not None:
        from minidem.engine.kernel import TRACE_COLUMNS

        files.write_csv(Path(directory) / "trace.csv", TRACE_COLUMNS, result.trace.tolist())
    elif (Path(directory) / "trace.csv").exists():
        warnings.warn(f"{directory}: trace.csv is an earlier run's (this run traced nothing): renamed "
                      f"{_set_aside(Path(directory) / 'trace.csv')}", stacklevel=2)
    if not wrote_series:
        from minidem.results.vtk import set_aside_unwritten_series

        try:
            told = set_aside_unwritten_series(directory)
        except MinidemError as exc:  # the run's own results are written: a warning, not a failed run
            told = f"{exc}: the VTK series in {directory} is an earlier run's, not this one's"
        if told:
            warnings.warn(told, stacklevel=2)
    # an earlier failed run's state before its blow-up, kept until a run here succeeds
    (Path(directory) / LAST_GOOD).unlink(missing_ok=True)
    return summary


def _set_aside(path: Path) -> str:
    """Rename ``path`` to NAME.previous.EXT, or NAME.previous.2.EXT and on when that is
    taken (an earlier set-aside result is never overwritten); returns the new name."""
    number = 1
    while True:
        target = path.with_name(f"{path.stem}.previous{'' if number == 1 else f'.{number}'}{path.suffix}")
        if not target.exists():
            path.replace(target)
            return target.name
        number += 1


def read_columns(path: str | Path) -> dict[str, np.ndarray]:
    """A CSV file minidem wrote (trace.csv, sweep.csv) as columns: numbers as float64
    arrays (an empty cell is NaN), text as object arrays (an empty cell is None)."""
    with open(path, newline="") as handle:
        rows = [row for row in csv.reader(handle) if row and not row[0].startswith("#")]
    if not rows:
        return {}
    names, body = rows[0], rows[1:]
    columns = {}
    for k, name in enumerate(names):
        cells = [row[k] if k < len(row) else "" for row in body]
        try:
            columns[name] = np.array([float(c) if c != "" else np.nan for c in cells], dtype=np.float64)
        except ValueError:
            columns[name] = np.array([c if c != "" else None for c in cells], dtype=object)
    return columns


class Series:
    """A ParaView time series (a ``.pvd`` collection) as pyvista data sets by time.

    ``series.times`` (s), ``len(series)``, ``series[k]`` (the k-th frame, negative k from
    the end), ``series.at(t)`` (the last frame at or before ``t``) and iteration over
    ``(time, mesh)`` pairs. Frames are read when asked for (a long run's series does not
    fit in memory at once)."""

    def __init__(self, pvd: Path):
        self.path = Path(pvd)
        try:
            root = ElementTree.parse(self.path).getroot()
        except (OSError, ElementTree.ParseError) as exc:
            raise MinidemError(f"{self.path}: not a readable ParaView collection: {exc}") from None
        entries = [(float(e.get("timestep")), e.get("file")) for e in root.iter("DataSet")]
        self.times = np.array([t for t, _ in entries], dtype=np.float64)
        self.files = [self.path.parent / name for _, name in entries]

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, index: int):
        import pyvista

        return pyvista.read(self.files[index])

    def __iter__(self):
        for k in range(len(self)):
            yield float(self.times[k]), self[k]

    def at(self, time_s: float):
        """The last frame written at or before ``time_s`` (the first frame before it)."""
        return self[max(0, int(np.searchsorted(self.times, time_s, side="right")) - 1)]

    def __repr__(self) -> str:
        span = f", t = {self.times[0]:.6g} .. {self.times[-1]:.6g} s" if len(self) else ""
        return f"<Series {self.path.name}: {len(self)} frame(s){span}>"


class Output:
    """What ``minidem run`` wrote in one output directory, read back (``minidem.open_results``).

    Attributes are read when first used; one that the run did not write is None:

    * ``summary``: summary.json as a dict (the keys of docs/cli.md);
    * ``final_state``: final_state.npz as a dict of arrays (``position``, ``velocity``,
      ``angular_velocity``, ``force``, ``torque``: (N, 3), SI units; and the contact state
      a resume needs), ``final_meta`` its metadata (step, time, law, ...);
    * ``trace``: trace.csv as columns (``time_s``, ``normal_force_n``, ...);
    * ``sweep``: a sweep's sweep.csv as columns (``y1``, ``et``, ``law``, ...);
    * ``series`` / ``contacts``: the particle and contact-network VTK series (:class:`Series`);
    * ``walls``: walls.vtu as a pyvista data set.
    """

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise MinidemError(f"{self.directory}: " + ("a file, not an output directory (give the directory a run "
                                                        "wrote into)" if self.directory.exists()
                                                        else "no such output directory"))
        if not any((self.directory / name).exists() for name in
                   ("summary.json", "final_state.npz", "sweep.csv", "particles.pvd", "last_good.npz")):
            raise MinidemError(f"{self.directory}: not a minidem output directory (none of summary.json, "
                               "final_state.npz, sweep.csv, particles.pvd)")
        self._cache: dict = {}

    def _file(self, name: str) -> Path | None:
        path = self.directory / name
        return path if path.exists() else None

    def _cached(self, name: str, load):
        """``load(path)`` of the file ``name`` in the directory, once; None if there is no such file."""
        if name not in self._cache:
            path = self._file(name)
            self._cache[name] = load(path) if path else None
        return self._cache[name]

    @property
    def summary(self) -> dict | None:
        return self._cached("summary.json", lambda path: json.loads(path.read_text()))

    def _state(self) -> tuple:
        from minidem.engine import checkpoint

        return self._cached(checkpoint.FINAL_STATE, checkpoint.read) or (None, None)

    @property
    def final_state(self) -> dict | None:
        return self._state()[0]

    @property
    def final_meta(self) -> dict | None:
        return self._state()[1]

    @property
    def trace(self) -> dict | None:
        return self._cached("trace.csv", read_columns)

    @property
    def sweep(self) -> dict | None:
        return self._cached("sweep.csv", read_columns)

    @property
    def series(self) -> Series | None:
        return self._cached("particles.pvd", Series)

    @property
    def contacts(self) -> Series | None:
        return self._cached("particles_contacts.pvd", Series)

    @property
    def walls(self):
        import pyvista

        return self._cached("walls.vtu", pyvista.read)

    def __repr__(self) -> str:
        held = [name for name in ("summary.json", "final_state.npz", "trace.csv", "sweep.csv", "particles.pvd",
                                  "walls.vtu") if self._file(name)]
        return f"<Output {self.directory}: {', '.join(held)}>"


def set_aside_earlier_results(directory: str | Path, started: float) -> str | None:
    """After a run into ``directory`` failed (a blow-up, a result it could not write): the
    summary.json, final_state.npz, trace.csv and last_good.npz an earlier run left there, older than ``started``
    (time.time() at the run's start), would read as this run's result (a script checking
    summary.json saw the old success), so they are renamed *.previous.* and kept. Returns
    what to tell the user, or None when there was nothing to move."""
    from minidem.engine.checkpoint import FINAL_STATE, LAST_GOOD
    from minidem.results.vtk import PREVIOUS_SERIES

    moved, kept = [], []
    for name in ("summary.json", FINAL_STATE, "trace.csv", LAST_GOOD):
        path = Path(directory) / name
        try:
            if path.stat().st_mtime >= started:  # this run's own (its final state, then a failed summary)
                continue
        except OSError:  # absent: the usual case
            continue
        try:
            moved.append(f"{name} -> {_set_aside(path)}")
        except OSError as exc:
            kept.append(f"{name} (could not be renamed: {exc.strerror or exc})")
    series = Path(directory) / PREVIOUS_SERIES
    try:
        if series.stat().st_mtime >= started:  # set aside by this run's first frame (SimulationFrames)
            moved.append(f"the VTK series to {PREVIOUS_SERIES}/")
    except OSError:
        pass
    if not moved and not kept:
        return None
    text = f"the earlier run's results in {directory} are not this run's: "
    return text + "; ".join(filter(None, (f"renamed {', '.join(moved)}" if moved else "",
                                          f"left as they are: {', '.join(kept)}" if kept else "")))
