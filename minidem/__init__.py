"""minidem: a small, fast, plugin-based soft-sphere DEM framework.

Data flows one way, and the subpackages follow it:

    scene/     scenario file (TOML) or dict -> validated Scene
    engine/    Scene -> compiled simulation -> RunResult
    results/   RunResult -> rebound measures, summaries, VTK series
    studies/   built on the above: sweeps, verify, reference solution, benchmarks

below them ``geometry/`` (contact geometry, neighbour search, wall shapes) and
``files`` (atomic writes), beside them the contact-model plugin API (``contact``:
laws, parts, presets, the hook, the built-in laws); ``cli`` on top. No module imports one of a later
stage.
"""

__version__ = "0.1.0"

from minidem.contact.hookspecs import hookimpl  # noqa: E402,F401  (the decorator plugin authors use)
