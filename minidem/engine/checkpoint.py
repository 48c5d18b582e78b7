"""Checkpoints: the complete state of a run in one ``.npz``, written atomically.

A checkpoint holds everything the compiled loop carries from one step to the next, so
``minidem run FILE --resume`` continues bit for bit where the run stopped:

* particles: position, velocity, angular velocity, and the force and torque of the
  last step (velocity Verlet opens every step with a half kick by them);
* every contact's state: the history and last overlap of each plane, cylinder, mesh
  and pair contact, with the contact identities (the Verlet lists of pairs and mesh
  candidates, their CSR offsets, exactly as built), and the positions at the last list
  build, so the next rebuild happens at the step it would have; the pairs' reverse index
  and the list of planes near each sphere (one plane contact per entry) follow from
  those and are made again on loading;
* the run loop: step counter (time is ``step * dt``, never a running sum), the contact
  statistics and peak trackers, the kinetic-energy samples and trace rows so far, the
  frames written (index and the ``.pvd`` entries), the blow-up guard's record;
* ``meta``: format version, minidem version, the kernel (law and engine build) and a
  hash of the scenario, so a resume with another scenario or engine is refused.

The engine draws no random numbers while running (fill generators run once, before
the scene is built), so there is no generator state to save.

The same file format serves ``final_state.npz`` (written at the end of every
``minidem run``) and ``last_good.npz`` (the state before a blow-up).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np

from minidem.files import atomic_write

# 2: pair_reaction_in_use (which reaction rows hold a touching pair's reaction)
# 3: plane_history and plane_overlap per near-plane entry (State.list_near_planes), not
#    per (sphere, plane)
# 4: sorted_step, and particle_id when the particles are stored in another order than the
#    scenario's (Simulation.sort_in_space)
# 5: pair_reaction is the force on i alone, (M, 3): the torque on the partner is not state
#    (State.pair_arrays)
FORMAT = 5
CHECKPOINT = "checkpoint.npz"
FINAL_STATE = "final_state.npz"
LAST_GOOD = "last_good.npz"

# scenario keys that may change between a run and its resume: where files go, how
# often checkpoints are written and how many threads run (results are the same for
# any thread count)
_FREE_KEYS = {("output", "directory"), ("output", "checkpoint_interval"), ("output", "checkpoint_wall_interval"),
              ("run", "threads")}


@dataclasses.dataclass
class Policy:
    """Where and how often :meth:`minidem.engine.simulation.Simulation.run` writes checkpoints.

    ``interval``: simulated seconds between checkpoints (None: none on that account);
    ``wall_interval``: wall-clock seconds between checkpoints (None or 0: none).
    A blow-up writes ``last_good.npz`` and Ctrl-C a last checkpoint in ``directory``.
    """

    directory: Path
    interval: float | None = None
    wall_interval: float | None = None

    @property
    def path(self) -> Path:
        return Path(self.directory) / CHECKPOINT


def fingerprint(sim) -> str:
    """Hash of everything that decides a run's trajectory: the scenario as given (after
    ``--set``, without the keys in ``_FREE_KEYS``), the particles and walls it produced,
    and the time step. The scenario's own order, not the order a run stores them in (which
    a run may change, Simulation.sort_in_space)."""
    scene = sim.input_scene
    raw = json.loads(json.dumps(scene.raw, default=str))
    for section, key in _FREE_KEYS:
        if isinstance(raw.get(section), dict):
            raw[section].pop(key, None)
    digest = hashlib.sha256(json.dumps(raw, sort_keys=True).encode())
    walls = scene.walls
    for array in (scene.position, scene.velocity, scene.angular_velocity, scene.radius, scene.particle_material,
                  scene.wall_point, scene.wall_normal, scene.wall_material, scene.gravity, walls.cylinder_base,
                  walls.cylinder_axis, walls.cylinder_radius, walls.cylinder_length, walls.triangles,
                  np.array([sim.dt])):
        digest.update(np.ascontiguousarray(array).tobytes())
    return digest.hexdigest()[:32]


def write(path: str | Path, arrays: dict, meta: dict) -> Path:
    """Write ``arrays`` and ``meta`` (JSON-able) to ``path`` atomically: a reader or a
    killed process sees the previous file or the new one, never a torn one."""
    payload = {name: np.asarray(array, order="C") for name, array in arrays.items()}
    payload["meta"] = np.frombuffer(json.dumps(dict(meta, format=FORMAT)).encode(), dtype=np.uint8)
    # streamed into the temporary file: an archive assembled in memory first, then copied
    # out as bytes, held the state twice more at the peak (settle, N = 200,000, the CLI's
    # final_state.npz: 526 MiB against 291 MiB for the run itself)
    return atomic_write(path, lambda handle: np.savez(handle, **payload))


def read(path: str | Path) -> tuple[dict, dict]:
    """(arrays, meta) of a checkpoint file."""
    # opened here, so a truncated or foreign file is closed when np.load refuses it
    # (np.load given a path leaks its handle then: 'unclosed file' after the error)
    with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files if name != "meta"}
        meta = json.loads(bytes(data["meta"]).decode())
    return arrays, meta


def require_checkpoint(source: str, directory: str | Path) -> Path:
    """The checkpoint's path in ``directory``, or a ScenarioError saying why there is none
    (checked before the output directory is made: a refused --resume creates nothing)."""
    from minidem.scene.scenario import ScenarioError

    path = Path(directory) / CHECKPOINT
    if not path.exists():
        finished = (Path(directory) / FINAL_STATE).exists()
        raise ScenarioError(
            f"{source}: --resume: no checkpoint {path}"
            + ("; the run in this directory has finished (final_state.npz)" if finished else
               "; the run wrote none (checkpoints are written every output.checkpoint_interval of simulated "
               "time or output.checkpoint_wall_interval of wall-clock time)")
            + "; run without --resume to start from t = 0")
    return path


def load_for_resume(sim, directory: str | Path) -> tuple[dict, dict]:
    """The checkpoint in ``directory`` if it belongs to this simulation; otherwise a
    ScenarioError that says why and what to do (the CLI exits with code 2)."""
    from minidem.scene.scenario import ScenarioError

    path = require_checkpoint(sim.scene.source, directory)
    try:
        arrays, meta = read(path)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is the same user error
        raise ScenarioError(f"{sim.scene.source}: --resume: cannot read {path}: {exc}; delete it and run "
                            "without --resume") from None
    if meta.get("format") != FORMAT:
        raise ScenarioError(f"{sim.scene.source}: --resume: {path} has checkpoint format {meta.get('format')}, "
                            f"this minidem writes format {FORMAT}; run without --resume")
    if meta["fingerprint"] != fingerprint(sim):
        raise ScenarioError(
            f"{sim.scene.source}: --resume: {path} was written for a different scenario (file, --set values, "
            f"particles, walls or time step differ from the run that wrote it at {meta['source']}); "
            "resuming would not continue that run. Use the same file and --set options, or run without "
            "--resume to start again")
    if meta["kernel"] != sim.kernel.__name__:
        raise ScenarioError(
            f"{sim.scene.source}: --resume: {path} was written by another build of the engine or of law "
            f"'{sim.law.name}' (kernel {meta['kernel']}, now {sim.kernel.__name__}): the continued run could "
            "not be bit-identical to an uninterrupted one; run without --resume to start again")
    return arrays, meta


# the temporary names of minidem.files.atomic_write and of the VTK writer's _PendingFile
_TEMPORARY = re.compile(r"^\..+\.(tmp\d+|\d+\.\d+\.tmp)$")


def remove_stale_temporaries(directory: str | Path) -> list[Path]:
    """Delete the hidden temporary files (``.NAME.tmp*``, ``.NAME.PID.K.tmp``) that an
    atomic write leaves when the process is killed between writing and renaming."""
    removed = []
    directory = Path(directory)
    if not directory.is_dir():
        return removed
    for path in directory.glob(".*"):
        if path.is_file() and _TEMPORARY.match(path.name):
            try:
                os.remove(path)
                removed.append(path)
            except OSError:
                pass
    return removed
