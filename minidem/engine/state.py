"""The arrays the compiled kernel advances (:class:`State`), grouped as it takes them, and
the copies of them a run keeps: the last good state, checkpoints and the final state.

A :class:`minidem.engine.simulation.Simulation` makes one per run; the run loop
(:mod:`minidem.engine.run_loop`) hands its tuples to the kernel, copies them between
chunks into a file (:meth:`State.capture_items`, :class:`StateCopy`) and puts a copy back
after a failure or on resume
(:meth:`State.restore`), bit for bit.
"""

from __future__ import annotations

import io
import mmap
import os
import tempfile
import warnings

import numpy as np

from minidem.engine import integrate
from minidem.errors import MinidemError
from minidem.geometry import neighbours
from minidem.geometry.order import mean_step
from minidem.scene.scenario import Scene

# State arrays a checkpoint holds: particle arrays, then the contact arrays of each
# argument tuple by position (None: fixed by the scene, not saved)
STATE_ARRAYS = ("position", "velocity", "angular_velocity", "force", "torque", "position_at_build")
_STATE_TUPLES = {
    # per near-plane entry (State.list_near_planes); the list itself follows from the
    # position at the last build (State.restore makes it again)
    "planes": (None, None, None, "plane_history", "plane_overlap", None, None),
    "cylinders": (None, None, None, None, None, "cylinder_history", "cylinder_overlap"),
    "meshes": (None, None, "mesh_offsets", "mesh_candidates", "mesh_history", "mesh_overlap"),
    # the reactions' slots and the transposed offsets follow from the list (State.restore
    # recomputes them); the reactions are kept: a step rewrites them before reading, but
    # the last good state's VTK frame and contact forces read them as they are
    "pairs": ("pair_offsets", "pair_neighbours", "pair_history", "pair_overlap", "pair_reaction", None, None,
              "pair_reaction_in_use", None, None),
}
PAIR_TUPLE = _STATE_TUPLES["pairs"]  # one name (or None) for each array of the kernel's pair tuple


# per-contact arrays whose rows are all zero while the contact is not touching (a contact
# that ends drops its history and its reaction): the last good state keeps only the rows
# in use (State.capture_items)
_SPARSE_ROWS = ("plane_history", "cylinder_history", "mesh_history", "pair_history", "pair_reaction",
                "pair_reaction_in_use")
# The Verlet lists follow from the position at the last build (State.build_lists: the
# same lists, bit for bit), so a capture does not hold them and State.restore makes them
# again. Held, the old lists stayed resident from a rebuild to the next copy of the state,
# and at the rebuild itself beside the old and the new list: 20 bytes a particle of the
# settle scene at 1,000,000 (docs/benchmarks.md, "Memory per particle"). Files hold them
# (RunLoop.write_state): a script reading pair_history needs its pairs.
LISTS = ("pair_offsets", "pair_neighbours", "mesh_offsets", "mesh_candidates")
_SPARSE_BLOCK = 1 << 16  # rows scanned at a time


def _sparse_rows(name: str, array: np.ndarray) -> dict[str, np.ndarray]:
    """``array`` as its rows (first index) that hold any non-zero bit: {name@rows: their
    indices, name@values: the rows (not taken yet: RowsTaken), name@shape: the shape}.
    Bits, not values, so a row of -0.0 is kept and the expansion gives every bit back."""
    rows = _rows_with_bits(array)
    return {name + "@rows": rows, name + "@values": RowsTaken(array, rows),
            name + "@shape": np.array(array.shape, dtype=np.int64)}


def rows_in_use(history: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the indices of the rows of ``history`` that hold any non-zero bit, those rows):
    a list's contact histories as ``neighbours.carry_history`` takes the old list's (a
    contact that ends drops its history, so the other rows are zero)."""
    rows = _rows_with_bits(history)
    return rows, np.take(history, rows, axis=0)


def _rows_with_bits(array: np.ndarray) -> np.ndarray:
    """The ascending indices of the rows of ``array`` that hold any non-zero bit. int32
    below 2^31 rows: 4 bytes a touching contact less in each array copied so, 29 bytes a
    particle for the pairs' three in the settled pile of 200,000 (2.45 touching pairs a
    particle)."""
    index_type = np.int32 if array.shape[0] < 2**31 else np.int64
    rows = np.zeros(0, dtype=index_type)
    if array.size:
        # an OR of the columns' bits, then np.take: several times faster than
        # (bits != 0).any(axis=1) and fancy indexing (settle, N = 200,000); a block of
        # rows at a time, so that the flags are not one more whole-array temporary at the
        # peak of a large run (8 bytes a row: 24 MiB for the pair list at N = 1,000,000)
        row_bytes = array.reshape(array.shape[0], -1).view(np.uint8)
        # rows of whole 8-byte words (the histories and reactions) as such; others (the
        # touching flags, a byte a row) byte by byte
        bits = row_bytes.view(np.uint64) if row_bytes.shape[1] % 8 == 0 else row_bytes
        found = [rows]
        for start in range(0, bits.shape[0], _SPARSE_BLOCK):
            block = bits[start:start + _SPARSE_BLOCK]
            in_use = block[:, 0].copy()
            for column in range(1, block.shape[1]):
                in_use |= block[:, column]
            found.append((np.flatnonzero(in_use) + start).astype(index_type))
        rows = np.concatenate(found)
    return rows


class RowsTaken:
    """The rows ``rows`` of ``array`` (a sparse copy's values, :func:`_sparse_rows`), not
    taken yet: :class:`StateCopy` writes them a block of rows at a time, so a copy of the
    state never holds a whole array of them (the touching pairs' histories and reactions,
    24 bytes a contact each: 12 MiB at N = 200,000, kept by the heap after the copy);
    ``np.array`` takes them all at once (:meth:`State.capture`)."""

    def __init__(self, array: np.ndarray, rows: np.ndarray):
        self.array, self.rows = array, rows
        self.shape, self.dtype = (rows.shape[0],) + array.shape[1:], array.dtype

    def blocks(self):
        for start in range(0, self.rows.shape[0], _SPARSE_BLOCK):
            yield np.take(self.array, self.rows[start:start + _SPARSE_BLOCK], axis=0)

    def __array__(self, dtype=None, copy=None):
        taken = np.take(self.array, self.rows, axis=0)
        return taken if dtype is None else taken.astype(dtype)


def _full_array(arrays: dict, name: str) -> np.ndarray:
    """The array ``name`` of a capture, expanded if it was captured sparse."""
    if name in arrays:
        return arrays[name]
    return expand_rows(arrays[name + "@rows"], arrays[name + "@values"], tuple(arrays[name + "@shape"]))


def expand_rows(rows: np.ndarray, values: np.ndarray, shape: tuple) -> np.ndarray:
    """The array of ``shape`` that holds ``values`` at ``rows`` and zeros elsewhere: what
    :func:`_sparse_rows` and :func:`rows_in_use` took, given back bit for bit."""
    full = np.zeros(shape, dtype=values.dtype)
    full[rows] = values
    return full


def full_arrays(arrays: dict) -> dict[str, np.ndarray]:
    """A capture with its sparse arrays expanded: the arrays a checkpoint file holds."""
    out = {name: array for name, array in arrays.items() if "@" not in name}
    for name in _SPARSE_ROWS:
        if name + "@rows" in arrays:
            out[name] = _full_array(arrays, name)
    return out


def pair_index_type(n_entries: int, n_particles: int):
    """The integer type of the pair list's partners and reaction slots: int32 below 2^31
    entries and particles (4 bytes an entry saved twice, and once more in the last good
    state), else int64. One type for every list of a run, so the kernel is compiled for
    one signature."""
    return np.int32 if max(n_entries, n_particles) < 2**31 else np.int64


def numpy_owned(array: np.ndarray) -> np.ndarray:
    """``array`` (made by compiled code), copied into memory numpy allocates if it is 4 MiB
    or more. numpy asks Linux for transparent huge pages for such arrays (madvise; the
    usual setting allows them only where asked), numba's allocator does not: the force
    pass reads the list's arrays every step, and at 1,000,000 spheres it ran 6 % slower
    with them on small pages (docs/benchmarks.md, "The list build: one scan, and huge
    pages"). The copy costs about 10 ms a list build there, and the compiled array is
    released at once."""
    return np.array(array) if array.nbytes >= 1 << 22 else array


def untouched_zeros(rows: int, columns: int) -> np.ndarray:
    """A (rows, columns) float64 array of zeros on an anonymous mapping of its own, whose
    pages are not resident until something writes into them. ``np.zeros`` promises that
    only above glibc's mmap threshold, which rises (up to 32 MiB) as mapped blocks are
    freed: below it the zeros come from the heap, cleared and so resident at once (the
    pairs' partner torques at N = 200,000: 22 MiB, all resident, none written on one
    thread). For an array written in few places or none; one written everywhere gains
    nothing and pays a page fault a page."""
    nbytes = rows * columns * 8
    if nbytes < mmap.PAGESIZE or not hasattr(mmap, "MAP_ANONYMOUS"):  # (Windows: numpy's zeros)
        return np.zeros((rows, columns))
    mapping = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    # the array holds the mapping (its base), which is unmapped with the last reference
    return np.frombuffer(mapping, dtype=np.float64).reshape(rows, columns)


def pair_arrays(offsets, partners, history, overlap, slot, reverse_offsets):
    """The kernel's pair tuple for a new list (``State.pairs``): its reactions zero and no
    pair touching yet. The reactions are in the transposed list's order (row ``slot[e]``
    for entry e), and so is ``reaction_in_use``, which marks the rows holding a touching
    pair's reaction; the force pass stores them for the partners finish_kick_drift
    finishes and, at the last step of a call whose state the run reads, for every
    touching pair (State.contact_pairs; kernel.advance's ``store_reactions``), and sums
    the others' straight into their force rows, marking those particles in
    ``reaction_pending`` (a byte a particle, zero between passes; see
    minidem.engine.kernel). So on one thread the reactions are written only where the
    state is read (a frame, a copy, a checkpoint, the end), and lie on a mapping of their
    own (``untouched_zeros``): between such steps and the next list build, none of their
    pages is resident. The torque on the partner, ``partner_torque`` (last, in the
    same order), is kept apart from its force: finish_kick_drift alone reads it, so the
    force pass writes it only for the partners that pass finishes (none on one thread)
    and its pages are mostly never resident. Not state: each row read is written in the
    same step (a capture does not hold it, a restore makes it zero)."""
    return (offsets, partners, history, overlap, untouched_zeros(partners.shape[0], 3), slot, reverse_offsets,
            np.zeros(partners.shape[0], dtype=np.uint8), np.zeros(offsets.shape[0] - 1, dtype=np.uint8),
            untouched_zeros(partners.shape[0], 3))


def on_memory_file_system(directory=None) -> bool:
    """Whether ``directory`` (default: the system's temporary directory) is on tmpfs or
    ramfs, by the longest mount point above it in /proc/self/mounts (False where there is
    none: not Linux)."""
    target = os.path.realpath(directory or tempfile.gettempdir())
    best, kind = "", ""
    try:
        with open("/proc/self/mounts") as mounts:
            for line in mounts:
                fields = line.split()
                if len(fields) < 3:
                    continue
                point = fields[1].replace("\\040", " ")
                inside = target == point or target.startswith(point.rstrip("/") + "/")
                if inside and len(point) >= len(best):
                    best, kind = point, fields[2]
    except OSError:
        return False
    return kind in ("tmpfs", "ramfs")


class StateCopy:
    """A copy of the state (:meth:`State.capture_items`) kept in a file, not in memory: the
    last good state of a run (:class:`minidem.engine.run_loop.RunLoop`), which a blow-up
    restores and Ctrl-C writes as the checkpoint, and nothing reads otherwise.

    Held in memory, that copy was the largest thing a run kept besides its live state: the
    particle arrays again (144 bytes a particle) and the touching contacts' histories and
    reactions (about 150 bytes a particle in a settled pile), 30 % of the run's memory
    (docs/benchmarks.md, "The last good copy in a file"). In a file it costs disk, and
    memory only as the system's page cache, which the system gives up when memory runs
    short (anonymous memory it cannot, without swap). The file has no name (an unlinked
    temporary file in ``directory``: the run's output directory, else the system's
    temporary directory), so nothing is left behind, whatever ends the process. A
    directory on tmpfs or ramfs (a common /tmp) is memory the system cannot give up
    either: there the copy is kept in the process's memory, where it is counted.

    Each :meth:`write` replaces the copy: the items are streamed in, one array at a time
    (``.npy`` records one after another), never all of them in memory at once. If the
    file cannot be made or written (no such directory, a full disk), the copy is kept in
    memory from then on, with a warning: the run goes on as before.
    """

    def __init__(self, directory=None):
        self.directory = directory
        self.handle = None
        self.offsets: dict[str, int] = {}

    def write(self, items) -> None:
        """Replace the copy by ``items()`` (a callable giving (name, array) pairs, as
        :meth:`State.capture_items`; called again if the file fails half-way)."""
        if self.handle is None:
            try:
                self.handle = (io.BytesIO() if on_memory_file_system(self.directory) else
                               tempfile.TemporaryFile(dir=self.directory, prefix=".minidem-last-good-"))
            except OSError as exc:
                self.handle = self._in_memory(exc)
        try:
            self._write(items())
        except OSError as exc:
            if isinstance(self.handle, io.BytesIO):
                raise
            self.close()
            self.handle = self._in_memory(exc)
            self._write(items())

    def _write(self, items) -> None:
        handle = self.handle
        handle.seek(0)
        handle.truncate()
        self.offsets = {}
        for name, array in items:
            self.offsets[name] = handle.tell()
            if isinstance(array, RowsTaken):  # the .npy header, then the rows a block at a time
                np.lib.format.write_array_header_1_0(handle, {
                    "descr": np.lib.format.dtype_to_descr(array.dtype), "fortran_order": False, "shape": array.shape})
                for block in array.blocks():
                    handle.write(memoryview(np.ascontiguousarray(block)).cast("B"))
            else:
                np.lib.format.write_array(handle, np.asarray(array, order="C"), allow_pickle=False)
        handle.flush()

    def read(self) -> dict[str, np.ndarray]:
        """The copy, as :meth:`State.capture` gives it."""
        handle, arrays = self.handle, {}
        for name, offset in self.offsets.items():
            handle.seek(offset)
            arrays[name] = np.lib.format.read_array(handle, allow_pickle=False)
        return arrays

    def close(self) -> None:
        handle, self.handle = self.handle, None
        if handle is not None:
            try:
                handle.close()
            except OSError:  # the buffered bytes of a write that failed (a full disk): the copy goes anyway
                pass

    def _in_memory(self, exc: OSError) -> io.BytesIO:
        where = self.directory or tempfile.gettempdir()
        warnings.warn(f"cannot keep the last good state in a temporary file in {where} ({exc.strerror or exc}): "
                      "it is kept in memory instead", stacklevel=3)
        return io.BytesIO()


class State:
    """The arrays the compiled kernel advances, grouped as it takes them.

    ``pairs`` and ``meshes`` hold Verlet lists (CSR) with one history row per entry, and
    ``planes`` the list of planes near each sphere likewise (:meth:`list_near_planes`);
    :meth:`Simulation.rebuild` replaces them, carrying every entry's history over.
    """

    def __init__(self, sim):
        """The state of ``sim`` (a :class:`minidem.engine.simulation.Simulation`, not
        imported here: the simulation builds its state) at its start time."""
        scene, walls = sim.scene, sim.scene.walls
        n, h = scene.n_particles, sim.law.history_size
        # the state at sim.start_time (t = 0, or first touch after an analytic flight)
        self.position = sim.start_position.copy()
        self.velocity = sim.start_velocity.copy()
        self.angular_velocity = scene.angular_velocity.copy()
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
        # the force and torque at the end of the last step, for a kernel that hands its law
        # the velocity predicted there (kernel END_VELOCITY; else no rows): a pair kernel's
        # force rows sum reactions during the force pass. Not part of a captured state:
        # the opening kick after a restore takes it from the force rows, which hold totals
        self.last_force = np.zeros((n if sim.end_velocity else 0, 6))
        self.follow_scene(scene)
        self.input_radius = sim.input_scene.radius  # the scenario's order (lists_of)
        # the mean distance of consecutive particles when they were last sorted (or at the
        # start): Simulation.rebuild sorts them again when they drift far from it
        self.sorted_step, self.sorts = mean_step(self.position), 0
        self.law = (sim.pair_row, sim.constants)
        # Plane contacts are kept per near-plane entry (neighbours.near_planes, CSR): the
        # planes each sphere may touch before the next list build, listed at each build
        # (list_near_planes), with each entry's history and last overlap, carried over to
        # the new list like a pair's. The kernel checks only those planes. Every plane is
        # listed for every sphere (margin None) in a scene without list builds, and for the
        # tracked (serial) kernel: its contact statistics interpolate each plane's touch and
        # separation times from the overlap of the step before, which a plane skipped since
        # the last build would hold stale.
        self.plane_margin = sim.skin + sim.max_reach if sim.parallel and (sim.pairs or walls.triangles.shape[0]) \
            else None
        self.history_size = h
        # what the Verlet lists are built with (build_lists)
        self.has_pairs, self.pair_cutoff, self.mesh_skin = sim.pairs, sim.skin + sim.max_reach, sim.skin
        self.planes = (scene.wall_point, scene.wall_normal, scene.wall_material)
        self.position_at_build = self.position.copy()
        self.list_near_planes()
        if sim.start_time > 0.0:
            # touching after an analytic flight: rounding may put the sphere a hair inside
            # the wall, but the previous overlap must read 'not yet touching' for the
            # first touch to be recorded
            np.minimum(self.planes[4], 0.0, out=self.planes[4])
        n_cylinders = walls.cylinder_base.shape[0]
        self.cylinders = (walls.cylinder_base, walls.cylinder_axis, walls.cylinder_radius, walls.cylinder_length,
                          walls.cylinder_material, np.zeros((n, n_cylinders, h)), np.full((n, n_cylinders), -1.0))
        empty_index = np.zeros(0, dtype=np.int64)
        self.meshes = (walls.triangles, walls.triangle_material, np.zeros(n + 1, dtype=np.int64), empty_index,
                       np.zeros((0, h)), np.zeros(0))
        # (offsets, partners, history, overlap, reactions (the force on i) in the
        # transposed list's order, each entry's slot there, transposed offsets, whether
        # each slot's pair touches, the particles given a reaction in the force pass, the
        # torques on the partners: pair_arrays)
        pair_index = np.zeros(0, dtype=pair_index_type(0, n))
        self.pairs = pair_arrays(np.zeros(n + 1, dtype=np.int64), pair_index, np.zeros((0, h)), np.zeros(0), pair_index,
                                 np.zeros(n + 1, dtype=np.int64))
        # each particle's first partner in the list (the smallest i whose row lists it,
        # itself if none; neighbours.reverse_index): the threads' blocks need it before
        # every call, and it changes only with the list (Simulation.rebuild, restore)
        self.first_partner = np.arange(n)
        self.builds = 0

    def follow_scene(self, scene: Scene) -> None:
        """The kernel's particle tuple with the scene's arrays (mass, radius, material) in
        the order the scene stores the particles (Simulation.use_order)."""
        self.mass, self.radius, self.particle_id = scene.mass, scene.radius, scene.particle_id
        self.particles = (self.position, self.velocity, self.angular_velocity, self.force, self.torque,
                          self.mass, 1.0 / self.mass, 1.0 / self.inertia, self.radius, scene.particle_material,
                          self.last_force)

    @property
    def inertia(self) -> np.ndarray:
        """Each particle's moment of inertia (kg m^2), the bits of Scene.inertia, from the
        mass kept here: Scene computes the mass anew at each access, 1.5 ms at 200,000
        particles, and the run loop reads the inertia at every call and sample. Not kept
        itself: 8 bytes a particle more at a list build, the peak of a large run."""
        return 0.4 * self.mass * self.radius**2

    def list_near_planes(self) -> None:
        """The planes each sphere may touch until the next list build (at position_at_build),
        as the kernel's plane tuple (point, normal, material, history (entries, h), last
        overlap (entries,), near offsets, near planes). An entry of the old list for the
        same (sphere, plane) hands over its history and last overlap
        (``neighbours.carry_history``); a new one starts with no history and the current
        overlap (at a rebuild it is below -(skin / 2 + reach): not touching, for any law).
        Every plane for every sphere (no margin): the list never changes, nothing to do
        after the first."""
        wall_point, wall_normal, wall_material = self.planes[:3]
        if self.plane_margin is None and len(self.planes) == 7:
            return
        offsets, planes = self.near_plane_list()
        # zeros from the operating system: rows no contact is carried into stay unwritten
        # (not resident) until a sphere touches that plane
        history = np.zeros((planes.shape[0], self.history_size))
        overlap = self.plane_overlaps(offsets, planes)
        if len(self.planes) == 7:
            neighbours.carry_history(*self.planes[5:], *rows_in_use(self.planes[3]), self.planes[4], offsets, planes,
                                     history, overlap)
        self.planes = (wall_point, wall_normal, wall_material, history, overlap, offsets, planes)

    def build_lists(self, position: np.ndarray | None = None, radius: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The Verlet lists at ``position`` (default position_at_build), by their names in a
        capture (LISTS): the pairs closer than their radii plus ``pair_cutoff`` (partners
        int32 below 2**31 entries, ``pair_index_type``) and the mesh triangles within
        ``mesh_skin``. What :meth:`Simulation.rebuild` makes, and :meth:`restore` makes
        again, bit for bit."""
        n = self.position.shape[0]
        radius = self.particles[8] if radius is None else radius
        position = self.position_at_build if position is None else position
        lists = {"pair_offsets": np.zeros(n + 1, dtype=np.int64),
                 "pair_neighbours": np.zeros(0, dtype=pair_index_type(0, n)),
                 "mesh_offsets": np.zeros(n + 1, dtype=np.int64), "mesh_candidates": np.zeros(0, dtype=np.int64)}
        if self.has_pairs:
            offsets, found = neighbours.build_pairs(position, radius, self.pair_cutoff)
            lists["pair_offsets"] = numpy_owned(offsets)
            lists["pair_neighbours"] = numpy_owned(found.astype(pair_index_type(found.shape[0], n), copy=False))
        if self.meshes[0].shape[0]:
            lists["mesh_offsets"], lists["mesh_candidates"] = neighbours.mesh_candidates(
                position, radius, self.mesh_skin, self.meshes[0])
        return lists

    def lists_of(self, arrays: dict) -> dict[str, np.ndarray]:
        """The Verlet lists of a capture (which holds none, LISTS): the live ones if it
        was taken since the last list build (it holds the live position at build), else
        made from its position at build (also while a rebuild has let go of the live pair
        list: an interrupt's checkpoint)."""
        if self.pairs is not None and np.array_equal(arrays["position_at_build"], self.position_at_build):
            return {name: array for name, array in self.live_arrays().items() if name in LISTS}
        # with the radii in the order the capture was taken in (a run may have sorted the
        # particles since: Simulation.sort_in_space)
        stored = arrays.get("particle_id")
        return self.build_lists(arrays["position_at_build"],
                                self.input_radius if stored is None else self.input_radius[stored])

    def near_plane_list(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets, planes): the planes near each sphere at position_at_build, CSR."""
        radius = self.particles[8]  # the particle tuple's radius (kernel order)
        return neighbours.near_planes(self.position_at_build, radius, self.planes[0], self.planes[1],
                                      self.plane_margin)

    def plane_overlaps(self, offsets, planes) -> np.ndarray:
        """The overlap R - (x - p) . n of each near-plane entry's sphere with its plane, now."""
        wall_point, wall_normal = self.planes[:2]
        sphere = neighbours.rows_of_entries(offsets)
        return self.particles[8][sphere] - np.einsum("ek,ek->e", self.position[sphere] - wall_point[planes],
                                                     wall_normal[planes])

    def plane_contacts(self):
        """(sphere, plane) of every near-plane entry, aligned with the plane histories and
        overlaps (planes[3], planes[4])."""
        offsets, planes = self.planes[5:7]
        return neighbours.rows_of_entries(offsets), planes

    def contact_pairs(self):
        """(pairs (M, 2) particle indices as stored, normal force (M,) N) of touching particle
        pairs."""
        offsets, neighbours_, _, overlap, reaction, slot = self.pairs[:6]
        first = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
        touching = overlap > 0.0
        i, j = first[touching], neighbours_[touching]
        normal = self.position[i] - self.position[j]
        normal /= np.linalg.norm(normal, axis=1)[:, None]
        return np.column_stack([i, j]), np.einsum("mk,mk->m", reaction[slot[touching], :3], normal)

    # -- checkpoints -------------------------------------------------------------
    def capture(self) -> dict[str, np.ndarray]:
        """Copies of every array the kernel carries from one step to the next (the contact
        histories exactly as they are, rows aligned with the lists at the position at
        build); the Verlet lists not at all (``LISTS``: :meth:`restore` makes them
        again from the position at build, :meth:`lists_of` for a file). What
        :meth:`capture_items` gives, copied: the last good state of a run is those items
        written into a file instead (:class:`StateCopy`)."""
        return {name: np.array(array) for name, array in self.capture_items()}

    def capture_items(self):
        """(name, array) of everything a copy of the state holds, one at a time: the live
        arrays themselves where they are kept whole (valid until the kernel runs again),
        so that a writer streams them without holding a second copy.

        The per-contact histories and reactions (``_SPARSE_ROWS``) are given as their
        non-zero rows only (see :func:`_sparse_rows`), each made when it is asked for: a
        row is zero while its wall or pair is not touching, most of them in a pile (a
        sphere of the settle scene touches no wall, and about half of its listed pairs
        are apart), so the copy is about half the size of the live state.
        :meth:`restore` and :func:`full_arrays` (what a checkpoint file holds) give the
        same bits back.
        """
        for name, array in self.live_arrays().items():
            if name in LISTS:
                continue
            if name in _SPARSE_ROWS:
                yield from _sparse_rows(name, array).items()
            else:
                yield name, array

    def live_arrays(self) -> dict[str, np.ndarray]:
        """The arrays :meth:`capture` copies, as they are (no copy: for a file written
        before the kernel runs again, e.g. the final state)."""
        live = {name: getattr(self, name) for name in STATE_ARRAYS}
        for group, names in _STATE_TUPLES.items():
            live.update((name, array) for name, array in zip(names, getattr(self, group)) if name is not None)
        live["builds"] = np.array(self.builds, dtype=np.int64)
        live["sorted_step"] = np.array([self.sorted_step])  # m; an array of one, as the files hold
        if self.particle_id is not None:  # rows in a stored order (Simulation.use_order)
            live["particle_id"] = self.particle_id
        return live

    def restore(self, arrays: dict) -> None:
        for name in STATE_ARRAYS:  # in place: the kernel's particle tuple holds these arrays
            getattr(self, name)[...] = arrays[name]
        # a capture holds no lists (LISTS): those of the restored position at build, again
        lists = {} if all(name in arrays for name in LISTS) else self.build_lists()
        for group, names in _STATE_TUPLES.items():
            items = list(getattr(self, group))
            for k, name in enumerate(names):
                if name in lists:
                    items[k] = lists[name]
                elif name is not None:  # replaced: list rebuilds change the lengths
                    # in the live array's type (a run's lists have one index type); none
                    # after a list build that failed (Simulation.rebuild): the saved type
                    items[k] = np.array(_full_array(arrays, name), order="C",
                                        dtype=None if items[k] is None else items[k].dtype)
            setattr(self, group, tuple(items))
        # (the list's partners, the histories): one row each per entry
        for what, listed, histories in (("pair", self.pairs[1], self.pairs[2]),
                                        ("mesh", self.meshes[3], self.meshes[4])):
            if histories.shape[0] != listed.shape[0]:
                raise MinidemError(f"the saved {what} contacts ({histories.shape[0]} entries) do not match the "
                                   f"Verlet list at the saved last list build ({listed.shape[0]}): the state was "
                                   "not written by this version of minidem for this scene")
        offsets, partners = self.pairs[:2]
        if partners.shape[0]:
            reverse_offsets, slot, self.first_partner = neighbours.reverse_index(offsets, partners, len(offsets) - 1)
        else:
            reverse_offsets, slot = np.zeros_like(offsets), partners.copy()
            self.first_partner = np.arange(len(offsets) - 1)
        # the particles given a reaction in the force pass (zero between passes) and the
        # partner torques (not state) anew, as a new list's (pair_arrays)
        self.pairs = self.pairs[:5] + (slot, reverse_offsets, self.pairs[7], np.zeros(len(offsets) - 1, dtype=np.uint8),
                                       untouched_zeros(partners.shape[0], 3))
        # the plane entries' history and overlap restored above belong to the list of
        # the planes near each sphere at the restored position_at_build: that list, again
        offsets, planes = self.near_plane_list()
        if planes.shape[0] != self.planes[4].shape[0] or planes.shape[0] != self.planes[3].shape[0]:
            raise MinidemError(f"the saved plane contacts ({self.planes[4].shape[0]} entries) do not match the "
                               f"planes near each sphere at the saved last list build ({planes.shape[0]}): the "
                               "state was not written by this version of minidem for this scene")
        self.planes = self.planes[:5] + (offsets, planes)
        self.builds = int(arrays["builds"])
        self.sorted_step = float(np.asarray(arrays["sorted_step"]).reshape(-1)[0])

    def count_contacts(self) -> int:
        return int(np.count_nonzero(self.pairs[3] > 0) + np.count_nonzero(self.planes[4] > 0)
                   + np.count_nonzero(self.cylinders[6] > 0) + np.count_nonzero(self.meshes[5] > 0))

    def deepest_contact(self) -> tuple[float, float]:
        """(the deepest overlap (m), the largest overlap over its contact's smaller radius)
        at the last step, each the maximum over every contact (in a scene of unlike spheres
        they may be two contacts), (0, 0) if none touches. From the overlaps the kernel
        stores per contact: an entry not touching holds its last apart overlap, at most the
        law's lives_above, which is never above 0. A wall contact's radius is its sphere's.

        One pass over each contact array, as count_contacts; the radii are looked up only
        for the contacts that can hold the largest ratio: a contact's ratio is at most its
        overlap over the smallest radius, and the largest is at least the deepest overlap
        over the largest radius, so only overlaps of deepest x smallest / largest or more
        are candidates (in a scene of one radius, the deepest contacts alone)."""
        radius = self.particles[8]
        cylinder_overlap = self.cylinders[6]
        # each kind of contact: its overlaps and the radius of the smaller sphere of each entry
        pair_offsets, partners, rows = self.pairs[0], self.pairs[1], neighbours.rows_of_entries
        kinds = (
            (self.pairs[3], lambda e: np.minimum(radius[rows(pair_offsets, e)], radius[partners[e]])),
            (self.planes[4], lambda k: radius[rows(self.planes[5], k)]),
            (self.meshes[5], lambda k: radius[rows(self.meshes[2], k)]),
            (cylinder_overlap.reshape(-1), lambda k: radius[k // max(1, cylinder_overlap.shape[1])]),
        )
        deepest = max([0.0] + [float(overlap.max()) for overlap, _ in kinds if overlap.size])
        if deepest <= 0.0:
            return 0.0, 0.0
        threshold = deepest * float(radius.min()) / float(radius.max())
        ratio = 0.0
        for overlap, smaller_radius in kinds:
            if overlap.size:
                candidates = np.flatnonzero(overlap >= threshold)
                if candidates.size:
                    ratio = max(ratio, float((overlap[candidates] / smaller_radius(candidates)).max()))
        return deepest, ratio

    def kinetic_energy(self, inertia) -> float:
        return float(integrate.kinetic_energy(self.mass, inertia, self.velocity, self.angular_velocity))
