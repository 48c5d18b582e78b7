"""The helper process of a first run (minidem.engine.warmup) compiles the engine's
shared functions for exactly the argument types the engine passes them: after it, the
engine's own calls (neighbour-list build, the guard, the kinetic energy) load them from
numba's cache instead of compiling them again."""

import json
import os
import subprocess
import sys


_ENGINE_CALLS = """
import json
from minidem.engine import blowup, integrate, simulation
from minidem.geometry import neighbours
from minidem.scene import scenario
scene = scenario.load_scene("scenarios/bench/settle.toml", ["fill.0.count=20", "output.vtk=false"])
sim = simulation.Simulation(scene, compile=False)
state = simulation.State(sim)
sim.rebuild(state)
blowup.Guard(sim).check(state, 0.0, 0.0)
state.kinetic_energy(scene.inertia)
print(json.dumps({name: [sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values())]
                  for name, f in (("build_pairs", neighbours.build_pairs), ("carry_history", neighbours.carry_history),
                                  ("reverse_index", neighbours.reverse_index), ("survey", blowup.survey),
                                  ("kinetic_energy", integrate.kinetic_energy))}))
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
