"""Command line: ``minidem run``, ``minidem laws``, ``minidem verify``, ``minidem docs``, ``minidem render``,
``minidem bench``.

Exit codes: 0 success, 2 bad input (scenario, law or option), 1 failure during the run.
A Python traceback is shown only with ``--debug``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shlex
import signal
import sys
import time
import traceback
import warnings
from pathlib import Path

EXIT_OK, EXIT_FAILURE, EXIT_BAD_INPUT = 0, 1, 2


def _format_value(value) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def print_summary(summary: dict, out=None) -> None:
    out = sys.stdout if out is None else out
    if summary["angle_deg"] is not None:  # the paper's impact: its rebound measures
        rows = [
            ("law", summary["law"], ""),
            ("impact angle", summary["angle_deg"], "deg"),
            ("impact speed", summary["speed"], "m/s"),
            ("en", summary["en"], "normal restitution"),
            ("et", summary["et"], "tangential restitution"),
            ("x", summary["x"], "2 tan(theta)/(1+en)"),
            ("y1", summary["y1"], "normalised rebound surface velocity"),
            ("y2", summary["y2"], "normalised rebound spin"),
            ("contact duration", summary["contact_duration_s"], "s"),
            ("max overlap", summary["max_overlap_m"], "m"),
            ("peak normal force", summary["peak_normal_force_n"], "N"),
            ("peak tangential force", summary["peak_tangential_force_n"], "N"),
            ("energy ratio", summary["energy_ratio"], "final/initial kinetic+rotational"),
        ]
    else:  # a scene: what a DEM user checks first
        rows = [
            ("law", summary["law"], ""),
            ("particles", summary["particles"], ""),
            ("contacts at end", summary["contacts_at_end"], "touching pairs and particle-wall contacts"),
            ("kinetic energy", summary["kinetic_energy_j"], "J, at the end (translational + rotational)"),
            ("peak kinetic energy", summary["peak_kinetic_energy_j"], "J, largest sampled"),
            ("energy ratio", summary["energy_ratio"], "final/initial kinetic+rotational"),
        ]
        if summary["en"] is not None:  # two spheres: their collision's measures
            rows[2:2] = [("en", summary["en"], "normal restitution of the pair"),
                         ("et", summary["et"], "tangential restitution of the pair")]
        if summary["max_overlap_m"] is not None:
            rows.append(("max overlap", summary["max_overlap_m"], "m, the largest of every step"))
        else:  # the parallel loop records no peaks: samples at the run's checks
            rows += [("max overlap, sampled", summary["sampled_max_overlap_m"], "m, the deepest at the run's checks"),
                     ("max overlap / radius", summary["sampled_max_overlap_ratio"],
                      "sampled, the largest over a contact's smaller radius")]
        rows.append(("neighbour builds", summary["neighbour_builds"], "Verlet-list builds"))
    rows += [
        ("steps", summary["steps"], f"dt = {_format_value(summary['dt_s'])} s" + (
            f"; {summary['free_flight_steps']} of them free flight, solved in closed form"
            if summary.get("free_flight_steps") else "")),
        ("wall time", summary["wall_time_s"], "s"),
    ]
    width = max(len(name) for name, _, _ in rows)
    # the values' column as wide as its widest (a combination's name, hertz+tsuji+mindlin+epsd)
    values = [_format_value(value) for _, value, _ in rows]
    value_width = max(14, *(len(text) for text in values))
    for (name, _, note), text in zip(rows, values):
        print(f"  {name:<{width}}  {text:>{value_width}}  {note}", file=out)


def command_run(args) -> int:
    from minidem.engine import checkpoint, run_loop, simulation, warmup
    from minidem.files import OutputError
    from minidem.results.output import write_run_files
    from minidem.scene import scenario
    from minidem.studies import sweep

    data = scenario.read_toml(args.file)
    # with --set sweep.KEY=..., a file without [sweep] makes a sweep too (checked as one): a
    # single run ignored it, and an unknown key with it
    swept = sweep.has_sweep(scenario.apply_overrides(data, args.set or []))
    if getattr(args, "case", None) is not None:
        if not swept:
            raise scenario.ScenarioError(f"{args.file}: --case {args.case}: the scenario has no [sweep] table, so "
                                         "no cases: run it without --case")
        args = sweep.case_alone(args, data)  # the case's values as --set, its own directory
    elif swept:
        warmup.dismiss()  # a sweep's cases run in their own processes
        if args.resume and args.restart:
            raise scenario.ScenarioError(f"{args.file}: --resume and --restart contradict each other: a sweep "
                                         "resumes by default; --restart runs every case again")
        return sweep.command(args, data)
    for option, given in (("--scheduler", args.scheduler), ("--restart", args.restart), ("--workers", args.workers)):
        if given is not None and given is not False:
            warnings.warn(f"{option} ignored: " + (f"--case {args.case} runs one case alone (a single run)"
                                                   if getattr(args, "case", None) is not None
                                                   else f"{args.file} has no [sweep] table (a single run)"))
    # on a fresh install the scene's kernel compiles in a helper while the check of
    # overlapping spheres compiles the neighbour search here
    scene = scenario.load_scene(args.file, args.set, args.out, while_checking=functools.partial(
        warmup.kernel_beside_check, notify=None if args.quiet else _note))
    if args.resume:
        checkpoint.require_checkpoint(scene.source, scene.output_directory)
    directory = scenario.prepare_output_directory(scene.output_directory, scenario.output_origin(args.out, scene.raw), args.file)
    sim = simulation.Simulation(scene, notify=None if args.quiet else _note)
    policy = checkpoint.Policy(directory, scene.checkpoint_interval, scene.checkpoint_wall_interval)
    resume_from = checkpoint.load_for_resume(sim, directory) if args.resume else None
    if not args.quiet:
        print(f"minidem: {scene.source}: law '{sim.law.name}' ({sim.entry.packages}), "
              f"{scene.n_particles} particle(s), {_wall_count(scene.walls)} wall(s)")
        print(f"  time step {sim.dt:.4g} s ({sim.dt_reason})")
        chosen = scene.raw.get("run", {}).get("integrator", "auto") == "auto"
        print(f"  integrator {scene.integrator}" + (" (run.integrator = \"auto\")" if chosen else ""))
        if resume_from is not None:
            print(f"  resuming from {policy.path}: step {resume_from[1]['step']} "
                  f"(t = {resume_from[1]['time']:.6g} s) of {resume_from[1]['total_steps']}")
    # files a killed process left half-way through an atomic write (never under a final name)
    checkpoint.remove_stale_temporaries(directory)
    if not args.quiet and sim.start_time > 0.0:
        print(f"  analytic flight to the first touch: the steps start at t = {sim.start_time:.6g} s")
    frames = None
    if scene.vtk:
        from minidem.results.vtk import SimulationFrames

        frames = SimulationFrames(sim, directory)
    previous_sigterm = signal.signal(signal.SIGTERM, _terminate)
    started = time.time()
    with _progress_bar(scene, args.quiet, sim.dt) as progress:
        try:
            result = sim.run(progress=progress, on_frame=frames, checkpoints=policy, resume_from=resume_from)
        except (run_loop.RunFailure, OutputError):
            _say_set_aside(directory, started)
            raise
        except KeyboardInterrupt:
            if sim.interrupted_at is not None:
                time_s, path = sim.interrupted_at
                # the whole command, --set values and --out included: a resume must repeat them
                again = " ".join(shlex.quote(str(word)) for word in (
                    "minidem", "run", args.file, *(w for value in args.set for w in ("--set", value)),
                    *(("--out", args.out) if args.out is not None else ()), "--resume"))
                print(f"minidem: stopped at t = {time_s:.6g} s; checkpoint {path}: continue with `{again}`",
                      file=sys.stderr)
            else:  # while the kernel compiled or loaded: nothing computed that a checkpoint would keep
                print("minidem: stopped before the first step: " + (
                    f"the checkpoint {policy.path} is as it was" if resume_from is not None
                    else "no checkpoint (nothing was computed yet)"), file=sys.stderr)
            raise
        finally:
            signal.signal(signal.SIGTERM, previous_sigterm)
            if frames is not None:
                frames.close()
    try:
        summary = write_run_files(directory, result, wrote_series=frames is not None and frames.frames > 0)
    except OutputError:
        _say_set_aside(directory, started)
        raise
    if frames is not None:
        frames.succeeded()
    if args.quiet:  # --quiet keeps the warnings (docs/cli.md), on standard error
        for warning in summary["warnings"]:
            print(f"minidem: warning: {warning}", file=sys.stderr)
    else:
        print_summary(summary)
        for warning in summary["warnings"]:
            print(f"  warning: {warning}")
        print(f"  wrote {directory / 'summary.json'}, {directory / checkpoint.FINAL_STATE}"
              + (f", {directory / 'trace.csv'}" if result.trace is not None else "")
              + (f", {frames.pvd_path} ({frames.frames} frames)" if frames is not None else "")
              + (f", {frames.writer.contacts_pvd_path}" if frames is not None and scene.vtk_contacts else "")
              + (f", {frames.walls_path}" if frames is not None and frames.walls_path is not None else ""))
        # a resumed run timed only the steps after its checkpoint
        steps_here = result.steps - (resume_from[1]["step"] if resume_from is not None else 0)
        # flights flown in closed form cost next to nothing: no rate of steps then, which
        # would read as the compiled loop's (2.7e9 'steps/s' for the impact run on to 5 s)
        flown_here = result.flown_steps - (resume_from[1]["loop"].get("flown_steps", 0) if resume_from is not None
                                           else 0)
        rate = steps_here / result.wall_time if result.wall_time > 0 else float("inf")
        print(f"  {steps_here} steps in {result.wall_time:.3g} s: "
              + (f"{steps_here - flown_here} stepped, {flown_here} flown in closed form" if flown_here else
                 f"{rate:.4g} steps/s, {rate * scene.n_particles:.4g} particle-steps/s") + f" on {result.threads} thread(s)"
              + (f" (resumed at step {resume_from[1]['step']})" if resume_from is not None else ""))
    return EXIT_OK


def _wall_count(walls) -> int:
    """The walls a scenario gave: its [[walls]] tables (a box is one, a mesh is one, not
    its planes or triangles), and a plane of no table (the [impact] wall)."""
    import numpy as np

    tables = np.concatenate([walls.plane_table, walls.cylinder_table, walls.triangle_table])
    return len(set(tables[tables >= 0].tolist())) + int(np.count_nonzero(walls.plane_table < 0))


def _say_set_aside(directory: Path, started: float) -> None:
    """A failed run: an earlier run's results in its directory renamed (output.set_aside_earlier_results)."""
    from minidem.results.output import set_aside_earlier_results

    told = set_aside_earlier_results(directory, started)
    if told:
        print(f"minidem: {told}", file=sys.stderr)


def _path(text: str) -> Path:
    """A file or directory option: an empty one (``--out ""``, e.g. an unset shell
    variable) would be the working directory, which nobody asks for that way."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path: give a file or directory, e.g. out/run1")
    return Path(text)


def _particle_counts(text: str) -> tuple[int, ...]:
    """``--sizes``: comma-separated particle counts, each a whole number >= 2."""
    try:
        counts = tuple(int(part.replace("_", "")) for part in text.split(","))
    except ValueError:
        counts = ()
    if not counts or min(counts) < 2:
        raise argparse.ArgumentTypeError(f"'{text}': expected particle counts >= 2 separated by commas, "
                                         "e.g. 2000,20000,200000,1000000")
    return counts


def _run_steps(text: str) -> int:
    """``--steps``: a whole number of steps >= 1."""
    try:
        steps = int(text.replace("_", ""))
    except ValueError:
        steps = 0
    if steps < 1:
        raise argparse.ArgumentTypeError(f"'{text}': expected a whole number of steps >= 1, e.g. 400")
    return steps


def _variants(text: str) -> tuple[str, ...]:
    """``--variants``: the settle scene's start positions, comma-separated."""
    names = tuple(part.strip() for part in text.split(","))
    if not names or any(name not in ("lattice", "jitter") for name in names):
        raise argparse.ArgumentTypeError(f"'{text}': expected lattice, jitter or lattice,jitter")
    return names


def _note(text: str) -> None:
    """What a slow step of the set-up is doing (before the header: the time step needs it)."""
    print(f"minidem: {text} ...", file=sys.stderr, flush=True)


def _terminate(signum, frame):
    """SIGTERM (a job scheduler, `kill`) stops a run as Ctrl-C does: between two chunks
    of the compiled loop, with a checkpoint."""
    raise KeyboardInterrupt


class _progress_bar:
    """A tqdm bar (steps, simulated time, particles, contacts, ETA) that appears only
    once a run has taken more than two seconds; a no-op with --quiet."""

    def __init__(self, scene, quiet, dt):
        self.scene, self.quiet, self.dt, self.bar = scene, quiet, dt, None

    def __enter__(self):
        if self.quiet:
            return None
        return self

    def __call__(self, steps, total, contacts):
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="step", delay=2.0, dynamic_ncols=True, file=sys.stderr)
        # the postfix first: update() draws the bar, with the postfix it holds then
        self.bar.set_postfix_str(f"t={steps * self.dt:.4g} s, {self.scene.n_particles} particles, "
                                 f"{contacts} contacts", refresh=False)
        self.bar.update(steps - self.bar.n)

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.close()


def command_laws(args) -> int:
    from minidem.contact import laws

    registry = laws.registry()
    if args.json:
        payload = {
            "laws": [{
                "name": e.law.name, "plugin": e.plugin, "package": e.distribution, "version": e.version,
                "description": e.law.description, "aliases": list(e.law.aliases),
                "history_slots": e.law.history_size, "couples": bool(e.law.couples),
                "parameters": [{"name": p.name, "default": p.default, "unit": p.unit, "bounds": p.bounds_text(),
                                "required": p.required, "description": p.description} for p in e.law.parameters],
            } for e in registry.entries()],
            "presets": [{"name": p.name, "description": p.description, "parts": dict(p.parts),
                         "parameters": dict(p.parameters), "aliases": list(p.aliases)} for p in registry.presets()],
            "parts": [{
                "name": part.name, "kind": part.kind, "package": registry.part_origin(part.name)[1],
                "description": part.description, "energy": list(part.energy), "provides": list(part.provides),
                "requires": list(part.requires), "history_slots": part.history_size,
                "parameters": [{"name": p.name, "default": p.default, "unit": p.unit, "bounds": p.bounds_text(),
                                "required": p.required, "description": p.description} for p in part.parameters],
            } for part in registry.parts()],
            "broken": [vars(b) for b in registry.broken],
        }
        print(json.dumps(payload, indent=2))
        return EXIT_OK
    shown = [q for e in registry.entries() for q in e.law.parameters] + [
        q for kind in laws.KINDS for part in registry.parts(kind) for q in part.parameters]
    # one set of column widths for every table, from the longest name, unit and bounds shown
    widths = [max((len(text) for text in column), default=0) for column in
              zip(*((q.name, q.unit, q.bounds_text()) for q in shown))] or [0, 0, 0]

    def parameter_line(q, indent: str) -> str:
        default = "required" if q.required else ("derived" if q.default is None else f"{q.default:g}")
        return (f"{indent}- {q.name:<{widths[0]}} {default:>9} {q.unit:<{widths[1]}} {q.bounds_text():<{widths[2]}} "
                f"{q.description}")

    print("Laws (law = NAME):")
    for e in registry.entries():
        aliases = f" (aliases: {', '.join(e.law.aliases)})" if e.law.aliases else ""
        print(f"{e.law.name}{aliases}  [{e.distribution} {e.version}, plugin '{e.plugin}']")
        print(f"    {e.law.description}")
        for q in e.law.parameters:
            print(parameter_line(q, "    "))
        print(f"    history: {e.law.history_size} slot(s) per contact"
              + ("; returns a couple (couples=True: rolling or twisting resistance)" if e.law.couples else ""))
    for preset in registry.presets():
        print(f"{preset.name}  [preset: {' + '.join(preset.parts.values())}]")
        print(f"    {preset.description}")
        for name, value in preset.parameters.items():
            print(f"    - {name:<{widths[0]}} {value:>9g}")
    print("\nParts (combine one of each kind: [contact] normal = ..., damping = ..., tangential = ...):")
    for kind in laws.KINDS:
        print(f"{kind}:")
        for part in registry.parts(kind):
            plugin, dist, version = registry.part_origin(part.name)
            needs = f"; requires {', '.join(part.requires)}" if part.requires else ""
            gives = f"; provides {', '.join(part.provides)}" if part.provides else ""
            print(f"  {part.name}  [{dist} {version}, plugin '{plugin}'; energy: {', '.join(part.energy)}{gives}{needs}]")
            print(f"      {part.description}")
            for q in part.parameters:
                print(parameter_line(q, "      "))
    for b in registry.broken:
        print(f"BROKEN plugin '{b.plugin}'" + (f" {b.what} '{b.law}'" if b.law else "") + f": {b.reason}")
    return EXIT_OK


def command_docs(args) -> int:
    from minidem.scene import scenario

    text = scenario.reference_markdown()
    if args.write:
        from minidem.files import OutputError, atomic_write

        try:
            atomic_write(args.write, text)
        except OutputError as exc:  # not a run: the main handler's "run failed" would mislead
            print(f"minidem: docs: {exc}", file=sys.stderr)
            return EXIT_FAILURE
    else:
        print(text, end="")  # the bytes --write writes: `minidem docs > FILE` is the same file
    return EXIT_OK


def command_bench(args) -> int:
    from minidem.studies import bench

    return bench.command(args)


def command_verify(args) -> int:
    from minidem.studies import verify

    battery = verify.Battery(args.law, args.set)
    # named after the law as run: `hm --set contact.rolling=epsd` checks hm+epsd
    out = args.out or Path("out") / f"verify-{battery.law.name}"
    checks = verify.run_checks(battery, out, progress=lambda text: print(
        f"minidem: verify {battery.law.name}: {text}", file=sys.stderr, flush=True))
    # the battery as run: its --set values change what it checks
    print(" ".join(["minidem verify", args.law, *(f"--set {value}" for value in args.set or ())]))
    print(verify.format_table(checks))
    print(f"  report: {', '.join(str(path) for path in verify.report_files(out, checks))}")
    return EXIT_FAILURE if any(c.passed is False for c in checks) else EXIT_OK


def command_render(args) -> int:
    from minidem.results import render

    try:
        written = render.render(args.directory, args.array, args.out, args.animation, args.frame, args.fps,
                                notify=lambda text: print(f"minidem: {text}", file=sys.stderr, flush=True))
    except render.NoRenderWindow as exc:
        print(f"minidem: render failed: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    except render.RenderError as exc:
        print(f"minidem: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    for path in written:
        print(f"  wrote {path}")
    return EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    from minidem import __version__

    parser = argparse.ArgumentParser(prog="minidem", description="Soft-sphere DEM with pluggable contact laws.")
    parser.add_argument("--version", action="version", version=f"minidem {__version__}")
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks on errors")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a scenario file")
    run.add_argument("file", type=Path, help="scenario TOML file")
    run.add_argument("--out", type=_path, default=None, help="output directory (overrides output.directory)")
    run.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scenario value, dotted keys (repeatable): --set impact.angle_deg=30")
    run.add_argument("--quiet", action="store_true",
                     help="print only errors and 'minidem: warning:' messages (to standard error): no header, "
                     "summary or progress bar; the result's warnings stay in summary.json (sweep.csv for a sweep)")
    run.add_argument("--workers", type=int, default=None, metavar="N",
                     help="local worker processes for a [sweep] scenario (default: sweep.workers; 0: one per CPU)")
    run.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run a [sweep] scenario's cases on the workers of this Dask scheduler (tcp://HOST:PORT; "
                     "default: $DASK_SCHEDULER_ADDRESS if set; 'local': local processes); needs minidem[dask]")
    run.add_argument("--restart", action="store_true",
                     help="discard the journal of an earlier sweep in the output directory and run every case "
                     "(default: resume it, running only the missing cases)")
    run.add_argument("--resume", action="store_true",
                     help="continue from OUT/checkpoint.npz (same file, --set and --out): the result is bit for "
                          "bit that of an uninterrupted run")
    run.add_argument("--case", type=int, default=None, metavar="N",
                     help="run case N of a [sweep] scenario alone, as a single run with its own files (VTK series "
                          "included when output.vtk asks for it) in OUT/case_NNN (default OUT: the sweep's "
                          "directory); N as sweep.csv's case column")
    run.set_defaults(handler=command_run)

    show = sub.add_parser("laws", help="list installed contact laws and broken plugins")
    show.add_argument("--json", action="store_true", help="machine-readable output")
    show.set_defaults(handler=command_laws)

    check = sub.add_parser("verify", help="run the paper's verification battery on a contact law")
    check.add_argument("law", help="law name (see `minidem laws`)")
    check.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                       help="override the battery's scenario, e.g. --set contact.my_stiffness=1e8")
    check.add_argument("--out", type=_path, default=None, help="report directory (default out/verify-LAW)")
    check.set_defaults(handler=command_verify)

    docs = sub.add_parser("docs", help="print the scenario-file reference (markdown)")
    docs.add_argument("--write", type=_path, help="write it to this file instead")
    docs.set_defaults(handler=command_docs)

    draw = sub.add_parser("render", help="draw a run's particle series (OUT/particles.pvd) to a PNG and a GIF")
    draw.add_argument("directory", type=Path, metavar="OUT", help="output directory of a `minidem run` with VTK output")
    draw.add_argument("--array", default="velocity",
                      help="particle array to colour by (a vector by its magnitude): radius, velocity, "
                      "angular_velocity, force, particle_id, material_id (default velocity)")
    draw.add_argument("--out", type=_path, default=None, metavar="FILE.png", help="the picture (default OUT/render.png)")
    draw.add_argument("--frame", type=int, default=-1, help="frame of the series drawn to the PNG (default -1: the last)")
    draw.add_argument("--animation", default=None, metavar="FILE.gif",
                      help="the series as a GIF (default OUT/render.gif when it has more than one frame; '' for none)")
    draw.add_argument("--fps", type=float, default=10.0, help="frames per second of the GIF (default 10)")
    draw.set_defaults(handler=command_render)

    bench = sub.add_parser("bench", help="measure error against the reference solution and run time; "
                           "writes docs/benchmarks.md and docs/figures/")
    bench.add_argument("--quick", action="store_true", help="a small subset (CI smoke run)")
    bench.add_argument("--only", action="append", choices=("single-impact", "work-precision", "model-only",
                                                             "sweep-timing", "multi-particle", "multi-particle-scale",
                                                             "memory-order", "compile"),
                       help="run only this section (repeatable); multi-particle, multi-particle-scale (settle.md's "
                            "200,000 and 1,000,000 spheres), memory-order (the cost of a particle-step against N with "
                            "the particles given in a random order) and compile (the compile time of each shipped law "
                            "and combination) run only when named")
    bench.add_argument("--sizes", type=_particle_counts, default=None, metavar="N,N,...",
                       help="the particle counts of the settle scene: multi-particle (default 2000,20000), "
                            "multi-particle-scale (default 200000,1000000: at most 2e9 particle-steps a run, 2,000 "
                            "steps at 1,000,000; hours with LIGGGHTS), memory-order (default "
                            "20000,200000,1000000)")
    bench.add_argument("--variants", type=_variants, default=None, metavar="V,V",
                       help="multi-particle sections: lattice, jitter or both (default lattice,jitter)")
    bench.add_argument("--steps", type=_run_steps, default=None, metavar="STEPS",
                       help="multi-particle sections: steps of every run (default settle.md's: 10,000, fewer "
                            "at scale; memory-order: 400); the table says how many")
    bench.add_argument("--docs", type=_path, default=None, help="docs directory to write (default: the project's)")
    bench.set_defaults(handler=command_bench)
    parser.commands = sub.choices  # name -> the command's parser (main: its usage on an unknown option)
    return parser


class _PipeClosedSink:
    """sys.stdout for the console command: when the reader of a pipe goes away
    (`minidem run ... | head`), the rest of the output is dropped and the run carries on
    to write its result files, instead of dying with BrokenPipeError half-way."""

    def __init__(self, stream):
        self.stream, self.pipe_closed = stream, False

    def write(self, text: str) -> int:
        if not self.pipe_closed:
            try:
                return self.stream.write(text)
            except BrokenPipeError:
                self._close()
        return len(text)

    def flush(self) -> None:
        if not self.pipe_closed:
            try:
                self.stream.flush()
            except BrokenPipeError:
                self._close()

    def _close(self) -> None:
        self.pipe_closed = True
        # what is still buffered would fail again when Python exits: send it nowhere
        os.dup2(os.open(os.devnull, os.O_WRONLY), self.stream.fileno())

    def __getattr__(self, name):
        return getattr(self.stream, name)


def main(argv=None) -> int:
    if argv is None and not isinstance(sys.stdout, _PipeClosedSink):  # the console command itself
        sys.stdout = _PipeClosedSink(sys.stdout)
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # the command's own usage, not the top level's (exit 2)
        parser.commands[args.command].error(f"unrecognized arguments: {' '.join(unknown)}")
    from minidem.engine import warmup

    try:
        if args.handler is command_run:
            # on a fresh install, the helper that compiles beside the run starts before the
            # engine is imported here (minidem.engine.warmup.prestart)
            warmup.prestart()
        from minidem.contact.laws import LawError
        from minidem.files import OutputError
        from minidem.scene.scenario import ScenarioError
        from minidem.engine.run_loop import RunFailure
    except KeyboardInterrupt:  # a Ctrl-C while numba and the engine are imported: no traceback
        warmup.dismiss()
        print("minidem: interrupted", file=sys.stderr)
        return 130

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = lambda message, *a, **k: print(f"minidem: warning: {message}", file=sys.stderr)
        try:
            return args.handler(args)
        except (ScenarioError, LawError) as exc:
            if args.debug:  # the traceback, and the same exit code as without it
                traceback.print_exc()
            print(f"minidem: error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        except (RunFailure, OutputError) as exc:
            if args.debug:
                traceback.print_exc()
            print(f"minidem: run failed: {exc}", file=sys.stderr)
            return EXIT_FAILURE
        except KeyboardInterrupt:
            print("minidem: interrupted", file=sys.stderr)
            return 130
        except Exception as exc:  # noqa: BLE001 - never a bare traceback without --debug
            from minidem.engine.run_loop import interrupted

            if interrupted(exc):  # a Ctrl-C that surfaced as another error (numba's SystemError)
                print("minidem: interrupted", file=sys.stderr)
                return 130
            if args.debug:
                traceback.print_exc()
                print(f"minidem: internal error: {type(exc).__name__}: {exc}", file=sys.stderr)
            else:
                print(f"minidem: internal error: {type(exc).__name__}: {exc} (rerun with --debug for the traceback)",
                      file=sys.stderr)
            return EXIT_FAILURE
        finally:
            if args.handler is command_run:  # a prestarted helper no job was given to
                warmup.dismiss()


def console() -> None:
    """The ``minidem`` command: :func:`main`, then the process ends without tearing the
    interpreter down.

    Why: after a run whose kernel was just compiled, Python's own exit (collecting the
    cycles numba's compiler leaves, then freeing every module and the objects they hold)
    took 0.3-0.6 s of a first run of scenarios/oblique.toml, and 0.1-0.2 s of every later
    run (2-core AMD EPYC): memory the operating system takes back at once anyway. What an
    exit must do is still done first: the ``atexit`` handlers (helpers and pools of worker
    processes stopped, logging flushed) and the standard streams flushed. Every file
    minidem writes is closed before ``main`` returns. A thread still running (not a
    daemon) is waited for, as Python would: the exit is then Python's own.

    Before numpy is imported, its BLAS is held to one thread unless the user chose
    otherwise: minidem's work is in numba's loops and its own threads, and OpenBLAS' pool
    (a thread a core) spins for a while after numpy's import and after any call, on the
    core that the compile helper or the second run thread needs (2.5 % of a first run's
    CPU on a 2-core machine). The helper and sweep workers inherit it."""
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    try:
        code = main()
    except KeyboardInterrupt:  # a Ctrl-C before main's own handlers (parsing the options, the first imports)
        print("minidem: interrupted", file=sys.stderr)
        code = 130
    import atexit
    import threading

    if any(thread.is_alive() and not thread.daemon for thread in threading.enumerate()
           if thread is not threading.main_thread()):
        sys.exit(code)
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a reader gone (stdout is handled by _PipeClosedSink) or a closed stream
            pass
    if code is not None and not isinstance(code, int):
        sys.exit(code)  # what sys.exit makes of anything else
    os._exit(code or EXIT_OK)


if __name__ == "__main__":
    console()
