"""The code minidem generates and compiles, and where it is kept: the kernels specialised
for a law and a scene shape (minidem.engine.simulation.compile_kernel) and the modules of
combinations of parts (minidem.contact.compose) are written to one cache folder, under
names keyed by a hash of the code they run (:func:`force_dependencies`). Below both the
contact layer and the engine, which each write there."""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
import types
from pathlib import Path


def kernel_cache_path() -> Path:
    """Where specialised kernels are written (MINIDEM_CACHE_DIR/kernels; the folder may not
    exist yet)."""
    root = os.environ.get("MINIDEM_CACHE_DIR") or Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "minidem"
    return Path(root) / "kernels"


def cache_directory() -> Path:
    """Where specialised kernels and numba's cache of them live (MINIDEM_CACHE_DIR), made."""
    path = kernel_cache_path()
    path.mkdir(parents=True, exist_ok=True)
    return path


# Modules whose code a law may call but which cannot change under a minidem install
# without numba's or minidem's version changing (both are in the kernel key).
_STABLE_PACKAGES = {"numpy", "numba", "math", "cmath", "builtins", "llvmlite"}


@functools.lru_cache(maxsize=None)
def force_dependencies(force) -> tuple[str, tuple]:
    """Hash of the source of the law's force function and of everything it calls, followed
    transitively through jitted and plain functions, closures and modules of any package
    (a helper in a subpackage, minidem.contact.builtin_laws.common, another distribution), with
    the module-level constants they read (numba freezes those into the machine code);
    and the numba dispatchers met on the way. Read once per process per law, like the
    engine's sources (minidem.engine.simulation._engine_hash).

    Why: numba's own cache only notices a change in the file that defines a function, not
    in a function it calls, so an edited helper would otherwise leave a stale kernel."""
    import numba  # here: minidem run reads the cache path before it imports numba (warmup.prestart)

    digest = hashlib.sha256()
    seen: set = set()
    dispatchers: list = []

    def names_of(code) -> set:
        names = set(code.co_names) | set(code.co_freevars)
        for const in code.co_consts:
            if hasattr(const, "co_names"):
                names |= names_of(const)
        return names

    def visit_function(func) -> None:
        code = func.__code__
        if code in seen:
            return
        seen.add(code)
        try:
            text = inspect.getsource(func)
        except (OSError, TypeError):  # no source file (built at run time): its byte code
            text = code.co_code.hex() + repr(code.co_consts)
        digest.update(f"{func.__module__}.{func.__qualname__}\n{text}\n".encode())
        names = names_of(code)
        scope = dict(func.__globals__)
        for cell_name, cell in zip(code.co_freevars, func.__closure__ or ()):
            try:
                scope[cell_name] = cell.cell_contents
            except ValueError:  # an empty cell
                pass
        for name in sorted(names):
            if name in scope:
                visit_value(f"{func.__module__}.{name}", scope[name], names)

    def visit_value(label: str, value, names: set) -> None:
        if isinstance(value, numba.core.registry.CPUDispatcher):
            if value not in dispatchers:
                dispatchers.append(value)
            visit_function(value.py_func)
        elif isinstance(value, types.FunctionType):
            visit_function(value)
        elif isinstance(value, types.ModuleType):
            if value.__name__.split(".")[0] in _STABLE_PACKAGES or id(value) in seen:
                return
            seen.add(id(value))
            for name in sorted(names):  # attribute loads share co_names with globals
                if hasattr(value, name):
                    visit_value(f"{value.__name__}.{name}", getattr(value, name), names)
        elif isinstance(value, (bool, int, float, complex, str, bytes, tuple)):
            digest.update(f"{label}={value!r}\n".encode())

    visit_value(f"{force.py_func.__module__}.{force.py_func.__qualname__}", force, set())
    return digest.hexdigest(), tuple(dispatchers)
