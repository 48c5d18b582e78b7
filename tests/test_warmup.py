"""The helper process of a first run (minidem.engine.warmup) compiles the engine's
shared functions for exactly the argument types the engine passes them: after it, the
engine's own calls (neighbour-list build, the guard, the kinetic energy, the kernel's
block sum of energy samples) load them from
numba's cache instead of compiling them again."""

import json
import os
import subprocess
import sys


_ENGINE_CALLS = """
import json
import numpy as np
from minidem.engine import blowup, integrate, kernel, simulation
from minidem.engine.state import State
from minidem.geometry import neighbours
from minidem.scene import scenario
scene = scenario.load_scene("scenarios/bench/settle.toml", ["fill.0.count=20", "output.vtk=false"])
sim = simulation.Simulation(scene, compile=False)
state = State(sim)
sim.rebuild(state)
blowup.Guard(sim).check(state, 0.0, 0.0)
state.kinetic_energy(scene.inertia)
# the kernel's energy sample calls the block sum so (its particle_energy, run_loop.py)
kernel.total_energy(np.zeros(scene.n_particles), np.zeros(1))
print(json.dumps({name: [sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]
                  for name, f in (("build_pairs", neighbours.build_pairs), ("carry_history", neighbours.carry_history),
                                  ("reverse_index", neighbours.fill_reverse_index), ("survey", blowup.survey),
                                  ("kinetic_energy", integrate.kinetic_energy),
                                  ("block_sum", integrate.block_sum))}))
"""


_STARTS_A_HELPER = ("from minidem.engine import warmup; helper = warmup.start(True, False); "
                    "print(helper.process is not None); helper.wait()")


def test_the_engine_loads_what_the_helper_compiled(tmp_path):
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(tmp_path / "minidem"), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    # empty caches (a fresh install): a helper is started; it is the test's helper below,
    # so this one is stopped at once
    fresh = subprocess.run([sys.executable, "-c", _STARTS_A_HELPER.replace("helper.wait()", "helper.process.kill()")],
                           env=env, capture_output=True, text=True)
    assert fresh.stdout.split() == ["True"], fresh.stderr
    helper = subprocess.run([sys.executable, "-c", "from minidem.engine import warmup; "
                             "warmup.compile_shared(True, False)"], env=env, capture_output=True, text=True)
    assert helper.returncode == 0, helper.stderr
    engine = subprocess.run([sys.executable, "-c", _ENGINE_CALLS], env=env, capture_output=True, text=True)
    assert engine.returncode == 0, engine.stderr
    counts = json.loads(engine.stdout.strip().splitlines()[-1])
    # [cache hits, cache misses]: every function loaded, none compiled again
    assert all(hits >= 1 and misses == 0 for hits, misses in counts.values()), counts
    # and once they are cached, no helper is started
    again = subprocess.run([sys.executable, "-c", _STARTS_A_HELPER], env=env, capture_output=True, text=True)
    assert again.stdout.split() == ["False"], again.stderr


_LOAD_WITH_HELPER = """
import json, sys
from minidem.engine import simulation, warmup
from minidem.scene import scenario
overrides = ["fill.0.count=20", "output.vtk=false", "run.end_time=2e-5"]
scene = scenario.load_scene(sys.argv[1], overrides, while_checking=warmup.kernel_beside_check)
started = warmup._KERNEL_HELPERS.get(id(scene)) is not None
sim = simulation.Simulation(scene)
result = sim.run()
stats = lambda f: None if f is None else [sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]
print(json.dumps({"started": started, "steps": result.steps, "advance": stats(sim.kernel.advance),
                  "force_alone": stats(sim.law.force_alone)}))
"""


def test_the_run_loads_the_kernel_the_helper_compiled_beside_the_check(tmp_path):
    """On a fresh install `minidem run` starts a helper compiling the scene's kernel while
    the check of overlapping spheres compiles the neighbour search; the run then loads
    that kernel from the cache (a cache hit, no compilation of its own): the helper built
    the same Simulation and the same argument types as the run. scenarios/settle.toml's
    law is a combination (hm+epsd+sds_twisting): before the check the run's process also
    compiles its force_alone, the law's copy the kernel calls at a wall
    (warmup.compile_called_force), for the helper's kernel to load (only the run's side
    is seen here: compiled once, before the check)."""
    scene = "scenarios/settle.toml"
    found, env = _load_with_helper(tmp_path, scene)
    if (os.cpu_count() or 1) < 2:  # no second CPU: no helper, the run compiles its kernel itself
        assert not found["started"] and found["advance"][1] == 1, found
        return
    assert found["started"], found
    # [cache hits, cache misses] of the kernel's advance in the run's process
    assert found["advance"][0] >= 1 and found["advance"][1] == 0, found
    assert found["force_alone"] == [0, 1], found  # compiled once, here, before the check
    assert found["steps"] == 1, found
    # the next run finds the neighbour search cached: nothing to compile, no helper
    again = subprocess.run([sys.executable, "-c", _LOAD_WITH_HELPER, scene], env=env, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert not json.loads(again.stdout.strip().splitlines()[-1])["started"]


def _load_with_helper(tmp_path, scene: str):
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(tmp_path / "minidem"), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = subprocess.run([sys.executable, "-c", _LOAD_WITH_HELPER, scene], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.strip().splitlines()[-1]), env


_COMBINATION_INLINED = """
import json
from minidem.engine import simulation, warmup
from minidem.scene import scenario
started = []
plain = warmup._spawn
warmup._spawn = lambda job, arguments=(), *rest, **named: started.append([job, list(arguments)]) or plain(
    job, arguments, *rest, **named)
# one sphere on a plane: no neighbour search; a combination of parts (hm + epsd rolling
# resistance), whose generated force function takes the longer argument list
scene = scenario.load_scene("scenarios/oblique.toml", ['contact.law="hm"', 'contact.rolling="epsd"',
                                                        "contact.rolling_friction=0.1"])
sim = simulation.Simulation(scene)
result = sim.run()
stats = lambda f: [sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]
print(json.dumps({"couples": bool(sim.law.couples), "started": started, "separated": bool(result.separated),
                  "force": stats(sim.law.force), "force_alone": stats(sim.law.force_alone)}))
"""


def test_a_combination_force_is_inlined_in_the_kernel_and_its_wall_copy_compiled_beside_it(tmp_path):
    """A combination's generated ``force`` is inlined into the kernel, never compiled on
    its own (minidem.contact.compose: compiled on its own it stayed a call, and the tile
    of pair contacts could not be vector code). A wall contact calls its twin
    ``force_alone`` (ContactLaw.force_alone), which on a fresh install the helper compiles
    first, beside the kernel (warmup.start): the run's process loads it from the cache
    (a hit, no compilation of its own) and the helper was asked for the law by name."""
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(tmp_path / "minidem"), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = subprocess.run([sys.executable, "-c", _COMBINATION_INLINED], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    found = json.loads(run.stdout.strip().splitlines()[-1])
    assert found["couples"] and found["separated"], found
    # [cache hits, cache misses]: neither, the inlined dispatcher was never compiled
    assert found["force"] == [0, 0], found
    if (os.cpu_count() or 1) < 2:  # no second CPU: no helper, the kernel compiled the twin itself
        assert found["force_alone"] == [0, 1] and not found["started"], found
        return
    assert found["force_alone"] == [1, 0], found
    # the law's name is the first argument of compile_for_run
    assert ["compile_for_run", ["hm+epsd", True, False, False]] in found["started"], found


_HELPER_IMPORTS = """
import subprocess
import minidem
from minidem.engine import warmup
# how every helper process is started (warmup._spawn, warmup.prestart)
helper = warmup._python("import minidem; print(minidem.__file__)", stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
print(minidem.__file__)
print(helper.communicate()[0].decode().strip())
"""


def test_the_helper_imports_the_minidem_the_run_imported(tmp_path):
    """`minidem run` started from a folder holding another ``minidem/`` (the clone a user
    installed with ``pip install .``): the helper must import the package the run
    imported, not the folder's. numba caches a function under its source file's path,
    so a helper compiling the folder's copy filled a cache the run never reads, and the
    run compiled the law and the guard again (found timing a fresh clone's first run)."""
    clone = tmp_path / "clone"
    (clone / "minidem").mkdir(parents=True)
    (clone / "minidem" / "__init__.py").write_text("# a stale copy of the package, next to the scene files\n")
    script = tmp_path / "run.py"  # like the console script: the working directory is not on the run's sys.path
    script.write_text(_HELPER_IMPORTS)
    done = subprocess.run([sys.executable, str(script)], cwd=clone, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    run_package, helper_package = done.stdout.split()
    # (the project's own checkout may itself be called a clone: compare with this one's path)
    assert not run_package.startswith(str(clone)), run_package
    assert helper_package == run_package


_PRESTARTED_RUN = """
import json, sys
from minidem.engine import warmup
plain, started = warmup._python, []


def spy(code, **kwargs):  # every helper process, and whether this process had imported numba then
    started.append(["numba" in sys.modules, "helper.serve()" in code])
    return plain(code, **kwargs)


warmup._python = spy
from minidem import cli
code = cli.main(["run", "scenarios/oblique.toml", "--out", sys.argv[1], "--quiet"])
from minidem.contact import laws
force = laws.registry().entry("hmd").law.force
print(json.dumps({"code": code, "started": started,
                  "force": [sum(force.stats.cache_hits.values()), sum(force.stats.cache_misses.values())]}))
"""


def test_a_first_run_starts_its_helper_before_importing_the_engine(tmp_path):
    """`minidem run` on a fresh install starts the helper before it imports numba (its
    imports then overlap the run's own), hands it the law once it has read the scene,
    and the run's kernel loads the law from the cache; with the caches filled no helper
    process is started at all."""
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(tmp_path / "minidem"), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    runs = []
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", _PRESTARTED_RUN, str(tmp_path / "out")], env=env,
                              capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    first, again = runs
    assert first["code"] == 0 and again["code"] == 0, runs
    if (os.cpu_count() or 1) < 2:  # no second CPU: no helper, the kernel compiles the law itself
        assert first["started"] == [] and first["force"][1] == 1, first
    else:
        # one process, the prestarted one, started before numba was imported here
        assert first["started"] == [[False, True]], first
        hits, misses = first["force"]
        assert hits >= 1 and misses == 0, first
    assert again["started"] == [], again
