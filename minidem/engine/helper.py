"""The helper process's side of :mod:`minidem.engine.warmup`: what a first run's second
process compiles while the run compiles the rest.

``minidem run`` starts it (``warmup.prestart``, or ``warmup._spawn`` on demand) as ``python
-c "from minidem.engine import helper; helper.serve()"`` or with its job named on the
command line; the run's process never imports this module, and the job's results reach
the run only through numba's cache (and one line, "law", on standard output).
"""

from __future__ import annotations

import json
import pickle
import sys

from minidem.engine import warmup

# the jobs a helper takes (functions of this module), by name
JOBS = ("compile_for_run", "compile_kernel_of_scene")


def serve() -> None:
    """The prestarted helper's side: its job from the first line of standard input
    (``warmup._spawn``); none when the input ends first.

    First it imports what every job needs, while the run reads its scene: numba and the
    engine, and the registry of laws (the installed plugins). Imported after the job
    arrived, as they were until 2026-11-27, they took the first 0.4-0.7 s of the job, on
    the critical path of a scene whose kernel the helper compiles (settle.toml)."""
    try:
        from minidem.contact import laws
        from minidem.engine import simulation  # noqa: F401  (numba, the engine's functions, minidem.compile_speed)

        laws.registry()
    except Exception:  # the job imports them again and the run reports what fails
        pass
    line = sys.stdin.buffer.readline()
    if not line.strip():
        return
    job, arguments = json.loads(line)
    if job in JOBS:
        globals()[job](*arguments)


def compile_for_run(law_name: str | None, shared: bool, pairs: bool, meshes: bool) -> None:
    """The helper's side of :func:`minidem.engine.warmup.start`: the law's force function
    for the types the kernel passes it (then "law" on standard output: the run waits for
    that line before it would compile it itself), then the shared functions."""
    try:
        # the engine's set-up, as in the run: numba's compile-speed repairs and the
        # threading layer's order (minidem.engine.simulation); serve() has imported it,
        # a helper started with this job named has not
        from minidem.engine import simulation  # noqa: F401

        if law_name is not None:
            warmup.compile_called_force(law_name)
    finally:
        if law_name is not None:
            print("law", flush=True)  # compiled or not: the run must not wait any longer
    if shared:
        warmup.compile_shared(pairs, meshes)


def compile_kernel_of_scene() -> None:
    """The helper's side of :func:`minidem.engine.warmup.kernel_beside_check`: the scene
    from standard input, its Simulation as ``minidem run`` builds it, and the kernel's
    ``advance`` compiled for the types of the arguments the run passes (into the caches
    the run loads it from)."""
    from minidem.engine import run_loop, simulation

    scene = pickle.load(sys.stdin.buffer)
    sim = simulation.Simulation(scene)
    loop = run_loop.RunLoop(sim, 1, None, None, sim.loop_threads(), None, None)
    loop.compile_kernel()
    # then the guard's functions, unless the run has compiled them meanwhile (a call loads
    # them from the cache then), in the other order than the run's: whichever process is
    # free first takes them
    warmup.compile_guard(reverse=True)
