"""Scenario files: TOML -> overrides -> validated :class:`Scene`.

Every key a scenario may hold is declared once in ``SCHEMA`` (type, unit, default,
bounds, meaning); validation, the error messages and the scenario reference in
``docs/scenario-reference.md`` (``minidem docs``) all come from it, so they cannot
drift apart. Nothing is compiled or run here.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import difflib
import json
import math
import tomllib
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from minidem.errors import ScenarioError
from minidem.scene import derived


@dataclasses.dataclass(frozen=True)
class Key:
    name: str
    kind: str  # float, int, str, bool, vec3, float_or_auto, choice
    default: Any
    unit: str
    description: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple = ()
    required: bool = False

    def bounds_text(self) -> str:
        if self.kind == "choice":
            return " | ".join(f'"{c}"' for c in self.choices)
        if self.low is None and self.high is None:
            return ""
        lo = "-inf" if self.low is None else f"{self.low:g}"
        hi = "inf" if self.high is None else f"{self.high:g}"
        closed_high = self.high is not None and not self.high_open
        return f"{'(' if self.low_open else '['}{lo}, {hi}{']' if closed_high else ')'}"


REQUIRED = object()

# section -> (kind of section, keys, description). "table": one table; "tables": named
# sub-tables ([materials.NAME]); "array": array of tables ([[walls]]); "open": keys
# validated elsewhere (the law's parameters in [contact]).
SCHEMA: dict[str, tuple[str, tuple[Key, ...], str]] = {
    "materials": ("tables", (
        Key("youngs_modulus", "float", REQUIRED, "Pa", "Young's modulus E", low=0.0, low_open=True),
        Key("poisson_ratio", "float", REQUIRED, "-", "Poisson ratio nu; (-1, 0.5] is physical, up to 1 is "
            "accepted with a warning (the paper's kappa studies use nu = 2/3 and 5/6); nu = 1 only against bodies of "
            "other materials (two bodies of nu = 1 have an infinite contact modulus E / (1 - nu^2))", low=-1.0, high=1.0,
            low_open=True),
        Key("density", "float", REQUIRED, "kg/m^3", "mass density", low=0.0, low_open=True),
    ), "Materials by name: `[materials.glass]`. Walls and particles refer to them by name."),
    "contact": ("open", (
        Key("law", "str", None, "", "contact law, preset or alias (`minidem laws` lists them); required "
            "unless the law is composed of parts (`normal = ...`)"),
        Key("normal", "str", None, "", "normal part (e.g. \"hertz\", \"hooke\"; adhesive \"jkr\", \"dmt\" with "
            "`surface_energy` in J/m^2, \"sjkr\" with `cohesion_energy_density` in J/m^3): compose the law of parts instead of naming one; with a preset `law`, "
            "replaces the preset's part"),
        Key("damping", "str", None, "", "damping part (e.g. \"tsuji\", \"viscous\") or \"none\""),
        Key("tangential", "str", None, "", "tangential part (e.g. \"mindlin\", \"linear_history\") or \"none\""),
        Key("rolling", "str", None, "", "rolling-resistance part (\"epsd\", \"sds_rolling\", \"constant_torque\") "
            "or \"none\"; with a combination of parts or with a paper law (`law = \"hm\"`, which takes a rolling "
            "and a twisting part but no other)"),
        Key("twisting", "str", None, "", "twisting-resistance part (\"marshall\", \"sds_twisting\") or \"none\"; "
            "as `rolling`"),
        Key("pairs", "table", None, "", "per-material-pair parameter values: `[contact.pairs.\"beads/steel\"]` "
            "friction = 0.5 (the two material names joined by '/', either order)"),
    ), "The contact law and its parameters (friction included): a law or preset by name (`law = "
       "\"hmd\"`) or a combination of parts (`normal = \"hertz\"`, `damping = \"tsuji\"`, `tangential = "
       "\"mindlin\"`). Every other key is a parameter of the law or of one of its parts, checked against "
       "its declaration (see docs/laws.md)."),
    "walls": ("array", (
        Key("type", "choice", "plane", "", "wall shape (see minidem/geometry/walls.py)",
            choices=("plane", "box", "cylinder", "mesh")),
        Key("material", "str", REQUIRED, "", "material name"),
        Key("point", "vec3", (0.0, 0.0, 0.0), "m", "plane: a point of the plane; cylinder: centre of its base"),
        Key("normal", "vec3", None, "-", "plane (required): normal pointing to the side the spheres are on "
            "(normalised)"),
        Key("lower", "vec3", None, "m", "box (required): lower corner"),
        Key("upper", "vec3", None, "m", "box (required): upper corner"),
        Key("open_top", "bool", False, "", "box: leave out the upper z face (5 planes)"),
        Key("axis", "vec3", (0.0, 0.0, 1.0), "-", "cylinder: axis direction from the base (normalised)"),
        Key("radius", "float", None, "m", "cylinder (required): inner radius", low=0.0, low_open=True),
        Key("length", "float", None, "m", "cylinder (required): length along the axis", low=0.0, low_open=True),
        Key("bottom", "bool", False, "", "cylinder: close the base with a plane"),
        Key("file", "str", None, "", "mesh (required): STL/OBJ/PLY/VTK surface file, relative to the "
            "scenario file"),
        Key("scale", "float", 1.0, "-", "mesh: factor applied to the file's coordinates (e.g. 0.001 for mm)",
            low=0.0, low_open=True),
        Key("offset", "vec3", (0.0, 0.0, 0.0), "m", "mesh: shift applied after scaling"),
    ), "Walls, one `[[walls]]` table each: infinite planes, an axis-aligned box (its 5 or 6 faces as "
       "planes), the inside of a finite cylinder, or a triangle mesh. [impact].wall counts planes, "
       "a box adds its planes in the order lower x, upper x, lower y, upper y, lower z, upper z."),
    "particles": ("array", (
        Key("position", "vec3", REQUIRED, "m", "centre"),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), "m/s", "initial velocity"),
        Key("angular_velocity", "vec3", (0.0, 0.0, 0.0), "rad/s", "initial angular velocity"),
        Key("radius", "float", REQUIRED, "m", "sphere radius", low=0.0, low_open=True),
        Key("material", "str", REQUIRED, "", "material name"),
    ), "Individual spheres, one `[[particles]]` table each."),
    "fill": ("array", (
        Key("kind", "choice", REQUIRED, "", "generator (see minidem/scene/fills.py)",
            choices=("lattice", "random", "file")),
        Key("material", "str", REQUIRED, "", "material name"),
        Key("radius", "float", None, "m", "lattice, random (required): sphere radius (random: the smallest)",
            low=0.0, low_open=True),
        Key("radius_max", "float", None, "m", "random: largest radius (radii uniform in radius..radius_max)",
            low=0.0, low_open=True),
        Key("lower", "vec3", None, "m", "lattice, random (required): lower corner of the region"),
        Key("upper", "vec3", None, "m", "lattice, random (required): upper corner of the region"),
        Key("spacing", "float", None, "m", "lattice (required): site spacing; first centre at lower + "
            "spacing/2, filled x fastest, then y, then z", low=0.0, low_open=True),
        Key("count", "int", None, "-", "number of spheres (random: required; lattice: default all sites)",
            low=0),
        Key("jitter", "float", 0.0, "m", "lattice: uniform random x and y shift in [-jitter, jitter]",
            low=0.0),
        Key("seed", "int", 12345, "-", "random seed (jitter, random)", low=0),
        Key("file", "str", None, "", "file (required): CSV whose first line is a header naming its columns "
            "(x,y,z,radius and optionally vx,vy,vz,wx,wy,wz, lower case, any order) or a VTK point file with "
            "a radius array, relative to the scenario file"),
        Key("velocity", "vec3", (0.0, 0.0, 0.0), "m/s", "initial velocity (lattice, random)"),
    ), "Particle generators, one `[[fill]]` table each, added after [[particles]]."),
    "impact": ("table", (
        Key("material", "str", REQUIRED, "", "material of the sphere"),
        Key("radius", "float", REQUIRED, "m", "sphere radius", low=0.0, low_open=True),
        Key("speed", "float", None, "m/s", "impact speed Vi (required unless normal_speed is given)", low=0.0,
            low_open=True),
        Key("angle_deg", "float", 0.0, "deg", "impact angle from the wall normal", low=0.0, high=90.0,
            high_open=True),
        Key("normal_speed", "float", None, "m/s", "instead of speed and angle_deg: the approach speed along the "
            "wall normal (Chung & Ooi's tests at constant normal speed)", low=0.0, low_open=True),
        Key("tangential_speed", "float", None, "m/s", "with normal_speed: the speed along the tangent; speed "
            "and angle_deg follow from the two", low=0.0),
        Key("gap", "float", 0.0, "m", "distance from the sphere to the wall at t = 0, travelled at the impact "
            "velocity before first touch (0: touching at t = 0)", low=0.0),
        Key("wall", "int", 0, "-", "index of the plane hit, counting the planes of [[walls]] in order (a plane "
            "adds 1, a box its 5 or 6 faces, a cylinder its bottom if it has one, a mesh none)", low=0),
        Key("spin", "float", 0.0, "rad/s", "initial spin about the axis n x t (n wall normal, t "
            "tangential direction of travel)"),
        Key("tangent", "vec3", None, "-", "tangential direction of travel; default: the first of x, y, z "
            "not parallel to the normal, made orthogonal to it"),
    ), "One sphere placed touching a wall (zero overlap at t = 0, or `gap` away) with velocity Vi at angle_deg: "
       "the paper's oblique impact. Rebound measures (en, et, x, y1, y2) are reported for it."),
    "run": ("table", (
        Key("dt", "float_or_auto", "auto", "s", "time step, or \"auto\": the smallest of contact_time / "
            "steps_per_contact, 0.2 x the Rayleigh time and 0.2 x the integrator's stability limit, which a "
            "dashpot lowers (docs/time-step.md; the run's summary names the one that set it)",
            low=0.0, low_open=True),
        Key("steps_per_contact", "int", 4000, "-", "steps per normal-impact duration when dt = \"auto\" (at least: the "
            "Rayleigh or stability limit named under dt may make the step smaller)",
            low=20),
        Key("integrator", "choice", "auto", "", "\"auto\": \"analytic_flight\" for one particle among plane "
            "walls (its free flights are then flown in closed form, not stepped, unless output.trace asks for "
            "every step), else "
            "\"velocity_verlet\"; "
            "\"velocity_verlet\" (second order); "
            "\"symplectic_euler\" (v += F dt/m, then x += v dt); \"analytic_flight\" (velocity Verlet, with "
            "the free flight before the first contact solved in closed form and the steps starting at the "
            "exact touch time, and every later free flight flown in closed form in whole steps; one particle "
            "and plane walls). See docs/time-step.md",
            choices=("auto", "velocity_verlet", "symplectic_euler", "analytic_flight")),
        Key("allow_unstable_dt", "bool", False, "", "accept a run.dt above the integrator's stability limit "
            "(refused otherwise, with the limit and a suggested dt; see docs/time-step.md)"),
        Key("stop", "choice", "separation", "", "\"separation\": stop when the last contact ends (the "
            "particle loops then run serial, which records the separation instant within the step); "
            "\"time\": run to end_time (more than 16 particles: parallel loops)", choices=("separation", "time")),
        Key("end_time", "float", None, "s", "simulated time to run (required for stop = \"time\"; "
            "a safety limit otherwise, default 100 contact times)", low=0.0, low_open=True),
        Key("gravity", "vec3", (0.0, 0.0, 0.0), "m/s^2", "gravitational acceleration"),
        Key("skin", "float", None, "m", "Verlet neighbour-list skin; the list is rebuilt when a particle "
            "has moved skin/2; default: half the largest radius", low=0.0),
        Key("threads", "int", 0, "-", "most threads for the particle loops (0: all numba may use, "
            "NUMBA_NUM_THREADS). Scenes of fewer than 5,000 particles use one; larger ones time their "
            "chunks and run on one when that is faster (a loaded machine; docs/multi-particle.md, "
            "'Threads'). Results are bit-for-bit the same for any count", low=0),
    ), "Run control."),
    "output": ("table", (
        Key("directory", "str", None, "", "output directory (relative to the working directory); "
            "default out/<scenario file stem>; `--out` overrides"),
        Key("trace", "bool", False, "", "write trace.csv: the probed contact (particle 0 with the impact "
            "wall) at every step"),
        Key("vtk", "bool", None, "", "write a ParaView time series (particles.pvd, walls.vtu); default: "
            "on for scenes without [impact]"),
        Key("interval", "float", None, "s", "simulated time between VTK frames (t = 0 and the final state are always frames); "
            "default: 1/50 of the run's expected length, run.end_time, or for a run to separation the flight to the "
            "first touch and one contact time",
            low=0.0, low_open=True),
        Key("contacts", "bool", False, "", "also write the contact network (particles_contacts.pvd: lines "
            "between touching particles with cell array normal_force)"),
        Key("checkpoint_interval", "float", None, "s", "simulated time between checkpoints (OUT/checkpoint.npz, "
            "the complete state; `minidem run --resume` continues from it bit for bit); default: none on "
            "this account", low=0.0, low_open=True),
        Key("checkpoint_wall_interval", "float", 600.0, "s", "wall-clock time between checkpoints, so every "
            "long run has them; 0: none on this account", low=0.0),
    ), "What is written where. `minidem run` also writes OUT/final_state.npz (the state at the end, "
       "in the checkpoint format) and, when a run blows up, OUT/last_good.npz (the state before it)."),
    "sweep": ("table", (
        Key("cases", "table", REQUIRED, "", 'dotted scenario key -> list of values, e.g. {"contact.law" = '
            '["hmd", "ls"], "impact.angle_deg" = [1.0, 5.0]}; the cases are the cartesian product (first '
            "key slowest), each the base scenario with those values set (as `--set` would)"),
        Key("workers", "int", 0, "-", "local worker processes (0: one per CPU; `minidem run --workers` "
            "overrides; with `--scheduler` the cluster's workers run the cases)", low=0),
        Key("keep_traces", "bool", False, "", "write each case's per-step contact trace to "
            "OUT/traces/case_NNN.csv (as output.trace does for a single run)"),
        Key("figures", "list", ["y1", "y2", "et"], "", 'PNG figures to draw: "y1", "y2" (against x, with '
            'the rigid-body lines of eqs 6-8), "et" (against the angle), "force_displacement" (needs '
            'keep_traces); Chung & Ooi\'s, against sweep.abscissa: "hertz" (max overlap, peak force, contact '
            'duration beside Hertz theory), "restitution" (en obtained against requested), "rebound" (rebound '
            'tangential velocity, spin, rebound angle and recoil ratio beside rigid-body impulse theory), '
            '"force_time" (normal force against time from the traces of sphere-wall cases; needs keep_traces). '
            'A scenario without [impact] draws none by default (the default figures are an impact\'s)'),
        Key("series_labels", "list", None, "", "legend labels, one per combination of the swept keys other "
            "than sweep.abscissa and the keys varying together with it (default: the values)"),
        Key("title", "str", None, "", "figure title"),
        Key("together", "list", [], "", 'groups of swept keys that vary together instead of forming a product, '
            'e.g. [["particles.0.angular_velocity.2", "particles.1.angular_velocity.2"]] (both spheres spin '
            "alike); the lists of a group must be as long as each other"),
        Key("abscissa", "str", None, "", 'the swept key on the x axis of the "hertz", "restitution" and '
            '"rebound" figures (default impact.angle_deg); the curves are the other keys\' values'),
    ), "A parameter sweep: `minidem run` runs every case (in parallel: local processes, or a Dask "
       "cluster with `--scheduler`) and writes OUT/sweep.csv (case, law, angle_deg, x, y1, y2, et, en, "
       "contact_duration_s, energy_ratio, max_overlap_m, steps, dt_s, peak_normal_force_n, the collision "
       "measures of docs/chung-ooi.md when a hertz, restitution or rebound figure is asked for, the swept keys, "
       "trace_file (with keep_traces), status, error; the "
       "same file for any back end and worker count) and the figures. Finished cases are journalled in "
       "OUT/sweep.journal: running the same command again resumes an interrupted sweep. See "
       "docs/paper-reproduction.md and docs/sweeps-on-a-cluster.md."),
}


# The keys each wall `type` and fill `kind` uses: a key of the section that the chosen
# type/kind does not use is refused (it would be silently ignored), and the reference
# lists these sets. "type" defaults to "plane".
KEYS_BY_KIND: dict[str, tuple[str, dict[str, tuple[str, ...]]]] = {
    "walls": ("type", {
        "plane": ("type", "material", "point", "normal"),
        "box": ("type", "material", "lower", "upper", "open_top"),
        "cylinder": ("type", "material", "point", "axis", "radius", "length", "bottom"),
        "mesh": ("type", "material", "file", "scale", "offset"),
    }),
    "fill": ("kind", {
        "lattice": ("kind", "material", "radius", "lower", "upper", "spacing", "count", "jitter", "seed", "velocity"),
        "random": ("kind", "material", "radius", "radius_max", "lower", "upper", "count", "seed", "velocity"),
        "file": ("kind", "material", "file"),
    }),
}


@dataclasses.dataclass(frozen=True)
class Material:
    name: str
    youngs_modulus: float
    poisson_ratio: float
    density: float


@dataclasses.dataclass
class Impact:
    speed: float
    angle_deg: float
    wall: int
    normal: np.ndarray
    tangent: np.ndarray


@dataclasses.dataclass
class Scene:
    """A validated scenario: SI units, structure-of-arrays, float64."""

    source: str
    materials: list[Material]
    law_name: str
    law_parameters: dict[str, Any]
    position: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    radius: np.ndarray
    particle_material: np.ndarray
    wall_point: np.ndarray
    wall_normal: np.ndarray
    wall_material: np.ndarray
    dt: float | None
    steps_per_contact: int
    stop: str
    end_time: float | None
    gravity: np.ndarray
    output_directory: Path
    trace: bool
    impact: Impact | None = None
    raw: dict = dataclasses.field(default_factory=dict)
    walls: Any = None  # minidem.geometry.walls.WallSet: every wall kind (planes also in wall_point...)
    skin: float | None = None
    threads: int = 0
    vtk: bool = False
    output_interval: float | None = None
    vtk_contacts: bool = False
    checkpoint_interval: float | None = None
    checkpoint_wall_interval: float | None = None
    fill_ranges: list = dataclasses.field(default_factory=list)  # (first, stop) particle index per [[fill]]
    integrator: str = "velocity_verlet"
    allow_unstable_dt: bool = False
    # [contact.pairs."a/b"]: (material index, material index) (both orders) -> the law's
    # parameters for that pair, the scene's values with the pair's overrides
    pair_parameters: dict = dataclasses.field(default_factory=dict)
    # the index in the scenario of each stored particle, when the engine stores them in
    # another order (reordered); None: the scenario's own order
    particle_id: np.ndarray | None = None

    @property
    def n_particles(self) -> int:
        return self.radius.shape[0]

    @property
    def has_walls(self) -> bool:
        """Any plane, cylinder or mesh wall."""
        walls = self.walls
        return bool(self.wall_point.shape[0] or (walls is not None and (
            walls.cylinder_base.shape[0] or walls.triangles.shape[0])))

    @property
    def one_sphere_among_planes(self) -> bool:
        """One particle and no cylinder or mesh walls: its free flight to a plane has a
        closed form (run.integrator = "analytic_flight")."""
        walls = self.walls
        return self.n_particles == 1 and not walls.cylinder_base.shape[0] and not walls.triangles.shape[0]

    def reordered(self, order: np.ndarray) -> "Scene":
        """This scene with its particles stored in ``order`` (``order[k]``: the particle
        stored at k); ``particle_id`` keeps each one's index in the scenario."""
        ids = np.arange(self.n_particles, dtype=np.int64) if self.particle_id is None else self.particle_id

        def rows(array):  # a broadcast row (all particles alike, 0 bytes a particle) stays one
            return array if array.ndim and array.strides[0] == 0 else array[order]

        return dataclasses.replace(
            self, position=self.position[order], velocity=rows(self.velocity),
            angular_velocity=rows(self.angular_velocity), radius=rows(self.radius),
            particle_material=rows(self.particle_material), particle_id=ids[order])

    def in_scenario_order(self, stored: np.ndarray) -> np.ndarray:
        """Rows in storage order (one per particle) put back in the scenario's order."""
        if self.particle_id is None:
            return stored
        rows = np.empty_like(stored)
        rows[self.particle_id] = stored
        return rows

    def scenario_index(self, stored: int) -> int:
        """The scenario's index of the particle stored at ``stored``."""
        return stored if self.particle_id is None else int(self.particle_id[stored])

    def particle_name(self, stored: int) -> str:
        """The scenario table the particle stored at ``stored`` came from (the [impact]
        sphere is particle 0), as error messages name it."""
        index = self.scenario_index(stored)
        for k, (first, stop) in enumerate(self.fill_ranges):
            if first <= index < stop:
                return f"fill[{k}] (particle {index}, sphere {index - first} of the fill)"
        if self.impact is not None:
            return "impact" if index == 0 else f"particles[{index - 1}]"
        return f"particles[{index}]"

    @property
    def mass(self) -> np.ndarray:
        density = np.array([m.density for m in self.materials])[self.particle_material]
        return 4.0 / 3.0 * math.pi * self.radius**3 * density

    @property
    def inertia(self) -> np.ndarray:
        return 0.4 * self.mass * self.radius**2


# ---------------------------------------------------------------------------------
# reading and overriding
# ---------------------------------------------------------------------------------
def read_toml(path: str | Path) -> dict:
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ScenarioError(f"{path}: no such scenario file") from None
    except OSError as exc:
        raise ScenarioError(f"{path}: cannot read: {exc.strerror}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise ScenarioError(f"{path}: not UTF-8 text ({exc.reason}: byte 0x{raw[exc.start]:02x} at offset "
                            f"{exc.start}, line {line}); a scenario file is TOML, which must be UTF-8") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: TOML syntax error: {_toml_error(exc, text)}") from None
    except RecursionError:  # tomllib parses nested tables and arrays recursively
        raise ScenarioError(f"{path}: TOML nested too deeply to read (tables or arrays thousands of levels "
                            f"deep); a scenario nests at most {MAX_DEPTH} levels") from None
    _check_depth(data, str(path))
    return data


# A scenario's deepest value is 4 levels down ([sweep] cases = {"key" = [[...]]}); far
# deeper nesting is a generated or corrupted file, refused before anything recurses on it.
MAX_DEPTH = 32


def _check_depth(value, source: str) -> None:
    """Refuse tables and arrays nested more than MAX_DEPTH levels (iteratively: the check
    itself must not overflow the stack it protects)."""
    pending = [(value, [])]
    while pending:
        node, path = pending.pop()
        if len(path) > MAX_DEPTH:
            shown = ".".join(path[:4])
            raise ScenarioError(f"{source}: '{shown}...' is nested {len(path)}+ levels deep; a scenario nests at most "
                                f"{MAX_DEPTH} levels (tables and arrays)")
        if isinstance(node, dict):
            pending.extend((v, path + [str(k)]) for k, v in node.items())
        elif isinstance(node, list):
            pending.extend((v, path + [str(i)]) for i, v in enumerate(node))


def _toml_error(exc: tomllib.TOMLDecodeError, text: str) -> str:
    """tomllib's message, with the key named when it is a duplicate ("Cannot overwrite a
    value" says only the line)."""
    import re

    message = str(exc)
    found = re.search(r"\(at line (\d+), column (\d+)\)", message)
    if found and ("overwrite" in message or "Cannot declare" in message):
        line = text.splitlines()[int(found.group(1)) - 1] if int(found.group(1)) <= len(text.splitlines()) else ""
        key = line.split("=", 1)[0].strip() if "=" in line else line.strip()
        if key:
            message += f": '{key}' is given twice (a key may appear once in a table, and a [table] header once)"
    return message


_NO_ASSIGNMENT = "expected KEY=VALUE, e.g. --set impact.angle_deg=30"


def parse_override(text: str) -> tuple[list[str], Any]:
    """'impact.angle_deg=30' -> (['impact', 'angle_deg'], 30.0). The value is read as a
    TOML value when it is one (numbers, booleans, arrays, quoted strings), else as a bare string."""
    if "=" not in text:
        raise ScenarioError(f"--set {text!r}: {_NO_ASSIGNMENT}")
    path, end = _read_key(text, f"--set {text!r}", assignment=True)
    key, value_text = text[:end].strip(), text[end + 1:]
    try:
        value = tomllib.loads(f"v = {value_text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = value_text.strip()
    except RecursionError:
        raise ScenarioError(f"--set {key}=...: the value is nested too deeply to read") from None
    _check_depth(value, f"--set {key}")
    return path, value


def key_path(key: str, context: str) -> list[str]:
    """A dotted key as TOML writes it -> its parts: 'contact.pairs."beads/steel".friction'
    -> ['contact', 'pairs', 'beads/steel', 'friction']. ``context`` starts the error."""
    return _read_key(key, context, assignment=False)[0]


def _read_key(text: str, context: str, assignment: bool) -> tuple[list[str], int]:
    """(the parts of the dotted key that ``text`` starts with, where the key ends): at the
    first '=' outside a quoted part when ``assignment`` (KEY=VALUE), else at the end. A bare
    part runs to the next dot (so 'contact.pairs.beads/steel.friction' needs no quotes); a
    part that starts with a double or single quote is read as a TOML string and may hold dots
    or '='. As in TOML, a quote elsewhere is a character of a bare part (o'brien)."""
    stops = ".=" if assignment else "."
    parts: list[str] = []
    at = 0
    while True:
        while at < len(text) and text[at].isspace():
            at += 1
        if at < len(text) and text[at] in "\"'":
            quote, end = text[at], at + 1
            while end < len(text) and text[end] != quote:
                end += 2 if quote == '"' and text[end] == "\\" else 1
            if end >= len(text):
                raise ScenarioError(f"{context}: {_NO_ASSIGNMENT} (no '=' outside the key's quotes)" if assignment
                                    else f"{context}: the quoted key part starting at {text[at:]!r} has no "
                                         f"closing {quote}")
            try:
                part = tomllib.loads(f"part = {text[at:end + 1]}")["part"]
            except tomllib.TOMLDecodeError as exc:
                raise ScenarioError(f"{context}: the quoted key part {text[at:end + 1]} is not a TOML string "
                                    f"({exc})") from None
            at = end + 1
            while at < len(text) and text[at].isspace():
                at += 1
            if at < len(text) and text[at] not in stops:
                raise ScenarioError(f"{context}: expected '.' or '=' after the quoted key part "
                                    f"{text[:at]!r}, found {text[at:]!r} (quote a whole part, as in "
                                    "contact.pairs.\"beads/steel\".friction)")
        else:
            end = at
            while end < len(text) and text[end] not in stops:
                end += 1
            part, at = text[at:end].strip(), end
        if not part:
            key = text.partition("=")[0].strip() if assignment else text
            raise ScenarioError(f"{context}: empty key part in {key!r}")
        parts.append(part)
        if at < len(text) and text[at] == ".":
            at += 1  # the next part: an empty one (a trailing dot) is refused above
            continue
        if assignment and at >= len(text):
            raise ScenarioError(f"{context}: {_NO_ASSIGNMENT} (no '=' outside the key's quotes)")
        return parts, at


def canonical_key(key: str, context: str) -> str:
    """One spelling of a dotted key, so that keys are compared as paths: each part bare
    where it can be ('"sweep".workers' -> 'sweep.workers'), else quoted."""
    def spelled(part: str) -> str:
        bare = (part == part.strip() and not any(c in part for c in ".=") and part[0] not in "\"'")
        return part if bare else json.dumps(part)
    return ".".join(spelled(part) for part in key_path(key, context))


def _list_index(part: str) -> int:
    """An index into a [[table]] array as --set writes it: 0, 1, ... (Python's negative
    indices, '-1' for the last, would make 'walls.-1' and 'fill.5' mean different things)."""
    if not part.isdecimal():
        raise ValueError(part)
    return int(part)


def apply_overrides(data: dict, overrides: list[str]) -> dict:
    data = copy.deepcopy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = data
        for depth, part in enumerate(path[:-1]):
            if isinstance(node, list):
                try:
                    node = node[_list_index(part)]
                except (ValueError, IndexError):
                    entries = "1 entry" if len(node) == 1 else f"{len(node)} entries"
                    raise ScenarioError(f"--set {text!r}: '{'.'.join(path[:depth + 1])}' is not a valid "
                                        f"index (the list has {entries})") from None
            else:
                node = node.setdefault(part, {})
            # a list entry or a table's key may hold a value where the path needs a table
            # (a sweep over particles.1.material of a file whose particles[1] is a number)
            if not isinstance(node, (dict, list)):
                raise ScenarioError(f"--set {text!r}: '{'.'.join(path[:depth + 1])}' is a value, not a table")
        if isinstance(node, list):
            try:
                node[_list_index(path[-1])] = value
            except (ValueError, IndexError):
                raise ScenarioError(f"--set {text!r}: bad list index {path[-1]!r} (the list has {len(node)} "
                                    f"entries, 0 to {len(node) - 1})") from None
        else:
            node[path[-1]] = value
    return data


# ---------------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------------
class _Errors:
    def __init__(self, source: str):
        self.source = source
        self.messages: list[str] = []

    # a message quotes the value it refuses; a list of two million numbers quoted whole
    # was 10 MB on standard error (a robustness review): its start and its length will do
    LONGEST_MESSAGE = 1000

    def add(self, where: str, message: str) -> None:
        if len(message) > self.LONGEST_MESSAGE:
            message = f"{message[:self.LONGEST_MESSAGE]} ... ({len(message):,} characters in all)"
        self.messages.append(f"{where}: {message}" if where else message)

    def has(self, where: str) -> bool:
        """Whether a message about the key ``where`` was already added."""
        return any(m.startswith(f"{where}: ") for m in self.messages)

    def has_under(self, where: str) -> bool:
        """Whether a message about ``where`` or any of its keys was already added: a table
        with a bad value is not used further (its other values would be combined with
        the None the bad one was dropped to)."""
        return any(m.startswith((f"{where}: ", f"{where}.", f"{where}[")) for m in self.messages)

    def raise_if_any(self) -> None:
        if self.messages:
            lines = "\n".join(f"  - {m}" for m in self.messages)
            raise ScenarioError(f"{self.source}: invalid scenario\n{lines}")


def _did_you_mean(name: str, valid) -> str:
    close = difflib.get_close_matches(name, list(valid), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _check_value(key: Key, value: Any, where: str, errors: _Errors) -> Any:
    def bad(expected):
        errors.add(where, f"expected {expected}, got {value!r}")

    if key.kind in ("float", "float_or_auto"):
        if key.kind == "float_or_auto" and value == "auto":
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return bad("a number" + (' or "auto"' if key.kind == "float_or_auto" else "") + f" ({key.unit})")
        value = float(value)
        if not math.isfinite(value):
            return bad("a finite number")
        unit = f" {key.unit}" if key.unit not in ("", "-") else ""
        if key.low is not None and (value < key.low or (key.low_open and value == key.low)):
            errors.add(where, f"must be {'>' if key.low_open else '>='} {key.low:g}{unit}, got {value:g}")
        if key.high is not None and (value > key.high or (key.high_open and value == key.high)):
            errors.add(where, f"must be {'<' if key.high_open else '<='} {key.high:g}{unit}, got {value:g}")
        return value
    if key.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            return bad("an integer")
        if key.low is not None and value < key.low:
            errors.add(where, f"must be >= {key.low:g}, got {value}")
        return value
    if key.kind == "bool":
        return value if isinstance(value, bool) else bad("true or false")
    if key.kind in ("str", "choice"):
        if not isinstance(value, str):
            return bad("a string")
        if key.kind == "choice" and value not in key.choices:
            errors.add(where, f"must be one of {', '.join(repr(c) for c in key.choices)}, got {value!r}"
                       + _did_you_mean(value, key.choices))
        return value
    if key.kind == "table":
        return value if isinstance(value, dict) else bad("a table, e.g. {\"impact.angle_deg\" = [1.0, 5.0]}")
    if key.kind == "list":
        return value if isinstance(value, list) else bad("a list")
    if key.kind == "vec3":
        if (not isinstance(value, list) or len(value) != 3
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in value)):
            return bad(f"a list of 3 numbers ({key.unit})")
        array = np.array(value, dtype=np.float64)
        if not np.all(np.isfinite(array)):
            return bad("finite numbers")
        return array
    raise AssertionError(key.kind)


_PART_KEYS = ("normal", "damping", "tangential", "rolling", "twisting")


def _contact_law(contact: dict, material_index: dict, raw_materials: dict, errors: _Errors):
    """(law name, its parameters, per-material-pair parameters) of a [contact] table: a
    law or preset by name, a combination of parts, or a preset with some parts replaced.
    Problems go to ``errors``; the law name is None when there is no usable law."""
    from minidem.contact import laws

    values = _check_table(contact, SCHEMA["contact"][1], "contact", errors, open_keys=True)
    registry = laws.registry()
    chosen = {kind: values[kind].lower() for kind in _PART_KEYS if isinstance(values.get(kind), str)}
    try:
        if isinstance(values.get("law"), str):
            entry = registry.entry(values["law"])
            if chosen:
                entry = registry.with_parts(entry, chosen)
        elif chosen:
            if "normal" not in chosen:
                raise laws.LawError("a law composed of parts needs a normal part: normal = \"hertz\" or \"hooke\" "
                                    "(`minidem laws` lists the parts), or law = \"...\" for a named law")
            entry = registry.combination(chosen)
        else:
            errors.add("contact", 'missing law = "..." (a law or preset) or normal = "..." (a law composed of '
                       "parts); `minidem laws` lists them")
            return None, {}, {}
    except laws.LawError as exc:
        errors.add("contact.law" if "law" in contact and not chosen else "contact", str(exc))
        return None, {}, {}
    law = entry.law
    given = {k: v for k, v in contact.items() if k not in ("law", "pairs", *_PART_KEYS)}
    law_parameters, law_errors = law.resolve_parameters(given)
    for message in law_errors:
        errors.add("contact", message)
    for key in given:
        # a misspelt key of the contact table itself (contact.rollingg = "epsd"), which the
        # law's parameter list alone neither names nor suggests
        close = difflib.get_close_matches(key, ("law", "pairs", *_PART_KEYS), n=1, cutoff=0.75)
        if close and not any(p.name == key for p in law.parameters):
            errors.add("contact", f"'{key}': did you mean the contact key '{close[0]}'? (contact keys: law, "
                                  f"pairs, {', '.join(_PART_KEYS)}; the law's parameters are listed above)")
    pair_parameters = {}
    pairs = contact.get("pairs")
    if isinstance(pairs, dict):
        for key, table in pairs.items():
            where = f'contact.pairs."{key}"'
            names = key.split("/") if isinstance(key, str) else []
            if len(names) != 2 or not all(names):
                errors.add(where, "expected two material names joined by '/', e.g. [contact.pairs.\"glass/steel\"]")
                continue
            unknown = [n for n in names if n not in raw_materials]
            if unknown:
                errors.add(where, f"unknown material '{unknown[0]}'" + _did_you_mean(unknown[0], raw_materials)
                           + f"; defined: {', '.join(raw_materials) or 'none'}")
                continue
            if not isinstance(table, dict) or not table:
                errors.add(where, f"expected a table of parameters of law '{law.name}', e.g. friction = 0.5")
                continue
            if not all(n in material_index for n in names):
                continue  # an invalid material, already reported
            resolved, pair_errors = law.resolve_parameters({**given, **table})
            for message in pair_errors:
                errors.add(where, message)
            a, b = material_index[names[0]], material_index[names[1]]
            if (a, b) in pair_parameters:
                errors.add(where, f"the pair '{names[0]}/{names[1]}' is given twice (in either order)")
            pair_parameters[(a, b)] = pair_parameters[(b, a)] = resolved
    return law.name, law_parameters, pair_parameters


def _check_table(table: Any, keys: tuple[Key, ...], where: str, errors: _Errors, open_keys=False) -> dict:
    if not isinstance(table, dict):
        errors.add(where, f"expected a table, got {type(table).__name__}")
        return {}
    by_name = {k.name: k for k in keys}
    out = {}
    for name, value in table.items():
        if name not in by_name:
            if not open_keys:
                errors.add(f"{where}.{name}", "unknown key" + _did_you_mean(name, by_name)
                           + f"; valid keys: {', '.join(by_name)}")
            continue
        out[name] = _check_value(by_name[name], value, f"{where}.{name}", errors)
    for key in keys:
        if key.name not in table:
            if key.default is REQUIRED:
                errors.add(f"{where}.{key.name}", f"missing required key ({key.description}"
                           + (f", {key.unit}" if key.unit and key.unit != "-" else "") + ")")
            else:
                out[key.name] = np.array(key.default, dtype=np.float64) if key.kind == "vec3" and key.default is not None else key.default
                if key.kind == "float_or_auto" and key.default == "auto":
                    out[key.name] = None  # as if "auto" had been written
    return out


def output_origin(out_option, data: dict) -> str:
    """Where a run's output directory came from (for error messages): --out, the
    scenario's output.directory, or the default out/<stem>."""
    if out_option is not None:
        return "--out"
    if isinstance(data.get("output"), dict) and data["output"].get("directory"):
        return "output.directory"
    return "the default output directory"


def prepare_output_directory(directory: str | Path, given_by: str, source: str) -> Path:
    """Create the output directory (and its parents) and check that files can be written
    in it, before anything is compiled or run: a bad directory is bad input, not a run
    that fails at its end and loses the result. ``given_by`` names where the directory
    came from (``--out``, ``output.directory``, or the default); ``source`` is the scenario file."""
    import os
    import tempfile

    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(prefix=".minidem-write-test-", dir=directory)
        os.close(handle)
        os.unlink(probe)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        if isinstance(exc, FileExistsError) or (directory.exists() and not directory.is_dir()):
            reason = "exists and is not a directory"
        elif isinstance(exc, NotADirectoryError):
            reason = "a parent of it is a file, not a directory"
        raise ScenarioError(f"{source}: {given_by} '{directory}': cannot use it as the output directory: "
                            f"{reason}; give a directory that can be created and written in") from None
    return directory


def _check_kind_keys(table: Any, section: str, kind: Any, where: str, errors: _Errors) -> None:
    """Refuse keys of the section that the table's type/kind does not use (KEYS_BY_KIND)."""
    selector, by_kind = KEYS_BY_KIND[section]
    if not isinstance(table, dict) or kind not in by_kind:
        return  # not a table, or a bad type/kind: reported already
    known = {k.name for k in SCHEMA[section][1]}
    default = "" if selector in table else ", the default"
    for name in table:
        if name in known and name not in by_kind[kind]:
            users = [k for k, names in by_kind.items() if name in names]
            hint = ("; velocities come from the file's vx, vy, vz columns (a VTK file's 'velocity' array)"
                    if section == "fill" and kind == "file" and name == "velocity" else "")
            errors.add(f"{where}.{name}", f'not used by {selector} = "{kind}"{default} (used by '
                       + " or ".join(f'{selector} = "{u}"' for u in users) + f"); valid keys for "
                       f"{selector} = \"{kind}\": {', '.join(by_kind[kind])}{hint}")


def load_scene(path: str | Path, overrides: list[str] = (), output_directory: str | Path | None = None,
               while_checking=None) -> Scene:
    data = apply_overrides(read_toml(path), list(overrides))
    try:
        return build_scene(data, str(path), output_directory, while_checking)
    except ScenarioError as exc:
        if not overrides:
            raise
        # a value from the command line is not in the file the message names: say so
        raise ScenarioError(f"{exc}\n  (the file's values with {' '.join(f'--set {o}' for o in overrides)})") from None


def _vtk_on(output: dict, impact, source: str) -> bool:
    """output.vtk as given, or its default (on for a scene without [impact]); a contact
    network asked for with the series off would be ignored without a word: said."""
    vtk = impact is None if output["vtk"] is None else output["vtk"]
    if output["contacts"] and not vtk:
        warnings.warn(f"{source}: output.contacts = true writes nothing while output.vtk is "
                      f"{'false' if output['vtk'] is False else 'off (the default for a scene with [impact])'}: "
                      "set output.vtk = true for the contact network", stacklevel=3)
    return vtk


def build_scene(data: dict, source: str = "<scenario>", output_directory=None, while_checking=None) -> Scene:
    """Validate a scenario (the dict a TOML file parses to) and build its Scene. Every
    problem is collected with its key and reported at once (ScenarioError); then what
    the values imply (masses, energies) and the initial geometry are checked.

    ``while_checking(scene)``: a context manager entered around the geometry check (the
    scene is complete then, and the check of overlapping spheres may have to compile the
    neighbour search first); ``minidem run`` compiles the scene's kernel beside it on a
    fresh install (``minidem.engine.warmup.kernel_beside_check``)."""
    errors = _Errors(source)
    for section in data:
        if section not in SCHEMA and section != "sweep":
            errors.add(section, "unknown section" + _did_you_mean(section, SCHEMA)
                       + f"; valid sections: {', '.join(SCHEMA)}")
    materials, material_of = _materials(data, source, errors)
    law_name, law_parameters, pair_parameters = _contact(data, material_of, errors)
    walls = _Walls()
    _wall_tables(data, source, errors, material_of, walls)
    bodies = _Bodies()
    _particle_tables(data, errors, material_of, bodies)
    impact = _impact(data, errors, material_of, walls, bodies)
    _fills(data, source, errors, material_of, bodies)
    if not bodies.count and not errors.messages:
        errors.add("", "the scene has no particles: add an [impact] block, [[particles]] or [[fill]]")
    run = _check_table(data.get("run", {}), SCHEMA["run"][1], "run", errors)
    if run.get("stop") == "time" and run.get("end_time") is None and not errors.has("run.end_time"):
        errors.add("run.end_time", 'required when run.stop = "time"')
    output = _check_table(data.get("output", {}), SCHEMA["output"][1], "output", errors)
    errors.raise_if_any()

    if output_directory is None:
        output_directory = output.get("directory") or Path("out") / Path(source).stem
    scene = Scene(
        source=source,
        materials=materials,
        law_name=law_name,
        law_parameters=law_parameters,
        pair_parameters=pair_parameters,
        position=bodies.array(0, (0, 3)),
        velocity=bodies.array(1, (0, 3)),
        angular_velocity=bodies.array(2, (0, 3)),
        radius=bodies.array(3, (0,)),
        particle_material=bodies.array(4, (0,)),
        wall_point=np.array(walls.point, dtype=np.float64).reshape(-1, 3),
        wall_normal=np.array(walls.normal, dtype=np.float64).reshape(-1, 3),
        wall_material=np.array(walls.material, dtype=np.int64),
        dt=run["dt"],
        steps_per_contact=run["steps_per_contact"],
        integrator=run["integrator"],
        allow_unstable_dt=run["allow_unstable_dt"],
        stop=run["stop"],
        end_time=run["end_time"],
        gravity=run["gravity"],
        output_directory=Path(output_directory),
        trace=output["trace"],
        impact=impact,
        raw=data,
        skin=run["skin"],
        threads=run["threads"],
        vtk=_vtk_on(output, impact, source),
        output_interval=output["interval"],
        vtk_contacts=output["contacts"],
        checkpoint_interval=output["checkpoint_interval"],
        checkpoint_wall_interval=output["checkpoint_wall_interval"],
        fill_ranges=bodies.fill_ranges,
    )
    scene.walls = walls.wall_set(scene)
    if scene.integrator == "auto":
        # Free flight is exact in closed form for one sphere among planes (constant
        # gravity, nothing to hit but the planes): stepping it at the contact's dt would
        # cost steps and place the first touch only to within a step. Touching at
        # t = 0 it is velocity Verlet, bit for bit.
        scene.integrator = "analytic_flight" if scene.one_sphere_among_planes else "velocity_verlet"
    derived.check_scene(scene)  # masses, inertias, energies: what the values imply
    with while_checking(scene) if while_checking is not None else contextlib.nullcontext():
        _check_geometry(scene)
    return scene


class _MaterialNames:
    """Material name -> index into the scene's materials; an unknown name is reported
    (with the names defined) and gives -1, as does a material whose table was invalid."""

    def __init__(self, materials: list[Material], raw: dict, errors: _Errors):
        self.index = {m.name: i for i, m in enumerate(materials)}
        self.raw, self.errors = raw, errors

    def __call__(self, name, where: str) -> int:
        if name in self.index:
            return self.index[name]
        if isinstance(name, str) and name in self.raw:
            return -1  # invalid material, already reported
        if isinstance(name, str):
            self.errors.add(where, f"unknown material '{name}'" + _did_you_mean(name, self.raw)
                            + f"; defined: {', '.join(self.raw) or 'none'}")
        return -1


def _materials(data: dict, source: str, errors: _Errors) -> tuple[list[Material], _MaterialNames]:
    """[materials.NAME] tables -> the materials and their names' lookup."""
    materials: list[Material] = []
    raw_materials = data.get("materials", {})
    if not isinstance(raw_materials, dict) or not raw_materials:
        errors.add("materials", "at least one material is needed, e.g. [materials.glass] with "
                   "youngs_modulus, poisson_ratio, density")
        raw_materials = {}
    for name, table in raw_materials.items():
        values = _check_table(table, SCHEMA["materials"][1], f"materials.{name}", errors)
        nu = values.get("poisson_ratio")
        if isinstance(nu, float) and 0.5 < nu <= 1.0:
            warnings.warn(f"{source}: materials.{name}.poisson_ratio = {nu:g} > 0.5 is not physical; "
                          "accepted for stiffness-ratio studies (the paper's Table 1)"
                          + ("; nu = 1 only against bodies of other materials (two bodies of it have an infinite "
                             "contact modulus E / (1 - nu^2))" if nu == 1.0 else ""), stacklevel=3)
        if all(isinstance(values.get(k), float) for k in ("youngs_modulus", "poisson_ratio", "density")):
            materials.append(Material(name, values["youngs_modulus"], values["poisson_ratio"], values["density"]))
    return materials, _MaterialNames(materials, raw_materials, errors)


def _contact(data: dict, material_of: _MaterialNames, errors: _Errors):
    """[contact] -> (law name, law parameters, per-pair parameters)."""
    contact = data.get("contact")
    if not isinstance(contact, dict):
        errors.add("contact", ("expected a table" if "contact" in data else "missing [contact] section")
                   + ' with at least law = "..." (or normal = "..." and the other parts) and the law\'s '
                   'parameters, e.g. friction (`minidem laws`)')
        return None, {}, {}
    return _contact_law(contact, material_of.index, material_of.raw, errors)


@dataclasses.dataclass
class _Walls:
    """The walls read so far: planes (a box's faces among them) as point, normal and
    material lists, with their origin per plane ([[walls]] index, what it is, display
    bounds); cylinders and meshes as the tuples _shaped_wall appends."""

    point: list = dataclasses.field(default_factory=list)
    normal: list = dataclasses.field(default_factory=list)
    material: list = dataclasses.field(default_factory=list)
    origin: list = dataclasses.field(default_factory=list)
    cylinders: list = dataclasses.field(default_factory=list)
    meshes: list = dataclasses.field(default_factory=list)

    def wall_set(self, scene: Scene):
        """The flat arrays the kernel reads (minidem.geometry.walls.WallSet)."""
        from minidem.geometry import walls as wall_shapes

        wall_set = wall_shapes.WallSet.empty()
        wall_set.set_planes(scene.wall_point, scene.wall_normal, scene.wall_material, self.origin)
        cylinders, meshes = self.cylinders, self.meshes
        if cylinders:
            wall_set.cylinder_base = np.array([c[0] for c in cylinders])
            wall_set.cylinder_axis = np.array([c[1] for c in cylinders])
            wall_set.cylinder_radius = np.array([c[2] for c in cylinders])
            wall_set.cylinder_length = np.array([c[3] for c in cylinders])
            wall_set.cylinder_material = np.array([c[4] for c in cylinders], dtype=np.int64)
            wall_set.cylinder_table = np.array([c[5] for c in cylinders], dtype=np.int64)
        if meshes:
            wall_set.triangles = np.concatenate([v[f] for v, f, *_ in meshes])
            wall_set.triangle_material = np.concatenate([np.full(len(f), m, dtype=np.int64)
                                                         for v, f, m, *_ in meshes])
            wall_set.triangle_table = np.concatenate([np.full(len(f), k, dtype=np.int64) for v, f, m, k, _ in meshes])
            wall_set.mesh_files = {k: name for v, f, m, k, name in meshes}
            wall_set.meshes = [(v, f) for v, f, *_ in meshes]
            wall_set.mesh_table = [k for v, f, m, k, _ in meshes]
        return wall_set


def _wall_tables(data: dict, source: str, errors: _Errors, material_of, walls: _Walls) -> None:
    """[[walls]] tables: planes here, boxes, cylinders and meshes through _shaped_wall."""
    tables = data.get("walls", [])
    if not isinstance(tables, list):
        errors.add("walls", "expected an array of tables: [[walls]]")
        tables = []
    for index, table in enumerate(tables):
        where = f"walls[{index}]"
        values = _check_table(table, SCHEMA["walls"][1], where, errors)
        kind = values.get("type")
        _check_kind_keys(table, "walls", kind, where, errors)
        if kind in ("box", "cylinder", "mesh"):
            _shaped_wall(kind, values, where, source, errors, material_of, walls.point, walls.normal,
                         walls.material, walls.cylinders, walls.meshes, index, walls.origin)
            continue
        normal = values.get("normal")
        if normal is None and kind == "plane" and not errors.has(f"{where}.normal"):
            errors.add(f"{where}.normal", "missing required key for a plane (normal pointing to the spheres)")
        if isinstance(normal, np.ndarray):
            length = float(np.linalg.norm(normal))
            if length == 0.0:
                errors.add(f"{where}.normal", "must not be the zero vector")
            else:
                normal = normal / length
        if isinstance(normal, np.ndarray) and isinstance(values.get("point"), np.ndarray):
            walls.point.append(values["point"])
            walls.normal.append(normal)
            walls.material.append(material_of(values.get("material"), f"{where}.material"))
            walls.origin.append((index, "plane", []))


@dataclasses.dataclass
class _Bodies:
    """The particles read so far, in blocks (one [[particles]] table, the impact sphere
    or a whole [[fill]]: arrays in SI, never one Python object per particle, which cost
    about 360 bytes a particle at the scene's assembly: more than the run itself at
    1,000,000 particles), and the index range of each [[fill]]."""

    blocks: list = dataclasses.field(default_factory=list)  # (position, velocity, spin, radius, material)
    count: int = 0
    fill_ranges: list = dataclasses.field(default_factory=list)

    def insert(self, index, position, velocity, spin, radius, material) -> None:
        """One sphere, first (index 0) or after the others (index = count)."""
        block = (np.reshape(np.asarray(position, dtype=np.float64), (1, 3)),
                 np.reshape(np.asarray(velocity, dtype=np.float64), (1, 3)),
                 np.reshape(np.asarray(spin, dtype=np.float64), (1, 3)), np.array([radius], dtype=np.float64),
                 np.array([material], dtype=np.int64))
        self.blocks.insert(0 if index == 0 else len(self.blocks), block)
        self.count += 1

    def extend(self, position, velocity, spin, radius, material) -> None:
        """A block of spheres after the others; ``material`` one id for all."""
        n = len(radius)
        self.blocks.append((np.asarray(position, dtype=np.float64).reshape(n, 3),
                            np.asarray(velocity, dtype=np.float64).reshape(n, 3),
                            np.asarray(spin, dtype=np.float64).reshape(n, 3), np.asarray(radius, dtype=np.float64),
                            np.full(n, material, dtype=np.int64)))
        self.count += n

    def array(self, k: int, shape) -> np.ndarray:
        """Quantity k of every block (0 position ... 4 material), in one array.

        Initial velocities and spins (k = 1, 2) that are the same for every sphere (a
        scene at rest, a fill poured at one speed) are one row broadcast to all, read-only:
        the run's state holds its own copy, and a second, per-particle one here cost 48
        bytes a particle that nothing reads one by one."""
        if not self.blocks:
            return np.zeros(shape, dtype=np.int64 if k == 4 else np.float64)
        if k in (1, 2):
            first = self.blocks[0][k][0].view(np.uint64)
            # compared bit for bit (== takes -0.0 for 0.0): the state starts from exactly what was given
            if all(bool((block[k].view(np.uint64) == first).all()) for block in self.blocks):
                return np.broadcast_to(self.blocks[0][k][0].copy(), (self.count, 3))
        return np.concatenate([block[k] for block in self.blocks])


def _particle_tables(data: dict, errors: _Errors, material_of, bodies: _Bodies) -> None:
    """[[particles]]: one sphere per table."""
    for index, table in enumerate(data.get("particles", []) if isinstance(data.get("particles", []), list) else []):
        where = f"particles[{index}]"
        values = _check_table(table, SCHEMA["particles"][1], where, errors)
        if all(k in values and values[k] is not None for k in ("position", "radius", "velocity", "angular_velocity")):
            bodies.insert(bodies.count, values["position"], values["velocity"], values["angular_velocity"],
                          values["radius"], material_of(values.get("material"), f"{where}.material"))
    if "particles" in data and not isinstance(data["particles"], list):
        errors.add("particles", "expected an array of tables: [[particles]]")


def _impact(data: dict, errors: _Errors, material_of, walls: _Walls, bodies: _Bodies) -> Impact | None:
    """[impact]: the paper's sphere, placed at its wall as particle 0 (the one the
    rebound is measured on)."""
    if "impact" not in data:
        return None
    values = _check_table(data["impact"], SCHEMA["impact"][1], "impact", errors)
    wall = values.get("wall")
    _impact_velocity(data["impact"], values, errors)
    if isinstance(wall, int) and not 0 <= wall < len(walls.normal):
        if not errors.has_under("walls"):  # a bad [[walls]] table is reported already
            errors.add("impact.wall", f"wall index {wall} does not exist: the scenario has "
                       f"{len(walls.normal)} valid wall(s) (an [[walls]] plane is needed)")
    elif all(isinstance(values.get(k), float) for k in ("radius", "speed", "angle_deg", "spin", "gap")):
        if values["angle_deg"] >= 90.0 and not errors.has("impact.angle_deg"):
            errors.add("impact.angle_deg", "must be < 90 deg (90 is parallel to the wall: no impact)")
        normal = walls.normal[wall]
        tangent = _tangent(normal, values.get("tangent"), errors)
        if tangent is not None:
            theta = math.radians(values["angle_deg"])
            bodies.insert(0, walls.point[wall] + (values["radius"] + values["gap"]) * normal,
                          values["speed"] * (math.sin(theta) * tangent - math.cos(theta) * normal),
                          values["spin"] * np.cross(normal, tangent), values["radius"],
                          material_of(values.get("material"), "impact.material"))
            return Impact(values["speed"], values["angle_deg"], wall, normal, tangent)
    return None


def _fills(data: dict, source: str, errors: _Errors, material_of, bodies: _Bodies) -> None:
    """[[fill]] generators, appended after the listed particles."""
    fills = data.get("fill", [])
    if not isinstance(fills, list):
        errors.add("fill", "expected an array of tables: [[fill]]")
        fills = []
    for index, table in enumerate(fills):
        first = bodies.count
        _fill(table, f"fill[{index}]", source, errors, material_of, bodies)
        bodies.fill_ranges.append((first, bodies.count))


def _required(values, keys, kind, where, errors) -> bool:
    missing = [k for k in keys if values.get(k) is None]
    for k in missing:
        # a value of the wrong type is dropped (None) after its own message: it is not also "missing"
        if not errors.has(f"{where}.{k}"):
            errors.add(f"{where}.{k}", f"missing required key for {kind}")
    return not missing


def _shaped_wall(kind, values, where, source, errors, material_of, wall_point, wall_normal, wall_material,
                 cylinders, meshes, index, plane_origin) -> None:
    """Box, cylinder and mesh walls (see minidem/geometry/walls.py); planes are handled inline."""
    from minidem.geometry import walls as wall_shapes

    material = material_of(values.get("material"), f"{where}.material")
    if errors.has_under(where):
        return
    if kind == "box":
        if _required(values, ("lower", "upper"), "a box", where, errors):
            if np.any(values["upper"] <= values["lower"]):
                errors.add(f"{where}.upper", f"must exceed lower on every axis, got lower "
                           f"{values['lower'].tolist()}, upper {values['upper'].tolist()}")
                return
            # an open box's sides are drawn up to its upper corner (they are infinite planes)
            lid = [(values["upper"].copy(), np.array([0.0, 0.0, -1.0]))] if values["open_top"] else []
            for point, normal, face in wall_shapes.box_planes(values["lower"], values["upper"], values["open_top"]):
                wall_point.append(point)
                wall_normal.append(normal)
                wall_material.append(material)
                plane_origin.append((index, f"box {face}", lid))
    elif kind == "cylinder":
        if _required(values, ("radius", "length"), "a cylinder", where, errors):
            axis = values["axis"]
            if float(np.linalg.norm(axis)) == 0.0:
                errors.add(f"{where}.axis", "must not be the zero vector")
                return
            axis = axis / np.linalg.norm(axis)
            cylinders.append((values["point"], axis, values["radius"], values["length"], material, index))
            if values["bottom"]:
                wall_point.append(values["point"])
                wall_normal.append(axis)
                wall_material.append(material)
                plane_origin.append((index, "cylinder bottom", []))
    elif kind == "mesh":
        if _required(values, ("file",), "a mesh", where, errors):
            path = Path(values["file"])
            if not path.is_absolute():
                path = Path(source).parent / path
            try:
                vertices, faces = wall_shapes.read_mesh(path, values["scale"], values["offset"])
            except ValueError as exc:
                errors.add(f"{where}.file", str(exc))
                return
            meshes.append((vertices, faces, material, index, str(path)))


# each fill kind's required keys, and its name in the message that one is missing
_FILL_REQUIRED = {"lattice": (("radius", "lower", "upper", "spacing"), "a lattice"),
                  "random": (("radius", "lower", "upper", "count"), "a random fill"),
                  "file": (("file",), "a file fill")}


def _fill(table, where, source, errors, material_of, bodies: _Bodies) -> None:
    """Particles from a [[fill]] generator (see minidem/scene/fills.py), appended to ``bodies``."""
    from minidem.scene import fills as generators

    values = _check_table(table, SCHEMA["fill"][1], where, errors)
    kind = values.get("kind")
    _check_kind_keys(table, "fill", kind, where, errors)
    material = material_of(values.get("material"), f"{where}.material")
    # every problem at once: a key the kind lacks beside the keys it does not use (review:
    # the missing count of a fill switched to "random" came only after the others were fixed)
    complete = kind not in _FILL_REQUIRED or _required(values, *_FILL_REQUIRED[kind], where, errors)
    if errors.has_under(where) or not complete:
        return
    try:
        if kind == "lattice":
            if values["spacing"] < 2.0 * values["radius"] + 2.0 * values["jitter"]:
                errors.add(f"{where}.spacing", f"must be at least 2 (radius + jitter) = "
                           f"{2 * (values['radius'] + values['jitter']):g} m so spheres start apart")
                return
            centres = generators.lattice(values["lower"], values["upper"], values["spacing"], values["count"],
                                         values["jitter"], values["seed"])
            radii = np.full(len(centres), values["radius"])
            speeds, spins = np.tile(values["velocity"], (len(centres), 1)), np.zeros((len(centres), 3))
        elif kind == "random":
            largest = values["radius_max"] or values["radius"]
            if largest < values["radius"]:
                errors.add(f"{where}.radius_max", "must be >= radius")
                return
            centres, radii = generators.random_packing(values["lower"], values["upper"], values["count"],
                                                       values["radius"], largest, values["seed"])
            speeds, spins = np.tile(values["velocity"], (len(centres), 1)), np.zeros((len(centres), 3))
        elif kind == "file":
            path = Path(values["file"])
            if not path.is_absolute():
                path = Path(source).parent / path
            read = generators.read_particles(path)
            centres, radii, speeds, spins = read["position"], read["radius"], read["velocity"], read["angular_velocity"]
        else:
            return
    except ValueError as exc:
        errors.add(where, str(exc))
        return
    bodies.extend(centres, speeds, spins, radii, material)


def _impact_velocity(table: dict, values: dict, errors: _Errors) -> None:
    """[impact] velocity as speed and angle_deg, or as normal_speed and tangential_speed:
    the second form is turned into the first (values is updated)."""
    if not isinstance(table, dict):
        return  # _check_table has said what [impact] should be
    components = [k for k in ("normal_speed", "tangential_speed") if k in table]
    if not components:
        if "speed" not in table:
            errors.add("impact.speed", "missing required key (impact speed Vi, m/s), or give normal_speed "
                       "(and tangential_speed) instead")
        return
    polar = [k for k in ("speed", "angle_deg") if k in table]
    if polar:
        errors.add(f"impact.{components[0]}", f"give either speed and angle_deg or normal_speed and "
                   f"tangential_speed, not both (the table also has {', '.join(polar)})")
        return
    if "normal_speed" not in table:
        errors.add("impact.normal_speed", "missing: tangential_speed needs normal_speed (m/s, > 0)")
        return
    normal, tangential = values.get("normal_speed"), values.get("tangential_speed") or 0.0
    if isinstance(normal, float) and isinstance(tangential, float):
        values["speed"] = math.hypot(normal, tangential)
        values["angle_deg"] = math.degrees(math.atan2(tangential, normal))


def _tangent(normal: np.ndarray, given, errors: _Errors):
    if given is not None:
        tangent = np.asarray(given, dtype=np.float64) - np.dot(given, normal) * normal
        if np.linalg.norm(tangent) < 1e-12:
            errors.add("impact.tangent", "must not be parallel to the wall normal")
            return None
        return tangent / np.linalg.norm(tangent)
    for axis in np.eye(3):
        tangent = axis - np.dot(axis, normal) * normal
        if np.linalg.norm(tangent) > 1e-6:
            return tangent / np.linalg.norm(tangent)
    raise AssertionError("no tangent for a unit normal")


# Initial overlaps below this fraction of the radius are round-off of "touching".
_TOUCH_TOLERANCE = 1e-9


def _check_geometry(scene: Scene, max_reported: int = 5) -> None:
    """Refuse particles behind or inside a wall and particles overlapping each other at
    t = 0: the first step would release the stored elastic energy as a blast."""
    errors = _Errors(scene.source)
    # (particle, message) for every particle behind or inside a wall, planes first; the
    # first max_reported are listed (a whole fill behind a wall is one mistake, not 4000)
    wall_findings: list[tuple[int, str]] = []
    for w in range(scene.wall_point.shape[0]):
        # (w counts planes: a box contributes several, a cylinder's bottom one; the
        # plane is named by its [[walls]] table and which face of it it is)
        plane = (scene.walls.plane_name(w) if scene.walls is not None else
                 f"plane {w} (through {scene.wall_point[w].tolist()}, normal {scene.wall_normal[w].tolist()})")
        overlap = scene.radius - (scene.position - scene.wall_point[w]) @ scene.wall_normal[w]
        for i in np.flatnonzero(overlap >= scene.radius):
            wall_findings.append((i, f"centre is on or behind {plane}; move the particle to the side the normal "
                                  "points to, or flip the wall's normal"))
        for i in np.flatnonzero((overlap > _TOUCH_TOLERANCE * scene.radius) & (overlap < scene.radius)):
            wall_findings.append((i, f"overlaps {plane} by {overlap[i]:.3g} m at t = 0; move it at least that "
                                  "far along the normal"))
    if scene.walls is not None:
        # cylinders and meshes as planes: every contact, whatever the wall, starts at first
        # touch during the run, with zero history (docs/multi-particle.md)
        from minidem.geometry.walls import initial_wall_overlaps

        for i, wall, overlap, behind in initial_wall_overlaps(scene.walls, scene.position, scene.radius,
                                                               _TOUCH_TOLERANCE):
            wall_findings.append((i, f"centre is on or outside {wall}; place it inside" if behind else
                                  f"overlaps {wall} by {overlap:.3g} m at t = 0; move it at least that far away "
                                  "from the wall"))
    for i, message in wall_findings[:max_reported]:
        errors.add(scene.particle_name(i), message)
    if len(wall_findings) > max_reported:
        errors.add("", f"... and {len(wall_findings) - max_reported} more particle-wall overlaps")
    if scene.n_particles > 1:
        from minidem.geometry.neighbours import build_pairs

        offsets, neighbours = build_pairs(scene.position, scene.radius, 0.0)
        first = np.repeat(np.arange(scene.n_particles), np.diff(offsets))
        gap = (np.linalg.norm(scene.position[first] - scene.position[neighbours], axis=1)
               - scene.radius[first] - scene.radius[neighbours])
        overlapping = np.flatnonzero(gap < -_TOUCH_TOLERANCE * np.minimum(scene.radius[first], scene.radius[neighbours]))
        for k in overlapping[:max_reported]:
            i, j = sorted((int(first[k]), int(neighbours[k])))
            errors.add(scene.particle_name(i), f"overlaps {scene.particle_name(j)} by {-gap[k]:.3g} m at "
                       "t = 0; place the spheres at least the sum of their radii apart")
        if len(overlapping) > max_reported:
            errors.add("", f"... and {len(overlapping) - max_reported} more overlapping pairs")
    errors.raise_if_any()


# ---------------------------------------------------------------------------------
# reference documentation, generated from SCHEMA
# ---------------------------------------------------------------------------------
def _toml(value) -> str:
    """A default as it would be written in a scenario file (the reference is read by people
    writing TOML: false, [0.0, 0.0, 1.0], "auto", not Python's False, (0.0, 0.0, 1.0), auto)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string: the same quoting and escapes
    if isinstance(value, (tuple, list, np.ndarray)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


def reference_markdown() -> str:
    lines = ["# Scenario file reference", "",
             "Generated from `minidem/scene/scenario.py` (`minidem docs --write docs/scenario-reference.md`); every key, unit, default "
             "and bound below is the one the validator applies. Units are SI throughout.", ""]
    for section, (shape, keys, description) in SCHEMA.items():
        header = {"tables": f"[{section}.NAME]", "array": f"[[{section}]]"}.get(shape, f"[{section}]")
        lines += [f"## `{header}`", "", description, ""]
        if section in KEYS_BY_KIND:
            selector, by_kind = KEYS_BY_KIND[section]
            lines += [f"Keys by `{selector}` (any other key of this table is refused):", ""]
            lines += [f'- `{selector} = "{kind}"`: ' + ", ".join(f"`{k}`" for k in names) for kind, names in by_kind.items()]
            lines.append("")
        lines += ["| key | type | unit | default | bounds | meaning |", "|---|---|---|---|---|---|"]
        for key in keys:
            default = "required" if key.default is REQUIRED else ("-" if key.default is None else f"`{_toml(key.default)}`")
            kind = key.kind.replace("float_or_auto", 'float or "auto"').replace("vec3", "[x, y, z]")
            lines.append(f"| `{key.name}` | {kind} | {key.unit or ''} | {default} | {key.bounds_text().replace('|', 'or')} "
                         f"| {key.description} |")
        lines.append("")
    return "\n".join(lines)
