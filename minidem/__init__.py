"""minidem: a small, fast, plugin-based soft-sphere DEM framework.

Data flows one way: scenario file (``scenario``) -> validated scene -> compiled
simulation (``simulation``, ``kernel``, ``contact``, ``integrate``) -> results
(``analysis``) and output writers (``output``). Contact laws are plugins (``laws``,
``hookspecs``).
"""

__version__ = "0.1.0"

from minidem.hookspecs import hookimpl  # noqa: E402,F401  (the decorator plugin authors use)
