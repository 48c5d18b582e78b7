"""The contact-model API: everything a plugin author imports.

A plugin registers **laws** (a contact model in one piece), **parts** (one piece of a
model: normal, damping, tangential, rolling, twisting, combined in the scenario file)
and **presets** (named combinations of parts) through one hook,
``minidem_register_laws(registry)``; the hook and its documentation are in
``minidem/contact/hookspecs.py``, the declarations in ``minidem/contact/declarations.py``,
the registry in ``minidem/contact/laws.py``, the generated force of a combination in
``minidem/contact/compose.py``, minidem's own laws and parts in
``minidem/contact/builtin_laws/`` (registered through the same entry point as any
plugin's). The guide is docs/writing-a-contact-law.md::

    import numba
    from minidem.contact import ContactPart, Parameter, hookimpl

    @numba.njit
    def dashpot(constants, effective_radius, effective_mass, normal_overlap, normal_velocity,
                normal_stiffness, elastic_normal_force):
        return constants[0] * normal_velocity

    @hookimpl
    def minidem_register_laws(registry):
        registry.add(ContactPart(name="my_dashpot", kind="damping", ...))
"""

from minidem.contact.hookspecs import hookimpl
from minidem.contact.declarations import (
    COUPLE_ARGUMENTS,
    ENERGY_ROLES,
    FORCE_ARGUMENTS,
    KINDS,
    PART_ARGUMENTS,
    ContactLaw,
    ContactPair,
    ContactPart,
    HistorySlot,
    LawError,
    Parameter,
    Preset,
    hertz_contact_time,
)
from minidem.contact.laws import load_registry

__all__ = [
    "COUPLE_ARGUMENTS", "ENERGY_ROLES", "FORCE_ARGUMENTS", "KINDS", "PART_ARGUMENTS", "ContactLaw", "ContactPair",
    "ContactPart", "HistorySlot", "LawError", "Parameter", "Preset", "hertz_contact_time", "hookimpl",
    "load_registry",
]
