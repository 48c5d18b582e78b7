"""``minidem bench --only multi-particle``: throughput of the "settle" scene beside LIGGGHTS.

The scene is ../shared/bench/settle.md (``scenarios/bench/settle.toml``): variants "lattice" and
"jitter", N = 2,000 and 20,000, 10,000 steps of 2e-5 s. ``--only multi-particle-scale`` runs
settle.md's scale variants, N = 200,000 and 1,000,000, with fewer steps (``steps_for``), in
a section of its own, so the two are measured in sittings of their own length (``--sizes``,
``--variants`` and ``--steps`` choose). Every run is a fresh process, so
its peak memory is that process's own (``ru_maxrss`` from ``os.wait4``). minidem runs on
one and two threads; LIGGGHTS 3.8 (``liggghts`` on the PATH, Debian's package) runs the
shared input script ``bench/liggghts/in.settle`` on one core, interleaved with minidem's
runs in the same sitting so that both see the same machine load. Times are the step
loops' (minidem: ``RunResult.wall_time``; LIGGGHTS: its "Loop time"); set-up is
excluded for both. Also measured: the neighbour-list build against N (linear cost) and
the cost of VTK output at the scene's default interval.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from minidem.engine import simulation
from minidem.studies import checkout

ROOT = checkout.ROOT
SETTLE = ROOT / "scenarios" / "bench" / "settle.toml"
SHARED_BENCH = ROOT.parent / "shared" / "bench" / "liggghts"
STEPS, DT = 10_000, 2e-5
# The scale variants (settle.md: N = 200,000 and 1,000,000, "fewer steps") run at most this
# many particle-steps: 10,000 steps up to 200,000 particles, 2,000 at 1,000,000
MOST_PARTICLE_STEPS = 2_000_000_000
SIZES = (2_000, 20_000)
SCALE_SIZES = (200_000, 1_000_000)
VARIANTS = ("lattice", "jitter")
LAYER_SITES, SPACING, FIRST_CENTRE = 45 * 45, 2.2e-3, 1.1e-3  # the lattice of settle.md
JITTER = {"lattice": 0.0, "jitter": 9e-5}  # m, as in settle.md and make_lattice.py

_CHILD = """
import json, resource, sys, time
from minidem.scene import scenario
from minidem.engine import run_loop, simulation
n, jitter, threads, steps, vtk, out = sys.argv[1:7]
if threads.endswith("pinned"):  # every chunk on that many threads: no probes of one (LoopThreads)
    threads = threads.removesuffix("pinned")
    run_loop.LoopThreads.PROBE_FIRST = 10**9
overrides = [f"fill.0.count={n}", f"fill.0.jitter={jitter}", f"run.threads={threads}",
             f"run.end_time={int(steps) * 2e-5!r}", f"output.vtk={vtk}"]
if sys.argv[8] != "-":  # a column taller than the scene file's 1 m box (above 919,000 spheres)
    overrides += [f"fill.0.upper=[0.1, 0.1, {sys.argv[8]}]", f"walls.0.upper=[0.1, 0.1, {sys.argv[8]}]"]
scene = scenario.load_scene(sys.argv[7], overrides, out)
order = sys.argv[9]  # "fill": as the lattice fill makes them; "shuffled": given in a random order,
if order != "fill":  # stored as minidem chooses; "shuffled-as-given": the spatial sort turned off
    import dataclasses, numpy
    scene = dataclasses.replace(scene.reordered(numpy.random.default_rng(1).permutation(scene.n_particles)),
                                particle_id=None)
    if order == "shuffled-as-given":
        simulation.REORDER_MIN_PARTICLES = 10**18
sim = simulation.Simulation(scene)
frames = None
if vtk == "true":
    from minidem.results.vtk import SimulationFrames
    frames = SimulationFrames(sim, scene.output_directory)
setup_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
cpu = time.process_time()
result = sim.run(on_frame=frames)
cpu = time.process_time() - cpu
if frames is not None:
    frames.close()
    frames.succeeded()  # an earlier bench's series set aside at the first frame is replaced
try:
    import numba
    layer = numba.threading_layer()
except ValueError:  # no parallel region ran (one thread, or a scene below PARALLEL_MIN_PARTICLES)
    layer = None
print(json.dumps({"layer": layer, "wall_s": result.wall_time, "cpu_s": cpu, "steps": result.steps, "threads": result.threads,
                  "mean_z_m": float(result.position[:, 2].mean()), "kinetic_energy_j": float(result.energy[-1, 1]),
                  "builds": result.neighbour_builds, "setup_rss_kib": setup_rss,
                  "thread_steps": {str(k): v for k, v in result.thread_steps.items()}}))
"""


_PEAK = """
import resource, subprocess, sys
done = subprocess.run(sys.argv[1:])
# RUSAGE_CHILDREN of this wrapper covers exactly the one child: its own peak RSS
print(f"peak_rss_kib={resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}", file=sys.stderr)
sys.exit(done.returncode)
"""


def _run_measured(argv, cwd=None) -> tuple[str, str, float]:
    """Run argv in a fresh process; (stdout, stderr, its peak RSS in MiB)."""
    done = subprocess.run([sys.executable, "-c", _PEAK, *map(str, argv)], cwd=cwd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{argv[0]} failed:\n{(done.stdout + done.stderr)[-2000:]}")
    peak = next(line for line in done.stderr.splitlines() if line.startswith("peak_rss_kib="))
    return done.stdout, done.stderr, int(peak.split("=")[1]) / 1024.0


def steps_for(n: int, steps: int | None = None) -> int:
    """Steps of a run of N particles: ``steps`` when given (``--steps``), else 10,000
    (settle.md), fewer for the scale variants."""
    return steps if steps else min(STEPS, MOST_PARTICLE_STEPS // n)


def box_height(n: int) -> float | None:
    """The box and fill height (m) N particles need when the scene file's 1 m is too
    short (the lattice's layers plus 1 cm, as make_lattice.py's zhi), else None."""
    layers = -(-n // LAYER_SITES)
    top = FIRST_CENTRE + SPACING * layers + 0.01
    return top if top > 1.0 else None


ORDERS = ("fill", "shuffled-as-given", "shuffled")


def run_minidem(n: int, jitter: float, threads: int | str, steps: int = STEPS, vtk: bool = False,
                out: Path | None = None, order: str = "fill") -> dict:
    """``threads``: run.threads, or e.g. "2pinned": two threads for every chunk.
    ``order``: the particles as the fill makes them, or given in a random order (ORDERS:
    stored as minidem chooses, or with its spatial sort turned off)."""
    out = out or Path(tempfile.gettempdir()) / "minidem-bench-settle"
    height = box_height(n)
    stdout, _, rss = _run_measured([sys.executable, "-c", _CHILD, n, repr(jitter), threads, steps,
                                    "true" if vtk else "false", out, SETTLE, "-" if height is None else repr(height),
                                    order])
    record = json.loads(stdout.strip().splitlines()[-1])
    record["peak_rss_mib"] = rss
    record["rate"] = n * record["steps"] / record["wall_s"]
    return record


def liggghts_executable() -> str | None:
    return shutil.which("liggghts")


def run_liggghts(data: Path, steps: int = STEPS) -> dict:
    script = SHARED_BENCH / "in.settle"
    started = time.perf_counter()
    stdout, _, rss = _run_measured([liggghts_executable(), "-in", script, "-var", "data", data, "-var", "nsteps",
                                    steps], cwd=data.parent)
    total = time.perf_counter() - started
    loop = next(float(line.split()[3]) for line in stdout.splitlines() if line.startswith("Loop time of"))
    n = int(next(line.split()[0] for line in data.read_text().splitlines()[:4] if line.endswith("atoms")))
    return {"wall_s": loop, "process_s": total, "peak_rss_mib": rss, "rate": n * steps / loop}


def lattice_data(n: int, jitter: float, folder: Path) -> Path:
    """The LIGGGHTS data file from the shared generator (same positions as minidem's)."""
    path = folder / f"settle_{n}_{jitter:g}.data"
    if not path.exists():
        subprocess.run([sys.executable, str(SHARED_BENCH / "make_lattice.py"), str(n), str(path)]
                       + ([repr(jitter)] if jitter else []), check=True, capture_output=True)
    return path


def import_baseline() -> dict:
    """Peak RSS (MiB) of a fresh interpreter at each stage before any simulation data."""
    # VmHWM, not ru_maxrss: Linux carries ru_maxrss across fork + exec, so a child of this
    # (large) process would report this process's peak at its first line
    code = ("import json\n"
            "r = lambda: int(next(l for l in open('/proc/self/status') if l.startswith('VmHWM')).split()[1]) / 1024\n"
            "out = {'python': r()}\nimport numpy\nout['numpy'] = r()\nimport numba\nout['numba'] = r()\n"
            "import minidem.engine.simulation\nout['minidem'] = r()\n"
            "from minidem.geometry.neighbours import reverse_index\nimport numpy as np\n"
            "reverse_index(np.zeros(2, dtype=np.int64), np.zeros(0, dtype=np.int64), 1)\n"
            "out['first compiled call'] = r()\nprint(json.dumps(out))")
    # twice: the first process may compile that call (a cache without it) and peak higher
    # (2026-11-25: 150 against 141 MiB), the second loads it, as the measured runs do
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def measure(repeats: int = 3, sizes=SIZES, variants=VARIANTS, thread_counts=(1, 2), echo=print,
            steps: int | None = None, extras: bool = True) -> dict:
    """``extras``: also the neighbour-list build against N and the VTK output overhead (the
    default section; the scale section measures the runs alone)."""
    have_liggghts = liggghts_executable() is not None and (SHARED_BENCH / "in.settle").exists()
    results = {"cases": {}, "steps": {}, "liggghts": have_liggghts}
    with tempfile.TemporaryDirectory(prefix="minidem-bench-") as tmp:
        folder = Path(tmp)
        echo("bench: warm-up (compile or load the settle kernel)")
        run_minidem(100, 0.0, 1, steps=10)
        run_minidem(100, 0.0, 2, steps=10)
        load = os.getloadavg()
        for n in sizes:
            for variant in variants:
                jitter = JITTER[variant]
                data = lattice_data(n, jitter, folder) if have_liggghts else None
                # pinned: the two-thread loops for every chunk (no one-thread probes), for
                # their speed-up alone; scenes below PARALLEL_MIN_PARTICLES never use them
                pinned = n >= simulation.PARALLEL_MIN_PARTICLES
                case = {"liggghts": [], **{f"minidem_{t}": [] for t in thread_counts},
                        **({"minidem_2_pinned": []} if pinned else {})}
                n_steps = steps_for(n, steps)
                for repeat in range(repeats):
                    # interleaved, so a change in the machine's load hits every code alike
                    if have_liggghts:
                        case["liggghts"].append(run_liggghts(data, n_steps))
                    for t in thread_counts:
                        case[f"minidem_{t}"].append(run_minidem(n, jitter, t, n_steps))
                    if pinned:
                        case["minidem_2_pinned"].append(run_minidem(n, jitter, "2pinned", n_steps))
                    echo(f"bench: {variant} N={n} repeat {repeat + 1}/{repeats}: "
                         + ", ".join(f"{k} {v[-1]['rate']:.3g}/s" for k, v in case.items() if v))
                results["cases"][(variant, n)] = case
                results["steps"][n] = n_steps
        results["load"] = (load, os.getloadavg())
        results["baseline"] = import_baseline()
        if not extras:
            return results
        echo("bench: neighbour-list build against N")
        from minidem.geometry.neighbours import benchmark_scaling

        results["neighbours"] = benchmark_scaling(n_values=(2_000, 20_000, 200_000), thread_counts=(1,), repeats=3)
        echo("bench: output overhead (VTK at the scene's default interval)")
        overhead = {"off": [], "on": []}
        for _ in range(repeats):
            overhead["off"].append(run_minidem(20_000, JITTER["jitter"], 1)["wall_s"])
            overhead["on"].append(run_minidem(20_000, JITTER["jitter"], 1, vtk=True, out=folder / "vtk")["wall_s"])
        results["output"] = overhead
        results["frames"] = len(list((folder / "vtk").glob("*.vtu")))
    return results


def _median(runs, key):
    return statistics.median(r[key] for r in runs) if runs else float("nan")


def pinned_text(case, one_thread_rate) -> str:
    if not case.get("minidem_2_pinned"):
        return "- (below 5,000: one thread)"
    rate = _median(case["minidem_2_pinned"], "rate")
    return f"{rate:.3g}, {rate / one_thread_rate:.2f}x"


def memory_growth(cases) -> str:
    """What N costs in memory: the growth of the peak from the smallest to the largest N,
    per added particle, minidem (one thread) beside LIGGGHTS."""
    sizes = sorted({n for _, n in cases})
    if len(sizes) < 2:
        return ""
    small, large = sizes[0], sizes[-1]
    parts = []
    for variant in sorted({v for v, _ in cases}):
        if (variant, small) not in cases or (variant, large) not in cases:
            continue
        growth = {code: _median(cases[(variant, large)][code], "peak_rss_mib")
                  - _median(cases[(variant, small)][code], "peak_rss_mib") for code in ("liggghts", "minidem_1")}
        per = {code: mib * 1024 * 1024 / (large - small) for code, mib in growth.items()}
        parts.append(f"{variant}: LIGGGHTS {growth['liggghts']:.0f} MiB ({per['liggghts']:.0f} bytes a particle), "
                     f"minidem {growth['minidem_1']:.0f} MiB ({per['minidem_1']:.0f} bytes)")
    return (f"What the particles themselves cost, the growth of the peak from {small:,} to {large:,} particles "
            "(minidem one thread: particle arrays, wall and pair histories, the Verlet list with its reactions, "
            "one copy of the last good state; the list entries grow as the pile packs): " + "; ".join(parts) + ".")


def fixed_against_liggghts(cases, fixed_mib) -> str:
    """The fixed cost beside LIGGGHTS' whole process at each N: why issue 15's target 3
    compares the particles' own bytes, not whole processes."""
    if fixed_mib is None:
        return ""
    sizes = {}
    for (_, n), case in cases.items():
        sizes.setdefault(n, []).append(_median(case["liggghts"], "peak_rss_mib"))
    parts = [f"{fixed_mib / statistics.median(peaks):.2f}x at N = {n:,}" for n, peaks in sorted(sizes.items())]
    return ("That fixed cost against LIGGGHTS' whole process: " + ", ".join(parts)
            + "; the particles' own cost, (peak - fixed cost) / N, is compared below.")


RESOLUTION_MIB = 5  # the fixed cost and a run's peak are two processes: a few MiB apart by chance


def per_particle_memory(cases, fixed_mib) -> str:
    """Bytes a particle at each N (issue 15, target 3): (peak - fixed cost) / N, minidem
    one thread, the fixed cost being a fresh interpreter's peak after numba's first
    compiled call. LIGGGHTS' per-particle cost is the growth of its peak (memory_growth)."""
    parts = []
    for (variant, n), case in sorted(cases.items(), key=lambda item: (item[0][0], item[0][1])):
        above = _median(case["minidem_1"], "peak_rss_mib") - fixed_mib
        # the fixed cost is another process's peak: a few MiB either way, so a small scene's
        # particles are below what this difference resolves rather than a negative cost
        parts.append(f"{variant} {n:,}: {above * 1024 * 1024 / n:.0f}" if above > RESOLUTION_MIB
                     else f"{variant} {n:,}: below resolution ({above:+.0f} MiB)")
    return ("Bytes a particle, minidem one thread, (peak - the fixed cost of the first compiled call) / N "
            f"(a difference under {RESOLUTION_MIB} MiB is not resolved): " + "; ".join(parts) + ".")


def section(results: dict, command: str, stamp, heading: str = "## Multi-particle throughput") -> str:
    cases = results["cases"]
    load_start, load_end = results["load"]
    steps = ", ".join(f"{count:,} steps at N = {n:,}" for n, count in sorted(results["steps"].items()))
    lines = [
        heading,
        "",
        stamp(command),
        f"Load average (1, 5, 15 min) at the start {', '.join(f'{x:.2f}' for x in load_start)}, at the end "
        f"{', '.join(f'{x:.2f}' for x in load_end)} (the machine is shared: other jobs ran meanwhile; the "
        "ratios, measured interleaved, are the useful part).",
        "",
        "Scene: `scenarios/bench/settle.toml` = ../shared/bench/settle.md (Hertz + Mindlin no-slip with history, "
        "e = 0.5, mu = 0.5, box of 5 planes, dt = 2e-5 s, "
        f"{steps}, skin 0.5 mm; start positions identical "
        "to the LIGGGHTS generator's). Each run is a fresh process; time = the step loop (set-up excluded; "
        "LIGGGHTS: its 'Loop time'); particle-steps/s = N x steps / time; medians of "
        f"{len(next(iter(cases.values()))['minidem_1'])} runs; peak memory = the process's ru_maxrss. "
        "LIGGGHTS 3.8.0 (Debian package), `liggghts -in bench/liggghts/in.settle` (hertz, tangential "
        "history), one core. minidem with run.threads = 2 runs scenes below 5,000 particles on one thread, "
        "and larger ones on two except for the chunks where one measured faster (docs/multi-particle.md, "
        "'Threads'): the column 'steps run on 2 threads' gives, per run, the share of the steps that did. "
        "'2 threads pinned' runs every chunk on two threads (no one-thread probes): the two-thread loops' own "
        "speed-up, whatever the load.",
        "",
        "| variant | N | LIGGGHTS 1 core | minidem 1 thread | ratio | minidem run.threads = 2 | speed-up over 1 "
        "thread | steps run on 2 threads | 2 threads pinned: rate, speed-up | peak MiB: LIGGGHTS / minidem 1 / 2 "
        "threads | minidem mean z (mm), kinetic energy (J), list builds |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for (variant, n), case in cases.items():
        lig = _median(case["liggghts"], "rate")
        one, two = _median(case["minidem_1"], "rate"), _median(case.get("minidem_2", []), "rate")
        two_text = f"{two:.3g} | {two / one:.2f}x" if case.get("minidem_2") else "- | -"
        last = case["minidem_1"][-1]
        on_two = [r["thread_steps"].get("2", 0) / max(1, r["steps"]) for r in case.get("minidem_2", [])]
        share = ", ".join(f"{100 * x:.0f} %" for x in on_two) or "-"
        lines.append(
            f"| {variant} | {n:,} | {lig:.3g} | {one:.3g} | {one / lig:.2f}x | {two_text} | {share} | "
            f"{pinned_text(case, one)} | "
            f"{_median(case['liggghts'], 'peak_rss_mib'):.0f} / {_median(case['minidem_1'], 'peak_rss_mib'):.0f} / "
            f"{_median(case.get('minidem_2') or case.get('minidem_2_pinned', []), 'peak_rss_mib'):.0f} | "
            f"{last['mean_z_m'] * 1e3:.3f}, "
            f"{last['kinetic_energy_j']:.2g}, {last['builds']} |")
    cpu_lines = []
    for (variant, n), case in cases.items():
        one = statistics.median(r["cpu_s"] for r in case["minidem_1"])
        two = statistics.median(r["cpu_s"] for r in case.get("minidem_2", [])) if case.get("minidem_2") else None
        cpu_lines.append(f"{variant} {n:,}: {one:.2f} s on 1 thread" + (f", {two:.2f} s on 2 threads" if two else ""))
    base = results["baseline"]
    layers = sorted({r["layer"] for case in cases.values() for runs in case.values() for r in runs
                     if isinstance(r, dict) and r.get("layer")})
    lines += [
        "",
        "Process CPU time of minidem's step loop (both threads summed; a check that the second thread adds "
        "work, not waiting): " + "; ".join(cpu_lines) + ".",
        f"numba threading layer of the two-thread runs: {', '.join(layers) or '-'}.",
        "",
        "Peak memory, split: a fresh interpreter is "
        + ", ".join(f"{k} {v:.0f} MiB" for k, v in base.items())
        + " (numba's first compiled call, even one loaded from the cache, sets up its typing and code-"
        "generation contexts and LLVM)."
        + "".join(" " + text for text in (fixed_against_liggghts(cases, base.get("first compiled call")),
                                          memory_growth(cases)) if text),
        "",
        per_particle_memory(cases, base.get("first compiled call", float("nan"))),
        "",
    ]
    if "neighbours" not in results:  # the scale section: the runs alone
        return "\n".join(lines)
    scaling = results["neighbours"]
    lines += ["Neighbour-list build (`minidem.geometry.neighbours.build_pairs`, random packings at a fixed volume "
              "fraction, one thread, median of 3): cost per particle is flat, i.e. linear in N:", "",
              "| N | seconds per build | microseconds per particle |", "|---|---|---|"]
    for (n, _), seconds in sorted(scaling.items()):
        lines.append(f"| {n:,} | {seconds:.4f} | {seconds / n * 1e6:.3f} |")
    off, on = statistics.median(results["output"]["off"]), statistics.median(results["output"]["on"])
    lines += ["", f"Output overhead: jitter, N = 20,000, one thread, VTK frames at the scene's default interval "
              f"(`output.interval = 0.01` s: {results['frames']} frames in 0.2 s): step loop {off:.2f} s without, "
              f"{on:.2f} s with output, {100 * (on / off - 1):+.1f} % (medians).", ""]
    return "\n".join(lines)


ORDER_SIZES, ORDER_STEPS = (20_000, 200_000, 1_000_000), 400
# A run below this many particle-steps lasts under a second, where the VM's jitter (runs of
# 400 steps at 20,000 spread 1.96-2.89e7 particle-steps/s) hides the order: more rounds there
ORDER_RESOLVED_PARTICLE_STEPS = 80_000_000
ORDER_MOST_REPEATS = 15


def order_repeats(repeats: int, n: int, steps: int) -> int:
    """Rounds at N: ``repeats``, more for runs too short to resolve (at most ORDER_MOST_REPEATS)."""
    return max(repeats, min(ORDER_MOST_REPEATS, repeats * ORDER_RESOLVED_PARTICLE_STEPS // (n * steps)))


def memory_order(repeats: int, command: str, stamp, echo=print, sizes=ORDER_SIZES, steps=None) -> str:
    """Issue 15, target 2: the cost of a particle-step against N, with the particles in the
    fill's (spatial) order and in a random order, stored as given or sorted by minidem
    (minidem.geometry.order). One thread, jitter, fresh processes, interleaved."""
    steps = steps or ORDER_STEPS
    echo("bench: warm-up (compile or load the settle kernel)")
    run_minidem(6_000, JITTER["jitter"], 1, steps=10, order="shuffled")
    load = os.getloadavg()
    rows = {}
    rounds = {n: order_repeats(repeats, n, steps) for n in sizes}
    for n in sizes:
        runs = {order: [] for order in ORDERS}
        for repeat in range(rounds[n]):
            for order in ORDERS:
                runs[order].append(run_minidem(n, JITTER["jitter"], 1, steps, order=order))
            echo(f"bench: memory order N={n} repeat {repeat + 1}/{rounds[n]}: "
                 + ", ".join(f"{order} {v[-1]['rate']:.3g}/s" for order, v in runs.items()))
        rows[n] = runs
    lines = ["## Memory order against N", "", stamp(command),
             f"Load average (1, 5, 15 min) at the start {', '.join(f'{x:.2f}' for x in load)}, at the end "
             f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}.", "",
             f"Scene: `scenarios/bench/settle.toml`, jitter, {steps:,} steps from rest (the same phase at every N), "
             "one thread, a fresh process a run, the three orders interleaved, medians of "
             + ", ".join(f"{rounds[n]} at {n:,}" for n in sizes) + " (more rounds where a run lasts under a "
             "second). 'fill': the particles as the lattice fill makes them (x fastest, then y, then z: spatial); "
             "'shuffled': the same particles given in a random order (seeded), which minidem stores sorted in "
             "space (docs/multi-particle.md, 'The order particles are stored in'); 'shuffled, as given': the same "
             "with that sort turned off. ns a particle-step = the step loop's wall time / (N x steps).", "",
             "| N | fill: particle-steps/s (ns each) | shuffled, as given | shuffled, sorted by minidem | "
             "as given / sorted |", "|---|---|---|---|---|"]
    for n, runs in rows.items():
        rate = {order: _median(v, "rate") for order, v in runs.items()}
        cells = [f"{rate[o]:.3g} ({1e9 / rate[o]:.1f})" for o in ORDERS]
        lines.append(f"| {n:,} | {cells[0]} | {cells[1]} | {cells[2]} | "
                     f"{rate['shuffled'] / rate['shuffled-as-given']:.2f}x |")
    first, last = min(rows), max(rows)
    for order in ("fill", "shuffled"):
        a, b = _median(rows[first][order], "rate"), _median(rows[last][order], "rate")
        lines.append(f"\n{order}: the rate at {last:,} is {b / a:.2f}x the rate at {first:,}.")
    return "\n".join(lines) + "\n"


def run(repeats: int, command: str, stamp, echo=print, sizes=SIZES, variants=VARIANTS, steps=None) -> str:
    return section(measure(repeats=repeats, sizes=sizes, variants=variants, echo=echo, steps=steps), command, stamp)


def run_scale(repeats: int, command: str, stamp, echo=print, sizes=SCALE_SIZES, variants=VARIANTS,
              steps=None) -> str:
    """settle.md's scale variants: one thread, two threads pinned (every chunk on two:
    their speed-up, issue 15 target 4) and LIGGGHTS, no extras."""
    results = measure(repeats=repeats, sizes=sizes, variants=variants, thread_counts=(1,), echo=echo, steps=steps,
                      extras=False)
    return section(results, command, stamp, heading="## Multi-particle throughput at scale")
