"""One run of a :class:`minidem.engine.simulation.Simulation`: the time loop in chunks
of compiled steps (:class:`RunLoop`), the thread count chosen chunk by chunk
(:class:`LoopThreads`), what a run returns (:class:`RunResult`) or raises
(:class:`RunFailure`), and how it holds Ctrl-C while it copies its state.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import signal
import time as wallclock
import warnings
from pathlib import Path

import numba
import numpy as np

from minidem import __version__, codecache
from minidem.contact import declarations, laws
from minidem.engine import blocks, integrate, kernel, warmup
from minidem.engine.law_signature import law_error
from minidem.engine.notices import notice_if_slow
from minidem.engine.state import LISTS, State, StateCopy, full_arrays
from minidem.errors import MinidemError
from minidem.scene.scenario import Scene, ScenarioError

# particle-steps between two copies of the last good state (small scenes: a copy has a
# fixed cost besides the arrays), and at least SNAPSHOT_STEPS steps: a copy costs a step
# or less at any N (bench/settle.toml, N = 2000: 0.13 ms a copy, 0.5 ms a step; N = 20,000:
# 2.2 ms, 1.5-3 ms), so about 1 % of the run
SNAPSHOT_PARTICLE_STEPS = 200_000
SNAPSHOT_STEPS = 100
# and at least this many times the last copy's duration of wall time apart: a copy is
# serial, so at 1 % of a one-thread run it was 2 % of a two-thread one (settle,
# N = 20,000, lattice: 100 steps are 88 ms on two threads, a copy ~2 ms); the copies'
# spacing changes no result (a failure replays from the copy to the last checked step)
SNAPSHOT_COST_RATIO = 200
# Chunks of the compiled loop end at every multiple of a step count fixed by the scene
# (and earlier for a list rebuild, a frame, a checkpoint or a probe of the thread count):
# the spacing of the energy samples (at least 200 a run) or CHECK_PARTICLE_STEPS
# particle-steps, whichever is fewer, but at least CHECK_STEPS steps. Between chunks come
# the blow-up guard's checks (~9 ns a particle of work, shared between a threaded run's
# threads), the thread blocks of the next call (two threads: ~8 ns a particle of work,
# mostly shared; 16-18 ns serial before the first partners were kept per list, see
# minidem.engine.blocks), Python's own work (~0.1 ms) and an unfused drift at
# each end of a call: a small scene is checked at every sample as before, and from
# ~20,000 particles on a chunk is CHECK_STEPS steps at least, so that work costs ~2 % of
# the cheapest steps (~40 ns a particle-step, settle's falling phase; at 20 steps it was
# ~6 % of a two-thread run at N = 1,000,000, whose kernel calls alone ran 1.95x one
# thread's); at N = 1,000,000 that is a chunk of
# ~2 s on one thread, falling, ~10 s in a dense pile (how long a Ctrl-C waits). A grid of
# steps, not of wall time, so the guard's record (the largest work of gravity, taken on
# the grid and at list rebuilds) is the same in a resumed run as in an uninterrupted one.
CHECK_STEPS = 50
CHECK_PARTICLE_STEPS = 1_000_000

class LoopThreads:
    """How many threads run the particle loops, chosen chunk by chunk between one and
    ``most`` (run.threads). Only the speed depends on it: the results are the same bits
    on any count.

    Two threads fork and join twice a step. On a machine shared with other jobs a thread
    descheduled at a join stalls the other, and a run on two threads was up to several
    times slower than on one (docs/multi-particle.md, "Threads"). So the run times its
    chunks (seconds per step) and now and then runs one chunk on the other count, keeping
    the faster. The first probe follows the first chunk: on a loaded machine two threads
    can be thirty times slower than one (6,000 particles: 16 ms a step against 0.5 ms),
    and waiting four chunks to find out cost such a run a quarter of its time. After a switch
    the other count is tried again ``PROBE_AGAIN`` chunks later; a probe that loses
    doubles the wait before the next one, up to ``PROBE_MAX`` chunks (see
    CHECK_PARTICLE_STEPS), so losing probes cost a few per cent.
    """

    PROBE_FIRST, PROBE_AGAIN, PROBE_MAX = 1, 4, 64
    # chunks shorter than this (cut short by a list rebuild) are too noisy to compare
    MIN_STEPS = 10
    # a probe runs this fraction of a chunk (at least 2 MIN_STEPS): a probe that loses
    # costs a quarter of a chunk on the slower count (settle, N = 20,000, lattice, 10,000
    # steps: 1.2 % of the steps on one thread instead of 3 %; run.threads = 2 stays ~2 %
    # behind two threads pinned, 8.77 s against 8.56 s, 2026-11-22 13:40 UTC)
    PROBE_FRACTION = 4

    def __init__(self, most: int):
        self.most = most
        self.current = most
        self.wait = self.PROBE_FIRST
        self.since_probe = 0
        self.seconds_per_step: dict[int, float] = {}
        self.steps: dict[int, int] = {}  # steps run on each count

    def choose(self) -> int:
        if self.most > 1 and self.since_probe >= self.wait:
            return 1 if self.current == self.most else self.most
        return self.current

    def record(self, threads: int, steps: int, seconds: float) -> None:
        self.steps[threads] = self.steps.get(threads, 0) + steps
        if self.most == 1 or steps < self.MIN_STEPS:
            return
        self.seconds_per_step[threads] = seconds / steps
        if threads == self.current:
            self.since_probe += 1
            return
        self.since_probe = 0  # a probe of the other count: keep the faster
        if seconds / steps < self.seconds_per_step.get(self.current, math.inf):
            self.current, self.wait = threads, self.PROBE_AGAIN
        else:
            self.wait = min(max(2 * self.wait, self.PROBE_AGAIN), self.PROBE_MAX)

    def most_used(self) -> int:
        return max(self.steps, key=self.steps.get) if self.steps else self.current


class RunFailure(MinidemError):
    """The run started but could not finish: the CLI exits with code 1."""


@dataclasses.dataclass
class RunResult:
    scene: Scene
    law: laws.ContactLaw
    constants: dict
    position: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    initial_velocity: np.ndarray
    initial_angular_velocity: np.ndarray
    steps: int
    dt: float
    dt_reason: str
    time: float
    separated: bool
    first_contact_time: float
    last_separation_time: float
    max_overlap: float
    peak_normal_force: float
    peak_tangential_force: float
    wall_time: float
    trace: np.ndarray | None
    force: np.ndarray | None = None
    torque: np.ndarray | None = None
    contacts: int = 0  # touching pairs and wall contacts at the end
    neighbour_builds: int = 0
    threads: int = 1  # threads that ran the particle loops for most of the steps (see LoopThreads)
    thread_steps: dict | None = None  # {threads: steps run on that many}
    energy: np.ndarray | None = None  # rows (time s, translational + rotational kinetic energy J)
    # False when the parallel loop ran: it records first touch (to the step) but not the
    # peaks and the separation, which would need a race between threads
    contact_statistics: bool = True
    # the largest work gravity did on the particles since t = 0 (J), at the run's checks
    gravity_work_max: float = 0.0
    # the most kinetic energy the contacts can supply at once (J): adhesion's bound per
    # contact times the most contacts (Simulation._prepare_reach); 0 for passive laws
    supply_budget: float = 0.0
    # at the run's checks: the deepest overlap (m) and the largest overlap over a contact's
    # smaller radius, samples where max_overlap (tracked runs only) is every step's
    sampled_max_overlap: float = 0.0
    sampled_max_overlap_ratio: float = 0.0
    # of ``steps``, those of free flight solved in closed form (run.integrator = "analytic_flight")
    flown_steps: int = 0

class RunLoop:
    """One run of a :class:`Simulation`: the time loop in chunks of compiled steps, with
    its schedule (energy samples, VTK frames, checkpoints, copies of the last good
    state), the checks between chunks, and what a failure or an interrupt leaves behind.

    The schedule is a function of the step number alone (never of wall time or of where
    a previous process stopped), so a resumed run samples, writes frames and checkpoints
    exactly where an uninterrupted one does."""

    def __init__(self, sim, chunk_steps, progress, on_frame, threads, policy, resume_from):
        from minidem.engine import blowup, checkpoint

        self.sim, self.kernel = sim, sim.kernel
        sim.scene = sim.start_scene  # a Simulation run again starts from its start order
        self.blowup, self.checkpoint = blowup, checkpoint
        self.chunk_steps, self.progress, self.on_frame, self.policy = chunk_steps, progress, on_frame, policy
        scene = self.scene
        self.state = sim.state = State(sim)
        probe_wall = scene.impact.wall if scene.impact is not None else (0 if scene.wall_point.shape[0] else -1)
        self.probe = np.zeros(8)
        self.stats = np.array([-1.0, -1.0, 0.0, 0.0, 0.0])
        self.status = np.zeros(4, dtype=np.int64)
        self.tracking = (probe_wall, self.probe, self.stats, self.status)
        self.stop_at_separation = scene.stop == "separation"
        end_time = sim.end_time
        if not math.isfinite(end_time):
            raise ScenarioError(f"{scene.source}: run.end_time is needed: the scene has no contact to stop at")
        self.start_time = sim.start_time  # > 0 after an analytic flight to first touch
        self.total_steps = max(0, int(math.ceil((end_time - self.start_time) / sim.dt - 1e-9)))
        self.half_skin_squared = (0.5 * sim.skin) ** 2
        self.no_trace = np.zeros((0, len(kernel.TRACE_COLUMNS)))
        self.guard = blowup.Guard(sim)
        self.frame_interval = sim.frame_interval(end_time)
        self.frames_on = on_frame is not None and bool(self.frame_interval)
        self.saves_series = self.frames_on and hasattr(on_frame, "checkpoint_state")
        # Kinetic energy: at least 200 samples a run (taken by the kernel, every
        # sample_steps), and at every frame and the end
        self.sample_steps = max(1, int(math.ceil(end_time / 200.0 / sim.dt - 1e-9)))
        self.particle_energy = np.zeros(scene.n_particles)
        self.energy_blocks = np.zeros(integrate.energy_blocks.py_func(scene.n_particles))  # no compile for a count
        self.no_samples = np.zeros(0)
        self.checkpoint_steps = (max(1, int(round(policy.interval / sim.dt)))
                                 if policy is not None and policy.interval else None)
        # The last good state (restored and written on a blow-up, and the checkpoint of a
        # Ctrl-C) is copied after a check has passed, at most every snapshot_steps, so
        # that copying it costs under ~1 % of the steps in between whatever the scene size.
        # (with particle-steps alone, N = 20,000 copied every 10 steps, i.e. every chunk:
        # 0.45 s of a 7.4 s run, jitter, 4,000 steps, two threads)
        self.snapshot_steps = max(SNAPSHOT_STEPS, SNAPSHOT_PARTICLE_STEPS // max(1, scene.n_particles))
        self.check_steps = max(1, min(chunk_steps, max(CHECK_STEPS, min(
            self.sample_steps, CHECK_PARTICLE_STEPS // max(1, scene.n_particles)))))
        # After an analytic flight the steps start at first touch: the flight's frames
        # (t = 0, interval, ... before the touch) are written from the closed form, and
        # the stepped frames follow every interval from the touch.
        self.flight_frames = (int(math.ceil(self.start_time / self.frame_interval - 1e-9))
                              if self.frames_on and self.start_time > 0.0 else 0)
        self.loop_threads = LoopThreads(threads)
        self.block_timing = blocks.BlockTiming()
        # loop: the run loop's own state, saved with the arrays in every checkpoint
        # deepest_overlap: the deepest overlap (m) and the largest over a contact's smaller
        # radius at the checks on the grid (State.deepest_contact)
        self.loop = {"steps": 0, "frames": 0, "last_frame_step": -1, "gravity_work_max": 0.0,
                     "deepest_overlap": [0.0, 0.0], "flown_steps": 0, "flight": None}
        # every free flight of the one sphere among planes solved in closed form (fly), not
        # only the one before the first touch; a trace, which has a row a step, is stepped
        self.flies = scene.integrator == "analytic_flight" and not scene.trace
        if self.flies:
            # the overlap above which the sphere's contact with each plane lives: 0, or
            # minus the reach of a law acting beyond touch for that pair of materials
            rows = sim.pair_row[scene.particle_material[0], scene.wall_material]
            self.plane_lives_above = (-sim.constants[rows, -1] if sim.law.reach is not None
                                      else np.zeros(rows.shape[0]))
        self.energy, self.trace_chunks = [], []
        self.resume_from, self.resumed = resume_from, resume_from is not None
        # the last good state's file (opened at its first copy, closed when the run ends),
        # beside the run's other files (its disk), else in the system's temporary directory
        directory = policy.directory if policy is not None else None
        self.good_copy = StateCopy(directory if directory and Path(directory).is_dir() else None)

    @property
    def scene(self) -> Scene:
        """The scene in the order its particles are stored now (Simulation.use_order)."""
        return self.sim.scene

    # -- the compiled steps ------------------------------------------------------
    def frame_step(self, index):
        """The step of frame ``index``: the first at or after its time, as the run's last
        step is the first at or after run.end_time (rounded to the nearest, a frame due at
        end_time fell one step before the end and the final state made a second frame,
        a step later)."""
        return int(math.ceil((index - self.flight_frames) * self.frame_interval / self.sim.dt - 1e-9))

    def call(self, start_step, n_steps, completing, trace, threads=None, dt=None, stop_at_separation=None,
             sampled=False, store_reactions=True):
        """``n_steps`` compiled steps from ``start_step``; returns (steps taken, whether the
        neighbour list must be rebuilt first). ``sampled``: the kinetic-energy samples of
        the steps taken are added to the run's (a replay after a failure takes none).
        ``store_reactions``: the pairs' contact forces of the state the call ends in are
        stored for a reader (kernel.advance); False where nothing reads that state."""
        threads = threads or self.loop_threads.current
        samples = (np.empty((start_step + n_steps) // self.sample_steps - start_step // self.sample_steps)
                   if sampled else self.no_samples)
        # every parallel loop of the chunk (the opening kick_drift too) on that many; a
        # serial kernel has none, and its list builds' count is set by Simulation.run
        if self.sim.parallel:
            numba.set_num_threads(threads)
        taken, needs_rebuild = self.kernel.advance(*self.arguments(start_step, n_steps, completing, trace, threads,
                                                                   dt, stop_at_separation, samples=samples,
                                                                   store_reactions=store_reactions))
        if sampled:
            first = start_step // self.sample_steps + 1
            # a fault returns after its step's forces, before that step's sample
            last_complete = start_step + taken - (1 if self.status[0] != kernel.OK else 0)
            for k in range(last_complete // self.sample_steps - first + 1):
                self.energy.append((self.start_time + (first + k) * self.sample_steps * self.sim.dt,
                                    float(samples[k])))
        return taken, needs_rebuild

    def arguments(self, start_step, n_steps, completing, trace, threads, dt=None, stop_at_separation=None,
                  one_block=False, samples=None, store_reactions=True):
        """The arguments of the kernel's ``advance`` (``one_block``: the blocks of one
        thread, whatever ``threads`` says: for their types alone; ``samples``: where the
        kinetic-energy samples go, None for none)."""
        state, sim = self.state, self.sim
        # a serial kernel runs its particle loops on one thread, whatever it is told
        bounds, first_partner, block_cycles = blocks.blocks(threads if sim.threaded and not one_block else 1,
                                                            state.planes, state.pairs, state.first_partner,
                                                            self.block_timing)
        # the contact kinds the kernel has no loops for go as empty tuples (kernel.advance)
        cylinders, meshes, pairs = (group if getattr(self.kernel, flag, True) else () for group, flag in
                                    ((state.cylinders, "CYLINDERS"), (state.meshes, "MESHES"), (state.pairs, "PAIRS")))
        return (state.particles, state.law, state.planes, cylinders, meshes, pairs,
                self.scene.gravity, state.position_at_build, self.half_skin_squared, sim.dt if dt is None else dt,
                self.start_time, start_step, n_steps, completing,
                self.stop_at_separation if stop_at_separation is None else stop_at_separation, store_reactions, trace,
                self.tracking, threads, bounds, first_partner, block_cycles,
                (self.sample_steps if samples is not None else 0, state.inertia,
                 self.no_samples if samples is None else samples, self.particle_energy, self.energy_blocks))

    def compile_kernel(self):
        """Compile (or load from the cache) the kernel's ``advance`` for the types of its
        arguments, before the neighbour lists exist (their arrays' types do not change
        when they are built): the helper (``minidem.engine.warmup``) meanwhile compiles
        the neighbour search the first list needs."""
        advance = self.kernel.advance
        if hasattr(advance, "compile"):  # a test may put a plain function there
            args = self.arguments(0, 1, True, self.no_trace, self.loop_threads.current, dt=0.0,
                                  stop_at_separation=False, one_block=True)
            advance.compile(tuple(advance.typeof_pyval(arg) for arg in args))

    def start(self):
        """The state at the first step: fresh (initial forces) or the checkpoint resumed."""
        sim, state, loop = self.sim, self.state, self.loop
        if self.resume_from is not None:
            arrays, meta = self.resume_from
            sim.use_order(state, arrays.get("particle_id"))  # rows in the order they were stored
            state.restore(arrays)
            self.probe[:], self.stats[:], self.status[:] = arrays["probe"], arrays["stats"], arrays["status"]
            saved = dict(meta["loop"])
            # a checkpoint written before deepest_overlap was kept: the samples start afresh
            saved.setdefault("deepest_overlap", [0.0, 0.0])
            saved.setdefault("flown_steps", 0)  # and before later flights were solved in closed form
            saved.setdefault("flight", None)
            loop.update({key: saved[key] for key in loop})
            self.energy = [(float(t), float(e)) for t, e in arrays["energy"]]
            if self.scene.trace and arrays["trace"].shape[0]:
                self.trace_chunks.append(arrays["trace"])
            if self.saves_series and meta["frames_series"] is None:
                # written by a run that wrote no frames (Simulation.run without on_frame):
                # the series starts at the resumed step, its frames due from there on
                loop["frames"] = next(index for index in range(loop["frames"], 1 << 62)
                                      if self.frame_step(index) >= loop["steps"])
                self.on_frame.restore({"particles": [], "contacts": []}, 0)
                warnings.warn(f"the checkpoint was written by a run that wrote no VTK frames: the series starts at "
                              f"t = {self.start_time + loop['steps'] * self.sim.dt:.6g} s, where the run resumes")
            elif self.saves_series:
                self.on_frame.restore(meta["frames_series"], loop["frames"])
            # restored: the file's arrays (every row of every history, the lists) are
            # released, not held beside the live state for the whole run (the caller keeps
            # the meta)
            arrays.clear()
            self.resume_from = None
        meshes = state.meshes[0].shape[0] > 0
        # on a fresh install the engine's shared functions compile in a helper process
        # beside the kernel (nothing is started when they are cached); or, when a helper
        # is compiling this scene's kernel already (started by `minidem run` beside the
        # scene's check), this process compiles them meanwhile
        kernel_helper = warmup.kernel_helper(sim.input_scene)  # started for the scene as read
        helper = warmup.start(sim.pairs, meshes, sim.law) if kernel_helper is None else kernel_helper
        try:
            # the one compilation of this kernel, reported against the law that caused it; a
            # user waiting for it is told what it is
            def compiling():
                return notice_if_slow(sim.notify, f"compiling the kernel of law '{sim.law.name}' for this scene "
                                       f"shape; it is cached in {codecache.cache_directory()} for later runs")

            if kernel_helper is not None:
                # the wait for the helper compiling the kernel: announced already by the
                # check's notice when that took 2 s (one line for one compilation)
                with contextlib.nullcontext() if kernel_helper.announced else compiling():
                    warmup.compile_shared(sim.pairs, meshes)
                    kernel_helper.wait()
            # loaded from the cache when a helper compiled it; compiled here (and announced
            # after 2 s) when none did, or it failed
            with compiling():
                with helper.law_compiled(declarations.called_force(sim.law)):
                    self.compile_kernel()
                sim.check_history_bounds()  # a plugin's law, once per kernel
                helper.wait()
                if not self.resumed and (sim.pairs or meshes):
                    sim.rebuild(state)
                self.first_call()
        except (numba.core.errors.NumbaError, ValueError, TypeError) as exc:
            # numba's own errors in the compile; and the bare ValueError or TypeError of
            # some return values, in the compile or at the first call (a list of three
            # where the kernel unpacks four): put to the force compiled alone, re-raised
            # as they are when it is not at fault
            error = law_error(sim.law, sim.entry, exc)
            if error is exc:
                raise
            raise error from exc
        finally:
            # a helper still running (the run failed or was interrupted while it compiled)
            # is ended and reaped here: left to the interpreter's exit, a second Ctrl-C
            # could land in its Popen.__del__ and print a traceback. Held: the second of two
            # quick Ctrl-C landed in this wait itself, and the helper's pipe was left to the
            # garbage collector ('warning: unclosed file')
            with _interrupts_deferred():
                helper.stop()
        if not self.resumed:
            self.energy.append((self.start_time, state.kinetic_energy(state.inertia)))
            if self.frames_on:
                if self.flight_frames:
                    sim._write_flight_frames(state, self.flight_frames, self.frame_interval, self.on_frame)
                self.on_frame(self.start_time, state)
                loop["frames"], loop["last_frame_step"] = self.flight_frames + 1, 0
        self.fingerprint = self.checkpoint.fingerprint(sim) if self.policy is not None else None
        self.good = self.snapshot()
        # the run loop, and the energy samples and trace chunks kept, at the end of the last
        # chunk that passed the checks
        self.mark_checked()

    def first_call(self):
        """The first compiled call: the initial forces, or the resumed state checked."""
        if not self.resumed:
            # zero-length step: initial forces (dt = 0, so no displacement increments)
            # and the closing kick (of zero), no drift; advance with dt = 0 and the
            # step's drift marked done, since calling compute_forces from Python
            # would compile it a second time
            self.call(0, 1, True, self.no_trace, dt=0.0, stop_at_separation=False)
        else:
            self.call(self.loop["steps"], 0, False, self.no_trace)  # changes nothing: the resumed state is untouched
        # the guard's compiled check too: wall_time is the loop's alone
        self.guard.check(self.state, self.start_time, 0.0)

    # -- the last good state, checkpoints and failures ---------------------------
    def mark_checked(self):
        self.checked, self.checked_counts = dict(self.loop), (len(self.energy), len(self.trace_chunks))

    def snapshot(self, reuse=None, live=False):
        """The state now, for checkpoints and as the last good state: a copy in the run's
        one file (:class:`StateCopy`, overwritten: one copy of the state, never two), or
        with ``live`` the state's own arrays, not copied (valid until the kernel runs
        again). ``reuse``: the snapshot whose file this overwrites, updated in place, so
        that its bookkeeping follows the file also when an interrupt held during the copy
        is raised before this returns. The arrays and the loop's bookkeeping are recorded
        together with SIGINT/SIGTERM held, so an interrupt never finds them from two
        different steps."""
        with _interrupts_deferred():
            snap = {} if reuse is None else reuse
            if live:
                snap["arrays"] = self.state.live_arrays()
            else:
                self.good_copy.write(self.state.capture_items)
                snap["arrays"] = self.good_copy
            snap.update(tracking=(self.probe.copy(), self.stats.copy(), self.status.copy()), loop=dict(self.loop),
                        energy=len(self.energy), trace=len(self.trace_chunks))
        return snap

    def write_state(self, name, snap, kind):
        sim = self.sim
        captured = snapshot_arrays(snap)
        arrays = full_arrays(captured)  # the files hold every row
        if not all(listed in arrays for listed in LISTS):  # and the lists (a capture holds none)
            arrays.update(self.state.lists_of(captured))
        del captured
        arrays["probe"], arrays["stats"], arrays["status"] = snap["tracking"]
        arrays["energy"] = np.array(self.energy[:snap["energy"]], dtype=np.float64).reshape(-1, 2)
        arrays["trace"] = np.concatenate(self.trace_chunks[:snap["trace"]]) if snap["trace"] else self.no_trace
        series = self.on_frame.checkpoint_state() if self.saves_series else None
        if series is not None:  # only the frames written up to the snapshot
            series = {key: value[:snap["loop"]["frames"]] for key, value in series.items()}
        step = snap["loop"]["steps"]
        meta = {"kind": kind, "source": self.scene.source, "minidem": __version__, "kernel": self.kernel.__name__,
                "law": sim.law.name, "law_package": sim.entry.packages,
                "fingerprint": self.fingerprint, "dt": sim.dt, "step": step, "time": self.start_time + step * sim.dt,
                "total_steps": self.total_steps, "loop": snap["loop"], "frames_series": series}
        return self.checkpoint.write(Path(self.policy.directory) / name, arrays, meta)

    def fail(self, message, suggestion=None):
        """Stop: go back to the last state that passed the checks, write it, raise RunFailure.

        That state is rebuilt from the last copy (``good``) by replaying the steps
        in between: runs are deterministic, so the replay gives it bit for bit."""
        sim, state, good, checked = self.sim, self.state, self.good, self.checked
        arrays = snapshot_arrays(good)
        sim.use_order(state, arrays.get("particle_id"))
        state.restore(arrays)
        del arrays
        for live, saved in zip((self.probe, self.stats, self.status), good["tracking"]):
            live[:] = saved
        step, completing = good["loop"]["steps"], False
        self.loop["flight"] = good["loop"]["flight"]  # the flights as the run flew them: the same bits
        while step < checked["steps"] and self.status[0] == kernel.OK:
            taken = self.fly(step, checked["steps"] - step, sampled=False) if self.flies and not completing else 0
            needs_rebuild = False
            if not taken:
                self.loop["flight"] = None
                n_steps, stop = self.stepped(checked["steps"] - step)
                taken, needs_rebuild = self.call(step, n_steps, completing, self.no_trace, stop_at_separation=stop)
            step, completing = step + taken, False
            if needs_rebuild:
                sim.rebuild(state)
                completing = True
        # the state now is the last good one: written from the live arrays, no copy
        last_good = self.snapshot(live=True)
        last_good["loop"] = dict(checked)
        last_good["energy"], last_good["trace"] = self.checked_counts
        good_step = checked["steps"]
        written = []
        if self.policy is not None:
            written.append(str(self.write_state(self.checkpoint.LAST_GOOD, last_good, "last good")))
        if self.frames_on and checked["last_frame_step"] != good_step:
            self.on_frame(self.start_time + good_step * sim.dt, state)
            written.append("the last VTK frame")
        where = f", written to {' and '.join(written)}" if written else ""
        advice = suggestion or sim.suggested_time_step()
        raise RunFailure(f"{message}. {advice[0].upper()}{advice[1:]}. Last good state: step {good_step} "
                         f"(t = {self.start_time + good_step * sim.dt:.6g} s){where}")

    def check(self, step, on_grid=True):
        """The blow-up guard between chunks (see :mod:`minidem.engine.blowup`). Its record
        of the work of gravity is kept from the checks ``on_grid`` (steps every run of the
        scene checks, resumed or not: the grid of chunks and the list rebuilds), not from a
        chunk cut short by a probe or a checkpoint due by wall time. Before a list rebuild
        (mid-step) a pair kernel's force and torque arrays are zero (the force pass sums
        reactions into them and stores totals only at a call's last step; a kernel without
        pairs holds the last step's totals there); a non-finite force of this step stops
        the kernel itself."""
        at_time = self.start_time + step * self.sim.dt
        fault, work_max = self.guard.check(self.state, at_time, self.loop["gravity_work_max"])
        if on_grid:
            self.loop["gravity_work_max"] = work_max
        if fault is not None:
            touching = self.blowup.contacts_of(self.state, fault.particle, self.scene.scenario_index)
            advice = None
            if fault.what == "energy":
                # energy from nowhere is an unstable step or a law that creates it, which no
                # step cures (hmd at a friction of 1000: the same stop at every step tried)
                advice = (f"{self.sim.suggested_time_step()}; if a smaller step stops the same way, at about the "
                          f"same energy, the contact law '{self.sim.law.name}' creates it (docs/laws.md, 'Laws that "
                          "create energy')")
            self.fail(f"blow-up ({fault.what}) at step {step} (t = {at_time:.6g} s): {fault.detail}; "
                      f"particle {self.scene.scenario_index(fault.particle)} touches "
                      + (", ".join(touching) if touching else "nothing"), advice)

    def check_status(self, steps):
        """A fault the kernel stopped for (a non-finite force, a sphere through a wall)."""
        status, sim = self.status, self.sim
        if status[0] != kernel.OK:
            advice = None
            if status[0] == kernel.NON_FINITE_FORCE:
                advice = ("A law's force must be finite at every overlap >= 0 and speed; if this one is, the time "
                          f"step may be too large: {sim.suggested_time_step()}")
            elif status[0] == kernel.TUNNELLED and sim.deepest_overlap[0] > 1.0:
                advice = ("no time step helps then: a stiffer material, a slower impact or weaker gravity "
                          f"(if it is the time step, {sim.suggested_time_step()})")
            self.fail(sim._fault_message(status, steps), advice)

    # -- the loop ----------------------------------------------------------------
    def next_goal(self, checks=True):
        """The step the next chunk ends at: the next frame, checkpoint or the end, and with
        ``checks`` the next multiple of check_steps (a flight, whose states all come from
        its start, needs no check between: the guard checks where it ends)."""
        steps, loop = self.loop["steps"], self.loop
        goal = min(self.total_steps, (steps // self.check_steps + 1) * self.check_steps) if checks else \
            self.total_steps
        if self.frames_on:
            goal = min(goal, max(steps + 1, self.frame_step(loop["frames"])))
        if self.checkpoint_steps:
            goal = min(goal, (steps // self.checkpoint_steps + 1) * self.checkpoint_steps)
        return goal

    def next_chunk(self):
        """(steps, threads, probing) of the next chunk: up to the next multiple of
        check_steps, frame or checkpoint (the kernel takes the energy samples on its way);
        a probe of the other thread count runs a short chunk, since it only has to time it."""
        steps = self.loop["steps"]
        chunk = self.next_goal() - steps
        chunk_threads = self.loop_threads.choose()
        probing = chunk_threads != self.loop_threads.current
        if probing:
            chunk = min(chunk, max(2 * LoopThreads.MIN_STEPS, chunk // LoopThreads.PROBE_FRACTION))
        return chunk, chunk_threads, probing

    def fly(self, start_step, n_steps, sampled=True):
        """Up to ``n_steps`` steps of the one sphere's free flight among plane walls solved
        in closed form instead of stepped; returns how many (0: it touches a plane, or
        will within two steps: the kernel steps).
        ``sampled``: the kinetic-energy samples of the steps flown are added to the run's.

        Whole steps of the run's grid: the schedule (energy samples, frames, checkpoints)
        and every later touch fall where stepping puts them. Velocity Verlet under the one
        constant force, gravity, is exact (x + v dt + g dt^2/2 a step), so the flight is
        the stepped one but for rounding, of which the closed form has less (one update,
        not one a step). Spin is constant in flight.

        A flight is planned once, from the state the kernel left (``loop["flight"]``: its
        first step, its last, a step or two short of the first touch (of a law acting beyond
        touch: of its reach), checked to be apart, and the position
        and velocity it starts from), and every state in it is computed from that start:
        the same bits however the run's chunks cut it, so a replay (``fail``) or a resumed
        run (the plan is saved in checkpoints) repeats it exactly. The stored overlap of each plane is
        set as the kernel's last step would have left it: the next step reads it as
        'not touching before' and times the touch from it."""
        state, loop, dt = self.state, self.loop, self.sim.dt
        gravity = self.scene.gravity
        flight = loop["flight"] = loop["flight"] or self.plan_flight(start_step)
        if flight is None:
            return 0
        first_step, end = flight[0], flight[1]
        steps = min(n_steps, end - start_step)
        if steps < 1:
            return 0
        start_position, start_velocity = np.array(flight[2]), np.array(flight[3])
        if sampled:
            first, last = start_step // self.sample_steps + 1, (start_step + steps) // self.sample_steps
            if last >= first:  # the kinetic energy at the sample steps it passes, as the kernel takes them
                sample_step = np.arange(first, last + 1) * self.sample_steps
                sample_velocity = start_velocity + ((sample_step - first_step) * dt)[:, None] * gravity
                spin = state.angular_velocity[0]
                energy = 0.5 * (state.mass[0] * np.einsum("sk,sk->s", sample_velocity, sample_velocity)
                                + state.inertia[0] * float(spin @ spin))
                self.energy.extend(zip((self.start_time + sample_step * dt).tolist(), energy.tolist()))
            # the guard's record of the work of gravity at the run's check grid the flight
            # passes, as stepping checks there (the energy samples are weighed against it).
            # That work is convex in time (m g.(x0 + v0 t + g t^2/2 - x_initial)): its
            # largest on the grid steps passed is at the first or the last of them
            first_grid = (start_step // self.check_steps + 1) * self.check_steps
            last_grid = (start_step + steps) // self.check_steps * self.check_steps
            for grid_step in {first_grid, last_grid} if last_grid >= first_grid else ():
                elapsed = (grid_step - first_step) * dt
                at_grid = integrate.ballistic_position(start_position, start_velocity, gravity, elapsed)
                loop["gravity_work_max"] = self.guard.budget(at_grid[None, :], loop["gravity_work_max"])[1]
            loop["flown_steps"] += steps
        elapsed = (start_step + steps - first_step) * dt
        state.position[0] = integrate.ballistic_position(start_position, start_velocity, gravity, elapsed)
        state.velocity[0] = start_velocity + elapsed * gravity
        overlap = state.planes[4]
        overlap[:] = state.plane_overlaps(*state.planes[5:7])
        probe_wall = self.tracking[0]
        if probe_wall >= 0:
            self.probe[kernel.PROBE_OVERLAP] = overlap[probe_wall]
        return steps

    def plan_flight(self, start_step):
        """The flight from the state now (fly's ``loop["flight"]``), or None where there is
        none: a contact lives, the kernel reported a fault, or the touch is within two steps."""
        state, dt, gravity = self.state, self.sim.dt, self.scene.gravity
        if self.touching() or self.status[0] != kernel.OK or not (
                np.isfinite(state.position[0]).all() and np.isfinite(state.velocity[0]).all()):
            # a contact lives: the kernel steps it; or a fault (a law's NaN force at the
            # first call) the kernel reports where it happened
            return None
        # apart from every plane (for a law acting beyond touch, beyond its reach): no
        # force but gravity, and the kernel has dropped every plane's history
        point, normal = state.planes[0], state.planes[1]
        position, velocity = state.position[0], state.velocity[0]
        radius = float(state.particles[8][0])
        free_time = min((integrate.time_to_touch(
            float((position - point[w]) @ normal[w]) - radius + float(self.plane_lives_above[w]),
            -float(velocity @ normal[w]), -float(gravity @ normal[w])) for w in range(point.shape[0])),
            default=math.inf)
        # a step or two short of the reach: the kernel steps on from a state still apart
        end = (self.total_steps if free_time >= (self.total_steps - start_step + 2) * dt
               else start_step + int(free_time / dt) - 1)
        # and apart there, whatever the rounding (halved until it is)
        while end > start_step and np.any(self.flown_overlaps(end - start_step, position, velocity)
                                            > self.entry_lives_above()):
            end = start_step + (end - start_step) // 2
        if end - start_step < 1:
            return None
        return (start_step, end, position.tolist(), velocity.tolist())

    def entry_lives_above(self):
        """plane_lives_above for each entry of the sphere's list of planes (state.planes)."""
        return self.plane_lives_above[self.state.planes[6]]

    def touching(self):
        """Whether the one sphere's contact with some plane lives (its stored overlap, the
        kernel's last step's, above the pair's lives_above), as the kernel decides it."""
        overlap = self.state.planes[4]
        return bool(overlap.shape[0]) and bool(np.any(overlap > self.entry_lives_above()))

    def flown_overlaps(self, steps, position, velocity):
        """The overlap with each entry's plane after ``steps`` steps of free flight from
        ``position``, ``velocity`` (as State.plane_overlaps computes it)."""
        moved = integrate.ballistic_position(position, velocity, self.scene.gravity, steps * self.sim.dt)
        point, normal, planes = self.state.planes[0], self.state.planes[1], self.state.planes[6]
        return float(self.state.particles[8][0]) - np.einsum("ek,ek->e", moved - point[planes], normal[planes])

    def stepped(self, n_steps):
        """(steps, stop_at_separation) of a chunk the kernel steps. Where flights are
        flown (fly): in contact or within a law's reach of a plane, until the contact ends
        (the flight after it is then flown); a sphere flying to a touch (fly stopped a
        step or two short of it) steps two steps."""
        if not self.flies:
            return n_steps, self.stop_at_separation
        if self.touching():
            return n_steps, True
        return min(n_steps, 2), self.stop_at_separation

    def copy_due(self, end, copied_wall, copy_seconds, last_checkpoint_wall):
        """(whether the last good state is copied at step ``end``, whether a checkpoint is
        due by the wall clock): at most every snapshot_steps, and SNAPSHOT_COST_RATIO
        times the last copy's duration apart."""
        now = wallclock.perf_counter()
        policy = self.policy
        return (end - self.good["loop"]["steps"] >= self.snapshot_steps
                and now - copied_wall >= SNAPSHOT_COST_RATIO * copy_seconds,
                bool(policy is not None and policy.wall_interval and now - last_checkpoint_wall >= policy.wall_interval))

    def read_at(self, end) -> bool:
        """Whether the run reads the state at step ``end`` whatever the wall clock: a
        frame, a checkpoint of the simulated-time interval, the end."""
        return (end >= self.total_steps or (self.frames_on and end >= self.frame_step(self.loop["frames"]))
                or bool(self.checkpoint_steps and end % self.checkpoint_steps == 0))

    def record(self, steps, returned_early):
        """After a chunk that passed the checks: energy sample, frame, progress; returns
        whether the run stops here at separation."""
        state, loop, stats = self.state, self.loop, self.stats
        now = self.start_time + steps * self.sim.dt
        # stop_at_separation: the last contact ended (the kernel returns early, or
        # it ended on the chunk's last step, which must not cost one more step)
        separating = self.stop_at_separation and (returned_early or (
            stats[kernel.FIRST_CONTACT_TIME] >= 0.0 and state.count_contacts() == 0))
        at_frame = self.frames_on and steps >= self.frame_step(loop["frames"])
        # every sample_steps the kernel has taken the sample
        if steps % self.sample_steps != 0 and (steps == self.total_steps or at_frame or separating):
            self.energy.append((now, state.kinetic_energy(state.inertia)))
        if steps % self.check_steps == 0 or steps == self.total_steps or separating:
            # on the grid only (as the guard's record): a probe's or a checkpoint's chunk
            # end depends on wall time, and the run's result must not
            # each its own maximum (a new list, never changed in place: snapshots share it)
            loop["deepest_overlap"] = [max(now, before) for now, before in
                                       zip(state.deepest_contact(), loop["deepest_overlap"])]
        if at_frame:
            self.on_frame(now, state)
            loop["frames"] += 1
            loop["last_frame_step"] = steps
        self.mark_checked()
        if self.progress is not None:
            self.progress(steps, self.total_steps, state.count_contacts())
        return separating

    def run(self) -> RunResult:
        try:
            return self.run_loop()
        finally:
            self.release_good()

    def release_good(self):
        """Close the last good copy's file (and free it): nothing restores from it now."""
        self.good = None
        self.good_copy.close()

    def run_loop(self) -> RunResult:
        sim, state, loop, policy = self.sim, self.state, self.loop, self.policy
        self.start()
        started = wallclock.perf_counter()
        last_checkpoint_wall = started
        separated, completing = False, False
        copied_wall, copy_seconds = started, 0.0
        try:
            while loop["steps"] < self.total_steps:
                steps = loop["steps"]
                chunk, chunk_threads, probing = self.next_chunk()
                with _interrupts_deferred():
                    flown = self.fly(steps, self.next_goal(checks=False) - steps) if self.flies and not completing \
                        else 0
                if flown:
                    taken, needs_rebuild = flown, False
                    # (no pairs, whose contact forces a copy would need stored: decided now)
                    copy_wanted, wall_checkpoint = self.copy_due(steps + flown, copied_wall, copy_seconds,
                                                                 last_checkpoint_wall)
                else:
                    loop["flight"] = None  # stepped: a flight after this is planned afresh
                    chunk, stop = self.stepped(chunk)
                    trace = np.zeros((chunk, len(kernel.TRACE_COLUMNS))) if self.scene.trace else self.no_trace
                    # decided before the call: the kernel stores the pairs' contact forces
                    # only for a state the run reads (kernel.advance)
                    copy_wanted, wall_checkpoint = self.copy_due(steps + chunk, copied_wall, copy_seconds,
                                                                 last_checkpoint_wall)
                    store_reactions = copy_wanted or wall_checkpoint or self.read_at(steps + chunk)
                    chunk_started = wallclock.perf_counter()
                    # compiled code never sees a signal before it returns anyway: held, a
                    # Ctrl-C is delivered here after the call, never inside numba's dispatcher
                    # (which then returned 'a result with an exception set', a SystemError)
                    with _interrupts_deferred():
                        taken, needs_rebuild = self.call(steps, chunk, completing, trace, chunk_threads, sampled=True,
                                                         stop_at_separation=stop, store_reactions=store_reactions)
                    self.loop_threads.record(chunk_threads, taken, wallclock.perf_counter() - chunk_started)
                    if self.scene.trace:
                        self.trace_chunks.append(trace[:taken])
                steps = loop["steps"] = steps + taken
                completing = False
                self.check_status(steps)
                if needs_rebuild:
                    # mid-step (drifted, forces pending): a runaway particle must not
                    # reach the neighbour grid
                    self.check(steps + 1)
                    sim.rebuild(state)
                    completing = True  # the next call completes the step from its forces
                    continue
                self.check(steps, on_grid=steps % self.check_steps == 0 or steps == self.total_steps)
                separating = self.record(steps, returned_early=taken < chunk and not flown)
                # the chunk as planned (a separation ends it early, and the run with it)
                whole = taken == (flown or chunk)
                checkpoint_due = policy is not None and not separating and whole and steps < self.total_steps and (
                    (self.checkpoint_steps and steps % self.checkpoint_steps == 0) or wall_checkpoint)
                now_wall = wallclock.perf_counter()
                if checkpoint_due or (copy_wanted and whole):
                    # after the checks: the state overwriting the last good one is good
                    self.good = self.snapshot(self.good)
                    copied_wall = wallclock.perf_counter()
                    copy_seconds = copied_wall - now_wall
                if checkpoint_due:  # the state the last good copy was just taken of, as it is
                    self.write_state(self.checkpoint.CHECKPOINT, self.snapshot(live=True), "checkpoint")
                    last_checkpoint_wall = wallclock.perf_counter()
                if separating:
                    separated = True
                    break
        except (KeyboardInterrupt, SystemError) as exc:
            self.interrupt(exc)
        if self.frames_on and loop["last_frame_step"] != loop["steps"]:
            # the state the run ends in is always a frame (also when the output interval
            # does not divide the run, or exceeds it): ParaView's last frame is the result
            self.on_frame(self.start_time + loop["steps"] * sim.dt, state)
            loop["frames"] += 1
            loop["last_frame_step"] = loop["steps"]
        wall_time = wallclock.perf_counter() - started
        if policy is not None:
            # the state's own arrays, not a copy, and the last good copy released first (the
            # run is over: nothing restores from it now): a second and third copy of the
            # state were the peak of a run that writes its final state
            self.release_good()
            self.write_state(self.checkpoint.FINAL_STATE, self.snapshot(live=True), "final")
            Path(policy.path).unlink(missing_ok=True)  # the run is complete: nothing to resume
        return self.result(separated, wall_time)

    def interrupt(self, exc):
        """Ctrl-C (or SIGTERM through the CLI) between chunks: keep what was done. A
        SystemError caused by a Ctrl-C (one that reached the dispatcher of a compiled
        function from another thread) is the same interrupt."""
        if not interrupted(exc):
            raise exc
        if self.policy is not None:
            with _interrupts_deferred():  # a second Ctrl-C must not tear this checkpoint
                written = self.write_state(self.checkpoint.CHECKPOINT, self.good, "checkpoint")
                self.sim.interrupted_at = (self.start_time + self.good["loop"]["steps"] * self.sim.dt, written)
        if isinstance(exc, KeyboardInterrupt):
            raise exc
        raise KeyboardInterrupt from exc

    def result(self, separated, wall_time) -> RunResult:
        sim, state, stats = self.sim, self.state, self.stats
        steps = self.loop["steps"]
        scene, ordered = sim.input_scene, self.scene.in_scenario_order
        return RunResult(
            scene=scene, law=sim.law, constants=sim.constants_by_pair, position=ordered(state.position),
            velocity=ordered(state.velocity), angular_velocity=ordered(state.angular_velocity),
            initial_velocity=scene.velocity, initial_angular_velocity=scene.angular_velocity, steps=steps, dt=sim.dt,
            dt_reason=sim.dt_reason,
            time=self.start_time + steps * sim.dt, separated=separated, first_contact_time=stats[0],
            last_separation_time=stats[1], max_overlap=stats[2], peak_normal_force=stats[3],
            peak_tangential_force=stats[4], wall_time=wall_time,
            trace=np.concatenate(self.trace_chunks) if self.trace_chunks else None, force=ordered(state.force),
            torque=ordered(state.torque), contacts=state.count_contacts(), neighbour_builds=state.builds,
            threads=self.loop_threads.most_used(), thread_steps=dict(self.loop_threads.steps),
            energy=np.array(self.energy), contact_statistics=not sim.parallel,
            gravity_work_max=self.loop["gravity_work_max"], supply_budget=sim.supply_budget,
            sampled_max_overlap=self.loop["deepest_overlap"][0],
            sampled_max_overlap_ratio=self.loop["deepest_overlap"][1], flown_steps=self.loop["flown_steps"],
        )


@contextlib.contextmanager
def _interrupts_deferred():
    """Hold SIGINT and SIGTERM for the duration of the block: they are delivered (and
    raise KeyboardInterrupt through the CLI's handler) as soon as it ends, so that the
    copy of the last good state, which a Ctrl-C writes as the checkpoint, is never torn.

    The handlers are swapped for one that only records the signal (a signal mask would
    hold it in this thread only: a Ctrl-C sent to the process, delivered to one of
    numba's threads, would still raise here, and inside a compiled function's
    dispatcher that was 'SystemError: ... returned a result with an exception set').
    Outside the main thread (a Dask worker's) Python delivers no signal: nothing to hold."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = {number: signal.signal(number, lambda signum, frame: caught.append(signum))
                for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            # None: a handler installed outside Python (an embedding application) cannot be
            # put back from here; the default action is the closest
            signal.signal(number, handler if handler is not None else signal.SIG_DFL)
        if caught:  # now, to the handlers the run had (KeyboardInterrupt, or the CLI's SIGTERM)
            signal.raise_signal(caught[0])


def snapshot_arrays(snap) -> dict:
    """The arrays of a snapshot (RunLoop.snapshot): its copy read back from the file, or
    the live arrays it refers to."""
    return snap["arrays"].read() if isinstance(snap["arrays"], StateCopy) else snap["arrays"]


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is a KeyboardInterrupt or was caused by one (a SystemError of
    numba's dispatcher when Ctrl-C arrived as a compiled function returned)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
