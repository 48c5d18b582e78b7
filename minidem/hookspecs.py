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
    """Register contact laws.

    Call ``registry.add(law)`` once per :class:`minidem.laws.ContactLaw` the plugin
    provides. ``registry.add`` checks the declaration at once (name, parameters,
    history slots, constants, that ``force`` is a numba-compiled function and that
    ``prepare`` is callable); a law that fails the checks is recorded as *broken*
    with the reason and the plugin's name, and every other law stays usable.

    Law names are lower-case identifiers (``[a-z][a-z0-9_]*``) and must be unique
    across all installed plugins; a second law with a taken name is refused and
    reported, the first one is kept.

    Nothing is compiled at registration: a law costs nothing until a scenario uses it.
    """
