"""minidem's built-in contact laws (the paper's models).

This module is reached only through the ``minidem`` entry point in minidem's own
``pyproject.toml``, exactly like a third-party plugin: the engine never imports it.
"""

from minidem.contact.hookspecs import hookimpl


@hookimpl
def minidem_register_laws(registry):
    from minidem.contact.builtin_laws import adhesion, hertz, linear, parts, rolling

    for law in linear.LAWS + hertz.LAWS:
        registry.add(law)
    for part in parts.PARTS + rolling.PARTS + adhesion.PARTS:
        registry.add(part)
