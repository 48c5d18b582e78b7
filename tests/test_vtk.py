"""Tests for minidem.results.vtk: files are checked with two independent readers (meshio's
pure-Python parser and VTK's own XML readers, which is what ParaView uses)."""

import os
import random
import signal
import subprocess
import sys
import textwrap
import time
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest
import pyvista as pv
import vtk
from vtk.util.numpy_support import vtk_to_numpy

import minidem.results.vtk as vtkmod
from minidem.results.vtk import VTKSeriesWriter, plane_to_quad, write_surface_vtu

REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

POINT_ARRAYS = ("radius", "velocity", "angular_velocity", "force", "particle_id",
                "material_id")

# (binary, encoding): raw appended, base64 inline, ascii
MODES = [(True, "raw"), (True, "base64"), (False, "raw")]
MODE_IDS = ["raw", "base64", "ascii"]


def make_state(n, seed=0):
    rng = np.random.default_rng(seed)
    return dict(
        positions=rng.normal(size=(n, 3)),
        # wide dynamic range so ascii round-tripping is actually exercised
        radii=rng.uniform(1e-4, 1e-3, n) * 10.0 ** rng.integers(-3, 3, n),
        velocities=rng.normal(size=(n, 3)),
        angular_velocities=rng.normal(size=(n, 3)) * 1e3,
        forces=rng.normal(size=(n, 3)) * 1e-7,
        particle_ids=rng.permutation(n).astype(np.int64) + 10_000_000_000,
        material_ids=rng.integers(0, 4, n),
    )


def expected_point_arrays(state):
    return dict(radius=state["radii"], velocity=state["velocities"],
                angular_velocity=state["angular_velocities"], force=state["forces"],
                particle_id=state["particle_ids"], material_id=state["material_ids"])


def vtk_read(path):
    """Read with VTK's own XML reader and fail on any VTK error or warning."""
    reader = (vtk.vtkXMLPolyDataReader() if path.endswith(".vtp")
              else vtk.vtkXMLUnstructuredGridReader())
    messages = []
    for event in ("ErrorEvent", "WarningEvent"):
        reader.AddObserver(event, lambda obj, ev: messages.append(ev))
    reader.SetFileName(path)
    reader.Update()
    assert not messages, f"VTK reported {messages} for {path}"
    assert reader.GetErrorCode() == 0
    return reader.GetOutput()


def _cell_types(grid):
    # GetCellTypesArray() is deprecated since VTK 9.6 in favour of GetCellTypes(),
    # which returned a different kind of object before.
    types = grid.GetCellTypes()
    if isinstance(types, vtk.vtkDataArray):
        return vtk_to_numpy(types)
    return vtk_to_numpy(grid.GetCellTypesArray())


def vtk_cell_arrays(grid):
    cells = grid.GetCells()
    return (vtk_to_numpy(cells.GetConnectivityArray()).astype(np.int64),
            vtk_to_numpy(cells.GetOffsetsArray()).astype(np.int64),
            np.asarray(_cell_types(grid)).astype(np.int64))


def parse_pvd(path):
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    return [(float(ds.get("timestep")), ds.get("file")) for ds in root.iter("DataSet")]


def leftover_temp_files(directory):
    return [f for f in os.listdir(directory) if f.startswith(".") or f.endswith(".tmp")]


def check_particle_file(path, state, time_s):
    n = state["positions"].shape[0]
    expected = expected_point_arrays(state)

    grid = vtk_read(path)
    assert grid.GetNumberOfPoints() == n
    assert grid.GetNumberOfCells() == n
    points = grid.GetPoints()
    if n:
        np.testing.assert_array_equal(vtk_to_numpy(points.GetData()), state["positions"])
    conn, offsets, types = vtk_cell_arrays(grid)
    np.testing.assert_array_equal(conn, np.arange(n))
    np.testing.assert_array_equal(types, np.full(n, vtk.VTK_VERTEX))
    pd = grid.GetPointData()
    for name in POINT_ARRAYS:
        arr = pd.GetArray(name)
        assert arr is not None, name
        assert arr.GetNumberOfTuples() == n
        got = vtk_to_numpy(arr)
        want = expected[name]
        assert got.shape == want.shape, name
        np.testing.assert_array_equal(got, want, err_msg=name)
        if name in ("particle_id", "material_id"):
            assert arr.GetDataType() == vtk.VTK_LONG_LONG or arr.GetDataType() == vtk.VTK_LONG
        else:
            assert arr.GetDataType() == vtk.VTK_DOUBLE
    assert points is None or points.GetDataType() == vtk.VTK_DOUBLE
    assert grid.GetFieldData().GetArray("TimeValue").GetValue(0) == time_s

    # pyvista.read goes through the same VTK reader, but also proves the file opens the
    # way users will typically open it.
    mesh = pv.read(path)
    assert mesh.n_points == n
    assert set(POINT_ARRAYS) <= set(mesh.point_data.keys())

    if n == 0:
        return  # meshio 5.3.5 cannot read files with zero cells (even its own)
    m = meshio.read(path)
    np.testing.assert_array_equal(m.points, state["positions"])
    assert [c.type for c in m.cells] == ["vertex"]
    np.testing.assert_array_equal(m.cells[0].data.ravel(), np.arange(n))
    for name in POINT_ARRAYS:
        assert m.point_data[name].shape == expected[name].shape, name
        np.testing.assert_array_equal(m.point_data[name], expected[name], err_msg=name)
    assert m.field_data["TimeValue"][0] == time_s


# --------------------------------------------------------------------------------------
# particle frames and .pvd
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("binary", "encoding"), MODES, ids=MODE_IDS)
def test_frames_round_trip_and_pvd(tmp_path, binary, encoding):
    # N changes between frames (particles inserted/removed); N=1 once tripped meshio's
    # raw-appended reader (see the block-order comment in vtk.py)
    sizes = [7, 50, 1, 33]
    times = [0.0, 1e-4, 2.5e-4, 1.0 / 3.0]
    states = [make_state(n, seed=k) for k, n in enumerate(sizes)]
    with VTKSeriesWriter(tmp_path, prefix="bed", binary=binary, encoding=encoding) as w:
        paths = [w.write_frame(t, **s) for t, s in zip(times, states)]
    assert w.closed

    assert [os.path.basename(p) for p in paths] == [f"bed_{i:06d}.vtu" for i in range(4)]
    for path, state, t in zip(paths, states, times):
        check_particle_file(path, state, t)

    entries = parse_pvd(tmp_path / "bed.pvd")
    assert [t for t, _ in entries] == times  # exact: timesteps are written with repr()
    assert [f for _, f in entries] == [os.path.basename(p) for p in paths]
    for _, f in entries:
        assert not os.path.isabs(f) and os.sep not in f
        assert (tmp_path / f).is_file()
    assert w.frames == list(zip(times, [os.path.basename(p) for p in paths]))
    assert not (tmp_path / "bed_contacts.pvd").exists()  # no contacts were given

    # The collection as ParaView-like readers see it.
    reader = pv.get_reader(str(tmp_path / "bed.pvd"))
    assert reader.time_values == times
    for k, t in enumerate(times):
        reader.set_active_time_value(t)
        assert reader.read()[0].n_points == sizes[k]

    assert leftover_temp_files(tmp_path) == []


@pytest.mark.parametrize(("binary", "encoding"), MODES[1:], ids=MODE_IDS[1:])
def test_text_modes_are_well_formed_xml(tmp_path, binary, encoding):
    with VTKSeriesWriter(tmp_path, binary=binary, encoding=encoding) as w:
        path = w.write_frame(0.0, **make_state(20))
    root = ET.parse(path).getroot()  # raw appended data is not XML by design; these are
    formats = {da.get("format") for da in root.iter("DataArray")}
    assert formats <= {"binary" if binary else "ascii", "ascii"}


@pytest.mark.parametrize("background_sync", [True, False])
@pytest.mark.parametrize("fsync", [True, False])
def test_sync_options_and_no_temp_files(tmp_path, fsync, background_sync):
    state = make_state(100)
    w = VTKSeriesWriter(tmp_path, fsync=fsync, background_sync=background_sync)
    for k in range(5):
        w.write_frame(k * 0.1, **state, contact_pairs=[[0, 1], [2, 3]],
                      contact_normal_force=[1.0, 2.0])
    w.close()
    w.close()  # idempotent
    assert leftover_temp_files(tmp_path) == []
    assert len(parse_pvd(tmp_path / "particles.pvd")) == 5
    assert len(parse_pvd(tmp_path / "particles_contacts.pvd")) == 5
    assert sorted(os.listdir(tmp_path)) == sorted(
        ["particles.pvd", "particles_contacts.pvd"]
        + [f"particles_{k:06d}.vtu" for k in range(5)]
        + [f"particles_contacts_{k:06d}.vtu" for k in range(5)])


def test_inputs_may_be_modified_right_after_write_frame(tmp_path):
    state = make_state(1000)
    snapshot = {k: v.copy() for k, v in state.items()}
    with VTKSeriesWriter(tmp_path) as w:  # background sync: file lands later
        path = w.write_frame(0.5, **state)
        for v in state.values():
            v[...] = 0
    check_particle_file(path, snapshot, 0.5)


def test_inputs_converted_to_float64_and_int64(tmp_path):
    state = make_state(40)
    odd = dict(state)
    odd["positions"] = np.asfortranarray(state["positions"].astype(np.float32))
    odd["velocities"] = state["velocities"][:, :].T.copy().T  # non-C-contiguous
    odd["radii"] = state["radii"].astype(np.float32)
    odd["particle_ids"] = (state["particle_ids"] - 10_000_000_000).astype(np.int32)
    odd["material_ids"] = state["material_ids"].astype(np.uint8)
    odd["forces"] = state["forces"].tolist()
    with VTKSeriesWriter(tmp_path) as w:
        path = w.write_frame(0.0, **odd)
    want = dict(state)
    want["positions"] = odd["positions"].astype(np.float64)
    want["radii"] = odd["radii"].astype(np.float64)
    want["particle_ids"] = odd["particle_ids"].astype(np.int64)
    check_particle_file(path, want, 0.0)


@pytest.mark.parametrize(("binary", "encoding"), MODES, ids=MODE_IDS)
def test_empty_frame(tmp_path, binary, encoding):
    state = make_state(0)
    with VTKSeriesWriter(tmp_path, binary=binary, encoding=encoding) as w:
        p0 = w.write_frame(0.0, **state)
        p1 = w.write_frame(1e-3, **state, contact_pairs=np.zeros((0, 2), dtype=np.int64),
                           contact_normal_force=np.zeros(0))
        p2 = w.write_frame(2e-3, **state, contact_pairs=[], contact_normal_force=[])
        p3 = w.write_frame(3e-3, **make_state(5))  # and back to particles
    for p, t in ((p0, 0.0), (p1, 1e-3), (p2, 2e-3)):
        check_particle_file(p, state, t)
    check_particle_file(p3, make_state(5), 3e-3)
    for k in (1, 2):
        grid = vtk_read(str(tmp_path / f"particles_contacts_{k:06d}.vtu"))
        assert grid.GetNumberOfPoints() == 0 and grid.GetNumberOfCells() == 0
        assert grid.GetCellData().GetArray("normal_force").GetNumberOfTuples() == 0
    assert [t for t, _ in parse_pvd(tmp_path / "particles.pvd")] == [0.0, 1e-3, 2e-3, 3e-3]
    assert [t for t, _ in parse_pvd(tmp_path / "particles_contacts.pvd")] == [1e-3, 2e-3]


def test_extra_arrays(tmp_path):
    state = make_state(10)
    temperature = np.linspace(290.0, 300.0, 10)
    in_contact = np.arange(10) % 2 == 0
    pairs = np.array([[0, 1], [1, 2], [5, 9]])
    overlap = np.array([1e-6, 2e-6, 3e-6])
    tangential = np.arange(9.0).reshape(3, 3)
    with VTKSeriesWriter(tmp_path) as w:
        path = w.write_frame(0.0, **state, contact_pairs=pairs,
                             extra_point_arrays={"temperature": temperature,
                                                 "in_contact": in_contact},
                             extra_contact_arrays={"overlap": overlap,
                                                   "tangential_force": tangential})
        with pytest.raises(ValueError, match="clashes"):
            w.write_frame(1.0, **state, extra_point_arrays={"radius": temperature})
        with pytest.raises(ValueError, match="shape"):
            w.write_frame(1.0, **state, extra_point_arrays={"t": temperature[:3]})
    m = meshio.read(path)
    np.testing.assert_array_equal(m.point_data["temperature"], temperature)
    np.testing.assert_array_equal(m.point_data["in_contact"], in_contact.astype(np.uint8))
    c = vtk_read(str(tmp_path / "particles_contacts_000000.vtu"))
    assert c.GetCellData().GetArray("normal_force") is None  # none was given
    np.testing.assert_array_equal(vtk_to_numpy(c.GetCellData().GetArray("overlap")), overlap)
    np.testing.assert_array_equal(
        vtk_to_numpy(c.GetCellData().GetArray("tangential_force")), tangential)
    assert len(parse_pvd(tmp_path / "particles.pvd")) == 1  # rejected frames not listed


# --------------------------------------------------------------------------------------
# contact network
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("binary", "encoding"), MODES, ids=MODE_IDS)
def test_contact_network(tmp_path, binary, encoding):
    rng = np.random.default_rng(3)
    frames = []
    with VTKSeriesWriter(tmp_path, binary=binary, encoding=encoding) as w:
        for k, (n, m) in enumerate([(30, 45), (30, 0), (12, 20), (12, None)]):
            state = make_state(n, seed=k)
            if m is None:
                w.write_frame(k * 1e-3, **state)  # a frame without contact output
                continue
            pairs = rng.integers(0, n, size=(m, 2))
            fn = rng.uniform(0, 10, m)
            w.write_frame(k * 1e-3, **state, contact_pairs=pairs, contact_normal_force=fn)
            frames.append((k, k * 1e-3, state, pairs, fn))

    entries = parse_pvd(tmp_path / "particles_contacts.pvd")
    assert entries == [(t, f"particles_contacts_{k:06d}.vtu") for k, t, *_ in frames]
    assert len(parse_pvd(tmp_path / "particles.pvd")) == 4
    for k, t, state, pairs, fn in frames:
        path = str(tmp_path / f"particles_contacts_{k:06d}.vtu")
        grid = vtk_read(path)
        m = len(pairs)
        assert grid.GetNumberOfCells() == m
        assert grid.GetNumberOfPoints() == len(state["positions"])
        np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()),
                                      state["positions"])
        conn, offsets, types = vtk_cell_arrays(grid)
        np.testing.assert_array_equal(conn.reshape(-1, 2), pairs)
        np.testing.assert_array_equal(types, np.full(m, vtk.VTK_LINE))
        nf = grid.GetCellData().GetArray("normal_force")
        assert nf.GetDataType() == vtk.VTK_DOUBLE
        np.testing.assert_array_equal(vtk_to_numpy(nf), fn)
        assert grid.GetFieldData().GetArray("TimeValue").GetValue(0) == t
        # a frame without contacts (k = 1: 30 points, 0 cells) is read by VTK above but
        # not by meshio 5.3.5 (its VTU reader indexes the first cell's type); the docs say so
        if m:
            mm = meshio.read(path)
            assert [c.type for c in mm.cells] == ["line"]
            np.testing.assert_array_equal(mm.cells[0].data, pairs)
            np.testing.assert_array_equal(mm.cell_data["normal_force"][0], fn)
            np.testing.assert_array_equal(mm.points, state["positions"])


def test_contact_validation(tmp_path):
    state = make_state(4)
    with VTKSeriesWriter(tmp_path) as w:
        with pytest.raises(ValueError, match="index particles"):
            w.write_frame(0.0, **state, contact_pairs=[[0, 4]])
        with pytest.raises(ValueError, match="index particles"):
            w.write_frame(0.0, **state, contact_pairs=[[-1, 2]])
        with pytest.raises(ValueError, match=r"\(M, 2\)"):
            w.write_frame(0.0, **state, contact_pairs=[[0, 1, 2]])
        with pytest.raises(ValueError, match="integers"):
            w.write_frame(0.0, **state, contact_pairs=[[0.0, 1.0]])
        with pytest.raises(ValueError, match="rows"):
            w.write_frame(0.0, **state, contact_pairs=[[0, 1]], contact_normal_force=[1, 2])
        with pytest.raises(ValueError, match="without contact_pairs"):
            w.write_frame(0.0, **state, contact_normal_force=[1.0])
    assert os.listdir(tmp_path) == []


# --------------------------------------------------------------------------------------
# walls
# --------------------------------------------------------------------------------------


def test_plane_to_quad():
    rng = np.random.default_rng(7)
    normals = [(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -3, 0), (1, 1, 0)] + list(
        rng.normal(size=(20, 3)))
    for normal in normals:
        point = rng.normal(size=3)
        h = 0.25
        v, f = plane_to_quad(point, normal, h)
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        assert v.shape == (4, 3) and f.tolist() == [[0, 1, 2, 3]]
        np.testing.assert_allclose(v.mean(axis=0), point, atol=1e-14)
        np.testing.assert_allclose((v - point) @ n, 0.0, atol=1e-14)  # in the plane
        edges = np.roll(v, -1, axis=0) - v
        np.testing.assert_allclose(np.linalg.norm(edges, axis=1), 2 * h)  # square...
        np.testing.assert_allclose(np.einsum("ij,ij->i", edges, np.roll(edges, -1, 0)), 0.0,
                                   atol=1e-14)  # ...with right angles
        face_normal = np.cross(v[1] - v[0], v[2] - v[0])  # right-hand rule = given normal
        np.testing.assert_allclose(face_normal / np.linalg.norm(face_normal), n, atol=1e-14)
    with pytest.raises(ValueError):
        plane_to_quad((0, 0, 0), (0, 0, 0), 1.0)
    with pytest.raises(ValueError):
        plane_to_quad((0, 0, 0), (0, 0, 1), 0.0)
    assert VTKSeriesWriter.plane_to_quad is plane_to_quad


@pytest.mark.parametrize(("binary", "encoding"), MODES, ids=MODE_IDS)
def test_walls(tmp_path, binary, encoding):
    floor = plane_to_quad((0, 0, 0), (0, 0, 1), 0.5)
    # a two-triangle slope and a two-quad box side
    slope = (np.array([[0, 0, 1], [1, 0, 1], [1, 1, 2], [0, 1, 2]], float),
             np.array([[0, 1, 2], [0, 2, 3]]))
    side = (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 0, 1], [1, 0, 1], [2, 0, 1]], float),
            np.array([[0, 1, 4, 3], [1, 2, 5, 4]], dtype=np.int32))
    with VTKSeriesWriter(tmp_path, binary=binary, encoding=encoding) as w:
        path = w.write_walls([floor, slope, side])
    assert path == str(tmp_path / "walls.vtu")

    want_points = np.vstack([floor[0], slope[0], side[0]])
    want_conn = np.concatenate([floor[1].ravel(), slope[1].ravel() + 4,
                                side[1].ravel() + 8])
    want_types = [vtk.VTK_QUAD, vtk.VTK_TRIANGLE, vtk.VTK_TRIANGLE, vtk.VTK_QUAD,
                  vtk.VTK_QUAD]
    want_wall_id = [0, 1, 1, 2, 2]

    grid = vtk_read(path)
    assert grid.GetNumberOfPoints() == 14 and grid.GetNumberOfCells() == 5
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()), want_points)
    conn, offsets, types = vtk_cell_arrays(grid)
    np.testing.assert_array_equal(conn, want_conn)
    np.testing.assert_array_equal(offsets, [0, 4, 7, 10, 14, 18])
    np.testing.assert_array_equal(types, want_types)
    np.testing.assert_array_equal(vtk_to_numpy(grid.GetCellData().GetArray("wall_id")),
                                  want_wall_id)
    areas = pv.read(path).compute_cell_sizes(length=False, volume=False)["Area"]
    np.testing.assert_allclose(areas, [1.0, np.sqrt(2) / 2, np.sqrt(2) / 2, 1.0, 1.0])

    m = meshio.read(path)
    np.testing.assert_array_equal(m.points, want_points)
    blocks = [(c.type, c.data.tolist()) for c in m.cells]
    assert blocks == [("quad", floor[1].tolist()), ("triangle", (slope[1] + 4).tolist()),
                      ("quad", (side[1] + 8).tolist())]
    assert np.concatenate(m.cell_data["wall_id"]).tolist() == want_wall_id
    assert leftover_temp_files(tmp_path) == []


def test_walls_validation_and_empty(tmp_path):
    with VTKSeriesWriter(tmp_path) as w:
        with pytest.raises(ValueError, match="faces"):
            w.write_walls([(np.zeros((3, 3)), np.array([[0, 1]]))])
        with pytest.raises(ValueError, match="outside"):
            w.write_walls([(np.zeros((3, 3)), np.array([[0, 1, 3]]))])
        with pytest.raises(ValueError, match="pair"):
            w.write_walls([np.zeros((3, 3))])
        path = w.write_walls([], name="no_walls")
    grid = vtk_read(path)
    assert grid.GetNumberOfPoints() == 0 and grid.GetNumberOfCells() == 0
    # module-level function for walls without a series
    p = write_surface_vtu(str(tmp_path / "w.vtu"), [plane_to_quad((0, 0, 0), (1, 0, 0), 1)])
    assert meshio.read(p).cells[0].type == "quad"


# --------------------------------------------------------------------------------------
# atomicity and failure handling
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("background_sync", [True, False])
def test_failed_rename_leaves_consistent_series(tmp_path, monkeypatch, background_sync):
    state = make_state(20)
    w = VTKSeriesWriter(tmp_path, background_sync=background_sync)
    w.write_frame(0.0, **state, contact_pairs=[[0, 1]], contact_normal_force=[1.0])

    real_replace = os.replace

    def failing_replace(src, dst):
        if os.path.basename(dst) == "particles_contacts_000001.vtu":
            raise OSError(28, "No space left on device (simulated)")
        return real_replace(src, dst)

    monkeypatch.setattr(vtkmod.os, "replace", failing_replace)
    if background_sync:
        w.write_frame(1.0, **state, contact_pairs=[[0, 1]], contact_normal_force=[1.0])
        with pytest.raises(OSError, match="simulated"):
            w.flush()  # the background error surfaces on the next call
    else:
        with pytest.raises(OSError, match="simulated"):
            w.write_frame(1.0, **state, contact_pairs=[[0, 1]], contact_normal_force=[1.0])
    monkeypatch.setattr(vtkmod.os, "replace", real_replace)

    assert leftover_temp_files(tmp_path) == []
    assert [t for t, _ in parse_pvd(tmp_path / "particles.pvd")] == [0.0]
    assert [t for t, _ in parse_pvd(tmp_path / "particles_contacts.pvd")] == [0.0]
    assert w.frames == [(0.0, "particles_000000.vtu")]

    # the series carries on after the failure
    w.write_frame(2.0, **state, contact_pairs=[[0, 1]], contact_normal_force=[1.0])
    w.close()
    for pvd in ("particles.pvd", "particles_contacts.pvd"):
        entries = parse_pvd(tmp_path / pvd)
        assert [t for t, _ in entries] == [0.0, 2.0]
        for _, f in entries:
            vtk_read(str(tmp_path / f))
    assert leftover_temp_files(tmp_path) == []


def test_failure_while_writing_bytes_keeps_previous_file(tmp_path):
    path = str(tmp_path / "x.pvd")
    vtkmod._atomic_write(path, [b"old complete content"])

    def chunks():
        yield b"new, half"
        raise KeyboardInterrupt  # e.g. Ctrl-C in the middle of a frame

    with pytest.raises(KeyboardInterrupt):
        vtkmod._atomic_write(path, chunks())
    assert open(path, "rb").read() == b"old complete content"
    assert leftover_temp_files(tmp_path) == []


def test_files_honour_umask(tmp_path):
    old = os.umask(0o022)
    try:
        with VTKSeriesWriter(tmp_path) as w:
            w.write_frame(0.0, **make_state(3))
    finally:
        os.umask(old)
    for f in os.listdir(tmp_path):
        assert os.stat(tmp_path / f).st_mode & 0o777 == 0o644, f


CHILD = textwrap.dedent("""
    import sys, numpy as np
    from minidem.results.vtk import VTKSeriesWriter
    n = 3000
    w = VTKSeriesWriter(sys.argv[1], background_sync=sys.argv[2] == "1")
    k = 0
    while True:
        s = np.full((n, 3), float(k))
        w.write_frame(k * 1e-3, s, np.full(n, float(k)), s, s, s, np.arange(n),
                      np.zeros(n, int), np.stack([np.arange(n - 1), np.arange(1, n)], 1),
                      np.full(n - 1, float(k)))
        if k == 2:
            print("running", flush=True)
        k += 1
""")


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
@pytest.mark.parametrize("background_sync", [True, False])
def test_kill_never_leaves_torn_pvd_or_frame(tmp_path, background_sync):
    """SIGKILL a writing process at random moments; everything any .pvd lists must be a
    complete, readable frame with the data of that frame."""
    env = dict(os.environ, PYTHONPATH=REPO_ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    rnd = random.Random(1234)
    for trial in range(4):
        d = tmp_path / f"run{trial}"
        proc = subprocess.Popen([sys.executable, "-c", CHILD, str(d), str(int(background_sync))],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        try:
            line = proc.stdout.readline()
            assert line.strip() == b"running", proc.stderr.read().decode()
            time.sleep(rnd.uniform(0.0, 0.3))
        finally:
            proc.kill()
            proc.wait()
            proc.stdout.close()
            proc.stderr.close()
        for pvd, n_cells in (("particles.pvd", 3000), ("particles_contacts.pvd", 2999)):
            entries = parse_pvd(d / pvd)
            # "running" follows write_frame(2), which has waited for frames 0 and 1
            # (frame 2 itself may still be syncing in the background)
            assert len(entries) >= 2
            for k, (t, f) in enumerate(entries):
                assert t == k * 1e-3
                grid = vtk_read(str(d / f))
                assert grid.GetNumberOfCells() == n_cells
                np.testing.assert_array_equal(vtk_to_numpy(grid.GetPoints().GetData()), k)
        # a kill may leave a hidden temp file of the frame in flight, and nothing else
        for f in leftover_temp_files(d):
            assert f.startswith(".particles") and f.endswith(".tmp"), f


# --------------------------------------------------------------------------------------
# API misuse and speed
# --------------------------------------------------------------------------------------


def test_argument_validation(tmp_path):
    state = make_state(5)
    with pytest.raises(ValueError, match="encoding"):
        VTKSeriesWriter(tmp_path, encoding="zlib")
    with pytest.raises(ValueError, match="prefix"):
        VTKSeriesWriter(tmp_path, prefix="a/b")
    w = VTKSeriesWriter(tmp_path / "new" / "dir")  # created on demand
    bad = dict(state, velocities=state["velocities"][:, :2])
    with pytest.raises(ValueError, match="velocities"):
        w.write_frame(0.0, **bad)
    with pytest.raises(ValueError, match="radii"):
        w.write_frame(0.0, **dict(state, radii=state["radii"][:4]))
    with pytest.raises(ValueError, match="particle_ids"):
        w.write_frame(0.0, **dict(state, particle_ids=state["radii"]))
    with pytest.raises(ValueError, match="finite"):
        w.write_frame(float("nan"), **state)
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w.write_frame(0.0, **state)
    with pytest.raises(RuntimeError, match="closed"):
        w.write_walls([])
    assert os.listdir(tmp_path / "new" / "dir") == []


def test_an_analytic_flight_run_has_the_flight_frames(tmp_path):
    """One sphere dropped 0.1 m onto a floor: the default integrator skips the flight (the
    steps start at first touch), but ParaView must still see it fall: frames at t = 0 and
    every output.interval before the touch, placed by the ballistic closed form, then the
    touch and the stepped frames every interval from it (independent review finding)."""
    from minidem.scene import scenario
    from minidem.engine import simulation
    from minidem.results.vtk import SimulationFrames

    scene = scenario.build_scene({
        "materials": {"glass": {"youngs_modulus": 70e9, "poisson_ratio": 0.3, "density": 2650.0}},
        "contact": {"law": "hm", "friction": 0.3, "restitution": 0.5},
        "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "glass"}],
        "particles": [{"position": [0.0, 0.0, 0.11], "radius": 0.01, "material": "glass"}],
        "run": {"gravity": [0.0, 0.0, -9.81], "stop": "time", "end_time": 0.2},
        "output": {"interval": 0.02, "directory": str(tmp_path)},
    }, "drop.toml")
    sim = simulation.Simulation(scene)
    assert scene.integrator == "analytic_flight" and sim.start_time > 0.1  # falls 0.1 m: 0.1428 s
    frames = SimulationFrames(sim, tmp_path)
    sim.run(on_frame=frames)
    frames.close()
    entries = parse_pvd(tmp_path / "particles.pvd")
    times = [float(t) for t, _ in entries]
    flight = [t for t in times if t < sim.start_time]
    assert flight == pytest.approx([0.02 * k for k in range(8)], abs=1e-15)  # 0 ... 0.14 < 0.1428
    assert times[len(flight)] == pytest.approx(sim.start_time, abs=1e-15)  # the touch
    # stepped frames every interval from the touch, and the end of the run
    stepped = np.diff(times[len(flight):-1])
    assert stepped == pytest.approx(np.full(stepped.size, 0.02), abs=sim.dt)
    assert times[-1] == pytest.approx(0.2, abs=sim.dt)
    for t, name in entries[:len(flight)]:
        grid = vtk_read(str(tmp_path / name))
        z = vtk_to_numpy(grid.GetPoints().GetData())[0, 2]
        assert z == pytest.approx(0.11 - 0.5 * 9.81 * t * t, abs=1e-15)  # free fall
        velocity = vtk_to_numpy(grid.GetPointData().GetArray("velocity"))[0]
        assert velocity == pytest.approx([0.0, 0.0, -9.81 * t], abs=1e-15)


def test_the_frame_due_at_the_end_is_the_final_state_not_one_step_before_it(tmp_path):
    """A frame's step is the first at or after its time, as the run's last step is the
    first at or after run.end_time: with end_time / dt = 1000.3 the frame due at end_time
    is the final state (step 1001). Rounded to the nearest step it was step 1000, and
    the final state made a second frame one step later (a review: frames at 0.04999999
    and 0.05000022 s)."""
    from minidem.scene import scenario
    from minidem.engine import simulation
    from minidem.results.vtk import SimulationFrames

    dt = 0.05 / 1000.3
    scene = scenario.build_scene({
        "materials": {"soft": {"youngs_modulus": 1e6, "poisson_ratio": 0.3, "density": 2500.0}},
        "contact": {"law": "hm", "friction": 0.3, "restitution": 0.5},
        "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "soft"}],
        "particles": [{"position": [0.0, 0.0, 0.5], "velocity": [1.0, 0.0, 0.0], "radius": 0.01,
                       "material": "soft"}],
        "run": {"stop": "time", "end_time": 0.05, "dt": dt, "integrator": "velocity_verlet"},
        "output": {"interval": 0.01, "directory": str(tmp_path)},
    }, "drift.toml")
    sim = simulation.Simulation(scene)
    frames = SimulationFrames(sim, tmp_path)
    sim.run(on_frame=frames)
    frames.close()
    times = [float(t) for t, _ in parse_pvd(tmp_path / "particles.pvd")]
    assert len(times) == 6 and times[-1] == pytest.approx(1001 * dt, rel=1e-12), times
    assert np.diff(times) == pytest.approx(np.full(5, 0.01), abs=dt), times



def test_the_python_walls_carry_the_arrays_of_walls_vtu(tmp_path):
    # result.walls_pyvista() had no arrays, while walls.vtu has wall_id and wall_table to
    # threshold one wall (a new user's report, 2026-11-28): the same cells, the same arrays
    import minidem

    result = minidem.run({
        "materials": {"glass": {"youngs_modulus": 70e9, "poisson_ratio": 0.3, "density": 2650.0}},
        "contact": {"law": "hm", "friction": 0.3, "restitution": 0.5},
        "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "glass"},
                  {"type": "box", "lower": [-0.1, -0.1, 0.0], "upper": [0.1, 0.1, 0.3], "open_top": True,
                   "material": "glass"}],
        "particles": [{"position": [0.0, 0.0, 0.05], "radius": 0.01, "material": "glass"}],
        "run": {"gravity": [0.0, 0.0, -9.81], "stop": "time", "end_time": 0.01},
        "output": {"vtk": True}}, out=tmp_path)
    python, written = result.walls_pyvista(), pv.read(tmp_path / "walls.vtu")
    assert python.n_cells == written.n_cells
    for name in ("wall_id", "wall_table"):
        assert python.cell_data[name].tolist() == written.cell_data[name].tolist(), name
    assert sorted(set(python.cell_data["wall_table"].tolist())) == [0, 1]  # the plane, the box
