"""minidem: a small, fast, plugin-based soft-sphere DEM framework.

Data flows one way, and the subpackages follow it:

    scene/     scenario file (TOML) or dict -> validated Scene
    engine/    Scene -> compiled simulation -> RunResult
    results/   RunResult -> rebound measures, summaries, VTK series
    studies/   built on the above: sweeps, verify, reference solution, benchmarks

below them ``geometry/`` (contact geometry, neighbour search, wall shapes), ``files``
(atomic writes) and ``codecache`` (where generated kernels are kept), beside them the contact-model plugin API (``contact``:
laws, parts, presets, the hook, the built-in laws); ``api`` (the Python API,
docs/python-api.md) and ``cli`` on top. No module imports one of a later stage.
"""

__version__ = "0.1.0"

from typing import TYPE_CHECKING  # noqa: E402

# The Python API (docs/python-api.md) and ``hookimpl`` (the decorator plugin authors use),
# loaded on first use: `import minidem` stays as light as a plugin or a sweep worker needs
# (no numba until something is compiled or run), and the `minidem` command can catch a
# Ctrl-C after ~20 ms of imports, not ~80 (the contact package's import was 60 ms of it).
_API = {
    "hookimpl": "minidem.contact.hookspecs",
    "Scenario": "minidem.api", "Result": "minidem.api", "SweepTable": "minidem.api", "load": "minidem.api",
    "run": "minidem.api", "sweep": "minidem.api", "open_results": "minidem.api",
    "MinidemError": "minidem.errors", "ScenarioError": "minidem.scene.scenario", "LawError": "minidem.contact.laws",
    "RunFailure": "minidem.engine.run_loop", "OutputError": "minidem.files",
}
__all__ = ["__version__", *_API]

if TYPE_CHECKING:  # what type checkers and editors see of the names loaded on first use
    from minidem.contact.hookspecs import hookimpl  # noqa: F401


def __getattr__(name: str):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'minidem' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
