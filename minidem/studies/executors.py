"""Where the cases of a sweep run: one interface, two back ends.

An executor takes a function and a list of tasks and yields ``(position, result)`` pairs
as the tasks finish, in any order; the caller puts them back in order. The function must
be importable by module path (Dask and the process pool send it by name, never its
code), pure and deterministic, so the results cannot depend on where or in which order
they ran.

* :class:`LocalProcesses`: processes on this machine (the default, no set-up).
* :class:`DaskCluster`: the workers of a running Dask distributed scheduler
  (``pip install 'minidem[dask]'``; ``minidem run FILE --scheduler tcp://HOST:PORT``).

A task that never came back because the infrastructure failed (a worker process died
too often, the process pool broke) is yielded as :class:`Lost`: it is not a result, and
the sweep reports it as not run, so that running the sweep again runs it.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, Protocol

from minidem.scene.scenario import ScenarioError
from minidem.engine.run_loop import RunFailure

DASK_ADDRESS_VARIABLE = "DASK_SCHEDULER_ADDRESS"  # Dask's own convention (dask.config "scheduler-address")
DASK_MISSING = "the Dask back end needs the dask extra: pip install 'minidem[dask]'"


@dataclasses.dataclass(frozen=True)
class Lost:
    """A task that did not come back (infrastructure failure, not a failed case)."""

    reason: str


class Executor(Protocol):
    description: str  # for messages and sweep.json, e.g. "local processes (2)"

    def run(self, function: Callable[[Any], Any], tasks: Sequence[Any],
            warm: Sequence[int] = ()) -> Iterator[tuple[int, Any]]:
        """Run ``function(task)`` for every task; yield ``(position in tasks, result or
        Lost)`` as each finishes, in any order. ``warm``: positions worth running first,
        each on its own (the first case of each kernel: compiled by different workers at
        the same time, then loaded from the disk cache by every other case); a back end
        may ignore it."""

    def close(self) -> None:
        ...


class BackendUnavailable(ScenarioError):
    """A back end that cannot be used as asked (exit 2: bad option or missing extra)."""


class BackendFailure(RunFailure):
    """A back end that failed while in use (exit 1)."""


# ---------------------------------------------------------------------------------
# local processes
# ---------------------------------------------------------------------------------
def _call_batch(function, batch):
    return [function(task) for task in batch]


# Tasks travel in batches: a case of the paper's impact takes a few milliseconds, about
# the cost of one round trip to a worker (more on a loaded machine), so one case per
# message would spend as long on messages as on work. At least 8 batches per worker
# keep the load balanced, at most 16 tasks per batch keep the loss small when a worker
# dies (its batch is rerun) and let workers that join later find work.
MAX_BATCH = 16


def batches(positions: Sequence[int], workers: int) -> list[list[int]]:
    size = max(1, min(MAX_BATCH, len(positions) // (max(1, workers) * 8)))
    return [list(positions[i:i + size]) for i in range(0, len(positions), size)]


def _exit_with_parent(parent: int, forked: bool) -> None:
    """Pool initializer: a worker whose parent was killed (kill -9) would wait for work
    forever (its siblings hold the queue open); this ends it within a second."""
    import threading

    def alive() -> bool:
        if forked:  # the parent's own child: re-parented when it dies
            return os.getppid() == parent
        try:  # started by a fork server: the parent is no ancestor, ask for it by pid
            os.kill(parent, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            pass
        return True

    def watch():
        while alive():
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="minidem-parent-watch").start()


def _fork_is_safe() -> bool:
    """False once numba's threading layer has started its threads in this process (a
    parallel multi-particle run): a forked child inherits locks held by threads that do
    not exist in it and can hang for ever (seen: a sweep after a parallel run in the same
    pytest process hung in its workers)."""
    parallel = sys.modules.get("numba.np.ufunc.parallel")
    return parallel is None or not getattr(parallel, "_is_initialized", False)


def _not_forked_hint(exc: BaseException) -> str:
    """Why workers that were not forked may die at once: each starts a fresh Python,
    which runs the main script again (multiprocessing's spawn and forkserver), and a
    script whose sweep is not under ``if __name__ == "__main__":`` starts the sweep
    again in every worker, which multiprocessing refuses."""
    from concurrent.futures.process import BrokenProcessPool

    script = getattr(sys.modules.get("__main__"), "__file__", None)
    if not isinstance(exc, BrokenProcessPool) or not script or _is_minidem_entry(script):
        return ""
    return (f" (the workers were not forked: numba's threads run in this process, so each starts a fresh Python, "
            f"which runs {script} again; if that script's top-level code is not under "
            f"'if __name__ == \"__main__\":', every worker starts the sweep again and dies: guard it, or pass "
            f"workers=1)")


def _is_minidem_entry(script: str) -> bool:
    """Whether the main script is minidem's own command (the console script, or
    ``python -m minidem``): its workers re-run no user code."""
    from pathlib import Path

    path = Path(script)
    return path.stem == "minidem" or Path(__file__).resolve().parents[1] in path.resolve().parents


class LocalProcesses:
    """Worker processes on this machine (forked where the platform allows it)."""

    def __init__(self, workers: int = 0):
        self.workers = workers or os.cpu_count() or 1
        self.description = f"local processes ({self.workers})"

    def run(self, function, tasks, warm=()):
        warm = [p for p in dict.fromkeys(warm) if 0 <= p < len(tasks)]
        rest = [p for p in range(len(tasks)) if p not in set(warm)]
        workers = min(self.workers, len(rest))
        if workers <= 1:
            for position in warm + rest:
                yield position, function(tasks[position])
            return
        methods = multiprocessing.get_all_start_methods()
        forked = "fork" in methods and _fork_is_safe()
        # else the workers load the kernels from the disk cache instead of inheriting them
        context = multiprocessing.get_context(
            "fork" if forked else "forkserver" if "forkserver" in methods else "spawn")
        pool = concurrent.futures.ProcessPoolExecutor(max_workers=workers, mp_context=context,
                                                      initializer=_exit_with_parent,
                                                      initargs=(os.getpid(), forked))
        try:
            # The warm cases (the first of each kernel) go first, one a task, so the
            # workers compile different kernels at the same time (a cold paper sweep is
            # mostly compilation); the other cases then load them from the disk cache.
            futures = {pool.submit(_call_batch, function, [tasks[p] for p in batch]): batch
                       for batch in [[p] for p in warm] + batches(rest, workers)}
            for future in concurrent.futures.as_completed(futures):
                batch = futures.pop(future)
                try:
                    results = future.result()
                except Exception as exc:  # noqa: BLE001 - a broken pool loses its tasks, not the sweep
                    results = [Lost(f"{type(exc).__name__}: {exc}" + ("" if forked else _not_forked_hint(exc)))
                               ] * len(batch)
                yield from zip(batch, results)
        finally:
            # on Ctrl-C or an abandoned generator: no new batches, do not wait for them
            pool.shutdown(wait=False, cancel_futures=True)

    def close(self):
        pass


# ---------------------------------------------------------------------------------
# Dask distributed
# ---------------------------------------------------------------------------------
def dask_available() -> bool:
    try:
        import distributed  # noqa: F401
    except ImportError:
        return False
    return True


class DaskCluster:
    """The workers of a running Dask scheduler. Tasks go in small batches
    (``Client.submit``) and come back through ``as_completed``; a worker that dies
    mid-batch has that batch rerun elsewhere by the scheduler, and a batch whose result
    died with its worker before it was fetched is run again (:func:`collect`)."""

    def __init__(self, address: str, connect_timeout_s: float = 20.0, source: str = "--scheduler"):
        try:
            from distributed import Client
        except ImportError:
            raise BackendUnavailable(f"{source} {address}: {DASK_MISSING}") from None
        if "://" not in address and ":" not in address:
            raise BackendUnavailable(f"{source} {address!r}: not a scheduler address; expected tcp://HOST:PORT "
                                     "(or 'local' for local processes)")
        self.address = address
        try:
            self.client = Client(address, timeout=connect_timeout_s, set_as_default=False)
        except (OSError, TimeoutError, ValueError) as exc:
            raise BackendFailure(f"cannot reach the Dask scheduler at {address} ({source}): "
                                 f"{type(exc).__name__}: {exc}") from None
        workers = len(self.client.scheduler_info().get("workers", {}))
        self.description = f"Dask scheduler {address} ({workers} worker(s) at start)"

    # A result that is lost with its worker is computed again, at most this many times
    # per batch; the scheduler itself gives up on a task after distributed's
    # ``allowed-failures`` (3) worker deaths during it and raises KilledWorker.
    MAX_ATTEMPTS = 4

    def run(self, function, tasks, warm=()):
        if not tasks:
            return
        workers = len(self.client.scheduler_info().get("workers", {}))
        groups = batches(range(len(tasks)), workers)
        yield from collect(self.client, function, [[tasks[p] for p in g] for g in groups], groups,
                           self.MAX_ATTEMPTS)

    def close(self):
        try:  # bounded: after a lost scheduler a plain close() waits for it to come back
            self.client.close(timeout=10)
        except Exception:  # noqa: BLE001 - nothing left to close cleanly
            pass


def collect(client, function, batches_of_tasks, groups, max_attempts: int) -> Iterator[tuple[int, Any]]:
    """Submit every batch and yield ``(position, result)`` as batches come back.

    A batch can finish on a worker that dies before its result is fetched: its future
    then turns "lost" (or back to "pending" while the scheduler recomputes it, because
    we still hold it), or fetching it fails. Neither is the case's failure, so the
    batch is waited for again or submitted again; only an error raised by the task
    itself, the scheduler's KilledWorker, or ``max_attempts`` losses make it Lost."""
    from distributed import as_completed

    futures = {}
    attempts = {}
    for index, batch in enumerate(batches_of_tasks):
        future = client.submit(_call_batch, function, batch, pure=False)
        futures[future] = index
        attempts[index] = 1
    pending = as_completed(list(futures), loop=client.loop)

    def again(index: int, reason: str):
        attempts[index] += 1
        if attempts[index] > max_attempts:
            return [(p, Lost(f"{reason} ({max_attempts} attempts)")) for p in groups[index]]
        future = client.submit(_call_batch, function, batches_of_tasks[index], pure=False)
        futures[future] = index
        pending.add(future)
        return []

    try:
        yield from _collect(client, pending, futures, groups, again)
    except BackendFailure:
        raise
    except Exception as exc:  # noqa: BLE001 - a client call after the scheduler went away
        if client.status == "running":
            raise
        raise _scheduler_lost(client, f"{type(exc).__name__}: {exc}", pending.count()) from None
    finally:
        if futures and client.status == "running":  # interrupted: cancel what nobody will wait for
            try:
                client.cancel(list(futures))
            except Exception:  # noqa: BLE001 - the scheduler went away meanwhile: nothing to cancel
                pass


def _collect(client, pending, futures, groups, again):
    """The loop of :func:`collect`: ``(position, result)`` of each batch as it comes."""
    for future in _while_scheduler_answers(client, pending):
        index = futures.pop(future)
        status = future.status
        if status == "finished":
            try:
                results = future.result()
            except Exception as exc:  # noqa: BLE001 - its data went with its worker
                future.release()
                yield from again(index, f"result lost: {type(exc).__name__}: {exc}")
                continue
            yield from zip(groups[index], results)
        elif status == "error":
            exc = future.exception()
            yield from ((p, Lost(f"{type(exc).__name__}: {exc}")) for p in groups[index])
        else:  # "lost" / "pending": finished on a worker that died; start it again
            future.release()
            yield from again(index, f"result lost with its worker (status {status})")
            continue
        future.release()


# A scheduler the client cannot reach for this long is lost: the sweep stops (exit 1,
# the finished cases kept in the journal) instead of waiting for it forever. distributed
# itself retries the connection for ~30 s (distributed.comm.timeouts.connect) and then
# leaves the client "connecting" with futures that never complete.
SCHEDULER_LOST_S = 30.0


def _while_scheduler_answers(client, pending, poll_s: float = 0.2):
    """The futures of ``pending`` (an as_completed) as they finish, as long as the client
    is connected to its scheduler; BackendFailure once it has not been for SCHEDULER_LOST_S."""
    unreachable_since = None
    while not pending.is_empty():
        if pending.has_ready():
            for future in pending.next_batch(block=False):
                yield future
            continue
        if client.status == "running":
            unreachable_since = None
        else:
            unreachable_since = unreachable_since or time.monotonic()
            if client.status in ("closed", "closing") or time.monotonic() - unreachable_since > SCHEDULER_LOST_S:
                raise _scheduler_lost(client, f"disconnected for {time.monotonic() - unreachable_since:.0f} s",
                                      pending.count())
        time.sleep(poll_s)


def _scheduler_lost(client, detail: str, batches_left: int) -> BackendFailure:
    address = getattr(getattr(client, "scheduler", None), "address", None) or "(unknown address)"
    return BackendFailure(f"lost the Dask scheduler {address} (client status '{client.status}': {detail}); "
                          f"{batches_left} batch(es) of cases did not come back. Restart the scheduler and run the "
                          "same command again: the finished cases are kept in the journal")


def from_options(scheduler: str | None, workers: int) -> Executor:
    """The back end the user asked for: ``--scheduler ADDRESS``, else the
    DASK_SCHEDULER_ADDRESS environment variable, else local processes
    (``--scheduler local`` forces them)."""
    source = "--scheduler"
    if scheduler is None and os.environ.get(DASK_ADDRESS_VARIABLE):
        scheduler, source = os.environ[DASK_ADDRESS_VARIABLE], DASK_ADDRESS_VARIABLE
    if scheduler is None or scheduler == "local":
        return LocalProcesses(workers)
    return DaskCluster(scheduler, source=source)


# ---------------------------------------------------------------------------------
# a scheduler and workers as separate processes on this machine (tests, benchmark)
# ---------------------------------------------------------------------------------
class LocalDaskProcesses:
    """``dask scheduler`` and N ``dask worker`` processes on 127.0.0.1 (random free
    ports, one thread each), each in its own process group so that it can be killed
    whole, and every one torn down on exit, also after an error. On a real cluster the
    user starts these (docs/sweeps-on-a-cluster.md).

    The groups stay in the caller's session: Linux's autogroup scheduler shares a busy
    CPU between sessions, so workers in sessions of their own would get more CPU than
    local worker processes and skew a comparison of the two."""

    def __init__(self, n_workers: int, env: dict | None = None, start_timeout_s: float = 60.0):
        self.n_workers, self.start_timeout_s = n_workers, start_timeout_s
        self.env = dict(os.environ if env is None else env)
        self.env.pop(DASK_ADDRESS_VARIABLE, None)
        self.processes: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.address: str | None = None
        self._tmp = None

    def _start(self, *args) -> subprocess.Popen:
        log = open(Path(self._tmp.name) / f"process{len(self.processes)}.log", "wb")
        process = subprocess.Popen([sys.executable, "-m", "dask", *args], env=self.env, stdout=log,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, process_group=0)
        log.close()
        self.processes.append(process)
        return process

    def __enter__(self) -> "LocalDaskProcesses":
        self._tmp = tempfile.TemporaryDirectory(prefix="minidem-dask-")
        try:
            scheduler_file = Path(self._tmp.name) / "scheduler.json"
            self._start("scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                        "--scheduler-file", str(scheduler_file))
            self.address = self._wait_for_scheduler(scheduler_file)
            for _ in range(self.n_workers):
                self.workers.append(self._start("worker", self.address, "--host", "127.0.0.1", "--nthreads", "1",
                                                "--nworkers", "1", "--no-dashboard"))
            self._wait_for_workers()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _wait_for_scheduler(self, scheduler_file: Path) -> str:
        import json

        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if self.processes[0].poll() is not None:
                raise RuntimeError(f"dask scheduler exited with {self.processes[0].returncode}:\n{self.logs()}")
            try:
                return json.loads(scheduler_file.read_text())["address"]
            except (OSError, ValueError, KeyError):
                time.sleep(0.1)
        raise RuntimeError(f"dask scheduler did not start in {self.start_timeout_s} s:\n{self.logs()}")

    def _wait_for_workers(self) -> None:
        from distributed import Client

        with Client(self.address, timeout=self.start_timeout_s, set_as_default=False) as client:
            client.wait_for_workers(self.n_workers, timeout=self.start_timeout_s)

    def kill_worker(self, index: int) -> int:
        """SIGKILL one worker's whole process group (as a machine that dies)."""
        process = self.workers[index]
        os.killpg(process.pid, signal.SIGKILL)
        return process.wait(timeout=30)

    def logs(self) -> str:
        if self._tmp is None:
            return ""
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}"
                         for p in sorted(Path(self._tmp.name).glob("*.log")))

    def __exit__(self, *exc) -> None:
        for process in reversed(self.processes):  # workers first, then the scheduler
            if process.poll() is None:
                try:
                    os.killpg(process.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for process in self.processes:
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                try:
                    os.killpg(process.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
                process.wait(timeout=10)
        # a worker's nanny-spawned process shares its group: make sure none is left
        for process in self.processes:
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None
