"""Time one sweep on each back end and worker count (docs/sweeps-on-a-cluster.md).

    python -m minidem.studies.bench_sweeps [--scenario scenarios/bench/sweep500.toml] [--repeats 5]

Runs ``minidem run SCENARIO --quiet --restart`` as a fresh process for local processes
(``--workers 1``, ``--workers 2``) and for a Dask scheduler with 1 and 2 workers
(``dask scheduler`` / ``dask worker --nthreads 1`` processes on 127.0.0.1, started once
and kept for every repeat, as a cluster would be). The kernel cache is warmed first and
every Dask cluster gets one untimed run, so the times are warm. The configurations take
turns within each repeat, so that the load of a shared machine falls on all of them
alike. Prints a markdown table of medians (and the fastest sweep): the sweep (cases only, ``sweep.json``
``wall_time_s``), the whole command (imports, plan, connection, writing) and the sum of
the cases' own run times (it grows when the workers wait for a core); and checks that
every run wrote the same sweep.csv.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from minidem.studies import checkout

ROOT = checkout.ROOT
DEFAULT_SCENARIO = ROOT / "scenarios" / "bench" / "sweep500.toml"


def _minidem() -> list[str]:
    script = Path(sys.executable).with_name("minidem")
    return [str(script)] if script.exists() else [sys.executable, "-m", "minidem.cli"]


def timed_run(scenario: Path, out: Path, *options: str) -> dict:
    started = time.perf_counter()
    done = subprocess.run(_minidem() + ["run", str(scenario), "--out", str(out), "--quiet", "--restart", *options],
                          capture_output=True, text=True)
    command_s = time.perf_counter() - started
    if done.returncode != 0:
        raise RuntimeError(f"minidem run {' '.join(options)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    info = json.loads((out / "sweep.json").read_text())
    return {"sweep_s": info["wall_time_s"], "command_s": command_s, "csv": (out / "sweep.csv").read_bytes(),
            "cases": info["cases"], "case_sum_s": info["cases_wall_time_s"]}


def _busy(loops: int = 3_000_000) -> float:
    started = time.perf_counter()
    total = 0
    for i in range(loops):
        total += i
    return time.perf_counter() - started


def spare_cores() -> float:
    """How many cores two busy processes get together right now (2.0 on an idle 2-core
    machine, 1.0 when other work leaves room for one): the ceiling of any speed-up."""
    import multiprocessing

    alone = min(_busy() for _ in range(3))
    with multiprocessing.get_context("fork").Pool(2) as pool:
        together = max(pool.map(_busy, [3_000_000, 3_000_000]))
    return 2.0 * alone / together


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main(argv=None) -> int:
    from minidem.studies.executors import LocalDaskProcesses, dask_available

    parser = argparse.ArgumentParser(prog="python -m minidem.studies.bench_sweeps", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args(argv)
    if not dask_available():
        print("needs dask: pip install 'minidem[dask]'", file=sys.stderr)
        return 2
    load_before, spare_before = os.getloadavg(), spare_cores()
    runs: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix="minidem-bench-sweeps-") as tmp:
        tmp = Path(tmp)
        print("warming the kernel cache", file=sys.stderr)
        timed_run(args.scenario, tmp / "warm", "--workers", "1")
        clusters = {}
        try:
            for n in args.workers:
                clusters[n] = LocalDaskProcesses(n).__enter__()
                timed_run(args.scenario, tmp / f"warm-dask{n}", "--scheduler", clusters[n].address)
            configs = [(f"local processes, --workers {n}", ("--workers", str(n))) for n in args.workers]
            configs += [(f"Dask, {n} worker(s) x 1 thread", ("--scheduler", clusters[n].address)) for n in args.workers]
            for repeat in range(args.repeats):
                for label, options in configs:
                    result = timed_run(args.scenario, tmp / "run", *options)
                    runs.setdefault(label, []).append(result)
                    print(f"repeat {repeat}: {label}: sweep {result['sweep_s']:.2f} s, command "
                          f"{result['command_s']:.2f} s", file=sys.stderr)
        finally:
            for cluster in clusters.values():
                cluster.__exit__(None, None, None)
    load_after, spare_after = os.getloadavg(), spare_cores()
    files = {r["csv"] for results in runs.values() for r in results}
    baseline = statistics.median(r["sweep_s"] for r in runs[f"local processes, --workers {args.workers[0]}"])
    first = {}
    print(f"Measured {datetime.date.today().isoformat()} on {os.cpu_count()} cores ({_cpu_model()}), "
          f"{platform.system()} {platform.release()}, Python {platform.python_version()}; load average "
          f"{load_before[0]:.1f} before, {load_after[0]:.1f} after; two busy processes got {spare_before:.2f} and "
          f"{spare_after:.2f} cores' worth together (before, after): the ceiling of any speed-up. `python -m minidem.studies.bench_sweeps --repeats "
          f"{args.repeats}` on {args.scenario.relative_to(ROOT) if args.scenario.is_relative_to(ROOT) else args.scenario}"
          f" ({next(iter(runs.values()))[0]['cases']} cases); medians of {args.repeats}. sweep.csv identical in "
          f"all {sum(len(r) for r in runs.values())} runs: {'yes' if len(files) == 1 else 'NO'}.\n")
    print("| back end | sweep (s) | fastest sweep (s) | whole command (s) | sum of the case times (s) | speed-up vs 1 "
          "worker, same back end | vs local --workers 1 |")
    print("|---|---|---|---|---|---|---|")
    for label, results in runs.items():
        sweep_s = statistics.median(r["sweep_s"] for r in results)
        command_s = statistics.median(r["command_s"] for r in results)
        case_sum_s = statistics.median(r["case_sum_s"] for r in results)
        backend = label.split(",")[0]
        first.setdefault(backend, sweep_s)
        fastest_s = min(r["sweep_s"] for r in results)
        print(f"| {label} | {sweep_s:.2f} | {fastest_s:.2f} | {command_s:.2f} | {case_sum_s:.2f} | {first[backend] / sweep_s:.2f} | "
              f"{baseline / sweep_s:.2f} |")
    return 0 if len(files) == 1 else 1


if __name__ == "__main__":
    sys.exit(main())
