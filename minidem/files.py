"""Atomic file writing for every result writer. Every file is written atomically (temporary file in the same
directory, flushed to disk, then renamed over the target), so an interrupted run never
leaves a half-written result."""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path


def atomic_write(path: str | Path, data: bytes | str) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with open(tmp, "wb") as handle:
        handle.write(data.encode() if isinstance(data, str) else data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)
    return path


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
