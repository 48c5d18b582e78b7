"""Contact laws: the declarative law object, the material pair it is prepared for, and
the registry that finds laws through entry points.

A contact law is data plus two functions (see ``docs/writing-a-contact-law.md``):

* ``prepare(pair, params) -> dict``: plain Python, run once per material pair before the
  simulation is compiled; turns material properties and law parameters into the named
  constants the force function reads.
* ``force(constants, effective_radius, effective_mass, normal_overlap,
  normal_overlap_increment, normal_velocity, tangential_increment, tangential_velocity,
  history) -> (fn, ftx, fty, ftz)``:
  a ``numba.njit`` function called by the engine's compiled contact loop. It sees one
  contact at a time and never particles, neighbour lists or walls.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import importlib.metadata
import inspect
import math
import numbers
import os
import re
import sys
import traceback
from typing import Any, Callable, Mapping

import pluggy

from minidem import hookspecs

ENTRY_POINT_GROUP = hookspecs.PROJECT_NAME
_NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_]*$")
_ALIAS_PATTERN = re.compile(r"^[a-z][a-z0-9_-]*$")  # matched lower-cased: the paper's names, e.g. "h-mdns"
# the force function's arguments, in the order the engine passes them
FORCE_ARGUMENTS = ("constants", "effective_radius", "effective_mass", "normal_overlap", "normal_overlap_increment",
                   "normal_velocity", "tangential_increment", "tangential_velocity", "history")


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A typed law parameter, settable from ``[contact]`` in a scenario file.

    ``default=None`` means "derived by ``prepare`` when not given" (for example the
    linear-spring stiffness calibrated from the Hertz contact time). ``low``/``high``
    are inclusive bounds unless ``low_open``/``high_open`` say otherwise; values must be
    finite, so an infinite bound is never reached (printed as an open side).
    """

    name: str
    default: float | None
    unit: str
    description: str
    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False
    high_open: bool = False
    required: bool = False

    def check(self, value: Any) -> str | None:
        """Return why ``value`` is invalid, or None when it is valid."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"must be a number, got {value!r}"
        value = float(value)
        if not math.isfinite(value):
            return f"must be finite, got {value!r}"
        if value < self.low or (self.low_open and value == self.low):
            return f"must be {'>' if self.low_open else '>='} {self.low:g}, got {value:g}"
        if value > self.high or (self.high_open and value == self.high):
            return f"must be {'<' if self.high_open else '<='} {self.high:g}, got {value:g}"
        return None

    def bounds_text(self) -> str:
        """The bounds in interval notation, as ``minidem laws`` and error messages print
        them: an infinite side is always open (``[0, inf)``), since values must be finite."""
        lo = "(" if self.low_open or math.isinf(self.low) else "["
        hi = ")" if self.high_open or math.isinf(self.high) else "]"
        return f"{lo}{self.low:g}, {self.high:g}{hi}"


@dataclasses.dataclass(frozen=True)
class HistorySlot:
    """Per-contact state the law keeps between steps.

    ``vector`` slots take three consecutive floats. The engine owns their geometry:
    it rotates them into the current tangent plane as the contact rotates (keeping
    their magnitude) and stores them as seen from the first particle of the pair, so a
    law can treat them as 2-D tangential vectors. Scalar slots are never touched by the
    engine. All slots are zero at first touch and dropped at separation.
    """

    name: str
    description: str
    vector: bool = False

    @property
    def size(self) -> int:
        return 3 if self.vector else 1


@dataclasses.dataclass(frozen=True)
class ContactPair:
    """What ``prepare`` knows about a pair of materials (paper section 2, general forms).

    Constants depend on the two materials only: the effective radius R* and mass m* of
    a contact change from contact to contact in a polydisperse scene, so the engine
    passes them to the force function. Laws that calibrate a constant from a size and a
    speed (the linear spring, eq 28) use ``reference_radius``/``reference_mass`` (the
    effective values of the scene's typical contact: the impact sphere on its wall, the
    pair of a two-sphere collision, or two mean particles) and ``reference_speed`` (the
    [impact] speed, or the two spheres' approach speed; None without one).
    """

    effective_modulus: float  # E*, Pa: 1/E* = (1-nu1^2)/E1 + (1-nu2^2)/E2
    effective_shear_modulus: float  # G*, Pa: 1/G* = (2-nu1)/G1 + (2-nu2)/G2
    poisson_ratio_1: float
    poisson_ratio_2: float
    reference_radius: float  # m
    reference_mass: float  # kg
    reference_speed: float | None = None

    @property
    def stiffness_ratio(self) -> float:
        """kappa = kt/kn of Hertz-Mindlin, 8 G* a / (2 E* a) = 4 G*/E* (eq 10)."""
        return 4.0 * self.effective_shear_modulus / self.effective_modulus

    @classmethod
    def from_materials(cls, mat1, mat2, reference_radius, reference_mass, reference_speed=None):
        e_star = 1.0 / ((1 - mat1.poisson_ratio**2) / mat1.youngs_modulus + (1 - mat2.poisson_ratio**2) / mat2.youngs_modulus)
        g1 = mat1.youngs_modulus / (2 * (1 + mat1.poisson_ratio))
        g2 = mat2.youngs_modulus / (2 * (1 + mat2.poisson_ratio))
        g_star = 1.0 / ((2 - mat1.poisson_ratio) / g1 + (2 - mat2.poisson_ratio) / g2)
        return cls(e_star, g_star, mat1.poisson_ratio, mat2.poisson_ratio, reference_radius, reference_mass, reference_speed)


def hertz_contact_time(effective_modulus: float, effective_radius: float, effective_mass: float, normal_speed: float) -> float:
    """Duration of an elastic Hertz normal impact, tc = 2.868 (m*^2/(R* E*^2 v))^(1/5) (eq 13)."""
    return 2.868 * (effective_mass**2 / (effective_radius * effective_modulus**2 * normal_speed)) ** 0.2


@dataclasses.dataclass(frozen=True)
class ContactLaw:
    """A contact force law, declared once and registered by a plugin.

    name          unique lower-case identifier used in scenario files (``law = "hmd"``)
    description   one line for ``minidem laws``
    parameters    the law's settable parameters (friction included when the law has it)
    constants     names of the per-material-pair constants ``prepare`` returns, in the
                  order the force function indexes them
    history       per-contact state slots
    prepare       ``prepare(pair: ContactPair, params: dict[str, float|None]) -> dict``
    force         numba ``@njit`` function (signature in the module docstring); must be
                  defined at module level so the engine can import it into its
                  specialised, cached kernel
    contact_time  optional ``contact_time(pair, constants: dict, effective_radius,
                  effective_mass, normal_speed) -> s``: the law's own normal-impact
                  duration, used for the automatic time step; the Hertz value (eq 13)
                  is used when absent
    aliases       other accepted names (the paper's names, e.g. "H-MDns")
    frictional    False when the law can never produce a tangential force; the engine
                  then drops spin from the compiled step. A law with a ``friction``
                  parameter is also treated as frictionless when friction = 0.
    stiffness     optional ``stiffness(pair, constants: dict, effective_radius,
                  effective_mass, normal_overlap) -> (kn, kt, damping_ratio)``: the
                  largest normal and tangential tangent stiffnesses (N/m) at that overlap
                  and the normal damping ratio, for the time-step stability limit
                  (docs/time-step.md); Hertz-Mindlin's undamped values are used when absent
    """

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    constants: tuple[str, ...]
    history: tuple[HistorySlot, ...]
    prepare: Callable[[ContactPair, dict], Mapping[str, float]]
    force: Any
    contact_time: Callable | None = None
    aliases: tuple[str, ...] = ()
    frictional: bool = True
    reference: str = ""
    stiffness: Callable | None = None

    @property
    def history_size(self) -> int:
        return sum(slot.size for slot in self.history)

    @property
    def vector_history_offsets(self) -> tuple[int, ...]:
        offsets, at = [], 0
        for slot in self.history:
            if slot.vector:
                offsets.append(at)
            at += slot.size
        return tuple(offsets)

    def parameter(self, name: str) -> Parameter:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(name)

    def resolve_parameters(self, given: Mapping[str, Any]) -> tuple[dict, list[str]]:
        """Defaults filled in and every value checked; returns (values, errors)."""
        errors, values = [], {}
        known = {p.name for p in self.parameters}
        for key in given:
            if key not in known:
                close = difflib.get_close_matches(key, sorted(known), n=1)
                hint = f" (did you mean '{close[0]}'?)" if close else ""
                valid = ", ".join(sorted(known)) or "none"
                errors.append(f"unknown parameter '{key}' for law '{self.name}'{hint}; valid: {valid}")
        for p in self.parameters:
            value = given.get(p.name, p.default)
            if value is None and p.required:
                errors.append(f"law '{self.name}' needs parameter '{p.name}' ({p.description}, unit {p.unit or '-'}, bounds {p.bounds_text()})")
                continue
            if value is None:
                values[p.name] = None
                continue
            why = p.check(value)
            if why:
                errors.append(f"'{p.name}' {why} (unit {p.unit or '-'}, bounds {p.bounds_text()})")
            else:
                values[p.name] = float(value)
        return values, errors

    def prepared_constants(self, pair: ContactPair, params: Mapping[str, Any]):
        """Run ``prepare`` and order its result as the force function expects."""
        import numpy as np

        produced = self.prepare(pair, dict(params))
        if not isinstance(produced, Mapping):
            raise LawError(f"law '{self.name}': prepare() must return a dict of constants, "
                           f"got {type(produced).__name__}")
        produced = dict(produced)
        missing = [c for c in self.constants if c not in produced]
        if missing:
            raise LawError(f"law '{self.name}': prepare() did not return constants {missing}")
        row = np.array([float(produced[c]) for c in self.constants], dtype=np.float64)
        if not np.all(np.isfinite(row)):
            bad = [c for c, v in zip(self.constants, row) if not math.isfinite(v)]
            raise LawError(f"law '{self.name}': prepare() returned non-finite constants {bad}")
        return row, produced

    def is_frictional(self, params: Mapping[str, Any]) -> bool:
        if not self.frictional:
            return False
        return params.get("friction", 1.0) != 0.0

    def source_fingerprint(self) -> str:
        """Hash of the force function's source, so a changed law never reuses a stale kernel."""
        func = getattr(self.force, "py_func", self.force)
        try:
            text = inspect.getsource(inspect.getmodule(func))
        except (OSError, TypeError):
            text = repr(func)
        return hashlib.sha256(text.encode()).hexdigest()[:12]


class LawError(Exception):
    """A law is unknown, broken, or its declaration or constants are invalid."""


@dataclasses.dataclass
class BrokenPlugin:
    plugin: str
    law: str | None
    reason: str
    aliases: tuple[str, ...] = ()  # the refused law's other names, so a lookup by one finds this


@dataclasses.dataclass
class RegisteredLaw:
    law: ContactLaw
    plugin: str  # entry-point name
    distribution: str  # package that provides it
    version: str


class LawRegistry:
    """All laws from all installed plugins, plus what failed to load and why."""

    def __init__(self):
        self._laws: dict[str, RegisteredLaw] = {}
        self._aliases: dict[str, str] = {}
        # name -> the third-party laws that claimed it (plugin, distribution, law), used or not
        self._claims: dict[str, list[tuple[str, str, str]]] = {}
        self.broken: list[BrokenPlugin] = []
        self._current = ("<direct>", "<direct>", "")

    # -- the object plugins receive in minidem_register_laws(registry) -------------
    def add(self, law: ContactLaw) -> None:
        plugin, dist, version = self._current
        problem = _declaration_problem(law)
        name = getattr(law, "name", None)
        if problem is None:
            problem = self._claim_problem(law, plugin, dist)
        if problem is not None:
            aliases = tuple(a.lower() for a in getattr(law, "aliases", ()) if isinstance(a, str)) \
                if isinstance(getattr(law, "aliases", None), tuple) else ()
            self.broken.append(BrokenPlugin(plugin, name if isinstance(name, str) else None, problem, aliases))
            return
        self._laws[law.name] = RegisteredLaw(law, plugin, dist, version)
        for alias in law.aliases:
            if alias.lower() != law.name:
                self._aliases[alias.lower()] = law.name

    def _owner(self, name: str) -> RegisteredLaw | None:
        if name in self._laws:
            return self._laws[name]
        return self._laws.get(self._aliases.get(name, ""))

    def _claim_problem(self, law: ContactLaw, plugin: str, dist: str) -> str | None:
        """Why ``law`` cannot have its name and aliases, or None. minidem's own laws are
        registered first and keep theirs: a plugin never replaces a built-in law, under
        its name or an alias. A third-party law is used only if no other third-party law
        claims any of its names: a clash refuses every law in it, whichever plugin was
        loaded first (so the plugins' order never decides which law a scenario runs)."""
        names = list(dict.fromkeys([law.name, *(a.lower() for a in law.aliases)]))
        for claimed in names:
            owner = self._owner(claimed)
            if owner is not None and (owner.distribution == hookspecs.PROJECT_NAME or owner.plugin == plugin):
                what = "name" if claimed == law.name else "alias"
                why = "; a plugin cannot replace a built-in law" if owner.plugin != plugin else ""
                return (f"{what} '{claimed}' is already taken by plugin '{owner.plugin}' ({owner.distribution}), "
                        f"law '{owner.law.name}'{why}")
        rivals = {}  # (plugin, distribution, law) -> the first name it shares with this law
        for claimed in names:
            for claimant in self._claims.get(claimed, []):
                rivals.setdefault(claimant, claimed)
        for claimed in names:
            self._claims.setdefault(claimed, []).append((plugin, dist, law.name))
        if not rivals:
            return None
        for (rival_plugin, rival_dist, rival_law), shared in rivals.items():
            rival = self._laws.get(rival_law)
            if rival is not None and rival.plugin == rival_plugin:  # in use until now: withdraw it
                del self._laws[rival_law]
                self._aliases = {a: n for a, n in self._aliases.items() if n != rival_law}
                self.broken.append(BrokenPlugin(rival_plugin, rival_law, (
                    f"name '{shared}' is also claimed by plugin '{plugin}' ({dist}), law '{law.name}'; neither "
                    "law is used: uninstall one of them"), tuple(a.lower() for a in rival.law.aliases)))
        (rival_plugin, rival_dist, rival_law), shared = next(iter(rivals.items()))
        return (f"name '{shared}' is also claimed by plugin '{rival_plugin}' ({rival_dist}), law '{rival_law}'; "
                "neither law is used: uninstall one of them")

    # -- lookup -------------------------------------------------------------------
    def names(self) -> list[str]:
        return sorted(self._laws)

    def entries(self) -> list[RegisteredLaw]:
        return [self._laws[n] for n in self.names()]

    def entry(self, name: str) -> RegisteredLaw:
        key = name.lower() if isinstance(name, str) else name
        if key in self._laws:  # a name before an alias
            return self._laws[key]
        if key in self._aliases:
            return self._laws[self._aliases[key]]
        for b in self.broken:
            if b.law is not None and (key == b.law or key in b.aliases):
                raise LawError(f"law '{name}' from plugin '{b.plugin}' is broken: {b.reason}")
        candidates = self.names() + sorted(self._aliases)
        close = difflib.get_close_matches(str(key), candidates, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        failed = [b for b in self.broken if b.law is None]
        if failed:
            hint += (f" {len(failed)} plugin(s) failed to load, so their laws are unknown: "
                     + "; ".join(f"'{b.plugin}': {b.reason}" for b in failed) + " (see `minidem laws`).")
        raise LawError(f"unknown contact law '{name}'. Available: {', '.join(self.names())}.{hint}")

    def get(self, name: str) -> ContactLaw:
        return self.entry(name).law

    def mark_broken(self, plugin: str, law: str | None, reason: str) -> None:
        """Record a law that failed later (e.g. at compile time) so it is listed as broken."""
        self.broken.append(BrokenPlugin(plugin, law, reason))


def _declaration_problem(law) -> str | None:
    if not isinstance(law, ContactLaw):
        return f"registry.add() expects a minidem.laws.ContactLaw, got {type(law).__name__}"
    if not isinstance(law.name, str) or not _NAME_PATTERN.match(law.name):
        return f"law name {law.name!r} is not a lower-case identifier"
    if not isinstance(law.description, str) or not law.description.strip():
        return "description must be a non-empty string"
    for field, kind in (("parameters", Parameter), ("history", HistorySlot)):
        items = getattr(law, field)
        if not isinstance(items, tuple) or not all(isinstance(x, kind) for x in items):
            return f"'{field}' must be a tuple of minidem.laws.{kind.__name__}"
    names = [p.name for p in law.parameters]
    if len(set(names)) != len(names):
        return "parameter names are not unique"
    for p in law.parameters:
        if p.default is not None and p.check(p.default):
            return f"default of parameter '{p.name}' {p.check(p.default)}"
    if not isinstance(law.constants, tuple) or not all(isinstance(c, str) for c in law.constants):
        return "'constants' must be a tuple of names"
    if not isinstance(law.aliases, tuple) or not all(
            isinstance(a, str) and _ALIAS_PATTERN.match(a.lower()) for a in law.aliases):
        return (f"'aliases' must be a tuple of names (letters, digits, '_' and '-', starting with a letter), "
                f"got {law.aliases!r}")
    if not callable(law.prepare):
        return "'prepare' is not callable"
    for hook in ("contact_time", "stiffness"):
        if getattr(law, hook) is not None and not callable(getattr(law, hook)):
            return f"'{hook}' must be a function or None, got {type(getattr(law, hook)).__name__}"
    if not hasattr(law.force, "py_func"):
        return "'force' is not a numba-compiled function (decorate it with @numba.njit)"
    func = law.force.py_func
    if "<locals>" in func.__qualname__ or func.__module__ == "__main__":
        return "'force' must be defined at module level in an importable module"
    try:
        force_import_name(law)
    except LawError as exc:
        return str(exc)
    arguments = [p for p in inspect.signature(func).parameters.values()
                 if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    if len(arguments) != len(FORCE_ARGUMENTS):
        return (f"'force' ({func.__qualname__}) takes {len(arguments)} arguments; the engine calls it with "
                f"{len(FORCE_ARGUMENTS)}: ({', '.join(FORCE_ARGUMENTS)})")
    return None


def force_import_name(law: ContactLaw) -> tuple[str, str]:
    """(module, attribute) under which the law's compiled force function can be imported:
    the engine's kernel imports it from there. Usually the function's own name; for
    ``force = numba.njit(_force_impl)`` the name it was bound to."""
    func = law.force.py_func
    module = sys.modules.get(func.__module__)
    if module is None:
        raise LawError(f"'force': its module '{func.__module__}' is not imported")
    if getattr(module, func.__qualname__, None) is law.force:
        return func.__module__, func.__qualname__
    for attribute, value in vars(module).items():
        if value is law.force:
            return func.__module__, attribute
    raise LawError(f"'force' ({func.__qualname__}) is not a module-level name of {func.__module__}: "
                   "the engine imports it from there (bind the compiled function to a name at module level)")


def _distribution_of(entry_point) -> tuple[str, str]:
    dist = getattr(entry_point, "dist", None)
    if dist is None:
        return "<unknown>", ""
    return dist.metadata["Name"], dist.version


def load_registry(extra_plugins: tuple = ()) -> LawRegistry:
    """Discover every plugin of the ``minidem`` entry-point group and collect its laws.

    Unlike pluggy's ``load_setuptools_entrypoints``, a plugin that fails to import or
    raises while registering is caught, recorded by name in ``registry.broken`` and does
    not stop the others. ``extra_plugins`` (objects or modules implementing hooks) serve
    tests and embedding applications.
    """
    registry = LawRegistry()
    manager = pluggy.PluginManager(hookspecs.PROJECT_NAME)
    manager.add_hookspecs(hookspecs)
    plugins = []
    # minidem's own laws first, so a third-party plugin can never take a built-in name
    # (whichever plugin registers a name first keeps it); the others in a fixed order
    found = [(_distribution_of(ep), ep) for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)]
    for (dist, version), ep in sorted(found, key=lambda item: (item[0][0] != hookspecs.PROJECT_NAME, item[1].name)):
        try:
            plugins.append((ep.name, dist, version, ep.load()))
        except PLUGIN_FAULTS as exc:  # any failure of a plugin is reported, never fatal
            registry.broken.append(BrokenPlugin(f"{ep.name} ({dist})", None, _one_line(exc)))
    for index, obj in enumerate(extra_plugins):
        plugins.append((getattr(obj, "__name__", f"extra{index}"), "<in-process>", "", obj))
    for plugin_name, dist, version, obj in plugins:
        try:
            manager.register(obj, name=plugin_name)
        except PLUGIN_FAULTS as exc:
            registry.broken.append(BrokenPlugin(plugin_name, None, f"invalid hook implementation: {_one_line(exc)}"))
            continue
        impls = [i for i in manager.hook.minidem_register_laws.get_hookimpls() if i.plugin is obj]
        for impl in impls:
            registry._current = (plugin_name, dist, version)
            try:
                impl.function(registry=registry)
            except PLUGIN_FAULTS as exc:
                registry.broken.append(BrokenPlugin(plugin_name, None, f"minidem_register_laws raised {_one_line(exc)}"))
        registry._current = ("<direct>", "<direct>", "")
    return registry


# What a plugin's code may raise without taking minidem down: every exception, and
# sys.exit() (SystemExit) or a stray GeneratorExit at import or in a hook; only Ctrl-C
# (KeyboardInterrupt) goes through, to stop minidem as the user asked.
PLUGIN_FAULTS = (Exception, SystemExit, GeneratorExit)


def _one_line(exc: BaseException) -> str:
    """Type, message and where: the innermost frame that is the plugin's own code (not
    importlib's, pluggy's or minidem's, which only carried the call), on one line."""
    frames = traceback.extract_tb(exc.__traceback__) if exc.__traceback__ else []
    own = [f for f in frames if not f.filename.startswith("<frozen")
           and not any(part in f.filename for part in (f"{os.sep}pluggy{os.sep}", f"{os.sep}importlib{os.sep}",
                                                        f"{os.sep}minidem{os.sep}laws.py"))]
    if isinstance(exc, SyntaxError) and exc.filename:
        where = f" (at {exc.filename}:{exc.lineno})"
    elif own:
        where = f" (at {own[-1].filename}:{own[-1].lineno})"
    else:  # raised by the machinery itself (a module not found, a hook's wrong arguments)
        where = ""
    return " ".join(f"{type(exc).__name__}: {exc}{where}".split())


_REGISTRY: LawRegistry | None = None


def registry() -> LawRegistry:
    """The process-wide registry, loaded on first use."""
    global _REGISTRY
    if _REGISTRY is None:
        _REGISTRY = load_registry()
    return _REGISTRY


def law_contact_time(law: ContactLaw, pair: ContactPair, constants: Mapping[str, float],
                     effective_radius: float, effective_mass: float, normal_speed: float) -> float:
    """The law's normal-impact duration (its own ``contact_time`` or Hertz, eq 13)."""
    if law.contact_time is not None:
        value = _call_law_function(law, "contact_time", law.contact_time, pair, constants, effective_radius,
                                   effective_mass, normal_speed)
        if not _positive_duration(value):
            raise LawError(f"law '{law.name}': contact_time() returned {value!r}; it must be a duration in s, "
                           "> 0 (math.inf where the law has no finite contact time)")
        return float(value)
    return hertz_contact_time(pair.effective_modulus, effective_radius, effective_mass, normal_speed)


def _call_law_function(law: ContactLaw, what: str, function, *args):
    """A law's own Python function (user code): any failure is the law's, reported as such."""
    try:
        return function(*args)
    except LawError:
        raise
    except PLUGIN_FAULTS as exc:
        raise LawError(f"law '{law.name}': its {what}() failed: {_one_line(exc)}") from exc


def _positive_duration(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and value > 0.0


def hertz_mindlin_stiffness(pair: ContactPair, effective_radius: float, normal_overlap: float) -> tuple[float, float]:
    """Tangent stiffnesses of Hertz-Mindlin at an overlap: dFn/dd = 2 E* a and the
    no-slip kt = 8 G* a, a = sqrt(R* d) (eqs 15-18)."""
    a = math.sqrt(effective_radius * normal_overlap)
    return 2.0 * pair.effective_modulus * a, 8.0 * pair.effective_shear_modulus * a


def law_stiffness(law: ContactLaw, pair: ContactPair, constants: Mapping[str, float], effective_radius: float,
                  effective_mass: float, normal_overlap: float) -> tuple[float, float, float]:
    """(kn, kt, damping ratio) of a law's contact at an overlap, for the stability limit:
    the law's own ``stiffness`` or undamped Hertz-Mindlin."""
    if law.stiffness is not None:
        result = _call_law_function(law, "stiffness", law.stiffness, pair, constants, effective_radius,
                                    effective_mass, normal_overlap)
        values = tuple(result) if isinstance(result, (tuple, list)) else ()
        if len(values) != 3 or not all(isinstance(x, numbers.Real) and not isinstance(x, bool)
                                       and math.isfinite(x) and x >= 0.0 for x in values):
            raise LawError(f"law '{law.name}': stiffness() returned {result!r}; it must return "
                           "(kn N/m, kt N/m, damping ratio), three finite numbers >= 0")
        return float(values[0]), float(values[1]), float(values[2])
    return (*hertz_mindlin_stiffness(pair, effective_radius, normal_overlap), 0.0)
