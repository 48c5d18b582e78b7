"""Hook specifications: the whole contract between minidem and a contact-law plugin.

A plugin is any importable module or object that implements one or more of the hooks
below, and is announced to minidem through an entry point in the ``minidem`` group of
its package metadata::

    # pyproject.toml of the plugin package
    [project.entry-points.minidem]
    my_laws = "my_package.laws"          # a module implementing minidem_register_laws

minidem's own laws are registered through exactly this path (see minidem's
``pyproject.toml``): there is no private back door, so anything a built-in law does, a
third-party law can do too.

Hooks are called with keyword arguments; a hook implementation may accept any subset
of the arguments listed in the specification (pluggy's rule).
"""

import pluggy

PROJECT_NAME = "minidem"

hookspec = pluggy.HookspecMarker(PROJECT_NAME)
#: Decorator for plugin authors: ``@minidem.hookimpl`` marks a function as a hook.
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


@hookspec
def minidem_register_laws(registry):
    """Register contact laws, contact-model parts and presets.

    Call ``registry.add(item)`` once per item the plugin provides, each one of:

    * :class:`minidem.contact.ContactLaw`: a whole contact model in one force function
      ``force(constants, effective_radius, effective_mass, normal_overlap,
      normal_overlap_increment, normal_velocity, tangential_increment,
      tangential_velocity, history) -> (fn, ftx, fty, ftz)``; a scenario names it with
      ``law = "name"``. A law declared with ``couples=True`` (rolling or twisting
      resistance of its own) takes four more arguments, ``rotation_increment`` (the
      first body's rotation relative to the second over the step, rad, a 3-tuple: what a
      spring integrates), ``relative_spin`` (w_i - w_j at the step's end, rad/s: what a
      dashpot reads), ``normal`` (n, from the second body to the first) and
      ``rolling_inertia`` (the pair's moment of inertia for relative rolling about the
      contact point, kg m^2: 1/(1/(1.4 m_i r_i^2) + 1/(1.4 m_j r_j^2)), 1.4 m r^2 at a
      wall; what an EPSD rolling dashpot's critical damping reads), and returns
      ``(fn, ftx, fty, ftz, mx, my, mz)``, the last three the couple on the first body
      (the second gets its opposite; at a wall the sphere is the first body).
    * :class:`minidem.contact.ContactPart`: one part of a model, of one kind
      (``minidem.contact.KINDS``: normal, damping, tangential, rolling, twisting), whose
      function has that kind's signature (``minidem.contact.PART_ARGUMENTS``). A scenario
      combines at most one part of each kind, a normal part always: ``normal = "hertz"``,
      ``damping = "tsuji"``, ``tangential = "mindlin"``, ``rolling = "epsd"``. The parts
      are coupled only through what the engine passes on: damping reads the normal
      part's elastic force and tangent stiffness, the tangential, rolling and twisting
      parts read the total normal force (their Coulomb-type limits) and the contact
      radius. A part declares what it may do to the energy (store, dissipate, supply),
      the traits it provides and requires (Tsuji damping requires a "hertzian" normal
      part), and its parameters, constants and history like a law.
    * :class:`minidem.contact.Preset`: a named combination of parts with parameter
      defaults (``law = "name"``).

    ``registry.add`` checks the declaration at once (names, parameters, history slots,
    constants, that the function is numba-compiled at module level and takes the
    arguments the engine passes, that ``prepare`` is callable); an item that fails the
    checks is recorded as *broken* with the reason and the plugin's name, and every other
    item stays usable.

    Names are lower-case identifiers (``[a-z][a-z0-9_]*``), one namespace for laws,
    parts and presets across all installed plugins: a plugin never replaces one of
    minidem's own, and two plugins claiming a name are both refused.

    Nothing is compiled at registration: a law or a part costs nothing until a scenario
    uses it; a combination is compiled into its kernel with its parts inlined (its pair
    contacts as vector code), and once on its own for the kernel's wall contacts.
    """
