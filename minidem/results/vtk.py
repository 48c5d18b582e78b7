"""VTK XML output that ParaView opens as one time series.

One ``.vtu`` (UnstructuredGrid) file per output frame holds the particles as points
with one vertex cell each, plus per-particle point arrays; applying ParaView's Glyph
filter (sphere, "Scale Array" = ``radius``, scale factor 2 because the glyph source
has unit diameter) shows the particles as spheres. Contacts, when given, go into a
separate per-frame ``.vtu`` of line cells joining the two particle centres, with the
cell array ``normal_force``. Each series gets a ``.pvd`` collection listing every frame
with its time, so ParaView loads the whole run with one "Open".

The XML is written by hand rather than through pyvista/meshio/vtk objects: a frame is
a few lines of XML followed by the arrays' raw bytes, which costs little more than the
disk write itself (~20x faster than building a pyvista or meshio object per frame).

Every file (frames and ``.pvd``) is written to a hidden temporary file in the same
directory, flushed, fsync'ed and then ``os.replace``'d onto its final name, so a run
killed at any instant leaves either the previous complete file or the new complete
file, never a truncated one; ParaView can also safely re-read a series while the run
is still writing it. The fsync (waiting for the disk) dominates the cost of a large
frame, so by default it runs on a helper thread, off the simulation's critical path.

Timing: ``python -m minidem.results.vtk`` (set ``BENCH_DIR`` to the output disk).

All arrays are written as Float64 (positions, radii, velocities, ... in SI units) or
Int64 (ids); connectivity is Int64 because the header type is UInt64 throughout.
"""

from __future__ import annotations

import base64
import itertools
import os
import re
import struct
import threading
from collections.abc import Iterable, Mapping, Sequence
from xml.sax.saxutils import quoteattr

import numpy as np

from minidem.geometry.walls import plane_to_quad

__all__ = ["VTKSeriesWriter", "plane_to_quad", "write_surface_vtu"]

# VTK cell type ids (vtkCellType.h).
_VTK_VERTEX = 1
_VTK_LINE = 3
_VTK_TRIANGLE = 5
_VTK_QUAD = 9

_F64 = np.dtype("<f8")
_I64 = np.dtype("<i8")
_U8 = np.dtype("u1")
_VTK_TYPE_NAME = {_F64: "Float64", _I64: "Int64", _U8: "UInt8"}

_ENCODINGS = ("raw", "base64")

# Unique temp names per process and call; a pid alone is not enough when one process
# owns several writers pointing at the same directory.
_tmp_counter = itertools.count()


# --------------------------------------------------------------------------------------
# atomic file replacement
# --------------------------------------------------------------------------------------


def _fsync_directory(directory: str) -> None:
    # The rename itself lives in the directory's metadata; without this an OS crash
    # right after os.replace may still show the old file (or none) after reboot.
    flags = os.O_RDONLY | getattr(os, "O_DIRECTORY", 0)
    try:
        fd = os.open(directory, flags)
    except OSError:  # e.g. Windows, where directories cannot be opened
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class _PendingFile:
    """A file fully written under a hidden temporary name, not yet renamed into place.

    Splitting "write the bytes" from "fsync + rename" lets the slow, GIL-free part
    (waiting for the disk) run on a background thread while the simulation continues;
    the bytes themselves are already in the OS page cache, so the caller may reuse its
    arrays at once.
    """

    __slots__ = ("path", "tmp", "file")

    def __init__(self, path: str, chunks: Iterable):
        self.path = path
        directory = os.path.dirname(os.path.abspath(path))
        # Leading dot hides it from ParaView's file dialog and from "*.vtu" globs; the
        # .tmp suffix keeps readers from mistaking it for a frame; the same directory
        # because os.replace is only atomic within one filesystem.
        self.tmp = os.path.join(
            directory, f".{os.path.basename(path)}.{os.getpid()}.{next(_tmp_counter)}.tmp")
        # os.open with 0o666 honours the umask, unlike tempfile.mkstemp's 0o600 which
        # would leave frames unreadable to colleagues after the rename.
        from minidem.files import output_error

        try:
            fd = os.open(self.tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                         | getattr(os, "O_BINARY", 0), 0o666)
        except OSError as exc:
            raise output_error(path, exc) from exc
        self.file = os.fdopen(fd, "wb")
        try:
            for chunk in chunks:
                self.file.write(chunk)
            self.file.flush()
        except OSError as exc:  # a full disk: named, and no temporary left
            self.abort()
            raise output_error(path, exc) from exc
        except BaseException:
            self.abort()
            raise

    def commit(self, fsync: bool) -> None:
        from minidem.files import output_error

        try:
            if fsync:
                os.fsync(self.file.fileno())
            self.file.close()
            os.replace(self.tmp, self.path)
        except OSError as exc:
            self.abort()
            raise output_error(self.path, exc) from exc
        except BaseException:
            self.abort()
            raise

    def abort(self) -> None:
        try:
            self.file.close()
        except OSError:
            pass
        try:
            os.unlink(self.tmp)
        except OSError:
            pass


def _commit_stages(stages: Sequence[Sequence[_PendingFile]], directory: str,
                   fsync: bool) -> None:
    """Rename stage after stage; with fsync, each stage's renames are made durable
    before the next stage starts, so a .pvd can never (even after an OS crash) list a
    frame file whose rename was lost. On error every uncommitted file is removed."""
    remaining = [p for stage in stages for p in stage]
    try:
        for stage in stages:
            for pending in stage:
                pending.commit(fsync)
                remaining.remove(pending)
            if fsync:
                _fsync_directory(directory)
    except BaseException:
        for pending in remaining:
            pending.abort()
        raise


def _atomic_write(path: str, chunks: Iterable, fsync: bool = True) -> None:
    """Write ``chunks`` (bytes-like objects) to ``path`` so that ``path`` is never seen
    half-written: temp file in the same directory, fsync, rename."""
    _commit_stages([[_PendingFile(path, chunks)]],
                   os.path.dirname(os.path.abspath(path)), fsync)


class _SyncJob(threading.Thread):
    """Background fsync + rename of one frame's files. Non-daemon on purpose: an
    interpreter that exits without close() still waits for the frame to land."""

    def __init__(self, stages, directory: str, fsync: bool):
        super().__init__(name="minidem-vtk-sync", daemon=False)
        self.args_ = (stages, directory, fsync)
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            _commit_stages(*self.args_)
        except BaseException as exc:  # re-raised in the simulation thread
            self.error = exc


# --------------------------------------------------------------------------------------
# UnstructuredGrid XML writer
# --------------------------------------------------------------------------------------


class _DataArray:
    __slots__ = ("name", "data", "ncomp", "vtk_type")

    def __init__(self, name: str, data: np.ndarray, ncomp: int):
        self.name = name
        self.data = data
        self.ncomp = ncomp
        self.vtk_type = _VTK_TYPE_NAME[data.dtype]


def _as_f64(a, shape_tail: tuple, what: str, n: int | None = None) -> np.ndarray:
    # ascontiguousarray is a no-op for the usual float64 C-ordered state arrays, so the
    # hot path copies nothing before the bytes go to the file.
    arr = np.ascontiguousarray(a, dtype=_F64)
    if arr.ndim != 1 + len(shape_tail) or arr.shape[1:] != shape_tail:
        want = "(N, " + ", ".join(map(str, shape_tail)) + ")" if shape_tail else "(N,)"
        raise ValueError(f"{what} must have shape {want}; got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{what} has {arr.shape[0]} rows, expected {n}")
    return arr


def _as_i64(a, what: str, n: int) -> np.ndarray:
    arr = np.asarray(a)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{what} must be integers; got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=_I64)
    if arr.shape != (n,):
        raise ValueError(f"{what} must have shape ({n},); got {arr.shape}")
    return arr


def _extra_array(name: str, a, n: int, what: str) -> _DataArray:
    arr = np.asarray(a)
    if arr.ndim not in (1, 2) or arr.shape[0] != n:
        raise ValueError(f"{what} {name!r} must have shape ({n},) or ({n}, k); got {arr.shape}")
    if arr.dtype == np.bool_:
        arr = np.ascontiguousarray(arr, dtype=_U8)
    elif np.issubdtype(arr.dtype, np.integer):
        arr = np.ascontiguousarray(arr, dtype=_I64)
    else:
        arr = np.ascontiguousarray(arr, dtype=_F64)
    return _DataArray(name, arr, 1 if arr.ndim == 1 else arr.shape[1])


def _ascii_text(arr: np.ndarray) -> str:
    # repr() of a Python float is the shortest string that round-trips exactly, so the
    # debugging format loses nothing; one tuple per line keeps it readable.
    if arr.size == 0:
        return ""
    fmt = repr if arr.dtype.kind == "f" else str
    if arr.ndim == 1:
        return "\n" + " ".join(map(fmt, arr.tolist())) + "\n"
    return "\n" + "\n".join(" ".join(map(fmt, row)) for row in arr.tolist()) + "\n"


def _data_array_tag(da: _DataArray, mode: str, offset: int, indent: str) -> str:
    # NumberOfComponents is omitted for scalars so that readers (meshio) hand back
    # (N,) rather than (N, 1).
    comp = f' NumberOfComponents="{da.ncomp}"' if da.data.ndim == 2 else ""
    head = f'{indent}<DataArray type="{da.vtk_type}" Name={quoteattr(da.name)}{comp}'
    if mode == "raw":
        return f'{head} format="appended" offset="{offset}"/>\n'
    if mode == "base64":
        # Header (payload byte count) and payload encoded as one stream: VTK's and
        # meshio's readers both accept this.
        blob = struct.pack("<Q", da.data.nbytes) + da.data.tobytes()
        text = base64.b64encode(blob).decode("ascii")
        return f'{head} format="binary">\n{text}\n{indent}</DataArray>\n'
    return f'{head} format="ascii">{_ascii_text(da.data)}{indent}</DataArray>\n'


def _unstructured_grid_chunks(
    points: np.ndarray,
    connectivity: np.ndarray,
    offsets: np.ndarray,
    types: np.ndarray,
    point_arrays: Sequence[_DataArray],
    cell_arrays: Sequence[_DataArray],
    mode: str,
    time_s: float | None = None,
) -> list:
    """Byte chunks of one ``.vtu`` file; large arrays are passed through as buffers so
    they reach the file without an intermediate copy."""
    points_da = _DataArray("Points", points, 3)
    cells_das = [_DataArray("connectivity", connectivity, 1),
                 _DataArray("offsets", offsets, 1),
                 _DataArray("types", types, 1)]
    # Appended blocks go in the *reverse* of their XML order. VTK does not care, but
    # meshio's raw reader renumbers offset attributes in place while looking them up
    # by value, so a renumbered early array can shadow a later one whose raw offset
    # happens to equal the new number (seen with N=1); in reverse order every
    # renumbered tag sits after the one being looked up, and find() hits the right tag.
    blocks = list(itertools.chain(point_arrays, cell_arrays, [points_da], cells_das))
    blocks.reverse()
    block_offset = {}
    if mode == "raw":
        offset = 0
        for da in blocks:
            block_offset[id(da)] = offset
            offset += 8 + da.data.nbytes

    def tag(da: _DataArray, indent: str) -> str:
        return _data_array_tag(da, mode, block_offset.get(id(da), 0), indent)

    n_points = points.shape[0]
    n_cells = types.shape[0]
    x = ['<?xml version="1.0"?>\n'
         '<VTKFile type="UnstructuredGrid" version="1.0" byte_order="LittleEndian" '
         'header_type="UInt64">\n'
         '  <UnstructuredGrid>\n']
    if time_s is not None:
        # TimeValue lets ParaView show the right time even when a single frame file is
        # opened without its .pvd.
        x.append('    <FieldData>\n'
                 '      <DataArray type="Float64" Name="TimeValue" NumberOfTuples="1" '
                 f'format="ascii">{float(time_s)!r}</DataArray>\n'
                 '    </FieldData>\n')
    x.append(f'    <Piece NumberOfPoints="{n_points}" NumberOfCells="{n_cells}">\n')
    if point_arrays:
        x.append("      <PointData>\n")
        x.extend(tag(da, "        ") for da in point_arrays)
        x.append("      </PointData>\n")
    if cell_arrays:
        x.append("      <CellData>\n")
        x.extend(tag(da, "        ") for da in cell_arrays)
        x.append("      </CellData>\n")
    x.append("      <Points>\n")
    x.append(tag(points_da, "        "))
    x.append("      </Points>\n      <Cells>\n")
    x.extend(tag(da, "        ") for da in cells_das)
    x.append("      </Cells>\n    </Piece>\n  </UnstructuredGrid>\n")
    if mode != "raw":
        x.append("</VTKFile>\n")
        return ["".join(x).encode("utf-8")]
    x.append('  <AppendedData encoding="raw">\n   _')
    chunks: list = ["".join(x).encode("utf-8")]
    for da in blocks:
        chunks.append(struct.pack("<Q", da.data.nbytes))
        if da.data.nbytes:
            chunks.append(memoryview(da.data).cast("B"))
    # The newline before the closing tag is required by meshio's raw reader, which
    # strips everything after the last newline of the appended section.
    chunks.append(b"\n  </AppendedData>\n</VTKFile>\n")
    return chunks


def write_surface_vtu(
    path: str,
    meshes: Sequence[tuple],
    binary: bool = True,
    encoding: str = "raw",
    fsync: bool = True,
    tables: Sequence[int] | None = None,
) -> str:
    """Write triangle/quad surface meshes into one ``.vtu`` file (atomically).

    ``meshes`` is a sequence of ``(vertices (K, 3), faces (F, 3) or (F, 4) int)``;
    faces index that mesh's own vertices. The cell array ``wall_id`` records which
    mesh (position in ``meshes``) each face came from, so ParaView can colour or
    threshold individual walls; ``tables`` (one int per mesh), written as the cell
    array ``wall_table``, which ``[[walls]]`` table of the scenario it belongs to (a
    box is five or six meshes of one table).
    """
    if tables is not None and len(tables) != len(meshes):
        raise ValueError(f"tables: one per mesh, got {len(tables)} for {len(meshes)} meshes")
    mode = _mode(binary, encoding)
    pts, conn, offs, types, wall_id, wall_table = [], [], [], [], [], []
    n_vert = 0
    n_conn = 0
    for i, mesh in enumerate(meshes):
        try:
            vertices, faces = mesh
        except (TypeError, ValueError):
            raise ValueError(f"wall mesh {i} must be a (vertices, faces) pair") from None
        v = _as_f64(vertices, (3,), f"wall mesh {i} vertices")
        f = np.asarray(faces)
        if f.ndim != 2 or f.shape[1] not in (3, 4):
            raise ValueError(f"wall mesh {i} faces must have shape (F, 3) or (F, 4); "
                             f"got {f.shape}")
        if f.size and not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"wall mesh {i} faces must be integers; got {f.dtype}")
        f = f.astype(_I64)
        if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
            raise ValueError(f"wall mesh {i} faces index vertices outside 0..{v.shape[0] - 1}")
        k = f.shape[1]
        pts.append(v)
        conn.append((f + n_vert).ravel())
        offs.append(n_conn + k * np.arange(1, f.shape[0] + 1, dtype=_I64))
        types.append(np.full(f.shape[0], _VTK_TRIANGLE if k == 3 else _VTK_QUAD, dtype=_U8))
        wall_id.append(np.full(f.shape[0], i, dtype=_I64))
        if tables is not None:
            wall_table.append(np.full(f.shape[0], int(tables[i]), dtype=_I64))
        n_vert += v.shape[0]
        n_conn += f.size

    def cat(parts, dtype, shape=(0,)):
        return np.ascontiguousarray(np.concatenate(parts), dtype=dtype) if parts \
            else np.zeros(shape, dtype=dtype)

    chunks = _unstructured_grid_chunks(
        cat(pts, _F64, (0, 3)),
        cat(conn, _I64),
        cat(offs, _I64),
        cat(types, _U8),
        [],
        [_DataArray("wall_id", cat(wall_id, _I64), 1)]
        + ([_DataArray("wall_table", cat(wall_table, _I64), 1)] if tables is not None else []),
        mode,
    )
    _atomic_write(path, chunks, fsync)
    return path


def _mode(binary: bool, encoding: str) -> str:
    if encoding not in _ENCODINGS:
        raise ValueError(f"encoding must be one of {_ENCODINGS}; got {encoding!r}")
    return encoding if binary else "ascii"


# --------------------------------------------------------------------------------------
# the series writer
# --------------------------------------------------------------------------------------


class _Collection:
    """A ``.pvd`` file kept in memory and rewritten whole (atomically) on every frame;
    rewriting is cheap next to a frame and means the file on disk is always valid."""

    def __init__(self, path: str):
        self.path = path
        self.entries: list[str] = []
        self.frames: list[tuple[float, str]] = []

    @staticmethod
    def _entry(time_s: float, filename: str) -> str:
        return f'    <DataSet timestep="{time_s!r}" group="" part="0" file={quoteattr(filename)}/>\n'

    def restore(self, frames) -> None:
        """Take over the frames of an earlier series (a resumed run); written at the next append."""
        self.frames = [(float(t), str(name)) for t, name in frames]
        self.entries = [self._entry(t, name) for t, name in self.frames]

    def append(self, time_s: float, filename: str) -> _PendingFile:
        """Add a frame and write the new .pvd under a temp name; pop() undoes it."""
        self.frames.append((time_s, filename))
        self.entries.append(self._entry(time_s, filename))
        text = ('<?xml version="1.0"?>\n'
                '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
                "  <Collection>\n" + "".join(self.entries) + "  </Collection>\n</VTKFile>\n")
        try:
            return _PendingFile(self.path, [text.encode("utf-8")])
        except BaseException:
            self.pop()
            raise

    def pop(self) -> None:
        self.frames.pop()
        self.entries.pop()


class VTKSeriesWriter:
    """Write particle (and contact) frames as ``.vtu`` files plus ``.pvd`` collections.

    Files in ``directory``:

    * ``{prefix}_{i:06d}.vtu`` -- frame ``i``: particle centres [m] as points, one
      vertex cell per particle, point arrays ``radius`` [m], ``velocity`` [m/s],
      ``angular_velocity`` [rad/s], ``force`` [N], ``particle_id``, ``material_id``
      (plus any ``extra_point_arrays``); the frame time [s] is also stored as field
      data ``TimeValue``.
    * ``{prefix}.pvd`` -- every particle frame with its time.
    * ``{prefix}_contacts_{i:06d}.vtu`` / ``{prefix}_contacts.pvd`` -- only for frames
      given ``contact_pairs``: the same points (particle centres, same order as the
      particle file), one line cell per contact, cell array ``normal_force`` [N].
      Reusing the particle points instead of two end points per contact keeps the
      file small (dense packings have ~3 contacts per particle).
    * ``walls.vtu`` (or the name given) -- from :meth:`write_walls`.

    ``binary=True`` writes raw appended binary (fastest, smallest);
    ``encoding="base64"`` makes binary files pure ASCII/XML-valid at ~1/3 more size
    and some CPU; ``binary=False`` writes human-readable ASCII for debugging (slow for
    large N, but values round-trip exactly).

    Durability: every file is written under a hidden temp name and ``os.replace``'d,
    so readers and a killed process never see a torn file. ``fsync=True`` (default)
    also survives an OS crash / power loss. Waiting for the disk is by far the largest
    cost of a frame, so with ``background_sync=True`` (default) the fsync + rename of a
    frame runs on a helper thread while the simulation continues: ``write_frame``
    returns once the bytes are in the OS page cache (the input arrays may then be
    modified), and the frame appears under its final name, and in the ``.pvd``, a
    moment later. At most one frame is in flight: the next ``write_frame`` (or
    ``flush``/``close``) first waits for it and re-raises any error it hit, in which
    case that frame is left out of the ``.pvd`` (and a ``write_frame`` that raises it
    writes nothing itself). ``background_sync=False`` does everything in the calling
    thread.

    Each writer starts a fresh series: an existing ``.pvd`` of the same prefix in
    ``directory`` is replaced at the first frame.

    The writer is not thread-safe; use one writer per series and call it from one
    thread.
    """

    def __init__(
        self,
        directory,
        prefix: str = "particles",
        binary: bool = True,
        *,
        encoding: str = "raw",
        fsync: bool = True,
        background_sync: bool = True,
    ):
        if not prefix or os.sep in prefix or (os.altsep and os.altsep in prefix):
            raise ValueError(f"prefix must be a plain file-name stem; got {prefix!r}")
        self.directory = os.fspath(directory)
        self.prefix = prefix
        self.binary = bool(binary)
        self.encoding = encoding
        self._mode = _mode(self.binary, encoding)
        self.fsync = bool(fsync)
        # Without fsync there is nothing slow left to hide behind a thread.
        self.background_sync = bool(background_sync) and self.fsync
        os.makedirs(self.directory, exist_ok=True)
        self._particles = _Collection(os.path.join(self.directory, f"{prefix}.pvd"))
        self._contacts = _Collection(os.path.join(self.directory, f"{prefix}_contacts.pvd"))
        self._frame_index = 0
        self._closed = False
        self._job: _SyncJob | None = None
        self._job_collections: list[_Collection] = []
        # Vertex-cell topology depends only on N, which rarely changes during a run.
        self._vertex_cells_n = -1
        self._vertex_cells: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    # -- properties ---------------------------------------------------------------------

    @property
    def pvd_path(self) -> str:
        return self._particles.path

    @property
    def contacts_pvd_path(self) -> str:
        return self._contacts.path

    @property
    def frames(self) -> list[tuple[float, str]]:
        """(time [s], file name relative to ``directory``) of every particle frame
        written so far (including one still being synced in the background)."""
        return list(self._particles.frames)

    @property
    def contact_frames(self) -> list[tuple[float, str]]:
        return list(self._contacts.frames)

    @property
    def closed(self) -> bool:
        return self._closed

    # -- writing ------------------------------------------------------------------------

    def _vertex_topology(self, n: int):
        if n != self._vertex_cells_n:
            connectivity = np.arange(n, dtype=_I64)
            self._vertex_cells = (connectivity, connectivity + 1,
                                  np.full(n, _VTK_VERTEX, dtype=_U8))
            self._vertex_cells_n = n
        return self._vertex_cells

    def write_frame(
        self,
        time_s: float,
        positions,
        radii,
        velocities,
        angular_velocities,
        forces,
        particle_ids,
        material_ids,
        contact_pairs=None,
        contact_normal_force=None,
        *,
        extra_point_arrays: Mapping[str, object] | None = None,
        extra_contact_arrays: Mapping[str, object] | None = None,
    ) -> str:
        """Write one frame; returns the (final) path of the particle ``.vtu``.

        Arrays are per particle (N rows): positions/velocities/angular_velocities/
        forces (N, 3), radii/particle_ids/material_ids (N,). ``contact_pairs`` (M, 2)
        holds row indices into these arrays (not particle ids); ``contact_normal_force``
        (M,) [N] requires ``contact_pairs``. The inputs are only read, and may be
        modified as soon as this returns.
        """
        self._check_open("write_frame")
        time_s = float(time_s)
        if not np.isfinite(time_s):
            raise ValueError(f"time_s must be finite; got {time_s}")

        pos = _as_f64(positions, (3,), "positions")
        n = pos.shape[0]
        point_arrays = [
            _DataArray("radius", _as_f64(radii, (), "radii", n), 1),
            _DataArray("velocity", _as_f64(velocities, (3,), "velocities", n), 3),
            _DataArray("angular_velocity",
                       _as_f64(angular_velocities, (3,), "angular_velocities", n), 3),
            _DataArray("force", _as_f64(forces, (3,), "forces", n), 3),
            _DataArray("particle_id", _as_i64(particle_ids, "particle_ids", n), 1),
            _DataArray("material_id", _as_i64(material_ids, "material_ids", n), 1),
        ]
        _add_extras(point_arrays, extra_point_arrays, n, "extra point array")

        contact_chunks = None
        if contact_pairs is not None:
            contact_chunks = self._contact_chunks(
                pos, contact_pairs, contact_normal_force, extra_contact_arrays, time_s)
        elif contact_normal_force is not None or extra_contact_arrays:
            raise ValueError("contact data given without contact_pairs")

        conn, offs, types = self._vertex_topology(n)
        chunks = _unstructured_grid_chunks(pos, conn, offs, types, point_arrays, [],
                                           self._mode, time_s)

        # Bound the work in flight to one frame, and surface its errors here.
        self._wait()

        i = self._frame_index
        name = f"{self.prefix}_{i:06d}.vtu"
        path = os.path.join(self.directory, name)
        frame_files: list[_PendingFile] = []
        pvd_files: list[_PendingFile] = []
        touched: list[_Collection] = []
        try:
            frame_files.append(_PendingFile(path, chunks))
            if contact_chunks is not None:
                cname = f"{self.prefix}_contacts_{i:06d}.vtu"
                frame_files.append(
                    _PendingFile(os.path.join(self.directory, cname), contact_chunks))
                pvd_files.append(self._contacts.append(time_s, cname))
                touched.append(self._contacts)
            pvd_files.append(self._particles.append(time_s, name))
            touched.append(self._particles)
        except BaseException:
            for pending in frame_files + pvd_files:
                pending.abort()
            for collection in touched:
                collection.pop()
            raise
        self._frame_index += 1

        # Frame files first, .pvd files second: a collection never lists a file that
        # is not complete on disk.
        stages = [frame_files, pvd_files]
        if self.background_sync:
            self._job = _SyncJob(stages, self.directory, self.fsync)
            self._job_collections = touched
            self._job.start()
        else:
            try:
                _commit_stages(stages, self.directory, self.fsync)
            except BaseException:
                for collection in touched:
                    collection.pop()
                raise
        return path

    def _contact_chunks(self, pos, contact_pairs, normal_force, extras, time_s):
        n = pos.shape[0]
        pairs = np.asarray(contact_pairs)
        if pairs.size == 0:
            pairs = pairs.reshape(0, 2)
        if pairs.ndim != 2 or pairs.shape[1] != 2:
            raise ValueError(f"contact_pairs must have shape (M, 2); got {pairs.shape}")
        if pairs.size and not np.issubdtype(pairs.dtype, np.integer):
            raise ValueError(f"contact_pairs must be integers; got dtype {pairs.dtype}")
        m = pairs.shape[0]
        # An out-of-range index would make ParaView read past the point array.
        if m and (pairs.min() < 0 or pairs.max() >= n):
            raise ValueError(f"contact_pairs must index particles 0..{n - 1}")
        connectivity = np.ascontiguousarray(pairs, dtype=_I64).reshape(-1)
        offsets = np.arange(2, 2 * m + 1, 2, dtype=_I64)
        types = np.full(m, _VTK_LINE, dtype=_U8)
        cell_arrays = []
        if normal_force is not None:
            cell_arrays.append(_DataArray(
                "normal_force", _as_f64(normal_force, (), "contact_normal_force", m), 1))
        _add_extras(cell_arrays, extras, m, "extra contact array")
        return _unstructured_grid_chunks(pos, connectivity, offsets, types, [], cell_arrays,
                                         self._mode, time_s)

    def _earlier_series(self, directory: str) -> list[str]:
        """The files of a series of this name in ``directory``: the collections
        (``{prefix}.pvd``, ``{prefix}_contacts.pvd``) and the frames they list, named
        ``{prefix}_NNNNNN.vtu`` or ``{prefix}_contacts_NNNNNN.vtu`` (never another file of
        the directory, whatever its name)."""
        from xml.etree import ElementTree

        pattern = re.compile(rf"{re.escape(self.prefix)}(_contacts)?_\d{{6}}\.vtu")
        found = []
        for collection in (f"{self.prefix}.pvd", f"{self.prefix}_contacts.pvd"):
            path = os.path.join(directory, collection)
            try:
                listed = [entry.get("file", "") for entry in ElementTree.parse(path).getroot().iter("DataSet")]
            except (OSError, ElementTree.ParseError):  # none, or not one minidem wrote
                continue
            found.append(collection)
            found += [name for name in listed if pattern.fullmatch(name)
                      and os.path.isfile(os.path.join(directory, name))
                      and not os.path.islink(os.path.join(directory, name))]
        return found

    def set_aside_earlier_frames(self, folder: str) -> str | None:
        """Move the series an earlier run left in the directory into its subfolder
        ``folder`` (the collections' relative names still resolve there), before the first
        frame of a run that does not continue a series: a shorter run writes fewer frames,
        and ParaView's file dialog groups every ``particles_*.vtu`` into one series, the
        two runs' frames mixed. Kept there until the run succeeds
        (:meth:`discard_set_aside`): a run that fails leaves the earlier run's series
        whole (a robustness review found it deleted at the first frame). When ``folder``
        exists already (left by a run that failed: it holds the series before it), the
        series here, that failed run's, is deleted instead. Returns the folder's path
        when something was moved."""
        from minidem.files import output_error

        names = self._earlier_series(self.directory)
        aside = os.path.join(self.directory, folder)
        if not names:
            return None
        try:
            if self._earlier_series(aside):  # a series set aside already (by a run that then failed)
                for name in names:
                    if name.endswith(".vtu"):
                        os.remove(os.path.join(self.directory, name))
                return None
            os.makedirs(aside, exist_ok=True)
            # the frames first, the collections last: a collection never lists a frame not there
            for name in sorted(names, key=lambda n: n.endswith(".pvd")):
                os.replace(os.path.join(self.directory, name), os.path.join(aside, name))
        except OSError as exc:  # a file named like the folder, permissions, a full disk
            raise output_error(aside, exc) from None
        return aside

    def discard_set_aside(self, folder: str) -> int:
        """After a run that succeeded: delete the earlier series in ``folder`` (its files
        only; the folder too once empty). Returns how many files were removed."""
        import warnings

        aside = os.path.join(self.directory, folder)
        names = self._earlier_series(aside)
        if os.path.isfile(os.path.join(aside, "walls.vtu")):  # put there by set_aside_unwritten_series
            names.append("walls.vtu")
        try:
            # the collections last: after a failure they still list what is left, for the next run
            for name in sorted(names, key=lambda n: n.endswith(".pvd")):
                os.remove(os.path.join(aside, name))
        except OSError as exc:  # the run itself succeeded: say so, do not fail it
            warnings.warn(f"could not remove the earlier VTK series in {aside}: {exc.strerror or exc}", stacklevel=2)
            return 0
        try:
            os.rmdir(aside)
        except OSError:  # absent, or holding files of the user's
            pass
        return len(names)

    def write_walls(self, meshes: Sequence[tuple], name: str = "walls", tables: Sequence[int] | None = None) -> str:
        """Write wall surfaces once, as ``{directory}/{name}.vtu``; returns the path.

        ``meshes``: list of ``(vertices (K, 3) [m], faces (F, 3) or (F, 4) int)``; use
        :func:`plane_to_quad` for infinite planes. Calling again overwrites the file
        (atomically), e.g. after walls have moved. Written synchronously: it is a
        one-off and small.
        """
        self._check_open("write_walls")
        if not name or os.sep in name or (os.altsep and os.altsep in name):
            raise ValueError(f"name must be a plain file-name stem; got {name!r}")
        path = os.path.join(self.directory, f"{name}.vtu")
        return write_surface_vtu(path, meshes, self.binary, self.encoding, self.fsync, tables)

    plane_to_quad = staticmethod(plane_to_quad)

    def restore(self, frames, contact_frames=()) -> None:
        """Continue an earlier series (a resumed run): its frames ((time s, file name)
        lists, as :attr:`frames` and :attr:`contact_frames` gave them) stay in the
        ``.pvd`` files, and the next frame gets the next index, overwriting any file a
        killed process wrote after them."""
        self._check_open("restore")
        self._wait()
        self._particles.restore(frames)
        self._contacts.restore(contact_frames)
        self._frame_index = len(self._particles.frames)

    def flush(self) -> None:
        """Wait until every frame written so far is renamed into place (and durable if
        ``fsync``); re-raises an error from the background sync."""
        self._wait()

    def _wait(self) -> None:
        job = self._job
        if job is None:
            return
        job.join()
        # Cleared only after join(): a Ctrl-C during join() must not lose track of the
        # frame in flight (its rollback would never happen).
        self._job = None
        if job.error is not None:
            for collection in self._job_collections:
                collection.pop()
            self._job_collections = []
            raise job.error
        self._job_collections = []

    def _check_open(self, what: str) -> None:
        if self._closed:
            raise RuntimeError(f"{what}() on a closed VTKSeriesWriter")

    def close(self) -> None:
        """Wait for the last frame to land and refuse further writes; idempotent."""
        try:
            self._wait()
        finally:
            self._closed = True

    def __enter__(self) -> "VTKSeriesWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _add_extras(out: list, extras, n: int, what: str) -> None:
    if not extras:
        return
    taken = {da.name for da in out}
    for key, value in extras.items():
        if key in taken:
            raise ValueError(f"{what} {key!r} clashes with an existing array name")
        out.append(_extra_array(key, value, n, what))
        taken.add(key)


def _benchmark(sizes=(20_000, 200_000), frames: int = 10,
               sim_time_between_frames_s: float = 0.5) -> None:  # pragma: no cover
    import tempfile
    import time

    rng = np.random.default_rng(0)
    for n in sizes:
        state = dict(
            positions=rng.random((n, 3)), radii=rng.random(n),
            velocities=rng.random((n, 3)), angular_velocities=rng.random((n, 3)),
            forces=rng.random((n, 3)), particle_ids=np.arange(n),
            material_ids=np.zeros(n, dtype=np.int64),
        )
        pairs = rng.integers(0, n, size=(3 * n, 2))
        fn = rng.random(3 * n)
        for label, kw, contacts in (
            ("raw, fsync in background", dict(), False),
            ("raw, fsync in loop thread", dict(background_sync=False), False),
            ("raw, no fsync", dict(fsync=False), False),
            ("raw, bg fsync, +3N contacts", dict(), True),
            ("base64, bg fsync", dict(encoding="base64"), False),
        ):
            with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_DIR")) as d:
                w = VTKSeriesWriter(d, **kw)
                extra = dict(contact_pairs=pairs, contact_normal_force=fn) if contacts else {}
                w.write_frame(0.0, **state, **extra)  # warm-up
                spent = 0.0  # time the simulation thread is blocked in the writer
                for k in range(frames):
                    time.sleep(sim_time_between_frames_s)  # the DEM steps in between
                    t0 = time.perf_counter()
                    w.write_frame(k * 1e-3, **state, **extra)
                    spent += time.perf_counter() - t0
                w.close()
                dt = spent / frames
                size = os.path.getsize(os.path.join(d, "particles_000001.vtu"))
                print(f"N={n:>7} {label:<28} {dt * 1e3:8.2f} ms/frame  "
                      f"({size / 1e6:.1f} MB particle file)")


if __name__ == "__main__":  # pragma: no cover
    _benchmark()


# the subfolder an earlier run's series waits in while a run writes its own (kept if it fails)
PREVIOUS_SERIES = "previous_series"


def set_aside_unwritten_series(directory) -> str | None:
    """A run that succeeded without writing a VTK series (``output.vtk = false``, or a
    scene whose output has none) into a directory holding an earlier run's series and
    ``walls.vtu``: they would read as this run's (``minidem.open_results``, ParaView), so
    they go where a run with frames puts them at its first frame, PREVIOUS_SERIES (a
    failed run's frames are deleted when that folder holds a series already; the folder
    is emptied by the next run with frames that succeeds). Returns what to tell the
    user, or None when there was nothing."""
    from minidem.files import output_error

    writer = VTKSeriesWriter(directory, "particles")
    earlier = writer._earlier_series(writer.directory)
    walls = os.path.join(writer.directory, "walls.vtu")
    has_walls = os.path.isfile(walls) and not os.path.islink(walls)
    if not earlier and not has_walls:
        return None
    aside = os.path.join(writer.directory, PREVIOUS_SERIES)
    writer.set_aside_earlier_frames(PREVIOUS_SERIES)
    try:
        # left when the folder held a series already: the collections, which list the
        # frames just deleted, and the walls
        for name in (f"{writer.prefix}.pvd", f"{writer.prefix}_contacts.pvd"):
            if name in earlier and os.path.isfile(os.path.join(writer.directory, name)):
                os.remove(os.path.join(writer.directory, name))
        if has_walls:
            os.makedirs(aside, exist_ok=True)
            if os.path.exists(os.path.join(aside, "walls.vtu")):  # the older series' walls
                os.remove(walls)
            else:
                os.replace(walls, os.path.join(aside, "walls.vtu"))
    except OSError as exc:
        raise output_error(aside, exc) from None
    return (f"{writer.directory}: the VTK series there is an earlier run's (this run wrote none): moved to "
            f"{aside}/ (or deleted where that folder holds an older one), as a run with frames does")


class SimulationFrames:
    """The ``on_frame`` callback of :meth:`minidem.engine.simulation.Simulation.run` that writes a
    ParaView series: ``particles.pvd`` (+ ``particles_contacts.pvd`` when the scene asks
    for the contact network) and ``walls.vtu``, all in ``directory``.

    Frames are binary (raw appended); the disk sync runs on a helper thread, so the
    simulation waits only for the bytes to reach the page cache.
    """

    def __init__(self, simulation, directory):
        from minidem.geometry.walls import display_meshes

        # frames in the scenario's order, whatever order the engine stores the particles in
        # (Scene.reordered; a run may sort them again): row k of every frame is particle k
        self.simulation = simulation
        scene = simulation.input_scene
        self.scene = scene
        self.writer = VTKSeriesWriter(directory, "particles")
        self.ids = np.arange(scene.n_particles, dtype=np.int64)
        lower = (scene.position - scene.radius[:, None]).min(axis=0)
        upper = (scene.position + scene.radius[:, None]).max(axis=0)
        meshes = display_meshes(scene.walls, lower, upper)
        self.walls_path = self.writer.write_walls(meshes, tables=scene.walls.display_tables()) if meshes else None
        self.frames = 0
        self.continues = False  # a resumed run's series (restore): its earlier frames are its own

    def __call__(self, time_s, state) -> None:
        if self.frames == 0 and not self.continues:
            self.writer.set_aside_earlier_frames(PREVIOUS_SERIES)
        self.write(time_s, state)

    def succeeded(self) -> None:
        """The run succeeded and its files are written: an earlier run's series set aside
        (PREVIOUS_SERIES) is replaced by this one's."""
        self.writer.discard_set_aside(PREVIOUS_SERIES)

    def write(self, time_s, state) -> None:
        pairs, normal_force = state.contact_pairs() if self.scene.vtk_contacts else (None, None)
        stored = self.simulation.scene
        if pairs is not None and stored.particle_id is not None:
            pairs = stored.particle_id[pairs]
        ordered = stored.in_scenario_order
        self.writer.write_frame(time_s, ordered(state.position), self.scene.radius, ordered(state.velocity),
                                ordered(state.angular_velocity), ordered(state.force), self.ids,
                                self.scene.particle_material, pairs, normal_force)
        self.frames += 1

    def checkpoint_state(self) -> dict:
        """The series so far, for a checkpoint: every frame listed is complete on disk."""
        self.writer.flush()
        return {"particles": self.writer.frames, "contacts": self.writer.contact_frames}

    def restore(self, saved: dict, frames: int) -> None:
        """Continue the series of a checkpoint (``frames`` frames written)."""
        self.writer.restore(saved["particles"][:frames], saved["contacts"][:frames])
        self.frames = frames
        self.continues = True

    def close(self) -> None:
        self.writer.close()

    @property
    def pvd_path(self) -> str:
        return self.writer.pvd_path
