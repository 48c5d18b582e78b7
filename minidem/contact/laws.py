"""The registry of contact laws: every law, part and preset of every installed plugin,
found through the ``minidem`` entry points and pluggy, each declaration checked as it is
registered (a broken plugin is reported by name and never takes the others down), and
the combinations of parts composed on demand (``minidem.contact.compose``).

The declarations themselves (:class:`ContactLaw`, :class:`ContactPart`,
:class:`Parameter`, ...) are in ``minidem.contact.declarations``; plugins import them
through ``minidem.contact``.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib.metadata
import inspect
import math
import numbers
import os
import re
import traceback
from typing import Any, Mapping

import pluggy

from minidem.contact import hookspecs
from minidem.contact.declarations import (
    COUPLE_ARGUMENTS,
    ENERGY_ROLES,
    FORCE_ARGUMENTS,
    FRICTION_LOAD_ARGUMENTS,
    KINDS,
    PART_ARGUMENTS,
    PART_NOTE_PREFIX,
    ContactLaw,
    ContactPair,
    ContactPart,
    HistorySlot,
    LawError,
    Parameter,
    Preset,
    hertz_contact_time,
    hertz_mindlin_stiffness,
    import_name,
)

ENTRY_POINT_GROUP = hookspecs.PROJECT_NAME
_NAME_PATTERN = re.compile(r"^[a-z][a-z0-9_]*$")
_ALIAS_PATTERN = re.compile(r"^[a-z][a-z0-9_-]*$")  # matched lower-cased: the paper's names, e.g. "h-mdns"

@dataclasses.dataclass
class BrokenPlugin:
    plugin: str
    law: str | None
    reason: str
    aliases: tuple[str, ...] = ()  # the refused law's other names, so a lookup by one finds this
    what: str = "law"  # what ``law`` names: a law, or a part ("rolling part") or preset refused


@dataclasses.dataclass
class RegisteredLaw:
    law: ContactLaw
    plugin: str  # entry-point name
    distribution: str  # package that provides it (a combination's: its parts' packages joined by " + ")
    version: str  # likewise

    @property
    def packages(self) -> str:
        """Each package with its version, once: "minidem 0.1.0", or for a combination of
        parts from two "minidem 0.1.0 + minidem-kk-parts 1.0.0"."""
        pairs = zip(self.distribution.split(" + "), self.version.split(" + "))
        return " + ".join(dict.fromkeys(f"{d} {v}".strip() for d, v in pairs))


class LawRegistry:
    """All laws from all installed plugins, plus what failed to load and why."""

    def __init__(self):
        self._laws: dict[str, RegisteredLaw] = {}
        self._aliases: dict[str, str] = {}
        # name -> the third-party laws that claimed it (plugin, distribution, law), used or not
        self._claims: dict[str, list[tuple[str, str, str]]] = {}
        self.broken: list[BrokenPlugin] = []
        self._current = ("<direct>", "<direct>", "")
        # parts (by name, every kind in one namespace, shared with laws and presets) and
        # presets, each with the (plugin, distribution, version) that registered it
        self._parts: dict[str, tuple[ContactPart, tuple[str, str, str]]] = {}
        self._presets: dict[str, tuple[Preset, tuple[str, str, str]]] = {}
        self._combinations: dict[str, RegisteredLaw] = {}

    # -- parts and presets -----------------------------------------------------------
    def _parts_and_presets(self) -> dict[str, str]:
        """name -> what holds it, for the messages of a refused name."""
        taken = {}
        for name, (part, (plugin, dist, _)) in self._parts.items():
            taken[name] = f"the {part.kind} part '{name}' of plugin '{plugin}' ({dist})"
        for name, (preset, (plugin, dist, _)) in self._presets.items():
            taken[name] = f"the preset '{name}' of plugin '{plugin}' ({dist})"
            for alias in preset.aliases:
                taken.setdefault(alias.lower(), taken[name])
        return taken

    def _add_part_or_preset(self, item) -> None:
        plugin, dist, version = self._current
        name = getattr(item, "name", None)
        problem = _part_problem(item) if isinstance(item, ContactPart) else _preset_problem(item)
        if problem is None:
            names = [item.name] + ([a.lower() for a in item.aliases] if isinstance(item, Preset) else [])
            for claimed in names:
                owner = self._parts_and_presets().get(claimed)
                if owner is None and self._owner(claimed) is not None:
                    law = self._owner(claimed)
                    owner = f"law '{law.law.name}' of plugin '{law.plugin}' ({law.distribution})"
                if owner is not None:
                    problem = f"name '{claimed}' is already taken by {owner}"
                    break
        if problem is not None:
            kind = getattr(item, "kind", None)
            what = "preset" if isinstance(item, Preset) else (f"{kind} part" if kind in KINDS else "part")
            self.broken.append(BrokenPlugin(plugin, name if isinstance(name, str) else None, problem, what=what))
            return
        if isinstance(item, ContactPart):
            self._parts[item.name] = (item, (plugin, dist, version))
        else:
            self._presets[item.name] = (item, (plugin, dist, version))

    def parts(self, kind: str | None = None) -> list[ContactPart]:
        """The registered parts (of one kind), sorted by name."""
        return [part for name, (part, _) in sorted(self._parts.items()) if kind in (None, part.kind)]

    def part_origin(self, name: str) -> tuple[str, str, str]:
        """(plugin, distribution, version) of a registered part."""
        return self._parts[name][1]

    def preset_of(self, entry: RegisteredLaw) -> Preset | None:
        """The preset an entry of ``entry()`` was made from, None for a law or a bare combination."""
        found = self._presets.get(entry.law.name)
        return found[0] if found is not None else None

    def presets(self) -> list[Preset]:
        return [preset for _, (preset, _) in sorted(self._presets.items())]

    def part(self, kind: str, name: str) -> ContactPart:
        """The part ``name`` of ``kind``; a LawError listing that kind's parts otherwise."""
        key = name.lower() if isinstance(name, str) else name
        found = self._parts.get(key)
        if found is not None and found[0].kind == kind:
            return found[0]
        for b in self.broken:
            if b.law is not None and key == b.law:
                raise LawError(f"{kind} part '{name}' from plugin '{b.plugin}' is broken: {b.reason}")
        available = [p.name for p in self.parts(kind)]
        if found is not None:
            why = f"'{name}' is a {found[0].kind} part, not a {kind} part"
        else:
            close = difflib.get_close_matches(str(key), available, n=1)
            why = f"unknown {kind} part '{name}'" + (f" (did you mean '{close[0]}'?)" if close else "")
        raise LawError(f"{why}; {kind} parts: {', '.join(available) or 'none installed'}, or \"none\" "
                       "(`minidem laws` lists them)")

    def combination(self, choice: Mapping[str, str], defaults: Mapping[str, float] | None = None,
                    name: str | None = None) -> RegisteredLaw:
        """The contact law made of the parts ``choice`` (kind -> part name; "none" or a
        missing kind: no part of that kind), composed and compiled once per process.
        Raises LawError for an unknown kind or part and for a combination the parts'
        declarations refuse (no normal part, a requirement not met)."""
        from minidem.contact import compose

        unknown = sorted(set(choice) - set(KINDS))
        if unknown:
            raise LawError(f"unknown part kind(s) {unknown}; kinds: {', '.join(KINDS)}")
        parts = tuple(self.part(kind, choice[kind]) for kind in KINDS
                      if choice.get(kind) not in (None, "none"))
        compose.check_combination(parts)
        key = "+".join(p.name for p in parts) + f"@{name}{sorted((defaults or {}).items())}"
        if key not in self._combinations:
            origins = [self._parts[p.name][1] for p in parts]
            law = compose.compose(parts, origins, defaults or {}, name)
            plugins = ", ".join(dict.fromkeys(o[0] for o in origins))
            dists = dict.fromkeys((o[1], o[2]) for o in origins)  # in KINDS order, each once
            self._combinations[key] = RegisteredLaw(law, plugins, " + ".join(d for d, _ in dists),
                                                    " + ".join(v for _, v in dists))
        return self._combinations[key]

    def with_parts(self, entry: RegisteredLaw, choice: Mapping[str, str]) -> RegisteredLaw:
        """``entry`` (from ``entry()``) with the parts ``choice`` (kind -> part name) added
        or replaced: a preset's or a combination's parts, or a law's rolling and twisting."""
        preset = self.preset_of(entry)
        if preset is not None:
            return self.combination({**preset.parts, **choice}, preset.parameters)
        own = {part.kind: part.name for part in entry.law.parts}
        if "normal" in own:  # a combination of parts
            return self.combination({**own, **choice})
        if own:  # a law with rolling or twisting parts (law+part...)
            return self.law_with_parts(self.entry(entry.law.name.split("+")[0]), {**own, **choice})
        return self.law_with_parts(entry, choice)

    def law_with_parts(self, entry: RegisteredLaw, choice: Mapping[str, str]) -> RegisteredLaw:
        """A law (one part covering normal, damping and tangential) with a rolling and/or
        a twisting part (``choice``: kind -> part name), composed once per process and
        named ``law+part...`` (``hm+epsd``). Without such a part, the law itself: its
        kernel is the one it always had. LawError when a part of another kind is chosen
        or the law declares no ``normal_part`` to give the couples their normal force."""
        from minidem.contact import compose

        law = entry.law
        couples = {kind: name for kind, name in choice.items() if name not in (None, "none")}
        others = sorted(set(couples) - {"rolling", "twisting"})
        if others:
            raise LawError(
                f"'{law.name}' is a single law (normal, damping and tangential in one part): it takes no "
                f"{' or '.join(others)} part (only a rolling and a twisting part). Compose the law of parts instead (normal = ..., "
                f"damping = ..., tangential = ...; `minidem laws` lists them), or drop "
                f"{', '.join('contact.' + k for k in others)}")
        if not couples:
            return entry
        parts = tuple(self.part(kind, couples[kind]) for kind in KINDS if kind in couples)
        if not law.normal_part or law.normal_part not in self._parts:
            raise LawError(f"law '{law.name}' declares no normal part (ContactLaw.normal_part) to give a rolling or "
                           f"twisting part its normal stiffness and contact radius: it takes no "
                           f"{' or '.join(couples)} part; compose the law of parts instead")
        normal = self._parts[law.normal_part][0]
        compose.check_combination((normal,) + parts)
        key = "+".join([law.name] + [p.name for p in parts])
        if key not in self._combinations:
            origins = [(entry.plugin, entry.distribution, entry.version)] + [self._parts[p.name][1] for p in parts]
            combined = compose.compose_with_law(law, normal, parts)
            dists = dict.fromkeys((o[1], o[2]) for o in origins)
            self._combinations[key] = RegisteredLaw(combined, ", ".join(dict.fromkeys(o[0] for o in origins)),
                                                    " + ".join(d for d, _ in dists), " + ".join(v for _, v in dists))
        return self._combinations[key]

    # -- the object plugins receive in minidem_register_laws(registry) -------------
    def add(self, law: ContactLaw | ContactPart | Preset) -> None:
        """Register a law, a part or a preset; a declaration that fails the checks is
        recorded in ``broken`` with the plugin's name and the reason."""
        if isinstance(law, (ContactPart, Preset)):
            self._add_part_or_preset(law)
            return
        plugin, dist, version = self._current
        problem = _declaration_problem(law)
        name = getattr(law, "name", None)
        if problem is None and name in self._parts_and_presets():
            problem = f"name '{name}' is already taken by {self._parts_and_presets()[name]}"
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
        """A law by name or alias, a preset, or a combination of parts written as their
        names joined by '+' in the order of KINDS (``"hertz+tsuji+mindlin"``)."""
        key = name.lower() if isinstance(name, str) else name
        if key in self._laws:  # a name before an alias
            return self._laws[key]
        if key in self._aliases:
            return self._laws[self._aliases[key]]
        if isinstance(key, str) and "+" in key:
            first, *rest = key.split("+")
            law = self._owner(first)
            if law is not None:  # a law with rolling and twisting parts ("hm+epsd")
                return self.law_with_parts(law, self._choice_of(rest))
        if isinstance(key, str) and ("+" in key or key in self._parts):  # a combination (of one part: "jkr")
            return self.combination(self._choice_of(key.split("+")))
        preset = self._preset(key)
        if preset is not None:
            return self.combination(preset.parts, preset.parameters, preset.name)
        for b in self.broken:
            if b.law is not None and (key == b.law or key in b.aliases):
                raise LawError(f"{b.what} '{name}' from plugin '{b.plugin}' is broken: {b.reason}")
        candidates = self.names() + sorted(self._aliases) + [p.name for p in self.presets()]
        close = difflib.get_close_matches(str(key), candidates, n=1)
        hint = f" Did you mean '{close[0]}'?" if close else ""
        failed = [b for b in self.broken if b.law is None]
        if failed:
            hint += (f" {len(failed)} plugin(s) failed to load, so their laws are unknown: "
                     + "; ".join(f"'{b.plugin}': {b.reason}" for b in failed) + " (see `minidem laws`).")
        presets = f"; presets: {', '.join(p.name for p in self.presets())}" if self._presets else ""
        raise LawError(f"unknown contact law '{name}'. Available: {', '.join(self.names())}{presets}.{hint} "
                       "Or compose one from parts: [contact] normal = ..., damping = ..., tangential = ... "
                       "(`minidem laws`).")

    def _preset(self, key) -> Preset | None:
        for preset in self.presets():
            if key == preset.name or key in (a.lower() for a in preset.aliases):
                return preset
        return None

    def _choice_of(self, names: list[str]) -> dict[str, str]:
        """kind -> part name for part names given without their kinds."""
        choice: dict[str, str] = {}
        for part_name in names:
            found = self._parts.get(part_name)
            if found is None:
                close = difflib.get_close_matches(part_name, sorted(self._parts), n=1)
                raise LawError(f"unknown part '{part_name}'" + (f" (did you mean '{close[0]}'?)" if close else "")
                               + f"; parts: {', '.join(sorted(self._parts)) or 'none installed'}")
            kind = found[0].kind
            if kind in choice:
                raise LawError(f"two {kind} parts, '{choice[kind]}' and '{part_name}': a combination has at "
                               f"most one part of each kind ({', '.join(KINDS)})")
            choice[kind] = part_name
        return choice

    def get(self, name: str) -> ContactLaw:
        return self.entry(name).law

    def mark_broken(self, plugin: str, law: str | None, reason: str) -> None:
        """Record a law that failed later (e.g. at compile time) so it is listed as broken."""
        self.broken.append(BrokenPlugin(plugin, law, reason))


def _declaration_problem(law) -> str | None:
    if not isinstance(law, ContactLaw):
        return f"registry.add() expects a minidem.contact.ContactLaw (or ContactPart, Preset), got {type(law).__name__}"
    if not isinstance(law.name, str) or not _NAME_PATTERN.match(law.name):
        return f"law name {law.name!r} is not a lower-case identifier"
    problem = _shared_declaration_problem(law)
    if problem is not None:
        return problem
    if not isinstance(law.aliases, tuple) or not all(
            isinstance(a, str) and _ALIAS_PATTERN.match(a.lower()) for a in law.aliases):
        return (f"'aliases' must be a tuple of names (letters, digits, '_' and '-', starting with a letter), "
                f"got {law.aliases!r}")
    if law.parts != ():
        return "'parts' is minidem's own (the parts of a combination it composed); leave it empty"
    if law.force_alone is not None:
        return "'force_alone' is minidem's own (a combination's force compiled on its own); leave it None"
    if not isinstance(law.couples, bool):
        return f"'couples' must be True or False, got {law.couples!r}"
    return _compiled_function_problem(law.force, "force", law.force_arguments)


def _parameter_problem(p: Parameter) -> str | None:
    """What is wrong with a parameter's declaration itself (its name, unit, description
    and bounds), before its default is checked: ``minidem laws`` prints every field, and
    a value must be able to pass the bounds."""
    import numpy as np  # here, as below: numba has imported it by the time a plugin registers

    if not isinstance(p.name, str) or not re.fullmatch(r"[A-Za-z0-9_-]+", p.name):
        return (f"parameter name {p.name!r} must be a key a scenario's [contact] table can use bare "
                "(letters, digits, _ and -)")
    for field in ("unit", "description"):
        value = getattr(p, field)
        if not isinstance(value, str) or not value.strip():
            return (f"parameter '{p.name}': {field} must be a non-empty string, got {value!r}"
                    + (' (write "-" for a number without a unit)' if field == "unit" else ""))
    for field in ("low", "high"):
        value = getattr(p, field)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or math.isnan(value):
            return f"parameter '{p.name}': {field} must be a number (or -inf/inf for none), got {value!r}"
    for field in ("low_open", "high_open", "required"):
        if not isinstance(getattr(p, field), (bool, np.bool_)):
            return f"parameter '{p.name}': {field} must be True or False, got {getattr(p, field)!r}"
    if p.low > p.high or (p.low == p.high and (p.low_open or p.high_open)):
        return f"parameter '{p.name}': its bounds {p.bounds_text()} admit no value (low must be below high)"
    return None


def _shared_declaration_problem(item) -> str | None:
    """The checks a law and a part share: description, parameters (unique names, valid
    defaults), history slots, constants, and that the Python hooks are callable."""
    if not isinstance(item.description, str) or not item.description.strip():
        return "description must be a non-empty string"
    for field, kind in (("parameters", Parameter), ("history", HistorySlot)):
        items = getattr(item, field)
        if not isinstance(items, tuple) or not all(isinstance(x, kind) for x in items):
            return f"'{field}' must be a tuple of minidem.contact.{kind.__name__}"
    for slot in item.history:
        if slot.exchange not in (None, 1, -1):
            return f"history slot '{slot.name}': exchange must be +1, -1 or None, got {slot.exchange!r}"
    names = [p.name for p in item.parameters]
    if len(set(names)) != len(names):
        return "parameter names are not unique"
    for p in item.parameters:
        problem = _parameter_problem(p)
        if problem:
            return problem
        if p.default is not None and p.check(p.default):
            return f"default of parameter '{p.name}' {p.check(p.default)}"
    if not isinstance(item.constants, tuple) or not all(isinstance(c, str) for c in item.constants):
        return "'constants' must be a tuple of names"
    if not callable(item.prepare):
        return "'prepare' is not callable"
    for hook in ("contact_time", "stiffness"):
        if getattr(item, hook) is not None and not callable(getattr(item, hook)):
            return f"'{hook}' must be a function or None, got {type(getattr(item, hook)).__name__}"
    return None


def _part_problem(part) -> str | None:
    """Why a part's declaration cannot be used, or None (checked at registration)."""
    if not isinstance(part.name, str) or not _NAME_PATTERN.match(part.name) or part.name == "none":
        return f"part name {part.name!r} is not a lower-case identifier (and not 'none')"
    if part.kind not in KINDS:
        return f"kind {part.kind!r} is not one of {', '.join(KINDS)}"
    problem = _shared_declaration_problem(part)
    if problem is not None:
        return problem
    for field in ("energy", "provides", "requires"):
        value = getattr(part, field)
        if not isinstance(value, tuple) or not all(isinstance(x, str) for x in value):
            return f"'{field}' must be a tuple of strings, got {value!r}"
    if not part.energy or not set(part.energy) <= set(ENERGY_ROLES):
        return f"'energy' must name one or more of {', '.join(ENERGY_ROLES)}, got {part.energy!r}"
    if not callable(part.reach) and (isinstance(part.reach, bool) or not isinstance(part.reach, numbers.Real)
                                     or not 0.0 <= part.reach < math.inf):
        return f"'reach' must be a distance in m, >= 0 and finite, or a function of (pair, constants, R*), got {part.reach!r}"
    if "supply" in part.energy and not callable(part.supply_bound):
        return ("a part with the energy role 'supply' must declare supply_bound(pair, constants, R*) -> J "
                "(the energy guard and verify bound what it may give)")
    if part.kind == "normal" and part.contact_time is None:
        return "a normal part must declare contact_time (the automatic time step needs it)"
    if part.friction_load is not None:
        if part.kind != "normal":
            return "only a normal part may declare friction_load (the load of the other parts' friction limits)"
        problem = _compiled_function_problem(part.friction_load, "friction_load", FRICTION_LOAD_ARGUMENTS)
        if problem is not None:
            return problem
    return _compiled_function_problem(part.function, "function", PART_ARGUMENTS[part.kind])


def _preset_problem(preset) -> str | None:
    if not isinstance(preset.name, str) or not _NAME_PATTERN.match(preset.name):
        return f"preset name {preset.name!r} is not a lower-case identifier"
    if not isinstance(preset.description, str) or not preset.description.strip():
        return "description must be a non-empty string"
    if not isinstance(preset.parts, Mapping) or not set(preset.parts) <= set(KINDS) or "normal" not in preset.parts:
        return f"'parts' must map kinds ({', '.join(KINDS)}) to part names, with a normal part"
    if not isinstance(preset.parameters, Mapping):
        return "'parameters' must be a dict of parameter defaults"
    if not isinstance(preset.aliases, tuple) or not all(
            isinstance(a, str) and _ALIAS_PATTERN.match(a.lower()) for a in preset.aliases):
        return f"'aliases' must be a tuple of names, got {preset.aliases!r}"
    return None


# the arguments of earlier minidems, recognised to say what changed (numba's typing error
# would not say why): a couple law's last ones ("couple") and a rolling part's whole list
_ROLLING_INERTIA = ("the pair's moment of inertia for their relative rolling about the contact point, kg m^2 "
                    "(Ai et al. 2011's I_r, for an EPSD dashpot)")
_EARLIER_ARGUMENTS = (
    # first (to 2026-11-27): one spin for the springs' increments and the dashpots alike
    ("couple", ("relative_spin", "normal", "dt"),
     f"the step's relative rotation for springs (was relative_spin * dt), the relative spin for dashpots, and "
     f"rolling_inertia, {_ROLLING_INERTIA}"),
    # then (2026-11-28): the rotation and the spin apart, no rolling inertia
    ("couple", ("rotation_increment", "relative_spin", "normal"), f"rolling_inertia last, {_ROLLING_INERTIA}"),
    ("rolling", ("constants", "effective_radius", "effective_mass", "normal_overlap", "contact_radius",
                 "normal_stiffness", "normal_force", "rolling_increment", "rolling_velocity", "history"),
     f"rolling_inertia after effective_mass, {_ROLLING_INERTIA}"),
)


def _earlier_arguments_problem(func, field: str, names: tuple[str, ...], arguments: tuple[str, ...]) -> str | None:
    """The message for a function written for the arguments of an earlier minidem."""
    for applies_to, earlier, change in _EARLIER_ARGUMENTS:
        if applies_to == "rolling" and names == earlier and arguments == PART_ARGUMENTS["rolling"]:
            return (f"'{field}' ({func.__qualname__}) takes the arguments of a rolling part of an earlier minidem; "
                    f"the engine now passes ({', '.join(arguments)}): {change}")
        if (applies_to == "couple" and names[-len(earlier):] == earlier
                and arguments[-len(COUPLE_ARGUMENTS):] == COUPLE_ARGUMENTS):
            return (f"'{field}' ({func.__qualname__}) takes ({', '.join(earlier)}) last, the couple arguments of an "
                    f"earlier minidem; the engine now passes ({', '.join(COUPLE_ARGUMENTS)}): {change}")
    return None


def _compiled_function_problem(function, field: str, arguments: tuple[str, ...]) -> str | None:
    """Why ``function`` cannot be imported into the kernel and called with ``arguments``."""
    if not hasattr(function, "py_func"):
        return f"'{field}' is not a numba-compiled function (decorate it with @numba.njit)"
    func = function.py_func
    if "<locals>" in func.__qualname__ or func.__module__ == "__main__":
        return f"'{field}' must be defined at module level in an importable module"
    try:
        import_name(function, field)
    except LawError as exc:
        return str(exc)
    given = [p for p in inspect.signature(func).parameters.values()
             if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    earlier = _earlier_arguments_problem(func, field, tuple(p.name for p in given), arguments)
    if earlier:
        return earlier
    if len(given) != len(arguments):
        hint = ""
        if field == "force" and arguments[:len(FORCE_ARGUMENTS)] == FORCE_ARGUMENTS:
            # the count of the other contract: the couples flag, not the function, is wrong
            other = FORCE_ARGUMENTS if len(arguments) > len(FORCE_ARGUMENTS) else FORCE_ARGUMENTS + COUPLE_ARGUMENTS
            if len(given) == len(other):
                hint = (" (the arguments of a law with couples=True: declare couples=True)" if len(other) >
                        len(FORCE_ARGUMENTS) else " (the arguments of a law without couples: couples=True is "
                        f"declared, which adds {', '.join(COUPLE_ARGUMENTS)})")
        return (f"'{field}' ({func.__qualname__}) takes {len(given)} arguments; the engine calls it with "
                f"{len(arguments)}: ({', '.join(arguments)}){hint}")
    # any names will do, but one of the engine's at another place is a swap (two vectors
    # of the same type, an increment and a velocity, compile either way and run wrong)
    for at, (parameter, expected) in enumerate(zip(given, arguments), start=1):
        if parameter.name != expected and parameter.name in arguments:
            return (f"'{field}' ({func.__qualname__}) takes '{parameter.name}' as argument {at}, where the engine "
                    f"passes '{expected}' ('{parameter.name}' is argument {arguments.index(parameter.name) + 1}); "
                    f"the engine calls it with ({', '.join(arguments)})")
    return None


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
        if not impls:
            registry.broken.append(BrokenPlugin(plugin_name, None, _no_hook(obj)))
        for impl in impls:
            registry._current = (plugin_name, dist, version)
            try:
                impl.function(registry=registry)
            except PLUGIN_FAULTS as exc:
                registry.broken.append(BrokenPlugin(plugin_name, None, f"minidem_register_laws raised {_one_line(exc)}"))
        registry._current = ("<direct>", "<direct>", "")
    return registry


def _no_hook(plugin) -> str:
    """Why a plugin registered nothing: pluggy ignores a hook function without the
    @minidem.hookimpl mark and keeps a marked one of an unknown name aside, so either
    mistake left the plugin's laws silently missing ("unknown contact law")."""
    hook = "minidem_register_laws"
    names = [name for name in dir(plugin) if callable(getattr(plugin, name, None))]
    if hook in names:
        return f"its {hook} is not marked as a hook: decorate it with @minidem.hookimpl"
    close = difflib.get_close_matches(hook, names, n=1, cutoff=0.8)
    if close:
        return f"it defines {close[0]}, not the hook {hook}: rename it"
    return f"it defines no {hook} hook (decorated with @minidem.hookimpl), so it registers no law"


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
                                                        f"{os.sep}minidem{os.sep}contact{os.sep}laws.py",
                                                        f"{os.sep}minidem{os.sep}contact{os.sep}declarations.py"))]
    if isinstance(exc, SyntaxError) and exc.filename:
        where = f" (at {exc.filename}:{exc.lineno})"
    elif own:
        where = f" (at {own[-1].filename}:{own[-1].lineno})"
    else:  # raised by the machinery itself (a module not found, a hook's wrong arguments)
        where = ""
    return " ".join(f"{type(exc).__name__}: {exc}{where}".split())


def prepare_for_pair(law: ContactLaw, distribution: str, pair: ContactPair, params: Mapping[str, Any],
                     materials: str, source: str = ""):
    """``law.prepared_constants(pair, params)``, with a failure of the law's prepare() (or of
    a part's, which compose notes on the exception) turned into a LawError naming the law,
    its package, the materials ("'glass'/'steel'"), the part and where: every caller (the
    engine, verify) reports it alike. ``source``: the scenario, when there is one."""
    try:
        return law.prepared_constants(pair, params)
    except LawError:
        raise
    except PLUGIN_FAULTS as exc:  # a plugin's prepare() is user code (sys.exit too)
        # a ValueError is how prepare() refuses parameters (its message is for the user);
        # anything else is a bug in it: say what and where
        why = str(exc) if type(exc) is ValueError else _one_line(exc)
        part = "".join(f" {note}" for note in getattr(exc, "__notes__", ()) if note.startswith(PART_NOTE_PREFIX))
        where = f"{source}: contact: " if source else ""
        raise LawError(f"{where}law '{law.name}' ({distribution}): prepare() failed for materials {materials}"
                       f"{part}: {why}") from exc


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


# a value no law writes by accident, in the guard slots past a history row
_GUARD_VALUE = 1.2345678e-300


def history_overrun(law: ContactLaw, constants_row, effective_radius: float, effective_mass: float,
                    contact_time: float, speed: float = 5.0) -> tuple[bool | None, str]:
    """Whether the law's force keeps to the history slots it declares: (True, what was
    called), (False, where it wrote past them) or (None, why it was not judged). numba checks no array bounds, and in the engine a write past them
    lands in the next contact's row (or past the array, a corrupted heap) unnoticed.
    The force is called directly (its wall copy, ``force_alone``, where there is one),
    on a history row followed by guard values, along an oblique loading-unloading path
    of ``contact_time`` at ``speed`` whose tangential velocity turns and reverses (every
    branch a tangential law has), and a relative spin that turns too (rolling and
    twisting parts). ``minidem verify``'s first check, and ``minidem run``'s for a law
    or part from a plugin (Simulation.check_history_bounds). A force that fails to
    compile raises numba's error (the caller reports it); one that raises on these
    made-up values is not judged (an overrun itself raises IndexError under
    NUMBA_BOUNDSCHECK=1)."""
    import numpy as np
    from numba.core.errors import NumbaError

    size = law.history_size
    duration = contact_time if math.isfinite(contact_time) and contact_time > 0.0 else 1e-4
    normal_speed, tangential_speed = speed * math.cos(math.radians(30.0)), speed * math.sin(math.radians(30.0))
    peak = normal_speed * duration / math.pi  # the overlap's scale (exact for a linear spring)
    buffer = np.full(size + 16, _GUARD_VALUE)
    buffer[:size] = 0.0
    history, steps, previous = buffer[:size], 200, 0.0
    dt = duration / steps
    force = law.force if law.force_alone is None else law.force_alone
    for step in range(1, steps):
        phase = math.pi * step / steps
        overlap = peak * math.sin(phase)
        velocity = (tangential_speed * math.cos(2.0 * phase), 0.3 * tangential_speed * math.sin(3.0 * phase), 0.0)
        arguments = (constants_row, effective_radius, effective_mass, overlap, overlap - previous,
                     normal_speed * math.cos(phase), (velocity[0] * dt, velocity[1] * dt, velocity[2] * dt),
                     velocity, history)
        if law.couples:
            spin = (40.0 * math.cos(2.0 * phase), 20.0 * math.sin(3.0 * phase), 30.0 * math.cos(phase))
            # the rolling inertia of a sphere at a wall, 1.4 m r^2 (COUPLE_ARGUMENTS)
            arguments += ((spin[0] * dt, spin[1] * dt, spin[2] * dt), spin, (0.0, 0.0, 1.0),
                          1.4 * effective_mass * effective_radius * effective_radius)
        try:
            force(*arguments)
        except NumbaError:
            raise  # does not compile: the caller reports it
        except Exception as exc:  # noqa: BLE001 - raised on these made-up values
            return None, f"not judged: the force raised {type(exc).__name__} at call {step} of {steps - 1}: {exc}"
        previous = overlap
        written = np.flatnonzero(buffer[size:] != _GUARD_VALUE)
        if written.size:
            by_part = ""
            if law.parts:  # each part writes its own slice from its own index 0: say whose slots are where
                own = size - sum(p.history_size for p in law.parts)  # a law given rolling or twisting parts
                slots = ", ".join(([f"the law's own {own}"] if own else [])
                                  + [f"{p.kind} '{p.name}' {p.history_size}" for p in law.parts])
                by_part = f" (by part, in order: {slots}; each part writes its own slice, from its index 0)"
            return False, (f"call {step} of {steps - 1}: the force wrote history[{size + int(written[0])}]; the law "
                           f"declares {size} slot(s){by_part}")
    return True, f"{steps - 1} calls along an oblique load-unload path"
