"""minidem plugin: the Walton-Braun linear hysteretic contact law.

minidem calls ``minidem_register_laws`` once, when it builds its law registry; nothing
is compiled until a scenario uses the law.
"""

from minidem import hookimpl

__version__ = "0.1.0"


@hookimpl
def minidem_register_laws(registry):
    from minidem_walton_braun.law import WALTON_BRAUN

    registry.add(WALTON_BRAUN)
