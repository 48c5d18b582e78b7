"""Validated scene -> compiled simulation -> run result.

``compile_kernel`` specialises the kernel template (``minidem/engine/kernel.py``) for one law
and one scene shape; ``Simulation`` prepares the per-material-pair constants, chooses
the time step and advances the compiled kernel in chunks (no Python call per step or
per contact). Between chunks it rebuilds the Verlet lists when the kernel asks
(carrying every contact's history into the new list), samples the kinetic energy and
hands frames to an output callback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.util
import math
import os
import re
import inspect
import signal
import sys
import time as wallclock
from pathlib import Path

import numba
import numpy as np

from minidem import __version__, codecache
from minidem.contact import history as contact_history, laws
from minidem.engine import blocks, compile_speed, integrate, kernel, warmup
from minidem.errors import MinidemError
from minidem.geometry import neighbours, primitives
from minidem.geometry.order import exchange_pairs, mean_step, permute_rows, scattered, spatial_order
from minidem.scene import derived
from minidem.scene.scenario import Scene, ScenarioError

# OpenMP first: its threads wait briefly at the end of a parallel region instead of
# sleeping, so the two fork-joins of every step cost less than with TBB (20,000 jitter,
# 2,000 steps on two threads: 2.20-2.27 s against 2.42-2.59 s with TBB; 3.50 s on one).
# Only the order of preference: numba falls back to TBB or its workqueue where OpenMP is
# missing, and a user's NUMBA_THREADING_LAYER(_PRIORITY) wins. The layer only schedules
# the explicit blocks of the kernel: results are the same bits on any layer.
if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
    numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
# numba's inliner copies each inlined function's IR once instead of once per basic block
# (the same machine code; a third less CPU in a first run: minidem.engine.compile_speed)
compile_speed.install()

_TEMPLATE = Path(kernel.__file__)
_BLOCK_START = "# >>> specialisation block"
_BLOCK_END = "# <<< specialisation block"
# the files a kernel is built from: the template and the modules it imports
_ENGINE_SOURCES = (Path(kernel.__file__), Path(primitives.__file__), Path(integrate.__file__),
                   Path(contact_history.__file__))
# Scenes with more particles than this run their particle loops in parallel; smaller
# ones run serial and record contact statistics (first touch, separation, peaks).
# A scene with run.stop = "separation" always runs serial: its stop and its contact
# duration need the separation instant, interpolated within the step, which only the
# serial loop can record without a race between threads.
PARALLEL_ABOVE = 16
# A PARALLEL kernel runs its particle loops on one thread, whatever run.threads says, for
# scenes with fewer particles than this: each step forks and joins the threads twice,
# which costs more than the second thread saves below this size (measured on the settle
# scene: docs/multi-particle.md, "Threads"). The results are the same bits either way.
# (The run.threads text in minidem/scene/scenario.py names this number.)
PARALLEL_MIN_PARTICLES = 5000
# Scenes with at least this many particles, in a scattered order, are stored sorted in
# space (minidem.geometry.order): below it the particles' arrays fit the core's own cache
# whatever their order
REORDER_MIN_PARTICLES = 5000
# ... and sorted again at a list rebuild when consecutive particles have drifted this many
# times further apart on average than just after the last sort (the particles mix as they
# flow), if the law declares how its history reads from a contact's other sphere
# (HistorySlot.exchange)
RESORT_RATIO = 2.0
# scene-shape flags of the kernel specialisation block, in order
KERNEL_FLAGS = ("SPIN", "PAIRS", "CYLINDERS", "MESHES", "PARALLEL", "TRACK")
# Automatic time step (docs/time-step.md): the smallest of the accuracy step (contact
# time / steps_per_contact) and these fractions of the Rayleigh time and of the
# integrator's stability limit
RAYLEIGH_FRACTION = 0.2
STABILITY_SAFETY = 0.2


# particle-steps between two copies of the last good state (small scenes: a copy has a
# fixed cost besides the arrays), and at least SNAPSHOT_STEPS steps: a copy costs a step
# or less at any N (bench/settle.toml, N = 2000: 0.13 ms a copy, 0.5 ms a step; N = 20,000:
# 2.2 ms, 1.5-3 ms), so about 1 % of the run
SNAPSHOT_PARTICLE_STEPS = 200_000
SNAPSHOT_STEPS = 100
# and at least this many times the last copy's duration of wall time apart: a copy is
# serial, so at 1 % of a one-thread run it was 2 % of a two-thread one (settle,
# N = 20,000, lattice: 100 steps are 88 ms on two threads, a copy ~2 ms); the copies'
# spacing changes no result (a failure replays from the copy to the last checked step)
SNAPSHOT_COST_RATIO = 200
# Chunks of the compiled loop end at every multiple of a step count fixed by the scene
# (and earlier for a list rebuild, a frame, a checkpoint or a probe of the thread count):
# the spacing of the energy samples (at least 200 a run) or CHECK_PARTICLE_STEPS
# particle-steps, whichever is fewer, but at least CHECK_STEPS steps. Between chunks come
# the blow-up guard's checks (~9 ns a particle of work, shared between a threaded run's
# threads), the thread blocks of the next call (two threads: ~8 ns a particle of work,
# mostly shared; 16-18 ns serial before the first partners were kept per list, see
# minidem.engine.blocks), Python's own work (~0.1 ms) and an unfused drift at
# each end of a call: a small scene is checked at every sample as before, and from
# ~20,000 particles on a chunk is CHECK_STEPS steps at least, so that work costs ~2 % of
# the cheapest steps (~40 ns a particle-step, settle's falling phase; at 20 steps it was
# ~6 % of a two-thread run at N = 1,000,000, whose kernel calls alone ran 1.95x one
# thread's); at N = 1,000,000 that is a chunk of
# ~2 s on one thread, falling, ~10 s in a dense pile (how long a Ctrl-C waits). A grid of
# steps, not of wall time, so the guard's record (the largest work of gravity, taken on
# the grid and at list rebuilds) is the same in a resumed run as in an uninterrupted one.
CHECK_STEPS = 50
CHECK_PARTICLE_STEPS = 1_000_000


class LoopThreads:
    """How many threads run the particle loops, chosen chunk by chunk between one and
    ``most`` (run.threads). Only the speed depends on it: the results are the same bits
    on any count.

    Two threads fork and join twice a step. On a machine shared with other jobs a thread
    descheduled at a join stalls the other, and a run on two threads was up to several
    times slower than on one (docs/multi-particle.md, "Threads"). So the run times its
    chunks (seconds per step) and now and then runs one chunk on the other count, keeping
    the faster. A probe that loses doubles the wait before the next one, up to
    ``PROBE_MAX`` chunks (see CHECK_PARTICLE_STEPS), so losing probes cost a few per cent.
    """

    PROBE_FIRST, PROBE_MAX = 4, 64
    # chunks shorter than this (cut short by a list rebuild) are too noisy to compare
    MIN_STEPS = 10
    # a probe runs this fraction of a chunk (at least 2 MIN_STEPS): a probe that loses
    # costs a quarter of a chunk on the slower count (settle, N = 20,000, lattice, 10,000
    # steps: 1.2 % of the steps on one thread instead of 3 %; run.threads = 2 stays ~2 %
    # behind two threads pinned, 8.77 s against 8.56 s, 2026-11-22 13:40 UTC)
    PROBE_FRACTION = 4

    def __init__(self, most: int):
        self.most = most
        self.current = most
        self.wait = self.PROBE_FIRST
        self.since_probe = 0
        self.seconds_per_step: dict[int, float] = {}
        self.steps: dict[int, int] = {}  # steps run on each count

    def choose(self) -> int:
        if self.most > 1 and self.since_probe >= self.wait:
            return 1 if self.current == self.most else self.most
        return self.current

    def record(self, threads: int, steps: int, seconds: float) -> None:
        self.steps[threads] = self.steps.get(threads, 0) + steps
        if self.most == 1 or steps < self.MIN_STEPS:
            return
        self.seconds_per_step[threads] = seconds / steps
        if threads == self.current:
            self.since_probe += 1
            return
        self.since_probe = 0  # a probe of the other count: keep the faster
        if seconds / steps < self.seconds_per_step.get(self.current, math.inf):
            self.current, self.wait = threads, self.PROBE_FIRST
        else:
            self.wait = min(2 * self.wait, self.PROBE_MAX)

    def most_used(self) -> int:
        return max(self.steps, key=self.steps.get) if self.steps else self.current


class RunFailure(MinidemError):
    """The run started but could not finish: the CLI exits with code 1."""


def _law_source_hash(law: laws.ContactLaw) -> str:
    """Hash of the code the law's force function runs (see minidem.codecache.force_dependencies)."""
    return codecache.force_dependencies(law.force)[0]


_LOADED: dict[str, object] = {}


@functools.lru_cache(maxsize=None)
def _engine_hash() -> str:
    """Hash of the engine sources a kernel is built from: read once per process (a sweep
    builds one Simulation per case, and these files do not change under a running one)."""
    engine = hashlib.sha256()
    for path in _ENGINE_SOURCES:
        engine.update(path.read_bytes())
    return engine.hexdigest()


def compile_kernel(entry: laws.RegisteredLaw, spin: bool, pairs: bool = False, cylinders: bool = False,
                   meshes: bool = False, parallel: bool = False, track: bool = True,
                   integrator: str = "velocity_verlet"):
    """Return the kernel module specialised for ``entry.law``, a scene shape and an
    integrator (compiled lazily, cached on disk). Integrators with the same kick split
    (velocity Verlet and analytic flight) share one kernel."""
    track = track and not parallel  # a parallel loop cannot record contact statistics
    flags = dict(zip(KERNEL_FLAGS, (bool(spin), bool(pairs), bool(cylinders), bool(meshes), bool(parallel),
                                    bool(track))))
    law = entry.law
    # a law with rolling or twisting parts takes the relative spin and returns a couple
    flags["COUPLES"] = bool(law.couples)
    # a law acting beyond touch (adhesion): contacts live down to -reach (the last
    # column of the constants row); without one the kernel is the same code as before
    flags["REACH"] = law.reach is not None
    flags["OPENING_KICK"] = integrate.OPENING_KICK[integrator]
    force_module, force_name = laws.force_import_name(law)
    law_hash, law_dispatchers = codecache.force_dependencies(law.force)
    key = hashlib.sha256(
        f"{_engine_hash()}|{law_hash}|{entry.distribution}|{entry.version}|{force_module}."
        f"{force_name}|{law.force_alone is not None}|{flags}|{law.vector_history_offsets}|{numba.__version__}|"
        f"{__version__}".encode()
    ).hexdigest()[:16]
    # a combination's name joins its parts with '+': a module name takes identifiers only
    module_name = f"minidem_kernel_{re.sub(r'[^A-Za-z0-9_]', '_', law.name)}_{key}"
    if module_name in _LOADED:
        return _LOADED[module_name]
    template = _TEMPLATE.read_text()
    head, rest = template.split(_BLOCK_START, 1)
    _, tail = rest.split(_BLOCK_END, 1)
    block = (f"{_BLOCK_START} (law '{law.name}' from {entry.distribution} {entry.version})\n"
             f"from {force_module} import {force_name} as law_force  # noqa: E402\n"
             + ("from {} import {} as law_force_alone  # noqa: E402\n\n".format(
                 *laws.import_name(law.force_alone, "force_alone"))
                if law.force_alone is not None else "law_force_alone = law_force\n\n")
             + "".join(f"{name} = {value}\n" for name, value in flags.items())
             # the law's vector history slots, as a compile-time constant the kernel unrolls
             + f"VECTOR_OFFSETS = {tuple(law.vector_history_offsets)!r}\n" + _BLOCK_END)
    path = codecache.cache_directory() / f"{module_name}.py"
    if not path.exists():
        # A new kernel: the code the law calls is new to this cache. Its functions' own
        # numba caches may hold machine code built against an older helper (numba checks
        # only each function's own file), and compiling the kernel would link that in:
        # drop them, so that they are compiled from the current sources.
        for dispatcher in law_dispatchers:
            cache = getattr(dispatcher, "_cache", None)
            if cache is not None:
                cache.flush()
        # written once and never touched again: numba keys its cache on the file's stamp
        tmp = path.with_suffix(f".tmp{os.getpid()}")
        tmp.write_text(head + block + tail)
        os.replace(tmp, path)
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    spec.loader.exec_module(module)
    _LOADED[module_name] = module
    return module


@dataclasses.dataclass
class RunResult:
    scene: Scene
    law: laws.ContactLaw
    constants: dict
    position: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    initial_velocity: np.ndarray
    initial_angular_velocity: np.ndarray
    steps: int
    dt: float
    dt_reason: str
    time: float
    separated: bool
    first_contact_time: float
    last_separation_time: float
    max_overlap: float
    peak_normal_force: float
    peak_tangential_force: float
    wall_time: float
    trace: np.ndarray | None
    force: np.ndarray | None = None
    torque: np.ndarray | None = None
    contacts: int = 0  # touching pairs and wall contacts at the end
    neighbour_builds: int = 0
    threads: int = 1  # threads that ran the particle loops for most of the steps (see LoopThreads)
    thread_steps: dict | None = None  # {threads: steps run on that many}
    energy: np.ndarray | None = None  # rows (time s, translational + rotational kinetic energy J)
    # False when the parallel loop ran: it records first touch (to the step) but not the
    # peaks and the separation, which would need a race between threads
    contact_statistics: bool = True
    # the largest work gravity did on the particles since t = 0 (J), at the run's checks
    gravity_work_max: float = 0.0
    # the most kinetic energy the contacts can supply at once (J): adhesion's bound per
    # contact times the most contacts (Simulation._prepare_reach); 0 for passive laws
    supply_budget: float = 0.0


# State arrays a checkpoint holds: particle arrays, then the contact arrays of each
# argument tuple by position (None: fixed by the scene, not saved)
_STATE_ARRAYS = ("position", "velocity", "angular_velocity", "force", "torque", "position_at_build")
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
              "pair_reaction_in_use", None),
}


# per-contact arrays whose rows are all zero while the contact is not touching (a contact
# that ends drops its history and its reaction): the last good state keeps only the rows
# in use (State.capture)
_SPARSE_ROWS = ("plane_history", "cylinder_history", "mesh_history", "pair_history", "pair_reaction",
                "pair_reaction_in_use")
# The Verlet lists follow from the position at the last build (State.build_lists: the
# same lists, bit for bit), so a capture does not hold them and State.restore makes them
# again. Held, the old lists stayed resident from a rebuild to the next copy of the state,
# and at the rebuild itself beside the old and the new list: 20 bytes a particle of the
# settle scene at 1,000,000 (docs/benchmarks.md, "Memory per particle"). Files hold them
# (_RunLoop.write_state): a script reading pair_history needs its pairs.
_LISTS = ("pair_offsets", "pair_neighbours", "mesh_offsets", "mesh_candidates")
_SPARSE_PARTS = ("@rows", "@values", "@shape")
_SPARSE_BLOCK = 1 << 16  # rows scanned at a time


def _sparse_rows(name: str, array: np.ndarray) -> dict[str, np.ndarray]:
    """``array`` as its rows (first index) that hold any non-zero bit: {name@rows: their
    indices, name@values: the rows, name@shape: the shape}. Bits, not values, so a row
    of -0.0 is kept and the expansion gives every bit back."""
    rows = np.zeros(0, dtype=np.int64)
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
            found.append(np.flatnonzero(in_use) + start)
        rows = np.concatenate(found)
    return {name + "@rows": rows, name + "@values": np.take(array, rows, axis=0),
            name + "@shape": np.array(array.shape, dtype=np.int64)}


def _full_array(arrays: dict, name: str) -> np.ndarray:
    """The array ``name`` of a capture, expanded if it was captured sparse."""
    if name in arrays:
        return arrays[name]
    full = np.zeros(tuple(arrays[name + "@shape"]), dtype=arrays[name + "@values"].dtype)
    full[arrays[name + "@rows"]] = arrays[name + "@values"]
    return full


def full_arrays(arrays: dict) -> dict[str, np.ndarray]:
    """A capture with its sparse arrays expanded: the arrays a checkpoint file holds."""
    out = {name: array for name, array in arrays.items() if "@" not in name}
    for name in _SPARSE_ROWS:
        if name + "@rows" in arrays:
            out[name] = _full_array(arrays, name)
    return out


@functools.cache
def _c_library():
    """glibc, for malloc_trim; None elsewhere (another C library: nothing is released)."""
    import ctypes

    try:
        library = ctypes.CDLL(None)
        library.malloc_trim  # noqa: B018 - present in glibc only
        return library
    except (AttributeError, OSError):
        return None


def release_free_memory() -> None:
    """Give the free pages of the C heap back to the system (glibc's malloc_trim), after
    a neighbour-list rebuild: the build's temporaries and the old list, freed, stay
    resident otherwise (glibc serves blocks below its mmap threshold, which it raises to
    the size of every mapped block freed, up to 32 MiB, from the heap). The allocation
    policy is unchanged (unlike fixing the mmap threshold, which made every large
    temporary of the step loop a fresh mapping, 3.4 % slower, see docs/multi-particle.md):
    pages the next rebuild takes are faulted in again, a fraction of a millisecond. Settle
    jitter N = 20,000, 10,000 steps, one thread: peak 187.5 -> 183.0 MB."""
    library = _c_library()
    if library is not None:
        library.malloc_trim(0)


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


def pair_arrays(offsets, partners, history, overlap, slot, reverse_offsets):
    """The kernel's pair tuple for a new list (``State.pairs``): its reactions zero and no
    pair touching yet. The reactions are in the transposed list's order (row ``slot[e]``
    for entry e), and so is ``reaction_in_use``, which marks the rows holding a touching
    pair's reaction; the force pass stores them for the partners finish_kick_drift
    finishes and, at a call's last step, for every touching pair (State.contact_pairs),
    and sums the others' straight into their force rows, marking those particles in
    ``reaction_pending`` (a byte a particle, zero between passes; see
    minidem.engine.kernel)."""
    return (offsets, partners, history, overlap, np.zeros((partners.shape[0], 6)), slot, reverse_offsets,
            np.zeros(partners.shape[0], dtype=np.uint8), np.zeros(offsets.shape[0] - 1, dtype=np.uint8))


class State:
    """The arrays the compiled kernel advances, grouped as it takes them.

    ``pairs`` and ``meshes`` hold Verlet lists (CSR) with one history row per entry, and
    ``planes`` the list of planes near each sphere likewise (:meth:`list_near_planes`);
    :meth:`Simulation.rebuild` replaces them, carrying every entry's history over.
    """

    def __init__(self, sim: "Simulation"):
        scene, walls = sim.scene, sim.scene.walls
        n, h = scene.n_particles, sim.law.history_size
        # the state at sim.start_time (t = 0, or first touch after an analytic flight)
        self.position = sim.start_position.copy()
        self.velocity = sim.start_velocity.copy()
        self.angular_velocity = scene.angular_velocity.copy()
        self.force = np.zeros((n, 3))
        self.torque = np.zeros((n, 3))
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
        # (offsets, partners, history, overlap, reactions (force on i, torque on j) in the
        # transposed list's order, each entry's slot there,
        # transposed offsets, whether each slot's pair touches: pair_arrays)
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
                          self.mass, 1.0 / self.mass, 1.0 / self.inertia, self.radius, scene.particle_material)

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
            neighbours.carry_history(*self.planes[5:], *self.planes[3:5], offsets, planes, history, overlap)
        self.planes = (wall_point, wall_normal, wall_material, history, overlap, offsets, planes)

    def build_lists(self, position: np.ndarray | None = None, radius: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The Verlet lists at ``position`` (default position_at_build), by their names in a
        capture (_LISTS): the pairs closer than their radii plus ``pair_cutoff`` (partners
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
        """The Verlet lists of a capture (which holds none, _LISTS): the live ones if it
        was taken since the last list build (it holds the live position at build), else
        made from its position at build (also while a rebuild has let go of the live pair
        list: an interrupt's checkpoint)."""
        if self.pairs is not None and np.array_equal(arrays["position_at_build"], self.position_at_build):
            return {name: array for name, array in self.live_arrays().items() if name in _LISTS}
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
    def capture(self, into: dict | None = None) -> dict[str, np.ndarray]:
        """Copies of every array the kernel carries from one step to the next (the contact
        histories exactly as they are, rows aligned with the lists at the position at
        build); the Verlet lists not at all (``_LISTS``: :meth:`restore` makes them
        again from the position at build, :meth:`lists_of` for a file).

        ``into``: an earlier capture, overwritten in place and returned: its arrays are
        reused where their shapes still fit (a copy into existing memory is ten times
        cheaper than a new allocation), and one that no longer fits is released before
        its replacement is allocated, so that a run never holds two old copies.

        The per-contact histories and reactions (``_SPARSE_ROWS``) are kept as their
        non-zero rows only (see :func:`_sparse_rows`): a row is zero while its
        wall or pair is not touching, most of them in a pile (a sphere of the settle
        scene touches no wall, and about two in three of its listed pairs are apart),
        so the last good state costs about half the memory of the live one.
        :meth:`restore` and :func:`full_arrays` (what a checkpoint file holds) give the
        same bits back.
        """
        live = self.live_arrays()
        del live["builds"]
        arrays = {} if into is None else into
        for name, array in live.items():
            target = arrays.pop(name, None)
            if name in _LISTS:
                del target
            elif name in _SPARSE_ROWS:
                del target
                for part in _SPARSE_PARTS:
                    arrays.pop(name + part, None)  # the old copy goes before the new one is made
                arrays.update(_sparse_rows(name, array))
            elif target is not None and target.shape == array.shape and target.dtype == array.dtype:
                np.copyto(target, array)
                arrays[name] = target
            else:
                del target
                for part in _SPARSE_PARTS:
                    arrays.pop(name + part, None)
                arrays[name] = array.copy()
        arrays["builds"] = np.array(self.builds, dtype=np.int64)
        return arrays

    def live_arrays(self) -> dict[str, np.ndarray]:
        """The arrays :meth:`capture` copies, as they are (no copy: for a file written
        before the kernel runs again, e.g. the final state)."""
        live = {name: getattr(self, name) for name in _STATE_ARRAYS}
        for group, names in _STATE_TUPLES.items():
            live.update((name, array) for name, array in zip(names, getattr(self, group)) if name is not None)
        live["builds"] = np.array(self.builds, dtype=np.int64)
        live["sorted_step"] = np.array([self.sorted_step])  # m; an array of one, as the files hold
        if self.particle_id is not None:  # rows in a stored order (Simulation.use_order)
            live["particle_id"] = self.particle_id
        return live

    def restore(self, arrays: dict) -> None:
        for name in _STATE_ARRAYS:  # in place: the kernel's particle tuple holds these arrays
            getattr(self, name)[...] = arrays[name]
        # a capture holds no lists (_LISTS): those of the restored position at build, again
        lists = {} if all(name in arrays for name in _LISTS) else self.build_lists()
        for group, names in _STATE_TUPLES.items():
            items = list(getattr(self, group))
            for k, name in enumerate(names):
                if name in lists:
                    items[k] = lists[name]
                elif name is not None:  # replaced: list rebuilds change the lengths
                    items[k] = np.array(_full_array(arrays, name), dtype=items[k].dtype, order="C")
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
        self.pairs = self.pairs[:5] + (slot, reverse_offsets) + self.pairs[7:]
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

    def kinetic_energy(self, inertia) -> float:
        return float(integrate.kinetic_energy(self.mass, inertia, self.velocity, self.angular_velocity))


class Simulation:
    """A scene bound to a compiled kernel, its constants and its time step."""

    def __init__(self, scene: Scene, registry: laws.LawRegistry | None = None, kernel_flags: dict | None = None,
                 compile: bool = True, notify=None):
        """``kernel_flags`` forces scene-shape flags on (e.g. {"PAIRS": True}) to measure
        what modelling only what a scene needs saves (``minidem bench``); results are
        the same, only the cost differs. ``compile=False`` stops after the constants, the
        time step and the checks of what they imply (validation: a sweep's every case,
        the input fuzz test); such a Simulation cannot run. ``notify(text)``: told what is
        being prepared when a law's prepare() or the kernel's compilation takes more than
        SLOW_NOTICE_S (the CLI prints it), so a long wait is never silent."""
        self.scene = scene
        self.notify = notify
        if scene.walls is None:  # a Scene built by hand: planes only
            from minidem.geometry.walls import WallSet

            scene.walls = WallSet.empty()
            scene.walls.set_planes(scene.wall_point, scene.wall_normal, scene.wall_material)
        registry = registry or laws.registry()
        self.entry = registry.entry(scene.law_name)
        self.law = self.entry.law
        # spin is needed when any material pair can carry a tangential force
        self.spin = any(self.law.is_frictional(params)
                        for params in (scene.law_parameters, *scene.pair_parameters.values()))
        self.pairs = scene.n_particles > 1
        # the multi-particle path, without contact statistics (only the serial loop of small
        # scenes and of runs to separation records them: kernel flag TRACK)
        self.parallel = scene.n_particles > PARALLEL_ABOVE and scene.stop != "separation"
        # its particle loops threaded (prange) only where a second thread can run them: a
        # scene below PARALLEL_MIN_PARTICLES runs on one thread whatever run.threads says,
        # and the serial kernel does the same operations in the same order (the same bits)
        # without numba's parallel pipeline, 33 of the 44 s of CPU of the first run of
        # scenarios/settle.toml (kernel flag PARALLEL)
        self.threaded = self.parallel and scene.n_particles >= PARALLEL_MIN_PARTICLES
        # A scattered scene is stored in space order (minidem.geometry.order): everything
        # from here on, the kernel and the files of its state (with particle_id), sees the
        # stored order; the results (RunResult, the VTK frames) come back in the scenario's.
        # Never for the serial, tracked loop: its probe is particle 0 of the scenario.
        self.input_scene = scene
        # (nor for a scene that records a trace: trace.csv follows the particle stored first)
        self.in_space_order = (self.parallel and scene.n_particles >= REORDER_MIN_PARTICLES
                               and scene.particle_id is None and not scene.trace)
        signs = self.law.exchange_signs
        # sorted again during the run (rebuild) only when the law says how a contact's
        # history reads from its other sphere: a sort can exchange the two
        self.exchange_signs = np.array(signs) if self.in_space_order and self.pairs and signs is not None else None
        self.skin = scene.skin if scene.skin is not None else 0.5 * float(scene.radius.max())
        # cells of half the list cutoff (LAMMPS' default bin for its sort): a jittered
        # lattice has one sphere a cell and sorts back to its fill's layers and rows
        self.sort_cell = 0.5 * (2.0 * float(scene.radius.max()) + self.skin)
        self.resort_ratio = RESORT_RATIO
        if self.in_space_order:
            order = self.space_order(scene.position)
            if scattered(scene.position, order):
                self.scene = scene = scene.reordered(order)
        # the order every run starts in (a run may sort the particles again: Simulation.scene)
        self.start_scene = self.scene
        # what the values imply (constants, contact time, dt, step count), checked before
        # the kernel is compiled: out of float64 range is bad input naming the keys
        with derived.arithmetic(scene, "deriving the contact constants and the time step"):
            self._prepare_constants()
            self.dt, self.dt_reason = self._choose_time_step()
            self._plan_flight()
        derived.check_simulation(self)
        self.state: State | None = None
        self.interrupted_at: tuple[float, Path] | None = None  # (time s, checkpoint) after Ctrl-C
        if not compile:
            return
        forced = kernel_flags or {}
        self.spin = forced.get("SPIN", self.spin)
        self.pairs = forced.get("PAIRS", self.pairs)
        self.parallel = forced.get("PARALLEL", self.parallel)
        self.threaded = forced.get("PARALLEL", self.threaded)
        with _notice_if_slow(notify, f"compiling (or loading from the cache) the kernel of law '{self.law.name}' "
                             "for this scene"):
            self.kernel = compile_kernel(self.entry, self.spin, self.pairs,
                                         forced.get("CYLINDERS", scene.walls.cylinder_base.shape[0] > 0),
                                         forced.get("MESHES", scene.walls.triangles.shape[0] > 0), self.threaded,
                                         not self.parallel,
                                         scene.integrator)

    # -- constants -------------------------------------------------------------
    def _reference_size(self) -> tuple[float, float]:
        scene = self.scene
        if scene.impact is not None:
            return float(scene.radius[0]), float(scene.mass[0])
        if self._two_sphere_collision() is not None:
            # the one contact there will be: its effective radius and mass
            r, m = scene.radius, scene.mass
            return float(r[0] * r[1] / (r[0] + r[1])), float(m[0] * m[1] / (m[0] + m[1]))
        return float(scene.radius.mean()), float(scene.mass.mean())

    def _two_sphere_collision(self) -> float | None:
        """The normal approach speed of a scene of two spheres, no walls and no gravity,
        that move towards each other (Chung & Ooi tests 1, 7, 8): the reference speed of
        laws calibrated from one (the linear spring's eq 28), as an [impact] speed is."""
        scene = self.scene
        if scene.impact is not None or scene.n_particles != 2 or scene.has_walls or np.any(scene.gravity != 0.0):
            return None
        n = scene.position[0] - scene.position[1]
        speed = -float((scene.velocity[0] - scene.velocity[1]) @ n) / float(np.linalg.norm(n))
        return speed if speed > 0.0 else None

    def _prepare_constants(self) -> None:
        scene, law = self.scene, self.law
        materials = scene.materials
        n = len(materials)
        radius, mass = self._reference_size()
        speed = scene.impact.speed if scene.impact is not None else self._two_sphere_collision()
        self.pair_row = np.zeros((n, n), dtype=np.int64)
        rows, self.pairs_, self.constants_by_pair = [], {}, {}
        for a in range(n):
            for b in range(a, n):
                pair = laws.ContactPair.from_materials(materials[a], materials[b], radius, mass, speed)
                try:
                    with _notice_if_slow(self.notify, f"preparing law '{law.name}' ({self.entry.distribution}) for "
                                         f"materials '{materials[a].name}'/'{materials[b].name}' (its prepare() "
                                         f"is still running)"):
                        row, named = law.prepared_constants(pair, scene.pair_parameters.get((a, b),
                                                                                            scene.law_parameters))
                except laws.LawError:
                    raise
                except laws.PLUGIN_FAULTS as exc:  # a plugin's prepare() is user code (sys.exit too)
                    # a ValueError is how prepare() refuses parameters (its message is for the
                    # user); anything else is a bug in it: say what and where
                    why = str(exc) if type(exc) is ValueError else laws._one_line(exc)
                    # the scenario and its key too: the values prepare() refused are the user's
                    raise laws.LawError(f"{scene.source}: contact: law '{law.name}' ({self.entry.distribution}): "
                                        f"prepare() failed for materials '{materials[a].name}'/"
                                        f"'{materials[b].name}': {why}") from exc
                self.pair_row[a, b] = self.pair_row[b, a] = len(rows)
                rows.append(row)
                self.pairs_[(a, b)] = pair
                self.constants_by_pair[(a, b)] = named
        self.constants = np.array(rows, dtype=np.float64).reshape(len(rows), len(law.constants))
        self._prepare_reach()

    def _prepare_reach(self) -> None:
        """A law acting beyond touch: its reach per material pair at the scene's largest
        R* (a sphere on a wall: its radius; two spheres: at most half the largest), kept
        as the last column of the constants row (the kernel reads it there; the parts
        index their own columns from the start), and the largest for the neighbour
        search. The adhesion budget of the energy guard: the law's supply bound per
        contact times the most contacts the scene can hold at once."""
        scene, law = self.scene, self.law
        self.max_reach, self.supply_budget = 0.0, 0.0
        largest_radius = float(scene.radius.max())
        keys = sorted(self.pairs_, key=lambda key: self.pair_row[key])
        if law.reach is not None:
            if scene.walls.triangles.shape[0]:
                raise laws.LawError(f"law '{law.name}' acts beyond touch (reach > 0): mesh walls do not support that "
                                    "yet; use plane or cylinder walls")
            reach = np.array([float(law.reach(self.pairs_[k], self.constants_by_pair[k], largest_radius))
                              for k in keys])
            if not np.all(np.isfinite(reach)) or np.any(reach < 0.0):
                raise laws.LawError(f"law '{law.name}': its reach {reach.tolist()} m must be finite and >= 0")
            self.constants = np.hstack([self.constants, reach[:, None]])
            self.max_reach = float(reach.max())
        if law.supply_bound is not None:
            per_contact = max(float(law.supply_bound(self.pairs_[k], self.constants_by_pair[k], largest_radius))
                              for k in keys)
            n = scene.n_particles
            walls = scene.walls.plane_point.shape[0] + scene.walls.cylinder_base.shape[0]
            # at most 12 equal spheres touch one (kissing number; 6 N pairs), each sphere
            # at most every plane and cylinder wall
            self.supply_budget = per_contact * (6 * n * (n > 1) + n * walls)

    # -- time step ---------------------------------------------------------------
    def characteristic_speed(self) -> float:
        scene = self.scene
        if scene.impact is not None:
            normal_speed = scene.impact.speed * max(math.cos(math.radians(scene.impact.angle_deg)), 1e-3)
            # gravity towards the wall over impact.gap speeds the sphere up before it touches
            n = scene.impact.normal
            wall = scene.impact.wall
            gap = max(float((scene.position[0] - scene.wall_point[wall]) @ n) - float(scene.radius[0]), 0.0)
            towards = max(-float(scene.gravity @ n), 0.0)
            return math.sqrt(normal_speed**2 + 2.0 * towards * gap)
        speeds = np.linalg.norm(scene.velocity, axis=1)
        extent = float(np.ptp(scene.position, axis=0).max() + 2 * scene.radius.max()) if scene.n_particles else 0.0
        fall = math.sqrt(2.0 * float(np.linalg.norm(scene.gravity)) * extent)
        # two particles may approach at twice the largest speed
        fastest = float(speeds.max(initial=0.0)) * (2.0 if scene.n_particles > 1 else 1.0)
        return max(fastest, fall, 1e-3)

    def contact_kinds(self):
        """(pair, named constants, effective radius, effective mass) of every kind of contact
        the scene can have: the smallest particle of each material against each wall
        material and against each particle material (two equal spheres: R/2, m/2)."""
        scene, walls = self.scene, self.scene.walls
        wall_materials = set(walls.plane_material.tolist()) | set(walls.cylinder_material.tolist()) \
            | set(walls.triangle_material.tolist())
        kinds = []
        for material in np.unique(scene.particle_material):
            members = scene.particle_material == material
            smallest = np.argmin(np.where(members, scene.radius, np.inf))
            r, m = float(scene.radius[smallest]), float(scene.mass[smallest])
            for other in sorted(wall_materials):
                key = (min(material, other), max(material, other))
                kinds.append((self.pairs_[key], self.constants_by_pair[key], r, m, "sphere-wall"))
            if scene.n_particles > 1:
                for other in np.unique(scene.particle_material):
                    key = (min(material, other), max(material, other))
                    kinds.append((self.pairs_[key], self.constants_by_pair[key], r / 2, m / 2, "sphere-sphere"))
        return kinds

    def contact_time(self) -> float:
        """Shortest normal-impact duration among the contact kinds the scene can have."""
        speed = self.characteristic_speed()
        times = [laws.law_contact_time(self.law, pair, named, r, m, speed)
                 for pair, named, r, m, _ in self.contact_kinds()]
        return min(times) if times else math.inf

    def rayleigh_time(self) -> float:
        """Rayleigh-wave crossing time of the smallest particle of each material,
        pi R sqrt(rho/G) / (0.1631 nu + 0.8766), the usual DEM time-step scale."""
        scene, times = self.scene, []
        for material in np.unique(scene.particle_material):
            mat = scene.materials[material]
            radius = float(scene.radius[scene.particle_material == material].min())
            shear = mat.youngs_modulus / (2.0 * (1.0 + mat.poisson_ratio))
            times.append(math.pi * radius * math.sqrt(mat.density / shear) / (0.1631 * mat.poisson_ratio + 0.8766))
        return min(times) if times else math.inf

    def stability_limit(self) -> tuple[float, str]:
        """Largest stable dt of the integrator on the scene's stiffest contact mode, and why.

        Velocity Verlet and symplectic Euler (the same positions) are stable on a linear
        oscillator of frequency omega for dt < 2/omega, or (2/omega)(sqrt(1 + zeta^2) - zeta)
        with damping ratio zeta. Each contact kind has a normal mode, omega^2 = kn/m*, and
        when it can carry friction a tangential mode in which the contact point moves
        against both the translation and the rotation of the sphere(s),
        omega^2 = kt (1/m* + R^2/I) = 3.5 kt/m* for solid spheres (I = 2/5 m R^2). The
        stiffnesses are the law's (``ContactLaw.stiffness``) at the largest overlap the
        scene should reach: Hertz's at the characteristic impact speed (eq 12) or under
        the particle's weight, whichever is larger.
        """
        speed = self.characteristic_speed()
        gravity = float(np.linalg.norm(self.scene.gravity))
        best, why = math.inf, "no contact possible"
        for pair, named, r, m, kind in self.contact_kinds():
            k_hertz = 4.0 / 3.0 * pair.effective_modulus * math.sqrt(r)
            impact = (15.0 * m * speed**2 / (16.0 * pair.effective_modulus * math.sqrt(r))) ** 0.4
            weight = (m * gravity / k_hertz) ** (2.0 / 3.0)
            overlap = max(impact, weight)
            normal, tangential, zeta = laws.law_stiffness(self.law, pair, named, r, m, overlap)
            # name the overlap only when the stiffness depends on it (not for a linear spring)
            depends = laws.law_stiffness(self.law, pair, named, r, m, 2.0 * overlap)[:2] != (normal, tangential)
            modes = [("normal", math.sqrt(normal / m), zeta)]
            if self.spin:
                modes.append(("tangential", math.sqrt(3.5 * tangential / m), 0.0))
            for mode, omega, damping in modes:
                limit = 2.0 / omega * (math.sqrt(1.0 + damping**2) - damping)
                if limit < best:
                    best = limit
                    why = (f"{mode} mode of a {kind} contact, omega = {omega:.4g} rad/s"
                           + (f", damping ratio {damping:.3g}" if damping else "")
                           + (f", stiffness at overlap {overlap:.3g} m" if depends else ""))
        return best, why

    def _choose_time_step(self) -> tuple[float, str]:
        scene = self.scene
        self.reference_contact_time = self.contact_time()
        self.stability, stability_why = self.stability_limit()
        limit_text = (f"stability limit {self.stability:.4g} s of run.integrator = \"{scene.integrator}\" "
                      f"({stability_why})")
        if scene.dt is not None:
            if scene.dt <= self.stability:
                return scene.dt, f"given in the scenario; {limit_text}"
            if not scene.allow_unstable_dt:
                suggested = self._automatic_time_step()[0]
                raise ScenarioError(
                    f"{scene.source}: run.dt = {scene.dt:.4g} s is above the {limit_text}; give run.dt <= "
                    f"{self.stability:.4g} s (suggested: {suggested:.4g} s, what run.dt = \"auto\" chooses), or "
                    "set run.allow_unstable_dt = true to run it anyway")
            import warnings

            warnings.warn(f"{scene.source}: run.dt = {scene.dt:.4g} s is {scene.dt / self.stability:.3g} times the "
                          f"{limit_text}: allowed by run.allow_unstable_dt", stacklevel=2)
            return scene.dt, f"given in the scenario, ABOVE the {limit_text} (run.allow_unstable_dt)"
        if not math.isfinite(self.reference_contact_time):
            raise ScenarioError(f"{scene.source}: run.dt = \"auto\" needs a possible contact (walls or two "
                                "particles); give run.dt")
        return self._automatic_time_step()

    def _automatic_time_step(self) -> tuple[float, str]:
        scene = self.scene
        rayleigh = self.rayleigh_time()
        candidates = [
            (self.reference_contact_time / scene.steps_per_contact,
             f"contact time {self.reference_contact_time:.4g} s / {scene.steps_per_contact} steps per contact"),
            (RAYLEIGH_FRACTION * rayleigh, f"{RAYLEIGH_FRACTION:g} x Rayleigh time {rayleigh:.4g} s"),
            (STABILITY_SAFETY * self.stability, f"{STABILITY_SAFETY:g} x stability limit {self.stability:.4g} s"),
        ]
        dt, reason = min(candidates)
        others = "; ".join(text for value, text in candidates if text != reason)
        return dt, f"auto: {reason} (the smallest of that, {others})"

    def _plan_flight(self) -> None:
        """run.integrator = "analytic_flight": the free flight before the first contact in
        closed form (minidem.engine.integrate.flight_to_first_touch); the run starts at touch."""
        scene = self.scene
        self.start_time = 0.0
        self.start_position, self.start_velocity = scene.position, scene.velocity
        walls = scene.walls
        # the free flight before first touch, also when it is stepped: the default
        # run.end_time of a single impact allows for it (a sphere released far from the
        # wall must still reach it)
        self.flight_time, flight = 0.0, None
        if scene.one_sphere_among_planes:
            flight = integrate.flight_to_first_touch(scene.position[0], scene.velocity[0], float(scene.radius[0]),
                                                     scene.wall_point, scene.wall_normal, scene.gravity)
            self.flight_time = flight[0] if flight is not None else 0.0
        if scene.integrator != "analytic_flight":
            return
        if not scene.one_sphere_among_planes:
            raise ScenarioError(f"{scene.source}: run.integrator = \"analytic_flight\" needs one particle and "
                                f"plane walls only (the scene has {scene.n_particles} particles, "
                                f"{walls.cylinder_base.shape[0]} cylinders, {walls.triangles.shape[0]} triangles); "
                                "use \"velocity_verlet\"")
        if flight is None:
            return
        duration, position, velocity, _ = flight
        if scene.end_time is not None and duration > scene.end_time:
            return  # no contact within the run: stepping it is as exact (constant force)
        self.start_time = duration
        self.start_position, self.start_velocity = position[None, :].copy(), velocity[None, :].copy()

    @property
    def end_time(self) -> float:
        """run.end_time, or the default: the flight to first touch and 100 contact times."""
        scene = self.scene
        if scene.end_time is not None:
            return scene.end_time
        return max(self.start_time, self.flight_time) + 100.0 * self.reference_contact_time

    # -- the order particles are stored in (minidem.geometry.order) ---------------------
    def use_order(self, state: State, particle_id) -> None:
        """Store the particles in the order ``particle_id`` names (the scenario's index of
        each row; None: the scenario's own order): the scene's arrays in that order and the
        state's tuple of them. The state's own arrays are the caller's to put in order (a
        restore reads them from a copy taken in that order)."""
        current = self.scene.particle_id
        if (particle_id is None and current is None) or (
                particle_id is not None and current is not None and np.array_equal(particle_id, current)):
            return
        self.scene = (self.input_scene if particle_id is None else
                      self.input_scene.reordered(np.asarray(particle_id, dtype=np.int64)))
        state.follow_scene(self.scene)

    def space_order(self, position: np.ndarray) -> np.ndarray:
        """The order the particles at ``position`` are stored in when sorted (``order[k]``:
        the particle stored at k). ``minidem verify`` replaces it on an instance, with a
        reversal at every list build (and ``resort_ratio`` 0), to check a law's
        HistorySlot.exchange."""
        return spatial_order(position, self.sort_cell)

    def sort_in_space(self, state: State) -> None:
        """Store the particles sorted in space again, with everything that has a row per
        particle, or per contact of a particle, in the new order: a pair whose spheres' order
        turns over is listed under the other sphere, its history as seen from there
        (HistorySlot.exchange). Between list builds: the lists made next start from it."""
        order = self.space_order(state.position)
        for name in _STATE_ARRAYS:
            setattr(state, name, getattr(state, name)[order])
        stored = self.scene.particle_id
        self.use_order(state, order if stored is None else stored[order])
        state.follow_scene(self.scene)  # the tuple of the arrays just made, whatever the order
        cylinders = state.cylinders
        state.cylinders = cylinders[:5] + (cylinders[5][order], cylinders[6][order])
        planes = state.planes
        offsets, (near, history, overlap) = permute_rows(planes[5], order, planes[6], planes[3], planes[4])
        state.planes = planes[:3] + (history, overlap, offsets, near)
        meshes = state.meshes
        offsets, (candidates, history, overlap) = permute_rows(meshes[2], order, meshes[3], meshes[4], meshes[5])
        state.meshes = meshes[:2] + (offsets, candidates, history, overlap)
        # the old list's reactions and transposed index go first (rebuilt after the list):
        # the renumbering holds the old list and the new one, not the whole pair tuple twice
        old, state.pairs = state.pairs[:4], None
        state.pairs = exchange_pairs(*old, order, self.exchange_signs) + (None,) * 5
        del old
        state.first_partner = None
        state.sorted_step = mean_step(state.position)
        state.sorts += 1

    # -- neighbour lists -----------------------------------------------------------
    def rebuild(self, state: State) -> None:
        """New Verlet lists at the current positions; every contact keeps its history.
        The particles are first sorted in space again when they have mixed (RESORT_RATIO)."""
        if (self.exchange_signs is not None and state.builds > 0
                and mean_step(state.position) > self.resort_ratio * state.sorted_step):
            self.sort_in_space(state)
        radius = self.scene.radius
        lists = None
        if self.pairs:
            old = state.pairs[:4]  # offsets, partners, history, overlap
            # The old list is referenced by ``old`` alone from here, and released once its
            # histories are carried over, before the reactions and their slots are
            # allocated: at its peak a rebuild holds the old list and the new one with its
            # histories, not two whole sets of pair arrays.
            state.pairs = None
            # likewise the old list's first partners (8 bytes a particle), recomputed with the
            # new list; a failure leaves none (State.restore recomputes them with the lists)
            state.first_partner = None
            try:
                lists = state.build_lists(state.position)  # the position at build from here on
                offsets, found = lists["pair_offsets"], lists["pair_neighbours"]
                # zeros from the operating system: rows no contact is carried into stay
                # unwritten (not resident) until a contact starts there
                history = np.zeros((found.shape[0], old[2].shape[1]))
                # a pair new to the list starts with overlap -1 (apart: the skin guarantees it)
                overlap = np.full(found.shape[0], -1.0)
                neighbours.carry_history(*old, offsets, found, history, overlap)
            except BaseException:
                state.pairs = old + (None, None, None, None)  # as before the call (a failure restores from it)
                raise
            del old
            if state.builds == 0:
                # t = 0: spheres may start touching; their overlap is the 'previous' one.
                # A few rows at a time: whole-list temporaries (three (M, 3) arrays) were
                # the peak of a large run's set-up (200 bytes a particle at N = 1,000,000)
                rows_at_once = 1 << 16
                for start in range(0, len(radius), rows_at_once):
                    stop = min(start + rows_at_once, len(radius))
                    entries = slice(offsets[start], offsets[stop])
                    first = np.repeat(np.arange(start, stop), np.diff(offsets[start:stop + 1]))
                    overlap[entries] = radius[first] + radius[found[entries]] - np.linalg.norm(
                        state.position[first] - state.position[found[entries]], axis=1)
            reverse_offsets, slot, state.first_partner = neighbours.reverse_index(offsets, found, len(radius))
            state.pairs = pair_arrays(offsets, found, history, overlap, slot, reverse_offsets)
        if state.meshes[0].shape[0]:
            triangles, triangle_material, old_offsets, old_found, old_history, old_overlap = state.meshes
            lists = lists or state.build_lists(state.position)
            offsets, found = lists["mesh_offsets"], lists["mesh_candidates"]
            history = np.zeros((found.shape[0], old_history.shape[1]))
            overlap = np.full(found.shape[0], -1.0)
            neighbours.carry_history(old_offsets, old_found, old_history, old_overlap, offsets, found, history,
                                     overlap)
            state.meshes = (triangles, triangle_material, offsets, found, history, overlap)
        # in place: a new array beside the old one, which the last good state held, was 24
        # bytes a particle more at the peak of a large run's rebuild
        np.copyto(state.position_at_build, state.position)
        state.list_near_planes()
        state.builds += 1
        # The freed pages go back to the system in a run on one thread only. A threaded
        # run keeps them for the next build, which would take their page faults again
        # on all its threads at once: 7.5 % of its time (N = 200,000 lattice, two threads,
        # 3,000 steps, five pairs interleaved: 19.35 s against 20.93 s by medians, every
        # pair faster; on one thread 32.0 against 32.3 s, not resolved; peaks 334-340 MiB
        # against 323-339). Decided by the run's thread count, not the chunk's: a
        # threaded run probes or falls back to one thread for some chunks (LoopThreads)
        if self.loop_threads() == 1:
            release_free_memory()

    # -- running -----------------------------------------------------------------
    def run(self, chunk_steps: int = 200_000, progress=None, on_frame=None, checkpoints=None,
            resume_from=None) -> RunResult:
        """Run the scene.

        progress(steps, total_steps, contacts): called after every chunk (at every energy
        sample of a small scene, every CHECK_STEPS steps or more of a large one; see
        CHECK_PARTICLE_STEPS). on_frame(time, state): called at t = 0 and every
        ``output_interval`` of simulated time (state: :class:`State`); an on_frame that
        also has ``checkpoint_state()`` and ``restore(saved, frames)`` (as
        :class:`minidem.results.vtk.SimulationFrames`) has its series saved in checkpoints.

        checkpoints: a :class:`minidem.engine.checkpoint.Policy` (where and how often to
        write checkpoints; the final state, the last good state of a failed run), or None
        to write no file. resume_from: (arrays, meta) of a checkpoint
        (:func:`minidem.engine.checkpoint.load_for_resume`): continue from it, bit for bit.

        Raises :class:`RunFailure` on a blow-up (see :mod:`minidem.engine.blowup`), after
        restoring ``self.state`` to the last good state (and writing it, with checkpoints).
        """
        scene, k = self.scene, self.kernel
        threads_before = numba.get_num_threads()
        loop_threads = self.loop_threads()
        # every parallel loop, the neighbour-list builds too, runs on the particle loops' count
        numba.set_num_threads(loop_threads)
        try:
            return _RunLoop(self, chunk_steps, progress, on_frame, loop_threads, checkpoints, resume_from).run()
        finally:
            numba.set_num_threads(threads_before)

    def loop_threads(self) -> int:
        """How many threads the run's particle loops use (one below PARALLEL_MIN_PARTICLES)."""
        scene = self.scene
        threads = min(scene.threads or numba.config.NUMBA_NUM_THREADS, numba.config.NUMBA_NUM_THREADS)
        return threads if self.parallel and scene.n_particles >= PARALLEL_MIN_PARTICLES else 1

    def frame_interval(self, end_time: float) -> float | None:
        scene = self.scene
        if not scene.vtk:
            return None
        return scene.output_interval if scene.output_interval is not None else end_time / 50.0

    def _write_flight_frames(self, state: State, count: int, interval: float, on_frame) -> None:
        """Frames at t = k interval, k < count, of the free flight an analytic-flight run
        does not step: the ballistic closed form (gravity the only force; the spin, with
        no torque, unchanged). The state is put back as it was."""
        scene = self.scene
        kept = {name: getattr(state, name).copy() for name in ("position", "velocity", "force", "torque")}
        for k in range(count):
            t = k * interval
            state.position[:] = scene.position + scene.velocity * t + 0.5 * scene.gravity * t * t
            state.velocity[:] = scene.velocity + scene.gravity * t
            state.force[:] = scene.mass[:, None] * scene.gravity
            state.torque[:] = 0.0
            on_frame(t, state)
        for name, array in kept.items():
            getattr(state, name)[:] = array

    def suggested_time_step(self) -> str:
        """A smaller time step to try after a blow-up, and why."""
        tc = self.reference_contact_time
        if math.isfinite(tc):
            # 50 steps per contact is the least a soft-sphere contact needs to be stable
            # and roughly resolved; never less than a tenfold reduction
            suggestion = min(self.dt / 10.0, tc / 50.0)
            why = f"the shortest contact lasts about {tc:.3g} s, {tc / self.dt:.3g} steps of the current one"
            if self.law.contact_time is None and self.entry.distribution != "minidem":
                # a plugin law without contact_time: tc is Hertz's, not necessarily the law's
                # (minidem's own laws without one are Hertz laws)
                why += f" (Hertz's, eq 13, assumed: law '{self.law.name}' declares no contact_time)"
        else:
            suggestion, why = self.dt / 10.0, "a tenth of the current one"
        return f"try run.dt = {suggestion:.3g} s ({why}; now {self.dt:.3g} s, {self.dt_reason})"

    def _fault_message(self, status, steps) -> str:
        """What the kernel stopped for (status codes of minidem.engine.kernel)."""
        code, particle, partner, kind = (int(x) for x in status)
        particle = self.scene.scenario_index(particle)  # as the scenario numbers them
        when = f"at step {steps} (t = {self.start_time + steps * self.dt:.6g} s)"
        walls = self.scene.walls
        if kind == kernel.PLANE:
            what = walls.plane_name(partner)
        elif kind == kernel.CYLINDER and partner < len(walls.cylinder_table):
            what = f"walls[{int(walls.cylinder_table[partner])}] (cylinder)"
        elif kind == kernel.TRIANGLE and partner < len(walls.triangle_table):
            table = int(walls.triangle_table[partner])
            # the triangles of all meshes are one array: number it within its own mesh
            own = partner - int(np.argmax(walls.triangle_table == table))
            what = f"triangle {own} of the mesh walls[{table}]"
        elif kind == kernel.PARTICLE:
            what = f"particle {self.scene.scenario_index(partner)}"
        else:
            what = f"partner {partner} (kind {kind})"
        if code == kernel.NON_FINITE_FORCE:
            return (f"law '{self.law.name}' ({self.entry.distribution}) returned a non-finite force {when} for "
                    f"particle {particle} against {what}")
        if code == kernel.TUNNELLED:
            return f"particle {particle} passed through {what} {when}: the time step is too large"
        return f"run stopped with status {code} {when}"


class _RunLoop:
    """One run of a :class:`Simulation`: the time loop in chunks of compiled steps, with
    its schedule (energy samples, VTK frames, checkpoints, copies of the last good
    state), the checks between chunks, and what a failure or an interrupt leaves behind.

    The schedule is a function of the step number alone (never of wall time or of where
    a previous process stopped), so a resumed run samples, writes frames and checkpoints
    exactly where an uninterrupted one does."""

    def __init__(self, sim, chunk_steps, progress, on_frame, threads, policy, resume_from):
        from minidem.engine import blowup, checkpoint

        self.sim, self.kernel = sim, sim.kernel
        sim.scene = sim.start_scene  # a Simulation run again starts from its start order
        self.blowup, self.checkpoint = blowup, checkpoint
        self.chunk_steps, self.progress, self.on_frame, self.policy = chunk_steps, progress, on_frame, policy
        scene = self.scene
        self.state = sim.state = State(sim)
        probe_wall = scene.impact.wall if scene.impact is not None else (0 if scene.wall_point.shape[0] else -1)
        self.probe = np.zeros(8)
        self.stats = np.array([-1.0, -1.0, 0.0, 0.0, 0.0])
        self.status = np.zeros(4, dtype=np.int64)
        self.tracking = (probe_wall, self.probe, self.stats, self.status)
        self.stop_at_separation = scene.stop == "separation"
        end_time = sim.end_time
        if not math.isfinite(end_time):
            raise ScenarioError(f"{scene.source}: run.end_time is needed: the scene has no contact to stop at")
        self.start_time = sim.start_time  # > 0 after an analytic flight to first touch
        self.total_steps = max(0, int(math.ceil((end_time - self.start_time) / sim.dt - 1e-9)))
        self.half_skin_squared = (0.5 * sim.skin) ** 2
        self.no_trace = np.zeros((0, len(kernel.TRACE_COLUMNS)))
        self.guard = blowup.Guard(sim)
        self.frame_interval = sim.frame_interval(end_time)
        self.frames_on = on_frame is not None and bool(self.frame_interval)
        self.saves_series = self.frames_on and hasattr(on_frame, "checkpoint_state")
        # Kinetic energy: at least 200 samples a run (taken by the kernel, every
        # sample_steps), and at every frame and the end
        self.sample_steps = max(1, int(math.ceil(end_time / 200.0 / sim.dt - 1e-9)))
        self.particle_energy = np.zeros(scene.n_particles)
        self.energy_blocks = np.zeros(integrate.energy_blocks.py_func(scene.n_particles))  # no compile for a count
        self.no_samples = np.zeros(0)
        self.checkpoint_steps = (max(1, int(round(policy.interval / sim.dt)))
                                 if policy is not None and policy.interval else None)
        # The last good state (restored and written on a blow-up, and the checkpoint of a
        # Ctrl-C) is copied after a check has passed, at most every snapshot_steps, so
        # that copying it costs under ~1 % of the steps in between whatever the scene size.
        # (with particle-steps alone, N = 20,000 copied every 10 steps, i.e. every chunk:
        # 0.45 s of a 7.4 s run, jitter, 4,000 steps, two threads)
        self.snapshot_steps = max(SNAPSHOT_STEPS, SNAPSHOT_PARTICLE_STEPS // max(1, scene.n_particles))
        self.check_steps = max(1, min(chunk_steps, max(CHECK_STEPS, min(
            self.sample_steps, CHECK_PARTICLE_STEPS // max(1, scene.n_particles)))))
        # After an analytic flight the steps start at first touch: the flight's frames
        # (t = 0, interval, ... before the touch) are written from the closed form, and
        # the stepped frames follow every interval from the touch.
        self.flight_frames = (int(math.ceil(self.start_time / self.frame_interval - 1e-9))
                              if self.frames_on and self.start_time > 0.0 else 0)
        self.loop_threads = LoopThreads(threads)
        self.block_timing = blocks.BlockTiming()
        # loop: the run loop's own state, saved with the arrays in every checkpoint
        self.loop = {"steps": 0, "frames": 0, "last_frame_step": -1, "gravity_work_max": 0.0}
        self.energy, self.trace_chunks = [], []
        self.resume_from = resume_from

    @property
    def scene(self) -> Scene:
        """The scene in the order its particles are stored now (Simulation.use_order)."""
        return self.sim.scene

    # -- the compiled steps ------------------------------------------------------
    def frame_step(self, index):
        return int(round((index - self.flight_frames) * self.frame_interval / self.sim.dt))

    def call(self, start_step, n_steps, completing, trace, threads=None, dt=None, stop_at_separation=None,
             sampled=False):
        """``n_steps`` compiled steps from ``start_step``; returns (steps taken, whether the
        neighbour list must be rebuilt first). ``sampled``: the kinetic-energy samples of
        the steps taken are added to the run's (a replay after a failure takes none)."""
        threads = threads or self.loop_threads.current
        samples = (np.empty((start_step + n_steps) // self.sample_steps - start_step // self.sample_steps)
                   if sampled else self.no_samples)
        # every parallel loop of the chunk (the opening kick_drift too) on that many
        numba.set_num_threads(threads)
        taken, needs_rebuild = self.kernel.advance(*self.arguments(start_step, n_steps, completing, trace, threads,
                                                                   dt, stop_at_separation, samples=samples))
        if sampled:
            first = start_step // self.sample_steps + 1
            # a fault returns after its step's forces, before that step's sample
            last_complete = start_step + taken - (1 if self.status[0] != kernel.OK else 0)
            for k in range(last_complete // self.sample_steps - first + 1):
                self.energy.append((self.start_time + (first + k) * self.sample_steps * self.sim.dt,
                                    float(samples[k])))
        return taken, needs_rebuild

    def arguments(self, start_step, n_steps, completing, trace, threads, dt=None, stop_at_separation=None,
                  one_block=False, samples=None):
        """The arguments of the kernel's ``advance`` (``one_block``: the blocks of one
        thread, whatever ``threads`` says: for their types alone; ``samples``: where the
        kinetic-energy samples go, None for none)."""
        state, sim = self.state, self.sim
        # a serial kernel runs its particle loops on one thread, whatever it is told
        bounds, first_partner, block_cycles = blocks.blocks(threads if sim.threaded and not one_block else 1,
                                                            state.planes, state.pairs, state.first_partner,
                                                            self.block_timing)
        # the contact kinds the kernel has no loops for go as empty tuples (kernel.advance)
        cylinders, meshes, pairs = (group if getattr(self.kernel, flag, True) else () for group, flag in
                                    ((state.cylinders, "CYLINDERS"), (state.meshes, "MESHES"), (state.pairs, "PAIRS")))
        return (state.particles, state.law, state.planes, cylinders, meshes, pairs,
                self.scene.gravity, state.position_at_build, self.half_skin_squared, sim.dt if dt is None else dt,
                self.start_time, start_step, n_steps, completing,
                self.stop_at_separation if stop_at_separation is None else stop_at_separation, trace,
                self.tracking, threads, bounds, first_partner, block_cycles,
                (self.sample_steps if samples is not None else 0, state.inertia,
                 self.no_samples if samples is None else samples, self.particle_energy, self.energy_blocks))

    def compile_kernel(self):
        """Compile (or load from the cache) the kernel's ``advance`` for the types of its
        arguments, before the neighbour lists exist (their arrays' types do not change
        when they are built): the helper (``minidem.engine.warmup``) meanwhile compiles
        the neighbour search the first list needs."""
        advance = self.kernel.advance
        if hasattr(advance, "compile"):  # a test may put a plain function there
            args = self.arguments(0, 1, True, self.no_trace, self.loop_threads.current, dt=0.0,
                                  stop_at_separation=False, one_block=True)
            advance.compile(tuple(advance.typeof_pyval(arg) for arg in args))

    def start(self):
        """The state at the first step: fresh (initial forces) or the checkpoint resumed."""
        sim, state, loop = self.sim, self.state, self.loop
        if self.resume_from is not None:
            arrays, meta = self.resume_from
            sim.use_order(state, arrays.get("particle_id"))  # rows in the order they were stored
            state.restore(arrays)
            self.probe[:], self.stats[:], self.status[:] = arrays["probe"], arrays["stats"], arrays["status"]
            loop.update({key: meta["loop"][key] for key in loop})
            self.energy = [(float(t), float(e)) for t, e in arrays["energy"]]
            if self.scene.trace and arrays["trace"].shape[0]:
                self.trace_chunks.append(arrays["trace"])
            if self.saves_series:
                self.on_frame.restore(meta["frames_series"], loop["frames"])
        meshes = state.meshes[0].shape[0] > 0
        # on a fresh install the engine's shared functions compile in a helper process
        # beside the kernel (nothing is started when they are cached); or, when a helper
        # is compiling this scene's kernel already (started by `minidem run` beside the
        # scene's check), this process compiles them meanwhile
        kernel_helper = warmup.kernel_helper(sim.input_scene)  # started for the scene as read
        helper = warmup.start(sim.pairs, meshes, sim.law) if kernel_helper is None else kernel_helper
        try:
            # the one compilation of this kernel, reported against the law that caused it; a
            # user waiting for it is told what it is
            def compiling():
                return _notice_if_slow(sim.notify, f"compiling the kernel of law '{sim.law.name}' for this scene "
                                       f"shape; it is cached in {codecache.cache_directory()} for later runs")

            if kernel_helper is not None:
                # the wait for the helper compiling the kernel: announced already by the
                # check's notice when that took 2 s (one line for one compilation)
                with contextlib.nullcontext() if kernel_helper.announced else compiling():
                    warmup.compile_shared(sim.pairs, meshes)
                    kernel_helper.wait()
            # loaded from the cache when a helper compiled it; compiled here (and announced
            # after 2 s) when none did, or it failed
            with compiling():
                with helper.law_compiled(laws.called_force(sim.law)):
                    self.compile_kernel()
                helper.wait()
                if self.resume_from is None and (sim.pairs or meshes):
                    sim.rebuild(state)
                self.first_call()
        except numba.core.errors.NumbaError as exc:
            raise laws.LawError(f"law '{sim.law.name}' from plugin '{sim.entry.plugin}' "
                                f"({sim.entry.distribution}): {force_problem(sim.law, exc)}") from exc
        if self.resume_from is None:
            self.energy.append((self.start_time, state.kinetic_energy(state.inertia)))
            if self.frames_on:
                if self.flight_frames:
                    sim._write_flight_frames(state, self.flight_frames, self.frame_interval, self.on_frame)
                self.on_frame(self.start_time, state)
                loop["frames"], loop["last_frame_step"] = self.flight_frames + 1, 0
        self.fingerprint = self.checkpoint.fingerprint(sim) if self.policy is not None else None
        self.good = self.snapshot()
        # the run loop, and the energy samples and trace chunks kept, at the end of the last
        # chunk that passed the checks
        self.mark_checked()

    def first_call(self):
        """The first compiled call: the initial forces, or the resumed state checked."""
        if self.resume_from is None:
            # zero-length step: initial forces (dt = 0, so no displacement increments)
            # and the closing kick (of zero), no drift; advance with dt = 0 and the
            # step's drift marked done, since calling compute_forces from Python
            # would compile it a second time
            self.call(0, 1, True, self.no_trace, dt=0.0, stop_at_separation=False)
        else:
            self.call(self.loop["steps"], 0, False, self.no_trace)  # changes nothing: the resumed state is untouched
        # the guard's compiled check too: wall_time is the loop's alone
        self.guard.check(self.state, self.start_time, 0.0)

    # -- the last good state, checkpoints and failures ---------------------------
    def mark_checked(self):
        self.checked, self.checked_counts = dict(self.loop), (len(self.energy), len(self.trace_chunks))

    def snapshot(self, reuse=None, live=False):
        """The state now, for checkpoints and as the last good state; ``reuse``: an
        older snapshot, overwritten in place (one copy of the state, not two); ``live``:
        the state's own arrays, not copied (valid until the kernel runs again). The
        arrays and the loop's bookkeeping are recorded together with SIGINT/SIGTERM
        held, so an interrupt never finds them from two different steps."""
        with _interrupts_deferred():
            snap = {} if reuse is None else reuse
            snap["arrays"] = (self.state.live_arrays() if live else
                              self.state.capture(into=reuse["arrays"] if reuse else None))
            snap.update(tracking=(self.probe.copy(), self.stats.copy(), self.status.copy()), loop=dict(self.loop),
                        energy=len(self.energy), trace=len(self.trace_chunks))
        return snap

    def write_state(self, name, snap, kind):
        sim = self.sim
        arrays = full_arrays(snap["arrays"])  # the files hold every row
        if not all(listed in arrays for listed in _LISTS):  # and the lists (a capture holds none)
            arrays.update(self.state.lists_of(snap["arrays"]))
        arrays["probe"], arrays["stats"], arrays["status"] = snap["tracking"]
        arrays["energy"] = np.array(self.energy[:snap["energy"]], dtype=np.float64).reshape(-1, 2)
        arrays["trace"] = np.concatenate(self.trace_chunks[:snap["trace"]]) if snap["trace"] else self.no_trace
        series = self.on_frame.checkpoint_state() if self.saves_series else None
        if series is not None:  # only the frames written up to the snapshot
            series = {key: value[:snap["loop"]["frames"]] for key, value in series.items()}
        step = snap["loop"]["steps"]
        meta = {"kind": kind, "source": self.scene.source, "minidem": __version__, "kernel": self.kernel.__name__,
                "law": sim.law.name, "law_package": f"{sim.entry.distribution} {sim.entry.version}",
                "fingerprint": self.fingerprint, "dt": sim.dt, "step": step, "time": self.start_time + step * sim.dt,
                "total_steps": self.total_steps, "loop": snap["loop"], "frames_series": series}
        return self.checkpoint.write(Path(self.policy.directory) / name, arrays, meta)

    def fail(self, message, suggestion=None):
        """Stop: go back to the last state that passed the checks, write it, raise RunFailure.

        That state is rebuilt from the last copy (``good``) by replaying the steps
        in between: runs are deterministic, so the replay gives it bit for bit."""
        sim, state, good, checked = self.sim, self.state, self.good, self.checked
        sim.use_order(state, good["arrays"].get("particle_id"))
        state.restore(good["arrays"])
        for live, saved in zip((self.probe, self.stats, self.status), good["tracking"]):
            live[:] = saved
        step, completing = good["loop"]["steps"], False
        while step < checked["steps"] and self.status[0] == kernel.OK:
            taken, needs_rebuild = self.call(step, checked["steps"] - step, completing, self.no_trace)
            step, completing = step + taken, False
            if needs_rebuild:
                sim.rebuild(state)
                completing = True
        # into the copy it was restored from, no longer needed: one copy of the state, not two
        last_good = self.snapshot(good)
        last_good["loop"] = dict(checked)
        last_good["energy"], last_good["trace"] = self.checked_counts
        good_step = checked["steps"]
        written = []
        if self.policy is not None:
            written.append(str(self.write_state(self.checkpoint.LAST_GOOD, last_good, "last good")))
        if self.frames_on and checked["last_frame_step"] != good_step:
            self.on_frame(self.start_time + good_step * sim.dt, state)
            written.append("the last VTK frame")
        where = f", written to {' and '.join(written)}" if written else ""
        advice = suggestion or sim.suggested_time_step()
        raise RunFailure(f"{message}. {advice[0].upper()}{advice[1:]}. Last good state: step {good_step} "
                         f"(t = {self.start_time + good_step * sim.dt:.6g} s){where}")

    def check(self, step, on_grid=True):
        """The blow-up guard between chunks (see :mod:`minidem.engine.blowup`). Its record
        of the work of gravity is kept from the checks ``on_grid`` (steps every run of the
        scene checks, resumed or not: the grid of chunks and the list rebuilds), not from a
        chunk cut short by a probe or a checkpoint due by wall time. Before a list rebuild
        (mid-step) the force and torque arrays are zero (the force pass sums reactions
        into them and stores totals only at a call's last step); a non-finite force of
        this step stops the kernel itself."""
        at_time = self.start_time + step * self.sim.dt
        fault, work_max = self.guard.check(self.state, at_time, self.loop["gravity_work_max"])
        if on_grid:
            self.loop["gravity_work_max"] = work_max
        if fault is not None:
            touching = self.blowup.contacts_of(self.state, fault.particle, self.scene.scenario_index)
            self.fail(f"blow-up ({fault.what}) at step {step} (t = {at_time:.6g} s): {fault.detail}; "
                      f"particle {self.scene.scenario_index(fault.particle)} touches "
                      + (", ".join(touching) if touching else "nothing"))

    def check_status(self, steps):
        """A fault the kernel stopped for (a non-finite force, a sphere through a wall)."""
        status, sim = self.status, self.sim
        if status[0] != kernel.OK:
            self.fail(sim._fault_message(status, steps),
                      None if status[0] != kernel.NON_FINITE_FORCE else
                      "A law's force must be finite at every overlap > 0 and speed; if this one is, the time "
                      f"step may be too large: {sim.suggested_time_step()}")

    # -- the loop ----------------------------------------------------------------
    def next_chunk(self):
        """(steps, threads, probing) of the next chunk: up to the next multiple of
        check_steps, frame or checkpoint (the kernel takes the energy samples on its way);
        a probe of the other thread count runs a short chunk, since it only has to time it."""
        steps, loop = self.loop["steps"], self.loop
        goal = min(self.total_steps, (steps // self.check_steps + 1) * self.check_steps)
        if self.frames_on:
            goal = min(goal, max(steps + 1, self.frame_step(loop["frames"])))
        if self.checkpoint_steps:
            goal = min(goal, (steps // self.checkpoint_steps + 1) * self.checkpoint_steps)
        chunk = goal - steps
        chunk_threads = self.loop_threads.choose()
        probing = chunk_threads != self.loop_threads.current
        if probing:
            chunk = min(chunk, max(2 * LoopThreads.MIN_STEPS, chunk // LoopThreads.PROBE_FRACTION))
        return chunk, chunk_threads, probing

    def record(self, steps, taken, chunk):
        """After a chunk that passed the checks: energy sample, frame, progress; returns
        whether the run stops here at separation."""
        state, loop, stats = self.state, self.loop, self.stats
        now = self.start_time + steps * self.sim.dt
        # stop_at_separation: the last contact ended (the kernel returns early, or
        # it ended on the chunk's last step, which must not cost one more step)
        separating = self.stop_at_separation and (taken < chunk or (
            stats[kernel.FIRST_CONTACT_TIME] >= 0.0 and state.count_contacts() == 0))
        at_frame = self.frames_on and steps >= self.frame_step(loop["frames"])
        # every sample_steps the kernel has taken the sample
        if steps % self.sample_steps != 0 and (steps == self.total_steps or at_frame or separating):
            self.energy.append((now, state.kinetic_energy(state.inertia)))
        if at_frame:
            self.on_frame(now, state)
            loop["frames"] += 1
            loop["last_frame_step"] = steps
        self.mark_checked()
        if self.progress is not None:
            self.progress(steps, self.total_steps, state.count_contacts())
        return separating

    def run(self) -> RunResult:
        sim, state, loop, policy = self.sim, self.state, self.loop, self.policy
        self.start()
        started = wallclock.perf_counter()
        last_checkpoint_wall = started
        separated, completing = False, False
        copied_wall, copy_seconds = started, 0.0
        try:
            while loop["steps"] < self.total_steps:
                steps = loop["steps"]
                chunk, chunk_threads, probing = self.next_chunk()
                trace = np.zeros((chunk, len(kernel.TRACE_COLUMNS))) if self.scene.trace else self.no_trace
                chunk_started = wallclock.perf_counter()
                # compiled code never sees a signal before it returns anyway: held, a
                # Ctrl-C is delivered here after the call, never inside numba's dispatcher
                # (which then returned 'a result with an exception set', a SystemError)
                with _interrupts_deferred():
                    taken, needs_rebuild = self.call(steps, chunk, completing, trace, chunk_threads, sampled=True)
                self.loop_threads.record(chunk_threads, taken, wallclock.perf_counter() - chunk_started)
                if self.scene.trace:
                    self.trace_chunks.append(trace[:taken])
                steps = loop["steps"] = steps + taken
                completing = False
                self.check_status(steps)
                if needs_rebuild:
                    # mid-step (drifted, forces pending): a runaway particle must not
                    # reach the neighbour grid
                    self.check(steps + 1)
                    sim.rebuild(state)
                    completing = True  # the next call completes the step from its forces
                    continue
                self.check(steps, on_grid=steps % self.check_steps == 0 or steps == self.total_steps)
                separating = self.record(steps, taken, chunk)
                checkpoint_due = policy is not None and not separating and steps < self.total_steps and (
                    (self.checkpoint_steps and steps % self.checkpoint_steps == 0)
                    or (policy.wall_interval and wallclock.perf_counter() - last_checkpoint_wall
                        >= policy.wall_interval))
                now_wall = wallclock.perf_counter()
                if checkpoint_due or (steps - self.good["loop"]["steps"] >= self.snapshot_steps
                                      and now_wall - copied_wall >= SNAPSHOT_COST_RATIO * copy_seconds):
                    # after the checks: the state overwriting the last good one is good
                    self.good = self.snapshot(self.good)
                    copied_wall = wallclock.perf_counter()
                    copy_seconds = copied_wall - now_wall
                if checkpoint_due:
                    self.write_state(self.checkpoint.CHECKPOINT, self.good, "checkpoint")
                    last_checkpoint_wall = wallclock.perf_counter()
                if separating:
                    separated = True
                    break
        except (KeyboardInterrupt, SystemError) as exc:
            self.interrupt(exc)
        if self.frames_on and loop["last_frame_step"] != loop["steps"]:
            # the state the run ends in is always a frame (also when the output interval
            # does not divide the run, or exceeds it): ParaView's last frame is the result
            self.on_frame(self.start_time + loop["steps"] * sim.dt, state)
            loop["frames"] += 1
            loop["last_frame_step"] = loop["steps"]
        wall_time = wallclock.perf_counter() - started
        if policy is not None:
            # the state's own arrays, not a copy, and the last good copy released first (the
            # run is over: nothing restores from it now): a second and third copy of the
            # state were the peak of a run that writes its final state
            self.good = None
            self.write_state(self.checkpoint.FINAL_STATE, self.snapshot(live=True), "final")
            Path(policy.path).unlink(missing_ok=True)  # the run is complete: nothing to resume
        return self.result(separated, wall_time)

    def interrupt(self, exc):
        """Ctrl-C (or SIGTERM through the CLI) between chunks: keep what was done. A
        SystemError caused by a Ctrl-C (one that reached the dispatcher of a compiled
        function from another thread) is the same interrupt."""
        if not interrupted(exc):
            raise exc
        if self.policy is not None:
            with _interrupts_deferred():  # a second Ctrl-C must not tear this checkpoint
                written = self.write_state(self.checkpoint.CHECKPOINT, self.good, "checkpoint")
                self.sim.interrupted_at = (self.start_time + self.good["loop"]["steps"] * self.sim.dt, written)
        if isinstance(exc, KeyboardInterrupt):
            raise exc
        raise KeyboardInterrupt from exc

    def result(self, separated, wall_time) -> RunResult:
        sim, state, stats = self.sim, self.state, self.stats
        steps = self.loop["steps"]
        scene, ordered = sim.input_scene, self.scene.in_scenario_order
        return RunResult(
            scene=scene, law=sim.law, constants=sim.constants_by_pair, position=ordered(state.position),
            velocity=ordered(state.velocity), angular_velocity=ordered(state.angular_velocity),
            initial_velocity=scene.velocity, initial_angular_velocity=scene.angular_velocity, steps=steps, dt=sim.dt,
            dt_reason=sim.dt_reason,
            time=self.start_time + steps * sim.dt, separated=separated, first_contact_time=stats[0],
            last_separation_time=stats[1], max_overlap=stats[2], peak_normal_force=stats[3],
            peak_tangential_force=stats[4], wall_time=wall_time,
            trace=np.concatenate(self.trace_chunks) if self.trace_chunks else None, force=ordered(state.force),
            torque=ordered(state.torque), contacts=state.count_contacts(), neighbour_builds=state.builds,
            threads=self.loop_threads.most_used(), thread_steps=dict(self.loop_threads.steps),
            energy=np.array(self.energy), contact_statistics=not sim.parallel,
            gravity_work_max=self.loop["gravity_work_max"], supply_budget=sim.supply_budget,
        )


@contextlib.contextmanager
def _interrupts_deferred():
    """Hold SIGINT and SIGTERM for the duration of the block: they are delivered (and
    raise KeyboardInterrupt through the CLI's handler) as soon as it ends, so that the
    copy of the last good state, which a Ctrl-C writes as the checkpoint, is never torn.

    The handlers are swapped for one that only records the signal (a signal mask would
    hold it in this thread only: a Ctrl-C sent to the process, delivered to one of
    numba's threads, would still raise here, and inside a compiled function's
    dispatcher that was 'SystemError: ... returned a result with an exception set').
    Outside the main thread (a Dask worker's) Python delivers no signal: nothing to hold."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {number: signal.signal(number, lambda signum, frame: caught.append(signum))
                for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            # None: a handler installed outside Python (an embedding application) cannot be
            # put back from here; the default action is the closest
            signal.signal(number, handler if handler is not None else signal.SIG_DFL)
        if caught:  # now, to the handlers the run had (KeyboardInterrupt, or the CLI's SIGTERM)
            signal.raise_signal(caught[0])


# A step of the set-up (a law's prepare(), the kernel's compilation) that takes longer
# than this is announced, so the user knows what minidem is waiting for.
SLOW_NOTICE_S = 2.0


@contextlib.contextmanager
def _notice_if_slow(notify, text: str):
    """Call ``notify(text)`` (from a timer thread) if the block runs longer than SLOW_NOTICE_S."""
    if notify is None:
        yield
        return
    import threading

    timer = threading.Timer(SLOW_NOTICE_S, notify, args=(f"{text} ({SLOW_NOTICE_S:g} s so far)",))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        timer.join()  # a notice being printed is finished before the block's caller goes on


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is a KeyboardInterrupt or was caused by one (a SystemError of
    numba's dispatcher when Ctrl-C arrived as a compiled function returned)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _numba_cause(exc: Exception) -> str:
    """The informative lines of a numba error (it buries the cause among 'During:' lines):
    the message, and where in the law's own code (never the generated kernel's lines)."""
    lines = [line.strip() for line in str(exc).splitlines()]
    message = [line for line in lines if line and not line.startswith(("File ", "During:", "^", "def ", "<source"))
               and "Failed in nopython mode pipeline" not in line]
    places = [line.rstrip(":") for line in lines if line.startswith("File ")
              and "minidem_kernel_" not in line and f"minidem{os.sep}kernel.py" not in line]
    where = f" ({places[-1]})" if places else ""
    return ("; ".join(message[:2]) or lines[0]) + where


_ROW, _FLOAT, _VECTOR = (numba.types.Array(numba.types.float64, 1, "C"), numba.types.float64,
                         numba.types.UniTuple(numba.types.float64, 3))
# a contact's history as the kernel hands it over (minidem.contact.history)
_HISTORY = contact_history.contact_history
# the argument types the kernel passes a law's force function (minidem.contact.laws.FORCE_ARGUMENTS)
_FORCE_SIGNATURE = (_ROW, *(_FLOAT,) * 5, _VECTOR, _VECTOR, _HISTORY)
# a law with a couple (law.couples) also takes the relative spin, the normal and dt
_COUPLE_FORCE_SIGNATURE = (*_FORCE_SIGNATURE, _VECTOR, _VECTOR, _FLOAT)


def force_signature(law: laws.ContactLaw) -> tuple:
    """The argument types the kernel passes the law's force function."""
    return _COUPLE_FORCE_SIGNATURE if law.couples else _FORCE_SIGNATURE

# the argument types a part's function is called with (minidem.contact.laws.PART_ARGUMENTS)
# and how many numbers it returns (0: one number)
_PART_SIGNATURES = {
    "normal": ((_ROW, *(_FLOAT,) * 4, _HISTORY), 3),
    "damping": ((_ROW, *(_FLOAT,) * 6), 0),
    "tangential": ((_ROW, *(_FLOAT,) * 7, _VECTOR, _VECTOR, _HISTORY), 3),
    "rolling": ((_ROW, *(_FLOAT,) * 6, _VECTOR, _VECTOR, _HISTORY), 3),
    "twisting": ((_ROW, *(_FLOAT,) * 8, _HISTORY), 0),
}


def _compiled_alone(function, signature, count: int, what: str, shape: str) -> str | None:
    """Why ``function`` does not compile with ``signature`` or does not return ``count``
    numbers (0: one number), naming its file and line; None when it is fine."""
    func = function.py_func
    try:
        _, line = inspect.getsourcelines(func)
        where = f"{func.__qualname__} in {inspect.getsourcefile(func)}, line {line}"
    except (OSError, TypeError):
        where = func.__qualname__
    try:
        function.compile(signature)
    except numba.core.errors.NumbaError as alone:
        return f"its {what} {where} does not compile: {_numba_cause(alone)}"
    returned = function.overloads[signature].signature.return_type
    number = (numba.types.Float, numba.types.Integer)
    if count == 0:
        if not isinstance(returned, number):
            return f"its {what} {where} must return a number ({shape}), it returns {returned}"
    elif not (isinstance(returned, numba.types.BaseTuple) and len(returned) == count
              and all(isinstance(t, number) for t in returned)):
        return f"its {what} {where} must return {count} numbers ({shape}), it returns {returned}"
    return None


def force_problem(law: laws.ContactLaw, exc: Exception) -> str:
    """Why a law's force function broke the kernel's compilation: compiled alone with the
    engine's argument types (each part of a combination with its kind's), so the message
    names the law's or the part's function and file (and a wrong return value), not the
    kernel line that called it."""
    shapes = {"normal": "elastic force, stiffness, contact radius", "damping": "the dashpot's force",
              "tangential": "ftx, fty, ftz", "rolling": "the couple mx, my, mz", "twisting": "the couple about n"}
    for part in law.parts:
        signature, count = _PART_SIGNATURES[part.kind]
        why = _compiled_alone(part.function, signature, count, "function", shapes[part.kind])
        if why:
            return f"{part.kind} part '{part.name}': {why}"
    if not law.parts:
        why = _compiled_alone(law.force, _FORCE_SIGNATURE, 4, "force function", "fn, ftx, fty, ftz")
        if why:
            return why
    return f"its force function does not compile in the engine: {_numba_cause(exc)}"


def run_scene(scene: Scene, progress=None) -> RunResult:
    return Simulation(scene).run(progress=progress)
