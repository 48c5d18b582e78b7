"""A contact law composed of parts: the combination's checks, its generated force
function and the ``ContactLaw`` the engine runs.

The engine knows one kind of law (``minidem.contact.declarations.ContactLaw``: a constants row, a
history row, one compiled force function). A combination of parts becomes exactly
that, so everything downstream (the kernel, its cache, the time step, checkpoints,
``minidem verify``) is the same code for a preset law and for a combination:

* constants: the parts' rows side by side, in the order of ``declarations.KINDS``; each part
  reads its own row from index 0 (a slice);
* history: likewise, each part its own slice (vector slots keep their meaning: the
  engine rotates them by their offset in the whole row);
* force: a small module generated into the kernel cache that imports the parts'
  functions and calls them in the order of KINDS, passing on what the next part reads
  (``declarations.PART_ARGUMENTS``). numba inlines it, with its parts, into the kernel (its IR,
  ``inline="always"``): compiled on its own and linked, as a preset law's force is,
  it stayed a call, which LLVM does not inline at its size, and the kernel's loop over
  a tile of pair contacts could not be vector code (settle scene, hm+epsd+sds_twisting:
  4.1 s a run against 2.6 s inlined, with ``minidem.contact.history._bounds``). Its
  name carries a hash of the parts' code, so a changed part never reuses a stale
  kernel (the kernel's own key follows every function the force calls). The module
  also holds ``force_alone``, the same force compiled on its own
  (``ContactLaw.force_alone``), which the kernel calls at a wall contact: inlined
  there too, the combination's code was typed and lowered twice inside the kernel
  (1.7 s of the ~11 s of settle's kernel), and a first run now compiles it beside the
  kernel (``minidem.engine.warmup``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import os
import sys
from typing import Mapping

import numba

from minidem.contact import declarations

_GENERATOR_VERSION = "6"  # bump when the generated source below changes shape


def check_combination(parts: tuple[declarations.ContactPart, ...]) -> None:
    """Refuse a combination the parts' declarations do not allow (LawError, one message
    naming every problem): no normal part, a trait a part requires that no other part
    provides, one parameter name declared differently by two parts."""
    problems = []
    kinds = [p.kind for p in parts]
    if "normal" not in kinds:
        named = ", ".join(f"{p.kind} '{p.name}'" for p in parts) or "no parts"
        problems.append(f"a combination needs a normal part (given {named}): the damping and tangential parts "
                        "act on the normal force")
    provided = {trait: part.name for part in parts for trait in part.provides}
    for part in parts:
        for trait in part.requires:
            if trait not in provided:
                normal = next((p for p in parts if p.kind == "normal"), None)
                offers = f" ('{normal.name}' provides {', '.join(normal.provides) or 'nothing'})" if normal else ""
                problems.append(f"{part.kind} part '{part.name}' requires a '{trait}' part{offers}")
    declared: dict[str, tuple[declarations.Parameter, str]] = {}
    for part in parts:
        for parameter in part.parameters:
            other = declared.get(parameter.name)
            if other is not None and other[0] != parameter:
                problems.append(f"parameter '{parameter.name}' is declared by both '{other[1]}' and '{part.name}' "
                                "with different meanings")
            declared.setdefault(parameter.name, (parameter, part.name))
    if problems:
        raise declarations.LawError("invalid combination " + "+".join(p.name for p in parts) + ": " + "; ".join(problems))


def compose(parts: tuple[declarations.ContactPart, ...], origins, defaults: Mapping[str, float],
            preset: str | None = None) -> declarations.ContactLaw:
    """The ContactLaw of a checked combination (see the module docstring). ``defaults``
    replace the parts' parameter defaults (a preset's values)."""
    name = preset or "+".join(p.name for p in parts)
    parameters = [dataclasses.replace(p, default=float(defaults[p.name]), required=False) if p.name in defaults else p
                  for p in _merged_parameters(parts)]
    unknown = sorted(set(defaults) - {p.name for p in parameters})
    if unknown:
        raise declarations.LawError(f"preset '{name}': parameters {unknown} belong to none of its parts")
    by_kind = {p.kind: p for p in parts}
    normal, damping, tangential = by_kind["normal"], by_kind.get("damping"), by_kind.get("tangential")

    def own(named: Mapping[str, float], part: declarations.ContactPart) -> dict[str, float]:
        return {c: named[f"{part.kind}.{c}"] for c in part.constants}

    def prepare(pair, params):
        prepared: dict[str, dict] = {}
        out = {}
        _prepare_parts(parts, pair, params, prepared, out)
        return out

    def contact_time(pair, named, effective_radius, effective_mass, normal_speed):
        return normal.contact_time(pair, own(named, normal), effective_radius, effective_mass, normal_speed)

    def stiffness(pair, named, effective_radius, effective_mass, normal_overlap):
        def of(part, default):
            if part is None or part.stiffness is None:
                return default
            return float(part.stiffness(pair, own(named, part), effective_radius, effective_mass, normal_overlap))

        kn_default, kt_default = declarations.hertz_mindlin_stiffness(pair, effective_radius, normal_overlap)
        return (of(normal, kn_default), of(tangential, kt_default if tangential else 0.0), of(damping, 0.0))

    # beyond touch: the combination lives as far as its farthest-reaching part
    reaching = [p for p in parts if p.has_reach]
    reach = None
    if reaching:
        def reach(pair, named, effective_radius):
            return max(p.reach_at(pair, own(named, p), effective_radius) for p in reaching)
    # energy supplied (adhesion): the parts' bounds add up
    supplying = [p for p in parts if "supply" in p.energy]
    supply_bound = None
    if supplying:
        def supply_bound(pair, named, effective_radius):
            return sum(float(p.supply_bound(pair, own(named, p), effective_radius)) for p in supplying)

    return _combined_law(
        None, parts,
        name=name,
        description=" + ".join(f"{p.kind} {p.name}" for p in parts),
        parameters=tuple(parameters),
        prepare=prepare,
        **_generated_force(parts),
        contact_time=contact_time,
        frictional=tangential is not None,
        stiffness=stiffness,
        couples="rolling" in by_kind or "twisting" in by_kind,
        reach=reach,
        supply_bound=supply_bound,
    )


def _merged_parameters(parts, first: tuple[declarations.Parameter, ...] = (), first_owner: str = "") -> list[declarations.Parameter]:
    """``first`` (a law's parameters), then each part's, each name once; a name declared
    with different meanings by two of them is refused (LawError naming both)."""
    merged, owners = list(first), {p.name: (p, first_owner) for p in first}
    for part in parts:
        for parameter in part.parameters:
            other = owners.get(parameter.name)
            if other is None:
                owners[parameter.name] = (parameter, part.name)
                merged.append(parameter)
            elif other[0] != parameter:
                raise declarations.LawError(f"parameter '{parameter.name}' is declared by both '{other[1]}' and "
                                    f"'{part.name}' with different meanings")
    return merged


def _combined_law(law: declarations.ContactLaw | None, parts: tuple[declarations.ContactPart, ...], **fields) -> declarations.ContactLaw:
    """The ContactLaw of ``parts`` after ``law`` (the law they extend, or None): the law's
    constants and history slots, then each part's named ``kind.name``; the references of
    both, each once; the other fields as given."""
    constants = (law.constants if law else ()) + tuple(f"{p.kind}.{c}" for p in parts for c in p.constants)
    history = (law.history if law else ()) + tuple(
        dataclasses.replace(slot, name=f"{p.kind}.{slot.name}") for p in parts for slot in p.history)
    references = ([law.reference] if law else []) + [p.reference for p in parts]
    return declarations.ContactLaw(constants=constants, history=history, parts=tuple(parts),
                           reference="; ".join(dict.fromkeys(r for r in references if r)), **fields)


def _prepare_parts(parts, pair, params, prepared: dict, out: dict) -> None:
    """Run each part's prepare in order (each sees what the kinds before it prepared, in
    ``prepared``) and put its constants into ``out`` as ``kind.name``."""
    for part in parts:
        values = {p.name: params.get(p.name) for p in part.parameters}
        try:
            produced = part.prepare(pair, values, dict(prepared))
        except (Exception, SystemExit) as exc:  # laws.prepare_for_pair names the part from this note
            exc.add_note(f"{declarations.PART_NOTE_PREFIX}{part.kind} part '{part.name}'")
            raise
        if not isinstance(produced, Mapping):
            raise declarations.LawError(f"part '{part.name}': prepare() must return a dict of constants, "
                                f"got {type(produced).__name__}")
        missing = [c for c in part.constants if c not in produced]
        if missing:
            raise declarations.LawError(f"part '{part.name}': prepare() did not return constants {missing}")
        not_numbers = {c: produced[c] for c in part.constants if not declarations._is_number(produced[c])}
        if not_numbers:
            raise declarations.LawError(
                f"{part.kind} part '{part.name}': prepare() ({declarations.located(part.prepare)}) must give each "
                f"constant as a number, got {', '.join(f'{c}={v!r}' for c, v in not_numbers.items())}")
        prepared[part.kind] = {c: float(produced[c]) for c in part.constants}
        out.update({f"{part.kind}.{c}": v for c, v in prepared[part.kind].items()})


def _generated_force(parts: tuple[declarations.ContactPart, ...]) -> dict:
    """Write (once) and import the module holding the combination's force function: its
    ContactLaw fields ``force`` and ``force_alone``."""
    lines, imports = [], []
    call = _part_calls(parts, imports, 0, 0)
    normal = next(p for p in parts if p.kind == "normal")
    functions = [p.function for p in parts]
    lines.append("    elastic, stiffness, contact_radius = normal_part(\n"
                 f"        {call['normal'][0]}, effective_radius, effective_mass, normal_overlap, "
                 f"normal_overlap_increment, {call['normal'][1]})")
    if "damping" in call:
        dashpot = (f"damping_part({call['damping'][0]}, effective_radius, effective_mass, normal_overlap, "
                   "normal_velocity, stiffness, elastic)")
        if "supply" in normal.energy:
            # an adhesive normal part (energy role 'supply', as verify tells adhesion)
            # pulls: its tension, and the dashpot's, is kept
            lines.append(f"    normal_force = elastic + {dashpot}")
        else:
            # a non-adhesive contact never pulls: the same rule as the paper's laws
            # (common.damped_normal_force), for which the damping parts map e
            # (its code joins the module's hash: a changed rule never reuses a stale kernel)
            from minidem.contact.builtin_laws.common import damped_normal_force

            imports.append("from minidem.contact.builtin_laws.common import damped_normal_force")
            lines.append(f"    normal_force = damped_normal_force(elastic, {dashpot})")
            functions.append(damped_normal_force)
    else:
        lines.append("    normal_force = elastic")
    # the load of the friction limits: the total normal force, or the normal part's own
    # (an adhesive contact's, declarations.ContactPart.friction_load)
    load = "normal_force"
    if normal.friction_load is not None:
        module, attribute = declarations.import_name(normal.friction_load, "friction_load")
        imports.append(f"from {module} import {attribute} as normal_friction_load")
        lines.append(f"    friction_load = normal_friction_load({call['normal'][0]}, effective_radius, elastic, "
                     "normal_force)")
        functions.append(normal.friction_load)
        load = "friction_load"
    if "tangential" in call:
        lines.append(f"    ftx, fty, ftz = tangential_part(\n        {call['tangential'][0]}, effective_radius, "
                     f"effective_mass, normal_overlap, normal_overlap_increment, contact_radius, elastic, {load},\n"
                     f"        tangential_increment, tangential_velocity, {call['tangential'][1]})")
    else:
        lines.append("    ftx, fty, ftz = 0.0, 0.0, 0.0")
    couples = "rolling" in call or "twisting" in call
    _couple_lines(call, lines, imports, load)
    lines.append("    return normal_force, ftx, fty, ftz" + (", mx, my, mz" if couples else ""))
    return _load_force([p.name for p in parts], functions, imports, lines, couples)


def _part_calls(parts, imports: list, constant_at: int, history_at: int) -> dict:
    """kind -> (its constants slice, its history slice) as generated source, the parts laid
    side by side from the given offsets; appends each part's import to ``imports``."""
    call = {}
    for part in parts:
        module, attribute = declarations.import_name(part.function, "function")
        imports.append(f"from {module} import {attribute} as {part.kind}_part")
        c_end, h_end = constant_at + len(part.constants), history_at + part.history_size
        call[part.kind] = (f"constants[{constant_at}:{c_end}]", f"history[{history_at}:{h_end}]")
        constant_at, history_at = c_end, h_end
    return call


def _couple_lines(call: dict, lines: list, imports: list, load: str = "normal_force") -> None:
    """The generated lines of the rolling and twisting parts named in ``call`` (kind ->
    (constants slice, history slice)); they read normal, stiffness, contact_radius and
    the load of their limits (the variable named ``load``) from the lines before them."""
    if "rolling" in call or "twisting" in call:
        imports.append("from minidem.contact.compose import split_spin")
        lines.append("    rolling_increment, twisting_increment = split_spin(rotation_increment, normal)")
        lines.append("    rolling_velocity, twisting_velocity = split_spin(relative_spin, normal)")
        lines.append("    mx, my, mz = 0.0, 0.0, 0.0")
    if "rolling" in call:
        lines.append(f"    mx, my, mz = rolling_part(\n        {call['rolling'][0]}, effective_radius, effective_mass, "
                     f"rolling_inertia, normal_overlap, contact_radius, stiffness, {load},\n        rolling_increment, "
                     f"rolling_velocity, {call['rolling'][1]})")
    if "twisting" in call:
        lines.append(f"    twist = twisting_part(\n        {call['twisting'][0]}, effective_radius, effective_mass, "
                     f"normal_overlap, contact_radius, stiffness, {load}, twisting_increment,\n"
                     f"        twisting_velocity, {call['twisting'][1]})")
        lines.append("    mx, my, mz = mx + twist * normal[0], my + twist * normal[1], mz + twist * normal[2]")


def _load_force(names: list[str], functions: list, imports: list, lines: list, couples: bool):
    """Write (once) and import the generated force module of a combination: {"force": the
    force numba inlines, "force_alone": the same compiled on its own}."""
    from minidem.codecache import cache_directory, force_dependencies

    combination = "+".join(names)
    arguments = declarations.FORCE_ARGUMENTS + (declarations.COUPLE_ARGUMENTS if couples else ())
    source = (f'"""Generated by minidem.contact.compose: the force of the combination {combination}. Do not edit."""\n\n'
              "import numba\n\n" + "\n".join(imports) + "\n\n\n"
              "@numba.njit(cache=True, inline=\"always\")\n"
              f"def force({', '.join(arguments)}):\n" + "\n".join(lines) + "\n\n\n"
              "# the same force compiled on its own: the kernel calls it at wall contacts\n"
              "# (ContactLaw.force_alone); the kernel's error model, so the same bits as inlined\n"
              "@numba.njit(cache=True, error_model=\"numpy\")\n"
              f"def force_alone({', '.join(arguments)}):\n"
              f"    return force({', '.join(arguments)})\n")
    # the module's name follows its source and the code of every function the parts call
    digest = hashlib.sha256(source.encode())
    for function in functions:
        digest.update(force_dependencies(function)[0].encode())
    digest.update(_GENERATOR_VERSION.encode())
    module_name = f"minidem_combination_{'_'.join(names)}_{digest.hexdigest()[:16]}"
    if module_name not in sys.modules:
        path = cache_directory() / f"{module_name}.py"
        if not path.exists():  # written once, never touched again (numba keys its cache on the stamp)
            tmp = path.with_suffix(f".tmp{os.getpid()}")
            tmp.write_text(source)
            os.replace(tmp, path)
        spec = importlib.util.spec_from_file_location(module_name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[module_name] = module
        spec.loader.exec_module(module)
    module = sys.modules[module_name]
    return {"force": module.force, "force_alone": module.force_alone}



def compose_with_law(law: declarations.ContactLaw, normal: declarations.ContactPart,
                     parts: tuple[declarations.ContactPart, ...]) -> declarations.ContactLaw:
    """A law (one part covering normal, damping and tangential: the paper's laws) with
    rolling and/or twisting ``parts``. The law's force runs unchanged on its own
    constants and history; ``normal`` (the law's ``normal_part``, reading the law's
    leading constants) gives the couples the tangent stiffness and contact radius; the
    couples get the law's total normal force. Constants and history: the law's, then the
    parts' (``kind.name``)."""
    leading = law.constants[:len(normal.constants)]
    if leading != normal.constants or normal.history:
        raise declarations.LawError(f"law '{law.name}': its normal_part '{normal.name}' must have no history and constants "
                            f"{list(normal.constants)} that are the law's first ones (the law's: {list(leading)})")
    parameters = _merged_parameters(parts, law.parameters, law.name)

    def prepare(pair, params):
        out = dict(law.prepare(pair, {p.name: params.get(p.name) for p in law.parameters}))
        _prepare_parts(parts, pair, params, {"normal": {c: float(out[c]) for c in normal.constants}}, out)
        return out

    def own(named):
        return {c: named[c] for c in law.constants}

    contact_time = None if law.contact_time is None else (
        lambda pair, named, radius, mass, speed: law.contact_time(pair, own(named), radius, mass, speed))
    stiffness = None if law.stiffness is None else (
        lambda pair, named, radius, mass, overlap: law.stiffness(pair, own(named), radius, mass, overlap))

    module, attribute = declarations.force_import_name(law)
    imports = [f"from {module} import {attribute} as law_force"]
    normal_module, normal_attribute = declarations.import_name(normal.function, "function")
    imports.append(f"from {normal_module} import {normal_attribute} as normal_part")
    call = _part_calls(parts, imports, len(law.constants), law.history_size)
    lines = [f"    normal_force, ftx, fty, ftz = law_force(\n        constants[0:{len(law.constants)}], "
             "effective_radius, effective_mass, normal_overlap, normal_overlap_increment, normal_velocity,\n"
             f"        tangential_increment, tangential_velocity, history[0:{law.history_size}])",
             f"    elastic, stiffness, contact_radius = normal_part(\n        constants[0:{len(normal.constants)}], "
             "effective_radius, effective_mass, normal_overlap, normal_overlap_increment, "
             f"history[{law.history_size}:{law.history_size}])"]
    _couple_lines(call, lines, imports)
    lines.append("    return normal_force, ftx, fty, ftz, mx, my, mz")
    forces = _load_force([law.name, *(p.name for p in parts)], [law.force, normal.function]
                         + [p.function for p in parts], imports, lines, True)
    return _combined_law(
        law, parts,
        name="+".join([law.name] + [p.name for p in parts]),
        description=f"{law.name} ({law.description}) + " + " + ".join(f"{p.kind} {p.name}" for p in parts),
        parameters=tuple(parameters),
        prepare=prepare,
        **forces,
        contact_time=contact_time,
        frictional=law.frictional,
        stiffness=stiffness,
        couples=True,
    )


@numba.njit(cache=True, inline="always")
def split_spin(relative_spin, normal):
    """The spin of the first body relative to the second split into its rolling part (in
    the tangent plane, a 3-tuple, rad/s) and its twisting part (along n, rad/s); the
    same split of a rotation over the step (rad)."""
    wx, wy, wz = relative_spin
    nx, ny, nz = normal
    along = wx * nx + wy * ny + wz * nz
    return (wx - along * nx, wy - along * ny, wz - along * nz), along
