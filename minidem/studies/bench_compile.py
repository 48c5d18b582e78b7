"""``minidem bench --only compile``: the compile time of each shipped contact model.

Every law, preset and combination of parts is compiled into its own kernel (issue 14:
"compiled once per combination, inlined"); this measures what that costs a user the
first time a scene names it. Each combination runs in a fresh process on a copy of a
cache already holding the engine's shared compiled functions (filled by one run of
``hm``), so the cold time is the combination's own kernel (and its parts' functions);
the warm time is a second ``Simulation(scene).run()`` in the same process (the kernel
loaded). Scene: 20 spheres falling onto a floor plane, the multi-particle (parallel)
kernel variant, 10 steps.

It also measures what a new user waits for (issue 15, target 5): the first
``minidem run`` of every shipped scene (``scenarios/*.toml``) as a whole process, with
empty caches (``MINIDEM_CACHE_DIR`` and ``NUMBA_CACHE_DIR`` pointing to new, empty
folders), then a second run on the caches the first one filled. Wall and CPU time
(user + system, of the child process) are both reported, medians of the rounds: on a
machine shared with other jobs the wall time is inflated more than the CPU time.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from minidem.studies import checkout

# the shipped scenes a newcomer runs first (README, docs/scenarios.md)
SCENES = checkout.ROOT / "scenarios"

# (name shown, the [contact] table): the paper's laws, the parts forms of two of them,
# every shipped rolling and twisting part with hertz + tsuji + mindlin, and the
# combinations the shipped scenes run
LINEAR = {"normal_stiffness": 100.0}  # N/m: stable at dt = 1e-5 s with 1 mm beads
COMBINATIONS = (
    [(law, {"law": law, "friction": 0.3, **(LINEAR if law == "ls" else {})})
     for law in ("hmd", "hm", "lth", "hmdns_integral", "hmdns_integral_reset", "ls")]
    + [("hertz+tsuji+mindlin", {"law": "hertz+tsuji+mindlin", "friction": 0.3}),
       ("hooke+viscous+linear_history", {"law": "hooke+viscous+linear_history", "friction": 0.3, **LINEAR})]
    + [(f"hertz+tsuji+mindlin+{part}", {"law": "hertz+tsuji+mindlin", kind: part, "friction": 0.3, **extra})
       for kind, part, extra in (
           ("rolling", "constant_torque", {"rolling_friction": 0.1}),
           ("rolling", "epsd", {"rolling_friction": 0.1}),
           ("rolling", "sds_rolling", {"rolling_friction": 0.1, "rolling_stiffness": 1e3}),
           ("twisting", "marshall", {}),
           ("twisting", "sds_twisting", {"twisting_stiffness": 1e-7, "twisting_friction": 1e-5}))]
    + [("hm+epsd (heap.toml, column collapse)", {"law": "hm", "rolling": "epsd", "friction": 0.3,
                                                 "rolling_friction": 0.1}),
       ("hm+epsd+sds_twisting (settle.toml)", {"law": "hm", "rolling": "epsd", "twisting": "sds_twisting",
                                               "friction": 0.3, "rolling_friction": 0.1,
                                               "twisting_stiffness": 1e-7, "twisting_friction": 1e-5})]
)

_CHILD = """
import json, sys, time
from minidem.scene import scenario
from minidem.engine import simulation
data = json.loads(sys.argv[1])
started = time.perf_counter()
simulation.Simulation(scenario.build_scene(data)).run()
cold = time.perf_counter() - started
started = time.perf_counter()
simulation.Simulation(scenario.build_scene(data)).run()
print(json.dumps({"cold_s": cold, "warm_s": time.perf_counter() - started}))
"""


def scene(contact: dict) -> dict:
    """20 spheres (1 mm) in a row 0.5 mm above a floor: 10 steps of 1e-5 s."""
    return {"materials": {"beads": {"youngs_modulus": 5e6, "poisson_ratio": 0.3, "density": 2500.0}},
            "contact": contact,
            "walls": [{"point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "beads"}],
            "particles": [{"position": [0.0025 * k, 0.0, 0.0015], "radius": 1e-3, "material": "beads"}
                          for k in range(20)],
            "run": {"stop": "time", "end_time": 1e-4, "dt": 1e-5, "gravity": [0.0, 0.0, -9.81], "threads": 1},
            "output": {"vtk": False}}


def _child(data: dict, cache: Path) -> dict:
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(cache / "minidem"), NUMBA_CACHE_DIR=str(cache / "numba"))
    done = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(data)], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"compile bench failed:\n{(done.stdout + done.stderr)[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def measure(combinations=COMBINATIONS, echo=print) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="minidem-bench-compile-") as folder:
        base = Path(folder) / "base"
        echo("bench: compile: filling the engine's shared cache (hm)")
        _child(scene({"law": "hm", "friction": 0.3}), base)
        for name, contact in combinations:
            cache = Path(folder) / "case"
            shutil.rmtree(cache, ignore_errors=True)
            # the engine's functions (in the installed package) stay cached; the kernels are
            # generated into the case's own MINIDEM_CACHE_DIR, so each is compiled afresh
            shutil.copytree(base / "numba", cache / "numba")
            timing = _child(scene(contact), cache)
            echo(f"bench: compile {name}: cold {timing['cold_s']:.1f} s, warm {timing['warm_s']:.2f} s")
            rows.append({"combination": name, **timing})
    return rows


def timed_run(scene: Path, cache: Path, out: Path) -> dict:
    """``minidem run scene`` in a fresh process on the caches in ``cache``: wall and CPU
    seconds (user + system of the child), from process start to exit."""
    env = dict(os.environ, MINIDEM_CACHE_DIR=str(cache / "minidem"), NUMBA_CACHE_DIR=str(cache / "numba"))
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", "from minidem.cli import console; console()",
                           "run", str(scene), "--out", str(out), "--quiet"],
                          env=env, capture_output=True, text=True)
    wall = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"compile bench: minidem run {scene} failed:\n{(done.stdout + done.stderr)[-2000:]}")
    return {"wall_s": wall, "cpu_s": (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)}


def measure_scenes(rounds: int, scenes=None, echo=print) -> list[dict]:
    """Cold (empty caches) and warm first runs of each scene, ``rounds`` times, interleaved
    scene by scene; medians."""
    scenes = sorted(SCENES.glob("*.toml")) if scenes is None else scenes
    runs = {scene: {"cold": [], "warm": []} for scene in scenes}
    for round_ in range(rounds):
        for scene in scenes:
            with tempfile.TemporaryDirectory(prefix="minidem-bench-cold-") as folder:
                cache = Path(folder) / "cache"  # empty: nothing compiled yet
                cold = timed_run(scene, cache, Path(folder) / "cold")
                warm = timed_run(scene, cache, Path(folder) / "warm")
            runs[scene]["cold"].append(cold)
            runs[scene]["warm"].append(warm)
            echo(f"bench: first run {scene.name} (round {round_ + 1}/{rounds}): cold {cold['wall_s']:.1f} s "
                 f"({cold['cpu_s']:.1f} s CPU), warm {warm['wall_s']:.1f} s ({warm['cpu_s']:.1f} s CPU)")
    rows = []
    for scene, timing in runs.items():
        row = {"scene": f"scenarios/{scene.name}", "rounds": rounds}
        for kind in ("cold", "warm"):
            for what in ("wall_s", "cpu_s"):
                row[f"{kind}_{what}"] = statistics.median(run[what] for run in timing[kind])
        rows.append(row)
    return rows


def section_scenes(rows: list[dict]) -> str:
    lines = ["### First run of each shipped scene", "",
             "`minidem run scenarios/NAME.toml` as a whole process (interpreter start to exit, output "
             "written), on a fresh install's empty caches (`MINIDEM_CACHE_DIR` and `NUMBA_CACHE_DIR` new, "
             "empty folders): every kernel and engine function the scene needs is compiled. 'Warm' is the "
             "same command again on the caches the first run filled (the run itself, loading included). "
             f"Medians of {rows[0]['rounds'] if rows else 0} round(s), scenes interleaved; CPU = user + "
             "system time of the process and of its helper process on a fresh install "
             "(minidem/engine/warmup.py: the law's force function and the engine's shared functions beside "
             "the kernel; for a scene with more than one sphere, the kernel itself beside the neighbour "
             "search that the check for overlapping spheres needs first). The difference "
             "cold - warm is what compiling costs.",
             "", "| scene | cold wall s | cold CPU s | warm wall s | warm CPU s |", "|---|---|---|---|---|"]
    for row in rows:
        lines.append(f"| `{row['scene']}` | {row['cold_wall_s']:.1f} | {row['cold_cpu_s']:.1f} | "
                     f"{row['warm_wall_s']:.1f} | {row['warm_cpu_s']:.1f} |")
    return "\n".join(lines) + "\n"


def section(rows: list[dict], command: str, stamp) -> str:
    lines = ["## Compile time and first runs", "", f"*{stamp(command)}*", "",
             "Each shipped law and combination compiles into its own kernel, once (then loaded from the "
             "cache). Measured in a fresh process per combination, on a copy of a cache holding the engine's "
             "shared functions (one run of `hm`), so 'cold' is the combination's own kernel and parts: "
             "`Simulation(scene).run()` of 20 spheres over a floor (the multi-particle kernel, 10 steps); "
             "'warm' a second run in the same process. Wall times on a shared machine (other jobs inflate them).",
             "", "| combination | cold (compile) s | warm s |", "|---|---|---|"]
    for row in rows:
        lines.append(f"| `{row['combination']}` | {row['cold_s']:.1f} | {row['warm_s']:.2f} |")
    return "\n".join(lines) + "\n"


def run(command: str, stamp, echo=print, rounds: int = 3) -> str:
    scenes = measure_scenes(rounds, echo=echo)
    return section(measure(echo=echo), command, stamp) + "\n" + section_scenes(scenes)
