"""Validated scene -> compiled simulation -> run result.

``compile_kernel`` specialises the kernel template (``minidem/kernel.py``) for one law
and one scene shape; ``Simulation`` prepares the per-material-pair constants, chooses
the time step and advances the compiled kernel in chunks (no Python call per step or
per contact).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import math
import os
import sys
import time as wallclock
from pathlib import Path

import numba
import numpy as np

from minidem import __version__, kernel, laws
from minidem.scenario import Scene, ScenarioError

_TEMPLATE = Path(kernel.__file__)
_BLOCK_START = "# >>> specialisation block"
_BLOCK_END = "# <<< specialisation block"
_ENGINE_SOURCES = ("kernel.py", "contact.py", "integrate.py")


class RunFailure(Exception):
    """The run started but could not finish: the CLI exits with code 1."""


def cache_directory() -> Path:
    """Where specialised kernels and numba's cache of them live (MINIDEM_CACHE_DIR)."""
    root = os.environ.get("MINIDEM_CACHE_DIR") or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "minidem"
    path = Path(root) / "kernels"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _law_source_hash(law: laws.ContactLaw) -> str:
    """Hash of every module beside the law's, so an edited helper also invalidates the kernel
    (numba's cache does not notice changes in a callee)."""
    module = sys.modules[law.force.py_func.__module__]
    digest = hashlib.sha256()
    folder = Path(module.__file__).parent
    for path in sorted(folder.glob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()


_LOADED: dict[str, object] = {}


def compile_kernel(entry: laws.RegisteredLaw, spin: bool):
    """Return the kernel module specialised for ``entry.law`` (compiled lazily, cached on disk)."""
    law = entry.law
    func = law.force.py_func
    engine = hashlib.sha256()
    for name in _ENGINE_SOURCES:
        engine.update((_TEMPLATE.parent / name).read_bytes())
    key = hashlib.sha256(
        f"{engine.hexdigest()}|{_law_source_hash(law)}|{entry.distribution}|{entry.version}|{func.__module__}."
        f"{func.__qualname__}|{spin}|{numba.__version__}|{__version__}".encode()
    ).hexdigest()[:16]
    module_name = f"minidem_kernel_{law.name}_{key}"
    if module_name in _LOADED:
        return _LOADED[module_name]
    template = _TEMPLATE.read_text()
    head, rest = template.split(_BLOCK_START, 1)
    _, tail = rest.split(_BLOCK_END, 1)
    block = (f"{_BLOCK_START} (law '{law.name}' from {entry.distribution} {entry.version})\n"
             f"from {func.__module__} import {func.__qualname__} as law_force  # noqa: E402\n\n"
             f"SPIN = {bool(spin)}\n{_BLOCK_END}")
    path = cache_directory() / f"{module_name}.py"
    if not path.exists():
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


class Simulation:
    """A scene bound to a compiled kernel, its constants and its time step."""

    def __init__(self, scene: Scene, registry: laws.LawRegistry | None = None):
        self.scene = scene
        registry = registry or laws.registry()
        self.entry = registry.entry(scene.law_name)
        self.law = self.entry.law
        self.spin = self.law.is_frictional(scene.law_parameters)
        self._prepare_constants()
        self.dt, self.dt_reason = self._choose_time_step()
        self.kernel = compile_kernel(self.entry, self.spin)

    # -- constants -------------------------------------------------------------
    def _reference_size(self) -> tuple[float, float]:
        scene = self.scene
        if scene.impact is not None:
            return float(scene.radius[0]), float(scene.mass[0])
        return float(scene.radius.mean()), float(scene.mass.mean())

    def _prepare_constants(self) -> None:
        scene, law = self.scene, self.law
        materials = scene.materials
        n = len(materials)
        radius, mass = self._reference_size()
        speed = scene.impact.speed if scene.impact is not None else None
        self.pair_row = np.zeros((n, n), dtype=np.int64)
        rows, self.pairs, self.constants_by_pair = [], {}, {}
        for a in range(n):
            for b in range(a, n):
                pair = laws.ContactPair.from_materials(materials[a], materials[b], radius, mass, speed)
                try:
                    row, named = law.prepared_constants(pair, scene.law_parameters)
                except laws.LawError:
                    raise
                except Exception as exc:  # noqa: BLE001 - a plugin's prepare() is user code
                    raise laws.LawError(f"law '{law.name}' ({self.entry.distribution}): prepare() failed for "
                                        f"materials '{materials[a].name}'/'{materials[b].name}': {exc}") from exc
                self.pair_row[a, b] = self.pair_row[b, a] = len(rows)
                rows.append(row)
                self.pairs[(a, b)] = pair
                self.constants_by_pair[(a, b)] = named
        self.constants = np.array(rows, dtype=np.float64).reshape(len(rows), len(law.constants))

    # -- time step ---------------------------------------------------------------
    def characteristic_speed(self) -> float:
        scene = self.scene
        if scene.impact is not None:
            return scene.impact.speed * max(math.cos(math.radians(scene.impact.angle_deg)), 1e-3)
        speeds = np.linalg.norm(scene.velocity, axis=1)
        extent = float(np.ptp(scene.position, axis=0).max() + 2 * scene.radius.max()) if scene.n_particles else 0.0
        fall = math.sqrt(2.0 * float(np.linalg.norm(scene.gravity)) * extent)
        return max(float(speeds.max(initial=0.0)), fall, 1e-3)

    def contact_time(self) -> float:
        """Shortest normal-impact duration among the contact kinds the scene can have."""
        scene = self.scene
        speed = self.characteristic_speed()
        times = []
        for material in np.unique(scene.particle_material):
            members = scene.particle_material == material
            smallest = np.argmin(np.where(members, scene.radius, np.inf))
            r, m = float(scene.radius[smallest]), float(scene.mass[smallest])
            partners = set(scene.wall_material.tolist()) if scene.wall_material.size else set()
            for other in partners:
                key = (min(material, other), max(material, other))
                times.append(laws.law_contact_time(self.law, self.pairs[key], self.constants_by_pair[key], r, m, speed))
            if scene.n_particles > 1:
                for other in np.unique(scene.particle_material):
                    key = (min(material, other), max(material, other))
                    times.append(laws.law_contact_time(self.law, self.pairs[key], self.constants_by_pair[key],
                                                       r / 2, m / 2, speed))
        return min(times) if times else math.inf

    def _choose_time_step(self) -> tuple[float, str]:
        scene = self.scene
        self.reference_contact_time = self.contact_time()
        if scene.dt is not None:
            return scene.dt, "given in the scenario"
        if not math.isfinite(self.reference_contact_time):
            raise ScenarioError(f"{scene.source}: run.dt = \"auto\" needs a possible contact (walls or two "
                                "particles); give run.dt")
        dt = self.reference_contact_time / scene.steps_per_contact
        return dt, (f"auto: contact time {self.reference_contact_time:.4g} s "
                    f"/ {scene.steps_per_contact} steps per contact")

    # -- running -----------------------------------------------------------------
    def run(self, chunk_steps: int = 200_000, progress=None) -> RunResult:
        scene, k = self.scene, self.kernel
        n, n_walls = scene.n_particles, scene.wall_point.shape[0]
        position = scene.position.copy()
        velocity = scene.velocity.copy()
        angular_velocity = scene.angular_velocity.copy()
        force = np.zeros((n, 3))
        torque = np.zeros((n, 3))
        mass = scene.mass
        inverse_mass = 1.0 / mass
        inverse_inertia = 1.0 / scene.inertia
        wall_history = np.zeros((n, n_walls, self.law.history_size))
        wall_overlap = scene.radius[:, None] - np.einsum(
            "iwk,wk->iw", position[:, None, :] - scene.wall_point[None, :, :], scene.wall_normal)
        probe_wall = scene.impact.wall if scene.impact is not None else (0 if n_walls else -1)
        probe = np.zeros(8)
        stats = np.array([-1.0, -1.0, 0.0, 0.0, 0.0])
        status = np.zeros(3, dtype=np.int64)
        stop_at_separation = scene.stop == "separation"
        end_time = scene.end_time if scene.end_time is not None else 100.0 * self.reference_contact_time
        if not math.isfinite(end_time):
            raise ScenarioError(f"{scene.source}: run.end_time is needed: the scene has no contact to stop at")
        total_steps = int(math.ceil(end_time / self.dt - 1e-9))
        trace_chunks = []
        args = (position, velocity, angular_velocity, force, torque, mass, inverse_mass, inverse_inertia,
                scene.radius, scene.particle_material, scene.gravity, scene.wall_point, scene.wall_normal,
                scene.wall_material, self.pair_row, self.constants, wall_history, wall_overlap)

        try:
            # zero-length step: initial forces (dt = 0, so no displacement increments) and
            # the one compilation of this kernel, reported against the law that caused it
            k.compute_forces(position, velocity, angular_velocity, force, torque, mass, scene.radius,
                             scene.particle_material, scene.gravity, scene.wall_point, scene.wall_normal,
                             scene.wall_material, self.pair_row, self.constants, wall_history, wall_overlap,
                             0.0, 0.0, probe_wall, probe, stats, status)
            k.advance(*args, self.dt, 0.0, 0, 0, stop_at_separation, probe_wall, probe,
                      np.zeros((0, len(kernel.TRACE_COLUMNS))), stats, status)
        except numba.core.errors.NumbaError as exc:
            raise laws.LawError(f"law '{self.law.name}' from plugin '{self.entry.plugin}' "
                                f"({self.entry.distribution}): its force function does not compile in the "
                                f"engine: {_numba_cause(exc)}") from exc
        started = wallclock.perf_counter()
        steps = 0
        separated = False
        while steps < total_steps and status[0] == kernel.OK:
            chunk = min(chunk_steps, total_steps - steps)
            trace = np.zeros((chunk if scene.trace else 0, len(kernel.TRACE_COLUMNS)))
            taken = k.advance(*args, self.dt, 0.0, steps, chunk, stop_at_separation, probe_wall, probe,
                              trace, stats, status)
            if scene.trace:
                trace_chunks.append(trace[:taken])
            steps += taken
            if progress is not None:
                progress(steps, total_steps)
            if taken < chunk and status[0] == kernel.OK:
                separated = True
                break
        wall_time = wallclock.perf_counter() - started
        if status[0] != kernel.OK:
            self._report_fault(status, steps)
        return RunResult(
            scene=scene, law=self.law, constants=self.constants_by_pair, position=position, velocity=velocity,
            angular_velocity=angular_velocity, initial_velocity=scene.velocity, initial_angular_velocity=scene.angular_velocity,
            steps=steps, dt=self.dt, dt_reason=self.dt_reason, time=steps * self.dt, separated=separated,
            first_contact_time=stats[0], last_separation_time=stats[1], max_overlap=stats[2],
            peak_normal_force=stats[3], peak_tangential_force=stats[4], wall_time=wall_time,
            trace=np.concatenate(trace_chunks) if trace_chunks else None,
        )

    def _report_fault(self, status, steps) -> None:
        code, particle, partner = (int(x) for x in status)
        when = f"at step {steps} (t = {steps * self.dt:.6g} s)"
        if code == kernel.NON_FINITE_FORCE:
            raise RunFailure(f"law '{self.law.name}' ({self.entry.distribution}) returned a non-finite force "
                             f"{when} for particle {particle} on wall {partner}; the time step is "
                             f"{self.dt:.3g} s ({self.dt_reason})")
        if code == kernel.TUNNELLED:
            raise RunFailure(f"particle {particle} passed through wall {partner} {when}: the time step "
                             f"{self.dt:.3g} s is too large for this impact; try run.dt = {self.dt / 10:.3g}")
        raise RunFailure(f"run stopped with status {code} {when}")


def _numba_cause(exc: Exception) -> str:
    """The informative lines of a numba error (it buries the cause among 'During:' lines)."""
    lines = [line.strip() for line in str(exc).splitlines()]
    useful = [line for line in lines if line and not line.startswith(("File ", "During:", "^", "def "))
              and "Failed in nopython mode pipeline" not in line and "is not typed" not in line[:0]]
    return "; ".join(useful[:3]) or lines[0]


def run_scene(scene: Scene, progress=None) -> RunResult:
    return Simulation(scene).run(progress=progress)
