"""The first run on a fresh install compiles on two cores: the kernel here, the engine's
shared functions in a helper process.

A run compiles two kinds of code: its kernel (one per law and scene shape,
``minidem.engine.kernel``) and the engine's shared functions, compiled once per
machine and cached for every later kernel: the neighbour search (``build_pairs``,
``carry_history``, ``reverse_index``, ``mesh_candidates``) and the blow-up guard's
survey and kinetic energy. Neither needs the other to compile (numba compiles each
function on its own and links only what it calls), so when the shared functions are not
in numba's cache yet, :func:`start` has them compiled in a second process (its side:
:mod:`minidem.engine.helper`) while this one
compiles the kernel, and the run loads them from the cache when it needs them
(:func:`Helper.wait` first). What it takes off the critical path: ~1 s of CPU (the
guard's survey and the kinetic energy) in the first run of scenarios/oblique.toml, ~3 s
(also the history carry-over and the transposed index of the Verlet list) in that of
scenarios/settle.toml, whose ``build_pairs`` is already compiled by then: the scene's
check for overlapping spheres at t = 0 needs it before anything else (2-core AMD EPYC).

A scene with more than one sphere needs the neighbour search before anything else, to
check that no spheres overlap at t = 0 (``minidem.scene.scenario``): on a fresh install
that is ~4 s of compiling (``build_pairs``, parallel) that the kernel's own ~6 s would
follow. ``minidem run`` therefore starts the helper earlier, around that check
(:func:`kernel_beside_check`), with the other job: it compiles the scene's kernel (the
scene sent to it pickled, its ``Simulation`` and the types of its ``advance`` built as
the run builds them), while this process compiles the neighbour search for the check and
then the other shared functions itself, and loads the kernel from the cache when the
helper is done (:func:`kernel_helper`); the guard's two functions go to whichever of the
two is free first. First run of scenarios/settle.toml: the two
compilations side by side instead of one after the other. A combination's kernel calls
its ``force_alone`` at walls (``minidem.contact.compose``): this process compiles that
first, before the check, while the helper inlines the kernel's functions, so the
kernel's typing loads it from the cache (:func:`compile_called_force`).

A preset law's force function is compiled on its own and linked into the kernel, so the
helper compiles it first (oblique: the hmd law, ~1.2 s) and the kernel's typing waits
for it (:meth:`Helper.law_compiled`); a combination's is inlined into the kernel's tile
of pair contacts and compiled with it, and its copy for walls (``force_alone``) is the
one the helper compiles first (``minidem.contact.declarations.called_force``). On a fresh
install ``minidem run`` starts the helper before it imports numba and the engine
(:func:`prestart`): the helper imports them while the run does (``helper.serve``), and is
handed its job (either of the two above) once the run has read the
scene; started after those imports, it reached the law ~0.35 s after the kernel's typing
did. The helper imports from the run's ``sys.path`` (:func:`_python`), so that it
compiles, and numba caches, the very files the run loads.

Only the wall time changes (the CPU time grows by the helper's own start, ~0.5 s): the
same functions are compiled for the same argument types and the run loads the same
machine code it would have compiled. A helper that cannot start, fails or compiled
other types costs only the CPU it used: the run then compiles whatever is missing
itself, as before. Nothing is started when the shared
functions are cached already (every run after the first), nor on a one-CPU machine.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import pickle
import select
import subprocess
import sys

from minidem import codecache  # no numba: prestart runs before numba is imported

# numba and numpy are imported where they are used: `minidem run` imports this module
# before them, to start a helper first (prestart)

# the longest a run waits for the helper before compiling what it still needs itself
WAIT_LIMIT_S = 120.0


def _dispatchers(pairs: bool, meshes: bool) -> dict:
    from minidem.engine import blowup, integrate
    from minidem.geometry import neighbours

    found = {"block_sum": integrate.block_sum, "survey": blowup.survey, "kinetic_energy": integrate.kinetic_energy}
    if pairs:
        found.update(build_pairs=neighbours.build_pairs, carry_history=neighbours.carry_history,
                     reverse_index=neighbours.fill_reverse_index)
    if meshes:
        found.update(mesh_candidates=neighbours.mesh_candidates, carry_history=neighbours.carry_history)
    return found


def _cached(dispatcher) -> bool:
    """Whether numba's cache holds machine code of this function (compiled by an earlier
    run, for its current source): an index with entries (the kernel's compile_kernel
    empties a law's index when a new kernel is built against it); True when that cannot be
    told (no helper then)."""
    try:
        return bool(dispatcher._cache._cache_file._load_index())
    except AttributeError:
        return True
    except Exception:  # an unreadable index: numba would compile it anew
        return False


def compile_shared(pairs: bool, meshes: bool) -> None:
    """Compile (into numba's cache) the shared functions a scene with pairs or meshes
    needs, by calling them on two particles with the argument types the engine passes
    (C-contiguous float64 and int64 arrays, a float skin, an int count)."""
    import numpy as np

    from minidem.engine.state import pair_index_type, rows_in_use
    from minidem.geometry import neighbours

    n, h = 2, 3
    position = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    scalar = np.ones(n)
    history, overlap = np.zeros((0, h)), np.zeros(0)
    index = np.zeros(0, dtype=np.int64)
    if pairs:
        # the pair list's partners in the engine's integer type (Simulation.rebuild)
        offsets, found = neighbours.build_pairs(position, scalar, 0.5)
        found = found.astype(pair_index_type(found.shape[0], n), copy=False)
        neighbours.carry_history(np.zeros(n + 1, dtype=np.int64), index.astype(found.dtype), *rows_in_use(history),
                                 overlap, offsets, found, np.zeros((found.shape[0], h)), np.full(found.shape[0], -1.0))
        neighbours.reverse_index(offsets, found, n)
    if meshes:
        triangles = np.array([[[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]])
        offsets, found = neighbours.mesh_candidates(position, scalar, 0.5, triangles)
        neighbours.carry_history(np.zeros(n + 1, dtype=np.int64), index, *rows_in_use(history), overlap, offsets,
                                 found, np.zeros((found.shape[0], h)), np.full(found.shape[0], -1.0))
    compile_guard()


def compile_guard(reverse: bool = False) -> None:
    """Compile (into numba's cache) the kernel's block sum of the energy samples, the
    blow-up guard's survey and the kinetic energy (``reverse``: in the other order, for a
    second process doing the same, see ``minidem.engine.helper.compile_kernel_of_scene``).

    The block sum first: the kernel's typing compiles it (a dispatcher of its own, called
    in a parallel loop), 0.15-0.2 s on the run's critical path unless it is cached by then
    (first run of scenarios/oblique.toml, numba's compile events)."""
    import numpy as np

    from minidem.engine import blowup, integrate

    position, vector, scalar = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), np.zeros((2, 3)), np.ones(2)
    calls = [lambda: integrate.block_sum(0, scalar),
             lambda: blowup.survey(position, vector, vector, vector, vector, scalar, scalar, position, np.zeros(3),
                                   np.zeros(3), np.zeros(3)),
             lambda: integrate.kinetic_energy(scalar, scalar, vector, vector)]
    for call in reversed(calls) if reverse else calls:
        call()


class Helper:
    """A helper process compiling the shared functions (see the module docstring)."""

    def __init__(self, process: subprocess.Popen | None, law_first: bool = False):
        self.process = process
        # it compiles the law's force function first and then says so on its standard output
        self.law_pending = law_first and process is not None
        # the run has told the user what this helper compiles (kernel_beside_check's notice)
        self.announced = False

    def wait_for_law(self) -> None:
        """Until the helper has compiled the law's force function (or ended)."""
        if self.law_pending:
            self.law_pending = False
            try:
                # "law", or nothing at its end; at most WAIT_LIMIT_S
                if select.select([self.process.stdout], [], [], WAIT_LIMIT_S)[0]:
                    self.process.stdout.readline()
            except (OSError, ValueError):
                pass

    @contextlib.contextmanager
    def law_compiled(self, force):
        """Around the kernel's compilation: when the kernel's typing reaches the law's force
        function (``force``, a numba dispatcher, compiled on its own and linked into the
        kernel), first wait for the helper compiling it, so that it is loaded from the cache
        instead of compiled a second time."""
        if not self.law_pending or not hasattr(force, "compile"):
            yield
            return
        plain_compile = force.compile

        def compile_after_helper(sig):
            self.wait_for_law()
            return plain_compile(sig)

        force.compile = compile_after_helper
        try:
            yield
        finally:
            del force.compile

    def stop(self) -> None:
        """End a helper whose work is no longer wanted (the run will not happen)."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self._release()

    def _release(self) -> None:
        if self.process is not None and self.process.stdout is not None:
            self.process.stdout.close()
        self.process, self.law_pending = None, False

    def wait(self) -> None:
        """Until the helper has finished (at most WAIT_LIMIT_S; a helper still running
        then is left to finish on its own, and the run compiles what it needs)."""
        if self.process is None:
            return
        try:
            self.process.wait(timeout=WAIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            pass
        self._release()


def _python(code: str, stdin, stdout) -> subprocess.Popen:
    """A process running ``code`` in this Python, with the same environment, so the same
    caches (MINIDEM_CACHE_DIR, NUMBA_CACHE_DIR).

    It imports from this process's ``sys.path``, not the one ``python -c`` would make: that
    puts the working directory first, and a user who cloned minidem and installed it with
    ``pip install .`` runs ``minidem run`` from the clone, whose ``minidem/`` folder the
    helper would then import instead of the installed package. numba keys its cache on the
    path of each function's source file, so everything the helper compiled from the
    clone's files was cached where the run never looks, and the run compiled it all again
    (the first run of scenarios/oblique.toml: the hmd law and the guard's functions twice,
    ~2 s more CPU in the run's process, 1.5-2 s more wall time)."""
    return subprocess.Popen([sys.executable, "-c", f"import sys; sys.path[:] = {list(sys.path)!r}; {code}"],
                            stdin=stdin, stdout=stdout, stderr=subprocess.DEVNULL)


def _spawn(job: str, arguments: tuple = (), stdin_bytes: bytes | None = None, law_first: bool = False) -> Helper:
    """A helper doing ``job(*arguments)`` (one of ``minidem.engine.helper.JOBS``) with ``stdin_bytes`` on its
    standard input: the helper :func:`prestart` started, if there is one, else a new one."""
    global _PRESTARTED
    process, _PRESTARTED = _PRESTARTED, None
    if process is not None and process.poll() is None:
        # it waits for one line naming its job; what follows is the job's input
        payload = (json.dumps([job, list(arguments)]) + "\n").encode() + (stdin_bytes or b"")
    else:
        try:
            process = _python(f"from minidem.engine import helper; helper.{job}(*{tuple(arguments)!r})",
                              stdin=subprocess.DEVNULL if stdin_bytes is None else subprocess.PIPE,
                              stdout=subprocess.PIPE if law_first else subprocess.DEVNULL)
        except OSError:
            return Helper(None)
        payload = stdin_bytes
    if payload is not None:
        try:
            with process.stdin:
                process.stdin.write(payload)
        except OSError:  # it died already: the run compiles everything itself
            pass
    return Helper(process, law_first)


# a helper `minidem run` started before importing the engine, waiting for its job
_PRESTARTED: subprocess.Popen | None = None


def prestart() -> None:
    """Start the helper of a first run now, before this process imports numba and the
    engine: ``minidem run`` calls this first thing. The helper imports them meanwhile
    (0.3-0.4 s in either process, ``helper.serve``) and then waits for its job
    (:func:`_spawn`: the law and the shared functions, or the scene's kernel), which the
    run decides once it has read the scene; or for none (:func:`dismiss`). Started from the run's process once its
    engine was imported, the helper spent its first 0.4 s importing while the run
    compiled, and the run's kernel then waited ~0.35 s for the law (first run of
    scenarios/oblique.toml, idle 2-core AMD EPYC).

    Only on a fresh install (no kernel was ever written to the cache: every first run of
    a new user), with a second CPU and the JIT on; anything else starts its helper as
    before, when it knows it needs one, so a run on warm caches starts no process."""
    global _PRESTARTED
    if _PRESTARTED is not None or (os.cpu_count() or 1) < 2:
        return
    if os.environ.get("NUMBA_DISABLE_JIT", "0").strip() not in ("", "0"):
        return
    try:
        if any(codecache.kernel_cache_path().glob("minidem_kernel_*.py")):
            return
        _PRESTARTED = _python("from minidem.engine import helper; helper.serve()", stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE)
    except OSError:  # an unreadable cache folder or no process: the run starts its helper itself
        _PRESTARTED = None


def dismiss() -> None:
    """End the prestarted helper without a job (nothing to compile, or no run follows)."""
    global _PRESTARTED
    process, _PRESTARTED = _PRESTARTED, None
    if process is not None:
        Helper(process).stop()
        process.stdin.close()


def _second_cpu() -> bool:
    import numba

    return (os.cpu_count() or 1) >= 2 and not numba.config.DISABLE_JIT


def start(pairs: bool, meshes: bool, law=None) -> Helper:
    """Start a helper when the law's force function (``law``, a ContactLaw) or some shared
    function the scene needs is not cached yet and there is a second CPU to run it on;
    otherwise a Helper that waits for nothing."""
    if not _second_cpu():
        dismiss()
        return Helper(None)
    from minidem.contact import declarations

    # the force the kernel calls at a wall (a preset law's, or a combination's force_alone;
    # a force numba inlines is compiled with the kernel: nothing to compile beside it)
    called = None if law is None else declarations.called_force(law)
    law_first = called is not None and not _cached(called)
    shared = not all(_cached(dispatcher) for dispatcher in _dispatchers(pairs, meshes).values())
    if not law_first and not shared:
        dismiss()
        return Helper(None)
    return _spawn("compile_for_run", (law.name if law_first else None, shared, bool(pairs), bool(meshes)),
                  law_first=law_first)


# scenes whose kernel a helper compiles (id -> (scene, helper)), until their run takes it
_KERNEL_HELPERS: dict[int, tuple] = {}


@contextlib.contextmanager
def kernel_beside_check(scene, notify=None):
    """Around the geometry check of a scene ``minidem run`` is about to run (the
    ``while_checking`` of ``minidem.scene.scenario.build_scene``): when the check must
    compile the neighbour search first (a fresh install), a helper compiles the scene's
    kernel meanwhile. Ended if the check refuses the scene (no run follows).
    ``notify(text)``: told what is compiled if that takes more than SLOW_NOTICE_S."""
    helper = Helper(None)
    if scene.n_particles > 1 and _second_cpu():
        from minidem.geometry import neighbours

        if not _cached(neighbours.build_pairs):
            try:
                sent = pickle.dumps(scene, protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:  # a scene that cannot be sent: the run compiles its kernel itself
                sent = None
            if sent is not None:
                helper = _spawn("compile_kernel_of_scene", stdin_bytes=sent)
    try:
        if helper.process is None:
            yield
        else:
            from minidem.codecache import cache_directory
            from minidem.engine.notices import notice_if_slow

            def told(text):
                helper.announced = True
                notify(text)

            with notice_if_slow(None if notify is None else told,
                                 "compiling the neighbour search for the check of overlapping spheres, "
                                 "and beside it the scene's kernel; both are cached in "
                                 f"{cache_directory()} for later runs"):
                # a combination's force_alone, while the helper is still inlining the
                # kernel (~2 s), so that the kernel's typing loads it from the cache (first
                # run of scenarios/settle.toml: ~0.9 s here, ~1.8 s less on the critical
                # path). Not a preset law's force: the helper's new kernel drops the cached
                # code of the functions its law calls (simulation.compile_kernel), which
                # could undo this process's work
                compile_called_force(scene.law_name, combination_only=True)
                yield
    except BaseException:
        helper.stop()
        raise
    if helper.process is not None:
        _KERNEL_HELPERS[id(scene)] = (scene, helper)


def compile_called_force(law_name: str, combination_only: bool = False) -> None:
    """Compile (into numba's cache) the force function the kernel of law ``law_name`` calls
    at a wall (``declarations.called_force``), for the types the kernel passes it; with
    ``combination_only``, only a combination's ``force_alone``. Whatever fails here the
    kernel compiles, and reports, itself."""
    try:
        from minidem.contact import declarations, laws
        from minidem.engine.law_signature import force_signature

        law = laws.registry().entry(law_name).law
        called = declarations.called_force(law)
        if called is not None and not (combination_only and law.force_alone is None) and not _cached(called):
            called.compile(force_signature(law))
    except Exception:
        pass


@atexit.register
def _stop_unclaimed() -> None:
    """A process leaving before its run (bad input found after the check) ends its helpers."""
    while _KERNEL_HELPERS:
        _KERNEL_HELPERS.popitem()[1][1].stop()
    dismiss()


def kernel_helper(scene) -> Helper | None:
    """The helper compiling this scene's kernel (:func:`kernel_beside_check`), or None;
    the run that asks takes it."""
    found = _KERNEL_HELPERS.pop(id(scene), None)
    if found is None or found[0] is not scene:
        return None
    return found[1]
