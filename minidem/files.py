"""Atomic file writing for every result writer. Every file is written atomically (temporary file in the same
directory, flushed to disk, then renamed over the target), so an interrupted run never
leaves a half-written result."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

from minidem.errors import MinidemError


class OutputError(MinidemError, OSError):
    """A result file could not be written (disk full, quota, permissions, a vanished
    directory): the CLI names the file and exits with code 1. The temporary file is gone
    and the file's previous version, if any, is untouched. An OSError still (code that
    catches those keeps working), and a MinidemError, whose message names the file."""


def output_error(path, exc: OSError) -> OutputError:
    reason = exc.strerror or str(exc)
    return OutputError(f"cannot write {path}: {reason} (errno {exc.errno}); the files written before are intact"
                       + ("; free some space and run again" if exc.errno in (28, 122) else ""))


def atomic_write(path: str | Path, data) -> Path:
    """Write ``data`` (bytes, str, or a callable given the open binary file, which writes
    the content itself: a large file is then streamed, never held whole in memory) to
    ``path`` atomically."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as handle:
            if callable(data):
                data(handle)
            else:
                handle.write(data.encode() if isinstance(data, str) else data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        _remove_quietly(tmp)
        raise output_error(path, exc) from exc
    except BaseException:  # Ctrl-C half-way: no temporary left behind either
        _remove_quietly(tmp)
        raise
    return path


def _remove_quietly(path) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def write_json(path: str | Path, payload: dict) -> Path:
    return atomic_write(path, json.dumps(payload, indent=2, default=_jsonable) + "\n")


def write_csv(path: str | Path, columns, rows) -> Path:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    for row in rows:
        writer.writerow([repr(float(x)) if isinstance(x, float) else x for x in row])
    return atomic_write(path, buffer.getvalue())


def _jsonable(value):
    import numpy as np

    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
