"""Validated scene -> compiled simulation -> run result.

``compile_kernel`` specialises the kernel template (``minidem/engine/kernel.py``) for one law
and one scene shape; ``Simulation`` prepares the per-material-pair constants, chooses
the time step, and between chunks of compiled steps rebuilds the Verlet lists when the
kernel asks (carrying every contact's history into the new list) and sorts the
particles in space again as they mix. The time loop itself, in chunks (no Python call
per step or per contact), is :mod:`minidem.engine.run_loop`; the arrays it advances,
:mod:`minidem.engine.state`.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.util
import math
import os
import re
import sys
from pathlib import Path

import numba
import numpy as np

from minidem import __version__, codecache, compile_speed
from minidem.contact import declarations, history as contact_history, laws
from minidem.engine import integrate, kernel
from minidem.engine.notices import notice_if_slow
from minidem.engine.run_loop import RunLoop, RunResult
from minidem.engine.state import PAIR_TUPLE, STATE_ARRAYS, State, expand_rows, pair_arrays, rows_in_use
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
# numba's compiles made faster, before the first (the same machine code: minidem.compile_speed)
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


def predicts_end_velocity(pairs: bool, track: bool) -> bool:
    """Whether the kernel hands its law the velocities predicted at the end of the step
    (kernel END_VELOCITY: every damped contact second order in dt, docs/time-step.md
    "Dashpots"): a single sphere, and the tracked loop of small scenes (at most
    PARALLEL_ABOVE particles, or a run to separation). The multi-particle path reads the
    drift's velocities, as LAMMPS and LIGGGHTS do: the prediction keeps each particle's
    last force, 48 bytes a particle, a twelfth of its memory there."""
    return not pairs or track


def compile_kernel(entry: laws.RegisteredLaw, spin: bool, pairs: bool = False, cylinders: bool = False,
                   meshes: bool = False, parallel: bool = False, track: bool = True,
                   integrator: str = "velocity_verlet", end_velocity: bool | None = None):
    """Return the kernel module specialised for ``entry.law``, a scene shape and an
    integrator (compiled lazily, cached on disk). Integrators with the same kick split
    (velocity Verlet and analytic flight) share one kernel. ``end_velocity`` None: the
    shape's rule (``predicts_end_velocity``)."""
    track = track and not parallel  # a parallel loop cannot record contact statistics
    flags = dict(zip(KERNEL_FLAGS, (bool(spin), bool(pairs), bool(cylinders), bool(meshes), bool(parallel),
                                    bool(track))))
    flags["END_VELOCITY"] = (predicts_end_velocity(flags["PAIRS"], flags["TRACK"]) if end_velocity is None
                             else bool(end_velocity))
    if flags["END_VELOCITY"] and flags["PAIRS"] and flags["PARALLEL"]:
        # a pair reads its partner's last force, which the partner's thread may be
        # overwriting in the same pass (finish_range): serial loops only
        raise ValueError("END_VELOCITY with pairs needs a serial kernel (PARALLEL False)")
    law = entry.law
    # a law with rolling or twisting parts takes the relative spin and returns a couple
    flags["COUPLES"] = bool(law.couples)
    # a law acting beyond touch (adhesion): contacts live down to -reach (the last
    # column of the constants row); without one the kernel is the same code as before
    flags["REACH"] = law.reach is not None
    flags["OPENING_KICK"] = integrate.OPENING_KICK[integrator]
    force_module, force_name = declarations.force_import_name(law)
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
                 *declarations.import_name(law.force_alone, "force_alone"))
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
    a neighbour-list rebuild: the build's temporaries, freed, stay resident otherwise
    (glibc serves blocks below its mmap threshold from the heap; lists_on_mappings fixes
    that threshold at 32 MiB, where glibc's own rule ends, after the first build on one
    thread). Pages the next rebuild takes are faulted in again, a fraction of a
    millisecond. Settle jitter N = 20,000, 10,000 steps, one thread: peak 187.5 -> 183.0
    MB (before lists_on_mappings)."""
    library = _c_library()
    if library is not None:
        library.malloc_trim(0)


# glibc's mallopt parameters, and the thresholds its dynamic rule ends at on a 64-bit
# system (the mmap threshold rises to the size of each mapped block freed, up to 32 MiB,
# and the trim threshold with it, to twice that)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 << 20
# blocks from this size up are mapped while a list is built
LIST_MAPPING_BYTES = 1 << 20


@contextlib.contextmanager
def lists_on_mappings(enabled: bool):
    """While a neighbour list is built, every block of LIST_MAPPING_BYTES or more gets a
    mapping of its own (glibc's mmap threshold lowered), so that the list's arrays, kept
    until the next build, go back to the system the moment that build releases them. From
    the heap (glibc serves blocks up to 32 MiB from it once a few mapped ones have been
    freed) they left holes the new list did not fit: the builds of the settled pile at
    N = 200,000 peaked at up to 301 MiB against 289 for the steps between them, with the
    lists mapped at 284 against 284 (docs/benchmarks.md, "A pile's memory at N =
    200,000"). Afterwards the thresholds are fixed where glibc's dynamic rule ends (mmap
    32 MiB, trim 64 MiB): the step loop's temporaries come from the heap as before (a
    threshold left low made every one of them a fresh mapping: 3.4 % slower,
    docs/multi-particle.md). One thread only, as
    release_free_memory: a threaded run would fault the new mappings' pages in on both
    threads at once."""
    library = _c_library() if enabled else None
    if library is None:
        yield
        return
    library.mallopt(_M_MMAP_THRESHOLD, LIST_MAPPING_BYTES)
    try:
        yield
    finally:
        library.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD_MAX)
        library.mallopt(_M_TRIM_THRESHOLD, 2 * _MMAP_THRESHOLD_MAX)


class Simulation:
    """A scene bound to a compiled kernel, its constants and its time step."""

    def __init__(self, scene: Scene, registry: laws.LawRegistry | None = None, kernel_flags: dict | None = None,
                 compile: bool = True, notify=None):
        """``kernel_flags`` forces scene-shape flags on (e.g. {"PAIRS": True}) to measure
        what modelling only what a scene needs saves (``minidem bench``); results are
        the same, only the cost differs (but with a dashpot: forcing PARALLEL on a small
        scene takes away the end-of-step velocity its tracked loop hands the law,
        ``predicts_end_velocity``; {"END_VELOCITY": False} does that alone). ``compile=False`` stops after the constants, the
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
        # the law reads the velocities at the end of the step (kernel END_VELOCITY); the
        # time-step limit of a dashpot depends on it
        self.end_velocity = predicts_end_velocity(self.pairs, not self.parallel)
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
        self.end_velocity = forced.get("END_VELOCITY", predicts_end_velocity(self.pairs, not self.parallel))
        with notice_if_slow(notify, f"compiling (or loading from the cache) the kernel of law '{self.law.name}' "
                             "for this scene"):
            self.kernel = compile_kernel(self.entry, self.spin, self.pairs,
                                         forced.get("CYLINDERS", scene.walls.cylinder_base.shape[0] > 0),
                                         forced.get("MESHES", scene.walls.triangles.shape[0] > 0), self.threaded,
                                         not self.parallel,
                                         scene.integrator, self.end_velocity)

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
                with notice_if_slow(self.notify, f"preparing law '{law.name}' ({self.entry.distribution}) for "
                                     f"materials '{materials[a].name}'/'{materials[b].name}' (its prepare() "
                                     f"is still running)"):
                    # the scenario too (scene.source): the values prepare() refused are the user's
                    row, named = laws.prepare_for_pair(law, self.entry.distribution, pair,
                                                       scene.pair_parameters.get((a, b), scene.law_parameters),
                                                       f"'{materials[a].name}'/'{materials[b].name}'", scene.source)
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
    def check_history_bounds(self) -> None:
        """A law, or a combination with a part, from a plugin other than minidem is run
        once through ``laws.history_overrun`` before its first run with this kernel: numba
        checks no array bounds, and a force writing past the history slots it declares
        would overwrite the next contact's history, or the heap, unnoticed (``minidem
        verify``'s first check, made for every plugin author who skips it). Its verdict
        is kept beside the kernel in the cache, whose name changes with the law's code:
        a few milliseconds, once. Raises LawError (exit 2) naming the law and the slot."""
        if self.entry.distribution == "minidem" or not hasattr(self.kernel, "__name__"):
            return
        marker = codecache.cache_directory() / f"{self.kernel.__name__}.history-checked"
        if marker.exists():
            return
        material = int(self.scene.particle_material[0])
        row = self.constants[self.pair_row[material, material]]
        passed, detail = laws.history_overrun(self.law, row, float(self.scene.radius[0]), float(self.scene.mass[0]),
                                              self.reference_contact_time, self.characteristic_speed())
        if passed is False:
            raise laws.LawError(
                f"law '{self.law.name}' from plugin '{self.entry.plugin}' ({self.entry.distribution}): its force "
                f"writes past the history it declares ({detail}), which in a run overwrites other contacts' history "
                "(numba checks no bounds): declare a HistorySlot for every value it keeps "
                "(docs/writing-a-contact-law.md)")
        if passed is None:  # not judged (it raised on the check's values): checked again next run
            return
        try:
            marker.write_text(f"{self.law.name}: history_overrun passed\n")
        except OSError:  # a read-only or full cache: the run goes on, the check is made again next time
            pass

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

    def stability_limit(self) -> tuple[float, str, bool]:
        """Largest stable dt of the integrator on the scene's stiffest contact mode, why,
        and whether that mode's dashpot lowers it.

        Velocity Verlet and symplectic Euler (the same positions) are stable on a linear
        oscillator of frequency omega for dt < 2/omega, or (2/omega)(sqrt(1 + zeta^2) - zeta)
        with damping ratio zeta, the dashpot reading the drift's velocity. A single sphere's
        kernel, and the tracked loop of a small scene, hand it the velocity predicted at
        the end of the step instead (kernel END_VELOCITY, v + dt a_last / 2 with velocity
        Verlet's closing half kick, ``predicts_end_velocity``), which
        makes the last acceleration part of the scheme: its limit is the same with zeta
        doubled (docs/time-step.md). Each contact kind has a normal mode, omega^2 = kn/m*, and
        when it can carry friction a tangential mode in which the contact point moves
        against both the translation and the rotation of the sphere(s),
        omega^2 = kt (1/m* + R^2/I) = 3.5 kt/m* for solid spheres (I = 2/5 m R^2). The
        stiffnesses are the law's (``ContactLaw.stiffness``) at the largest overlap the
        scene should reach: Hertz's at the characteristic impact speed (eq 12) or under
        the particle's weight, whichever is larger.
        """
        speed = self.characteristic_speed()
        gravity = float(np.linalg.norm(self.scene.gravity))
        # the kernel's END_VELOCITY with velocity Verlet's closing half kick (the doubling is
        # derived for it); symplectic Euler closes with no kick: nothing predicted
        predicted = self.end_velocity and integrate.OPENING_KICK[self.scene.integrator] == 0.5
        best, why, damped = math.inf, "no contact possible", False
        # the deepest overlap over the sphere's radius, for derived.check_simulation and a
        # sphere through a wall (_fault_message): (ratio, overlap m, radius m, kind, cause)
        self.deepest_overlap = (0.0, 0.0, 0.0, "", "")
        for pair, named, r, m, kind in self.contact_kinds():
            k_hertz = 4.0 / 3.0 * pair.effective_modulus * math.sqrt(r)
            impact = (15.0 * m * speed**2 / (16.0 * pair.effective_modulus * math.sqrt(r))) ** 0.4
            weight = (m * gravity / k_hertz) ** (2.0 / 3.0)
            overlap = max(impact, weight)
            radius = r if kind == "sphere-wall" else 2.0 * r  # a pair's r is R* = R/2 of the smaller sphere
            deepest = self._law_overlap(pair, named, r, m, speed, gravity, radius)
            if deepest is not None and deepest[0] / radius > self.deepest_overlap[0]:
                self.deepest_overlap = (deepest[0] / radius, deepest[0], radius, kind, deepest[1])
            normal, tangential, zeta = laws.law_stiffness(self.law, pair, named, r, m, overlap)
            # name the overlap only when the stiffness depends on it (not for a linear spring)
            depends = laws.law_stiffness(self.law, pair, named, r, m, 2.0 * overlap)[:2] != (normal, tangential)
            modes = [("normal", math.sqrt(normal / m), zeta)]
            if self.spin:
                modes.append(("tangential", math.sqrt(3.5 * tangential / m), 0.0))
            for mode, omega, damping in modes:
                if omega == 0.0:
                    continue  # a mode without stiffness sets no limit (a couple-only law's tangential)
                acting = 2.0 * damping if predicted else damping
                limit = 2.0 / omega * (math.sqrt(1.0 + acting**2) - acting)
                if limit < best:
                    best, damped = limit, damping > 0.0
                    why = (f"{mode} mode of a {kind} contact, omega = {omega:.4g} rad/s"
                           + (f", damping ratio {damping:.3g}"
                              + (", doubled by the end-of-step velocity it reads" if predicted else "")
                              if damping else "")
                           + (f", stiffness at overlap {overlap:.3g} m" if depends else ""))
        return best, why, damped

    # how deep _law_overlap looks, in radii (deeper: infinity)
    OVERLAP_SEARCH_RADII = 20.0

    def _law_overlap(self, pair, named, r, m, speed, gravity, radius):
        """The overlap (m) at which the law's elastic force, undamped, has stored a normal
        impact's kinetic energy at ``speed`` or carries the sphere's weight, whichever is
        deeper, and which of the two: integrated from the law's tangent stiffness
        (``laws.law_stiffness``: a linear spring's kn, Hertz's 2 E* a, a plugin's own) up to
        OVERLAP_SEARCH_RADII radii (infinity when deeper still). An upper bound: a dashpot stops the sphere
        sooner. None when the law's stiffness cannot be evaluated that deep."""
        energy, load = 0.5 * m * speed**2, m * gravity
        overlaps = radius * np.logspace(-8.0, math.log10(self.OVERLAP_SEARCH_RADII), 400)
        try:
            stiffness = np.array([laws.law_stiffness(self.law, pair, named, r, m, float(d))[0] for d in overlaps])
        except (laws.LawError, ArithmeticError, ValueError):
            return None
        steps = np.diff(overlaps, prepend=0.0)
        force = np.cumsum(0.5 * (stiffness + np.concatenate(([stiffness[0]], stiffness[:-1]))) * steps)
        stored = np.cumsum(0.5 * (force + np.concatenate(([0.0], force[:-1]))) * steps)
        by_energy, by_load = np.searchsorted(stored, energy), np.searchsorted(force, load)
        if max(by_energy, by_load) >= len(overlaps):
            return math.inf, f"a normal impact speed of {speed:.4g} m/s"
        if by_energy >= by_load:
            return float(overlaps[by_energy]), f"a normal impact speed of {speed:.4g} m/s"
        return float(overlaps[by_load]), f"the sphere's weight under gravity of {gravity:.4g} m/s^2"

    def _choose_time_step(self) -> tuple[float, str]:
        scene = self.scene
        self.reference_contact_time = self.contact_time()
        self.stability, stability_why, self.stability_damped = self.stability_limit()
        self.stability_why = stability_why
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
            # the mode named when a dashpot lowers the limit (the limit alone said nothing of why
            # it fell with the restitution)
            (STABILITY_SAFETY * self.stability, f"{STABILITY_SAFETY:g} x stability limit {self.stability:.4g} s"
             + (f" ({self.stability_why})" if self.stability_damped else "")),
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
        for name in STATE_ARRAYS:
            setattr(state, name, getattr(state, name)[order])
        if state.last_force.shape[0]:
            state.last_force = state.last_force[order]
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
        state.pairs = exchange_pairs(*old, order, self.exchange_signs) + (None,) * (len(PAIR_TUPLE) - len(old))
        del old
        state.first_partner = None
        state.sorted_step = mean_step(state.position)
        state.sorts += 1

    # -- neighbour lists -----------------------------------------------------------
    def rebuild(self, state: State) -> None:
        """New Verlet lists at the current positions; every contact keeps its history.
        The particles are first sorted in space again when they have mixed (RESORT_RATIO)."""
        # Memory is given back on one thread only (a thread count of the run, not of a
        # chunk: a threaded run probes or falls back to one thread for some chunks,
        # LoopThreads): a threaded run keeps the freed pages for its next build, which
        # would take their page faults again on all its threads at once: 7.5 % of its time
        # (N = 200,000 lattice, two threads, 3,000 steps, five pairs interleaved: 19.35 s
        # against 20.93 s by medians, every pair faster; on one thread 32.0 against 32.3 s,
        # not resolved; peaks 334-340 MiB against 323-339)
        one_thread = self.loop_threads() == 1
        with lists_on_mappings(one_thread):
            self._build_lists(state)
        if one_thread:
            release_free_memory()

    def _build_lists(self, state: State) -> None:
        if (self.exchange_signs is not None and state.builds > 0
                and mean_step(state.position) > self.resort_ratio * state.sorted_step):
            self.sort_in_space(state)
        radius = self.scene.radius
        lists = None
        if self.pairs:
            old_offsets, old_partners, old_history, old_overlap = state.pairs[:4]
            # The old list is referenced here alone from now, and released once its
            # histories are carried over, before the reactions and their slots are
            # allocated; of its histories only the rows in use are kept (the others are
            # zero), the whole array released before the new list's is made: at its peak a
            # rebuild holds the old list's partners and overlaps, the touching pairs'
            # histories and the new list, not two lists' histories (24 bytes a list entry,
            # 116 a particle of the settled pile at 200,000, less 28 a touching pair)
            state.pairs = None
            # likewise the old list's first partners (8 bytes a particle), recomputed with the
            # new list; a failure leaves none (State.restore recomputes them with the lists)
            state.first_partner = None
            history_width, carried = old_history.shape[1], None
            try:
                carried = rows_in_use(old_history)
                old_history = None
                lists = state.build_lists(state.position)  # the position at build from here on
                offsets, found = lists["pair_offsets"], lists["pair_neighbours"]
                # zeros from the operating system: rows no contact is carried into stay
                # unwritten (not resident) until a contact starts there
                history = np.zeros((found.shape[0], history_width))
                # a pair new to the list starts with overlap -1 (apart: the skin guarantees it)
                overlap = np.full(found.shape[0], -1.0)
                neighbours.carry_history(old_offsets, old_partners, *carried, old_overlap, offsets, found, history,
                                         overlap)
            except BaseException:
                # the list as before the call, the rest of the tuple made again by the
                # restore a failure does (State.restore)
                if old_history is None:
                    old_history = expand_rows(*carried, (old_partners.shape[0], history_width))
                state.pairs = (old_offsets, old_partners, old_history, old_overlap) + (None,) * (len(PAIR_TUPLE) - 4)
                raise
            del old_offsets, old_partners, old_overlap, carried
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
            neighbours.carry_history(old_offsets, old_found, *rows_in_use(old_history), old_overlap, offsets, found,
                                     history, overlap)
            state.meshes = (triangles, triangle_material, offsets, found, history, overlap)
        # in place: a new array beside the old one, which the last good state held, was 24
        # bytes a particle more at the peak of a large run's rebuild
        np.copyto(state.position_at_build, state.position)
        state.list_near_planes()
        state.builds += 1

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
        (:func:`minidem.engine.checkpoint.load_for_resume`): continue from it, bit for bit;
        its arrays dict is emptied once they are restored (a resumed run holds no second
        copy of the state), its meta is left as it was.

        Raises :class:`RunFailure` on a blow-up (see :mod:`minidem.engine.blowup`), after
        restoring ``self.state`` to the last good state (and writing it, with checkpoints).
        """
        loop_threads = self.loop_threads()
        if not self.parallel and not self.pairs and self.scene.walls.triangles.shape[0] == 0:
            # one sphere among planes and cylinders runs no parallel loop (no kernel's, no
            # neighbour list's or mesh candidates'): it leaves numba's threads unstarted
            # (numba.get_num_threads would start them), and a process without them can
            # still fork its sweep workers (studies.executors), which a process with them
            # cannot do safely
            return RunLoop(self, chunk_steps, progress, on_frame, loop_threads, checkpoints, resume_from).run()
        threads_before = numba.get_num_threads()
        # every parallel loop, the neighbour-list builds too, runs on the particle loops' count
        numba.set_num_threads(loop_threads)
        try:
            return RunLoop(self, chunk_steps, progress, on_frame, loop_threads, checkpoints, resume_from).run()
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
        if scene.output_interval is not None:
            return scene.output_interval
        expected = end_time
        if (scene.impact is not None and scene.stop == "separation" and scene.end_time is None
                and math.isfinite(self.reference_contact_time)):
            # an impact ends at its separation, not at its cap of 100 contact times: a frame
            # every 2 contact times had none inside the contact (review). Only an impact's
            # flight to the touch is known (flight_time): elsewhere the cap stands
            expected = min(end_time, max(self.start_time, self.flight_time) + self.reference_contact_time)
        return expected / 50.0

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
            return (f"law '{self.law.name}' ({self.entry.distribution}) returned a non-finite force"
                    + (" or couple" if self.law.couples else "") + f" {when} for particle {particle} against {what}")
        if code == kernel.TUNNELLED:
            ratio, overlap, radius, kind, cause = self.deepest_overlap
            if ratio > 1.0:  # the law itself lets it through (derived.check_simulation warned)
                depth = (f"about {overlap:.3g} m" if math.isfinite(overlap)
                         else f"more than {self.OVERLAP_SEARCH_RADII:g} radii")
                return (f"particle {particle} passed through {what} {when}: its contacts may need an overlap of "
                        f"{depth} ({cause}), more than its radius {radius:.3g} m")
            return f"particle {particle} passed through {what} {when}: the time step is too large"
        return f"run stopped with status {code} {when}"
