"""The first run on a fresh install compiles on two cores: the kernel here, the engine's
shared functions in a helper process.

A run compiles two kinds of code: its kernel (one per law and scene shape,
``minidem.engine.kernel``) and the engine's shared functions, compiled once per
machine and cached for every later kernel: the neighbour search (``build_pairs``,
``carry_history``, ``reverse_index``, ``mesh_candidates``) and the blow-up guard's
survey and kinetic energy. Neither needs the other to compile (numba compiles each
function on its own and links only what it calls), so when the shared functions are not
in numba's cache yet, :func:`start` compiles them in a second process while this one
compiles the kernel, and the run loads them from the cache when it needs them
(:func:`Helper.wait` first). What it takes off the critical path: ~1 s of CPU (the
guard's survey and the kinetic energy) in the first run of scenarios/oblique.toml, ~3 s
(also the history carry-over and the transposed index of the Verlet list) in that of
scenarios/settle.toml, whose ``build_pairs`` is already compiled by then: the scene's
check for overlapping spheres at t = 0 needs it before anything else (2-core AMD EPYC).

Only the wall time changes (the CPU time grows by the helper's own start, ~0.5 s): the
same functions are compiled for the same argument types and the run loads the same
machine code it would have compiled. A helper that cannot start, fails or compiled
other types costs only the CPU it used: the run then compiles whatever is missing
itself, as before. Nothing is started when the shared
functions are cached already (every run after the first), nor on a one-CPU machine.
"""

from __future__ import annotations

import os
import subprocess
import sys

import numba
import numpy as np

# the longest a run waits for the helper before compiling what it still needs itself
WAIT_LIMIT_S = 120.0


def _dispatchers(pairs: bool, meshes: bool) -> dict:
    from minidem.engine import blowup, integrate
    from minidem.geometry import neighbours

    found = {"survey": blowup.survey, "kinetic_energy": integrate.kinetic_energy}
    if pairs:
        found.update(build_pairs=neighbours.build_pairs, carry_history=neighbours.carry_history,
                     reverse_index=neighbours.reverse_index)
    if meshes:
        found.update(mesh_candidates=neighbours.mesh_candidates, carry_history=neighbours.carry_history)
    return found


def _cached(dispatcher) -> bool:
    """Whether numba's cache has an index for this function (compiled by an earlier run);
    True when that cannot be told (no helper then)."""
    try:
        return os.path.exists(dispatcher._cache._cache_file._index_path)
    except AttributeError:
        return True


def compile_shared(pairs: bool, meshes: bool) -> None:
    """Compile (into numba's cache) the shared functions a scene with pairs or meshes
    needs, by calling them on two particles with the argument types the engine passes
    (C-contiguous float64 and int64 arrays, a float skin, an int count)."""
    from minidem.engine import blowup, integrate
    from minidem.engine.simulation import pair_index_type
    from minidem.geometry import neighbours

    n, h = 2, 3
    position = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    vector, scalar = np.zeros((n, 3)), np.ones(n)
    history, overlap = np.zeros((0, h)), np.zeros(0)
    index = np.zeros(0, dtype=np.int64)
    if pairs:
        # the pair list's partners in the engine's integer type (Simulation.rebuild)
        offsets, found = neighbours.build_pairs(position, scalar, 0.5)
        found = found.astype(pair_index_type(found.shape[0], n), copy=False)
        neighbours.carry_history(np.zeros(n + 1, dtype=np.int64), index.astype(found.dtype), history, overlap,
                                 offsets, found, np.zeros((found.shape[0], h)))
        neighbours.reverse_index(offsets, found, n)
    if meshes:
        triangles = np.array([[[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]])
        offsets, found = neighbours.mesh_candidates(position, scalar, 0.5, triangles)
        neighbours.carry_history(np.zeros(n + 1, dtype=np.int64), index, history, overlap, offsets, found,
                                 np.zeros((found.shape[0], h)))
    blowup.survey(position, vector, vector, vector, vector, scalar, scalar, position, np.zeros(3), np.zeros(3),
                  np.zeros(3))
    integrate.kinetic_energy(scalar, scalar, vector, vector)


class Helper:
    """A helper process compiling the shared functions (see the module docstring)."""

    def __init__(self, process: subprocess.Popen):
        self.process = process

    def wait(self) -> None:
        """Until the helper has finished (at most WAIT_LIMIT_S; a helper still running
        then is left to finish on its own, and the run compiles what it needs)."""
        if self.process is None:
            return
        try:
            self.process.wait(timeout=WAIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            pass
        self.process = None


def start(pairs: bool, meshes: bool) -> Helper:
    """Start a helper when some shared function the scene needs is not cached yet and
    there is a second CPU to run it on; otherwise a Helper that waits for nothing."""
    if (os.cpu_count() or 1) < 2 or numba.config.DISABLE_JIT:
        return Helper(None)
    if all(_cached(dispatcher) for dispatcher in _dispatchers(pairs, meshes).values()):
        return Helper(None)
    code = f"from minidem.engine import warmup; warmup.compile_shared({bool(pairs)}, {bool(meshes)})"
    try:
        # the same environment, so the same caches (MINIDEM_CACHE_DIR, NUMBA_CACHE_DIR)
        process = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError:
        return Helper(None)
    return Helper(process)
