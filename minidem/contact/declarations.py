"""What a contact-law plugin declares: the law object (:class:`ContactLaw`), its parts
(:class:`ContactPart`) and presets (:class:`Preset`), their typed parameters and history
slots, the material pair a law is prepared for (:class:`ContactPair`), and the argument
lists of the compiled functions.

A contact law is data plus two functions (see ``docs/writing-a-contact-law.md``):

* ``prepare(pair, params) -> dict``: plain Python, run once per material pair before the
  simulation is compiled; turns material properties and law parameters into the named
  constants the force function reads.
* ``force(constants, effective_radius, effective_mass, normal_overlap,
  normal_overlap_increment, normal_velocity, tangential_increment, tangential_velocity,
  history) -> (fn, ftx, fty, ftz)``:
  a ``numba.njit`` function called by the engine's compiled contact loop. It sees one
  contact at a time and never particles, neighbour lists or walls.

Nothing here finds, checks or composes laws: the registry (``minidem.contact.laws``) and
the composition of parts (``minidem.contact.compose``) are built on these declarations,
and plugins import them through ``minidem.contact``.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import inspect
import math
import sys
from typing import Any, Callable, Mapping

from minidem.errors import MinidemError

# the force function's arguments, in the order the engine passes them
FORCE_ARGUMENTS = ("constants", "effective_radius", "effective_mass", "normal_overlap", "normal_overlap_increment",
                   "normal_velocity", "tangential_increment", "tangential_velocity", "history")
# a law with couples (ContactLaw.couples: rolling or twisting resistance) also gets these,
# and returns (fn, ftx, fty, ftz, mx, my, mz), the couple on the first body. As with the
# tangential pair above, the increment (what a spring integrates: the relative spin of
# the drift times dt, exact to second order) and the velocity (what a dashpot reads: at
# the step's end where the couple acts, when the kernel predicts it) are handed apart.
# rolling_inertia (kg m^2) is the pair's equivalent moment of inertia for their relative
# rolling about the contact point, 1/(1/(I_i + m_i r_i^2) + 1/(I_j + m_j r_j^2)) =
# 1.4 (m_i r_i^2)(m_j r_j^2)/(m_i r_i^2 + m_j r_j^2) for spheres, 1.4 m_i r_i^2 at a wall
# (Ai et al. 2011, model C's I_r; LIGGGHTS' rolling epsd). It is not a function of m* and
# R*: 1.4 m* R*^2, which minidem's epsd used until 2026-11-28, is a quarter of it between
# equal spheres
COUPLE_ARGUMENTS = ("rotation_increment", "relative_spin", "normal", "rolling_inertia")


def _is_number(value) -> bool:
    """Whether ``float(value)`` gives a number (None or a sequence does not)."""
    try:
        float(value)
    except (TypeError, ValueError):
        return False
    return True


# compose notes a part's failing prepare() on the exception in flight, as this prefix and
# "KIND part 'NAME'"; laws.prepare_for_pair puts the note into the error it reports
PART_NOTE_PREFIX = "in its "


def located(func) -> str:
    """``name in file, line N`` of a Python function, as error messages name it (the
    law's hooks here, its force and parts' functions in minidem.engine.law_signature)."""
    try:
        _, line = inspect.getsourcelines(func)
        return f"{getattr(func, '__qualname__', func)} in {inspect.getsourcefile(func)}, line {line}"
    except (OSError, TypeError):
        return str(getattr(func, "__qualname__", func))


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

    ``exchange`` is what the slot holds when the same contact is seen from its other
    sphere (i and j exchanged, so the normal points the other way): +1 the same value (a
    magnitude, a count, a flag, a couple about the normal, a scalar along an axis that
    turns with the contact), -1 its negative (a force, a displacement or a couple on the
    first body, a direction in the tangent plane). The engine re-sorts the particles of a
    run in space as they mix (docs/multi-particle.md), which can exchange the two spheres
    of a live contact; it does so only when every slot of the law says what that does
    (LAMMPS' granular sub-models declare the same as ``transfer_history_factor``). None
    (the default): not declared, and the particles of a run with this law keep the order
    they started in. ``tests/test_memory_order.py`` checks the shipped laws' signs: a run
    whose contacts are all seen from their other sphere half-way gives the same forces.
    """

    name: str
    description: str
    vector: bool = False
    exchange: int | None = None

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
    normal_part   optional name of a registered normal part whose constants are this
                  law's first constants (same names) and whose elastic force is the law's:
                  then ``law = NAME`` takes a rolling and a twisting part (``hm+epsd``),
                  the part reading the normal stiffness and contact radius from it
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
    couples: bool = False
    parts: tuple = ()  # a combination's ContactParts (set by minidem.contact.compose); () for a law
    # the normal part whose function, given this law's leading constants, computes the
    # law's elastic normal force, stiffness and contact radius: what lets a law (one part
    # covering normal, damping and tangential) take a rolling or twisting part
    normal_part: str = ""
    # a combination with a part acting beyond touch (set by compose): reach(pair, constants,
    # effective_radius) -> m, the separation (as a positive distance) up to which a contact lives
    reach: Callable | None = None
    # a combination with a part that supplies energy (adhesion, set by compose):
    # supply_bound(pair, constants, effective_radius) -> J, the most kinetic energy one
    # contact can give its bodies (the energy guard and verify add it per contact)
    supply_bound: Callable | None = None
    # a combination (set by compose): the same force compiled on its own, to be called
    # where the kernel evaluates one contact at a time (walls) while ``force``, which numba
    # inlines, is inlined only into the loop over a tile of pair contacts (vector code).
    # The law's code is then compiled twice as two functions, not twice inside the
    # kernel: a first run compiles ``force_alone`` beside the kernel
    # (minidem.engine.warmup). None: the kernel calls ``force`` there too
    force_alone: Any = None

    @property
    def energy_roles(self) -> tuple[str, ...]:
        """What the law may do to a contact's energy: its parts' roles; a law (no parts)
        is passive (store and dissipate)."""
        if not self.parts:
            return ("store", "dissipate")
        return tuple(role for role in ENERGY_ROLES if any(role in p.energy for p in self.parts))

    @property
    def history_size(self) -> int:
        return sum(slot.size for slot in self.history)

    @property
    def force_arguments(self) -> tuple[str, ...]:
        return FORCE_ARGUMENTS + (COUPLE_ARGUMENTS if self.couples else ())

    @property
    def exchange_signs(self) -> tuple[float, ...] | None:
        """Each history float's HistorySlot.exchange, or None when a slot does not declare
        it."""
        if any(slot.exchange is None for slot in self.history):
            return None
        return tuple(float(slot.exchange) for slot in self.history for _ in range(slot.size))

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
                errors.append(f"law '{self.name}' needs parameter '{p.name}' ({p.description}, unit {p.unit or '-'}, "
                              f"bounds {p.bounds_text()}): give it in [contact], or with --set contact.{p.name}=VALUE")
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
        not_numbers = {c: produced[c] for c in self.constants if not _is_number(produced[c])}
        if not_numbers:
            raise LawError(f"law '{self.name}': prepare() ({located(self.prepare)}) must give each constant as a "
                           f"number, got {', '.join(f'{c}={v!r}' for c, v in not_numbers.items())} (a parameter "
                           "whose default is None arrives as None when the scenario does not set it: derive the "
                           "constant's value from the others there)")
        row = np.array([float(produced[c]) for c in self.constants], dtype=np.float64)
        if not np.all(np.isfinite(row)):
            bad = [c for c, v in zip(self.constants, row) if not math.isfinite(v)]
            raise LawError(f"law '{self.name}': prepare() returned non-finite constants {bad}")
        return row, produced

    def is_frictional(self, params: Mapping[str, Any]) -> bool:
        """Whether the law needs the spheres' spin: it can produce a tangential force, or
        it has couples (rolling, twisting)."""
        if self.couples:
            return True
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


# ---------------------------------------------------------------------------------
# Contact models from parts
# ---------------------------------------------------------------------------------
# The kinds of part, in the order the composed force calls them. Each kind's function
# has one signature (PART_ARGUMENTS) and returns what the next kinds read: the normal
# part's elastic force and stiffness are the damping part's input, the total normal force
# is the tangential part's Coulomb limit. Those couplings are the whole of what parts
# share; everything else a part keeps to itself (its constants, its history).
KINDS = ("normal", "damping", "tangential", "rolling", "twisting")
PART_ARGUMENTS = {
    # -> (elastic normal force N, tangent stiffness dFn/d(overlap) N/m, contact radius m)
    "normal": ("constants", "effective_radius", "effective_mass", "normal_overlap", "normal_overlap_increment",
               "history"),
    # -> normal force added by the dashpot, N (positive pushes the pair apart)
    "damping": ("constants", "effective_radius", "effective_mass", "normal_overlap", "normal_velocity",
                "normal_stiffness", "elastic_normal_force"),
    # -> (ftx, fty, ftz) N, the force opposing the tangential motion, in the tangent plane
    "tangential": ("constants", "effective_radius", "effective_mass", "normal_overlap", "normal_overlap_increment",
                   "contact_radius", "elastic_normal_force", "normal_force", "tangential_increment",
                   "tangential_velocity", "history"),
    # -> (mx, my, mz) N m, the couple on the first body (the second gets its opposite);
    # rolling_increment: the rotation of the first body relative to the second over the
    # step, in the tangent plane (rad; a vector of the tangent plane, like a history
    # vector); rolling_velocity: that relative spin at the step's end (rad/s)
    # rolling_inertia: the pair's moment of inertia for relative rolling (COUPLE_ARGUMENTS), kg m^2
    "rolling": ("constants", "effective_radius", "effective_mass", "rolling_inertia", "normal_overlap",
                "contact_radius", "normal_stiffness", "normal_force", "rolling_increment", "rolling_velocity",
                "history"),
    # -> the couple about the normal on the first body, N m (positive along n);
    # twisting_increment: the relative rotation about n over the step (rad)
    "twisting": ("constants", "effective_radius", "effective_mass", "normal_overlap", "contact_radius",
                 "normal_stiffness", "normal_force", "twisting_increment", "twisting_velocity", "history"),
}
# a normal part's optional friction_load(...) -> N: the normal load the Coulomb-type
# limits of the tangential, rolling and twisting parts read instead of the total normal
# force (an adhesive contact's: Thornton & Yin 1991)
FRICTION_LOAD_ARGUMENTS = ("constants", "effective_radius", "elastic_normal_force", "normal_force")
# what a part may do to the energy of the contact (analysis and verify check each kind
# against its own bound): store it and give it back (a spring), dissipate it (a dashpot,
# sliding friction), or supply it (adhesion: at most the work of adhesion per contact)
ENERGY_ROLES = ("store", "dissipate", "supply")


@dataclasses.dataclass(frozen=True)
class ContactPart:
    """One part of a contact model, declared once and registered by a plugin.

    A contact model is a combination of at most one part of each kind (``KINDS``):
    ``[contact] normal = "hertz", damping = "tsuji", tangential = "mindlin"``. minidem
    generates the combination's force function, calling the parts' functions in the order
    of ``KINDS``, and compiles it into the kernel once per combination (the parts are
    inlined; no part a scene does not name is compiled or paid for).

    name          unique lower-case identifier across all parts and laws (``"hertz"``)
    kind          one of KINDS; the signature of ``function`` is PART_ARGUMENTS[kind]
    description   one line for ``minidem laws``
    parameters    settable from ``[contact]`` (flat: a combination's parts must not
                  declare the same parameter name twice, unless the declarations are equal)
    constants     names of the per-material-pair constants ``prepare`` returns, in the
                  order ``function`` indexes them (its own row, from index 0)
    history       per-contact state slots (its own slice of the contact's history, from 0)
    prepare       ``prepare(pair: ContactPair, params: dict, prepared: dict) -> dict``;
                  ``prepared`` maps each kind prepared before this one (KINDS order) to
                  its constants, e.g. a tangential stiffness set as a ratio of kn
    function      numba ``@njit`` function defined at module level
    energy        what the part may do to the contact's energy (ENERGY_ROLES)
    provides      traits the part offers to the others (a normal part: ``"hertzian"``
                  for Fn ~ d^1.5, ``"linear"`` for Fn = kn d)
    requires      traits the combination must provide (Tsuji damping maps restitution
                  for a Hertzian spring only: requires ``("hertzian",)``)
    reach         how far beyond touch the part acts (m, a separation: the overlap passed
                  to the part is negative down to -reach); 0: only while the surfaces
                  overlap. A number, or ``reach(pair, constants, effective_radius) -> m``
                  when it depends on the pair's constants and R* (JKR's pull-off
                  separation). The engine evaluates the function once per material pair at
                  the scene's largest R* (so it must not decrease with R*), widens the
                  neighbour search and the wall checks by it, and keeps the contact and its
                  history while the separation is below it; within that a part ends its own
                  contact at its per-contact separation (it knows R*)
    supply_bound  parts with the energy role "supply": ``supply_bound(pair, constants,
                  effective_radius) -> J``, an upper bound of the kinetic energy one contact
                  can give its bodies (adhesion: the depth of its potential well); the
                  energy guard and ``minidem verify`` allow it per contact
    pull_off      adhesive normal parts, optional: ``pull_off(pair, constants,
                  effective_radius) -> N``, the largest tensile force (JKR 3/2 pi gamma R*);
                  ``minidem verify`` checks a rebound against it
    friction_load normal parts, optional: a numba ``@njit`` function of
                  FRICTION_LOAD_ARGUMENTS returning the load (N) that the tangential,
                  rolling and twisting parts receive as ``normal_force`` for their
                  Coulomb-type limits; None: the total normal force. JKR: Thornton & Yin's
                  (1991) P + 2 Fc, so an adhesive contact has friction at zero or tensile
                  load (as LAMMPS' granular jkr)
    contact_time  normal parts: ``contact_time(pair, constants, effective_radius,
                  effective_mass, normal_speed) -> s``, for the automatic time step
    stiffness     normal parts: ``stiffness(pair, constants, R*, m*, overlap) -> kn``;
                  tangential parts: ``-> kt``; damping parts: ``-> damping ratio`` at
                  that overlap (the time-step stability limit)
    """

    name: str
    kind: str
    description: str
    parameters: tuple[Parameter, ...]
    constants: tuple[str, ...]
    history: tuple[HistorySlot, ...]
    prepare: Callable[[ContactPair, dict, dict], Mapping[str, float]]
    function: Any
    energy: tuple[str, ...] = ("store",)
    provides: tuple[str, ...] = ()
    requires: tuple[str, ...] = ()
    reach: float | Callable = 0.0
    contact_time: Callable | None = None
    stiffness: Callable | None = None
    reference: str = ""
    supply_bound: Callable | None = None
    pull_off: Callable | None = None
    friction_load: Any = None

    @property
    def history_size(self) -> int:
        return sum(slot.size for slot in self.history)

    @property
    def has_reach(self) -> bool:
        return callable(self.reach) or self.reach > 0.0

    def reach_at(self, pair, constants, effective_radius) -> float:
        """The part's reach (m) for a pair's constants and R*."""
        if callable(self.reach):
            return float(self.reach(pair, constants, effective_radius))
        return float(self.reach)


@dataclasses.dataclass(frozen=True)
class Preset:
    """A named combination of parts with parameter defaults: ``[contact] law = NAME``
    runs ``parts`` (kind -> part name) with ``parameters`` as defaults the scenario may
    override. A ``ContactLaw`` is its own preset (one part covering normal, damping and
    tangential: the paper's laws)."""

    name: str
    description: str
    parts: Mapping[str, str]
    parameters: Mapping[str, float] = dataclasses.field(default_factory=dict)
    aliases: tuple[str, ...] = ()
    reference: str = ""


class LawError(MinidemError):
    """A law is unknown, broken, or its declaration or constants are invalid."""

def called_force(law: ContactLaw):
    """The law's force function the kernel calls at a wall contact (``force_alone``, else
    ``force``), or None when numba inlines that one (nothing to compile on its own)."""
    force = law.force_alone if law.force_alone is not None else law.force
    if not hasattr(force, "compile") or getattr(force, "targetoptions", {}).get("inline") == "always":
        return None
    return force


def force_import_name(law: ContactLaw) -> tuple[str, str]:
    """(module, attribute) under which the law's compiled force function can be imported:
    the engine's kernel imports it from there. Usually the function's own name; for
    ``force = numba.njit(_force_impl)`` the name it was bound to."""
    return import_name(law.force, "force")


def import_name(function, field: str) -> tuple[str, str]:
    """(module, attribute) under which a compiled function of a law or part is imported
    by generated code (the kernel, a combination's force)."""
    func = function.py_func
    module = sys.modules.get(func.__module__)
    if module is None:
        raise LawError(f"'{field}': its module '{func.__module__}' is not imported")
    if getattr(module, func.__qualname__, None) is function:
        return func.__module__, func.__qualname__
    for attribute, value in vars(module).items():
        if value is function:
            return func.__module__, attribute
    raise LawError(f"'{field}' ({func.__qualname__}) is not a module-level name of {func.__module__}: "
                   "the engine imports it from there (bind the compiled function to a name at module level)")


def hertz_mindlin_stiffness(pair: ContactPair, effective_radius: float, normal_overlap: float) -> tuple[float, float]:
    """Tangent stiffnesses of Hertz-Mindlin at an overlap: dFn/dd = 2 E* a and the
    no-slip kt = 8 G* a, a = sqrt(R* d) (eqs 15-18)."""
    a = math.sqrt(effective_radius * normal_overlap)
    return 2.0 * pair.effective_modulus * a, 8.0 * pair.effective_shear_modulus * a
