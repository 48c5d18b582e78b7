"""Particle generators for ``[[fill]]`` tables: a lattice, a random non-overlapping
packing in a box region, or a file (CSV or VTK)."""

from __future__ import annotations

import csv
import random
import warnings
from pathlib import Path

import numpy as np


# what a run holds per particle, measured at 1,000,000 (591 bytes: docs/benchmarks.md, target 3)
BYTES_PER_PARTICLE = 600


def _check_memory(n: int, what: str) -> None:
    """Refuse a fill whose particles could not be held in this machine's memory, before
    anything is allocated: numpy's MemoryError for 455 PiB was an internal error (a
    robustness review)."""
    import os

    try:
        memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not told: numpy's own error stands
        return
    if n * BYTES_PER_PARTICLE > memory:
        raise ValueError(f"{what} = {n:,} particles would need about {n * BYTES_PER_PARTICLE / 2**30:,.0f} GiB "
                         f"({BYTES_PER_PARTICLE} bytes a particle); this machine has {memory / 2**30:,.1f} GiB: "
                         f"at most about {memory // BYTES_PER_PARTICLE:,} particles")


def lattice(lower, upper, spacing: float, count: int | None = None, jitter: float = 0.0,
            seed: int = 12345) -> np.ndarray:
    """Simple cubic lattice centres in the box lower..upper, first centre at
    lower + spacing/2, filled x fastest, then y, then z, up to ``count`` sites (all that
    fit when None).

    ``jitter`` shifts each site in x and y by a uniform offset in [-jitter, jitter],
    drawn in the order (dx, dy) per site from Python's ``random.Random(seed)``: the
    same sequence as the LIGGGHTS lattice generator of the benchmark, so both codes
    start from identical positions.
    """
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    sites = np.floor((upper - lower) / spacing + 1e-9).astype(np.int64)
    if np.any(sites < 1):
        raise ValueError(f"the region {lower.tolist()}..{upper.tolist()} holds no lattice site of spacing {spacing:g} m")
    capacity = int(np.prod(sites))
    n = capacity if count is None else int(count)
    if n > capacity:
        raise ValueError(f"count = {n} exceeds the {capacity} lattice sites ({sites[0]} x {sites[1]} x {sites[2]}) "
                         f"of spacing {spacing:g} m in the region; enlarge upper or reduce count")
    _check_memory(n, "count" if count is not None else f"the region's {sites[0]} x {sites[1]} x {sites[2]} sites")
    k = np.arange(n)
    index = np.column_stack([k % sites[0], (k // sites[0]) % sites[1], k // (sites[0] * sites[1])])
    position = lower + spacing * (index + 0.5)
    if jitter > 0.0:
        rng = random.Random(seed)
        for p in range(n):
            position[p, 0] += rng.uniform(-jitter, jitter)
            position[p, 1] += rng.uniform(-jitter, jitter)
    return position


# Random sequential addition of equal spheres saturates at a volume fraction of 0.3828
# (Zhang & Torquato 2013, Phys. Rev. E 88, 053312): a fill asking for more can never be
# placed, however long it tries, so it is refused before the first attempt. Walls only
# lower the fraction of the whole region (a face leaves a thin layer half empty; measured
# with radius 1 mm at 20,000 failures in a row: 0.28 of a 12 mm cube, 0.31 of a
# 30 x 30 x 20 mm box), so the region itself is the volume, not the region shrunk by the
# radius: the centres' region (a radius off each face) measured 0.40-0.48 on fills that
# succeed, and it vanishes for a layer one sphere thick, which fills 2/3 x 0.547 (random
# sequential addition of discs) = 0.36 of its region.
RSA_SATURATION = 0.383
# The bound above needs a bulk: a channel one sphere wide fills 0.7476 (Renyi) x pi/6 =
# 0.39 of its region, and unequal spheres saturate higher (small ones fill the gaps) by an
# amount that depends on the distribution. For those the bound is random close packing,
# which no addition without moving spheres reaches.
RANDOM_CLOSE_PACKING = 0.64
BULK_DIAMETERS = 4  # a region at least this many largest diameters wide on every axis

# Consecutive failed attempts after which a fill is declared jammed. Measured here with
# radius 1 mm: in a 30 x 30 x 20 mm region the longest run of failures before a success
# was 545 at 25 % solid and 10,009 at 30 %, and runs grow fast towards saturation (0.38):
# 10x that margin, at ~30 us an attempt, costs 3 s before a jammed fill is refused.
MAX_CONSECUTIVE_FAILURES = 100_000


def random_packing(lower, upper, count: int, radius_min: float, radius_max: float, seed: int = 12345,
                   max_consecutive_failures: int = MAX_CONSECUTIVE_FAILURES) -> tuple[np.ndarray, np.ndarray]:
    """``count`` spheres with radii uniform in [radius_min, radius_max], centres uniform
    in the region (every sphere wholly inside), none overlapping: random sequential
    addition with a cell grid of width 2 radius_max for the overlap test. Refused before
    the first attempt when the spheres would fill more of the region than random
    sequential addition can (RSA_SATURATION, or RANDOM_CLOSE_PACKING for unequal radii or
    a narrow region), and after max_consecutive_failures overlapping attempts in a row."""
    rng = np.random.default_rng(seed)
    lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
    if np.any(upper - lower <= 2 * radius_max):
        raise ValueError("the region is too small for a sphere of radius radius_max")
    volume = float(np.prod(upper - lower))
    equal = radius_max <= radius_min
    # mean of r^3 for r uniform in [a, b] is (b^4 - a^4) / (4 (b - a))
    mean_cube = radius_min ** 3 if equal else (radius_max ** 4 - radius_min ** 4) / (4.0 * (radius_max - radius_min))
    fraction = count * 4.0 / 3.0 * np.pi * mean_cube / volume
    bulk = bool(np.all(upper - lower >= BULK_DIAMETERS * 2.0 * radius_max))
    limit = RSA_SATURATION if equal and bulk else RANDOM_CLOSE_PACKING
    if fraction > limit:
        sizes = f"of radius {radius_min:g} m" if equal else f"of radii {radius_min:g}..{radius_max:g} m"
        which = ("equal spheres" if limit == RSA_SATURATION else
                 "unequal spheres" if not equal else f"spheres in a region under {BULK_DIAMETERS} diameters wide")
        raise ValueError(f"count = {count} spheres {sizes} would fill {fraction:.3f} of the region's volume; "
                         f"random sequential addition of {which} jams below {limit}: enlarge the region or "
                         f"reduce count well below {int(count * limit / fraction)} (the count at that limit), "
                         "or fill loosely and let the particles settle")
    _check_memory(count, "count")
    cell = 2.0 * radius_max
    grid: dict[tuple, list[int]] = {}
    position = np.empty((count, 3))
    radius = rng.uniform(radius_min, radius_max, count) if radius_max > radius_min else np.full(count, radius_min)
    placed = 0
    attempts = 0
    failures = 0
    while placed < count:
        attempts += 1
        if failures >= max_consecutive_failures:
            jammed = 4.0 / 3.0 * np.pi * float(np.sum(radius[:placed] ** 3)) / volume
            raise ValueError(f"placed only {placed} of {count} non-overlapping spheres in the region "
                             f"after {attempts - 1} attempts ({failures} in a row failed: it is jammed at "
                             f"{jammed:.3f} of the region, "
                             f"{count} spheres would fill {fraction:.3f}): the region is too full; enlarge it "
                             "or reduce count")
        r = radius[placed]
        x = rng.uniform(lower + r, upper - r)
        key = tuple((x // cell).astype(np.int64))
        clear = True
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    for other in grid.get((key[0] + dx, key[1] + dy, key[2] + dz), ()):
                        if np.sum((position[other] - x) ** 2) < (r + radius[other]) ** 2:
                            clear = False
                            break
                    if not clear:
                        break
                if not clear:
                    break
            if not clear:
                break
        if clear:
            position[placed] = x
            grid.setdefault(key, []).append(placed)
            placed += 1
            failures = 0
        else:
            failures += 1
    return position, radius


CSV_COLUMNS = ("x", "y", "z", "radius", "vx", "vy", "vz", "wx", "wy", "wz")


def _check_csv_header(path: Path) -> None:
    """The header line names only columns minidem reads: a file without a header (its
    first particle would be taken as one) or with a column that would be ignored (Vx for
    vx: the particle would start at rest) is refused."""
    with open(path, encoding="utf-8") as handle:
        header = next((line.split("#", 1)[0] for line in handle if line.split("#", 1)[0].strip()), None)
    if header is None:
        return  # empty: refused by the caller
    cells = [cell.strip() for cell in next(csv.reader([header]))]
    numbers = 0
    for cell in cells:
        try:
            float(cell)
            numbers += 1
        except ValueError:
            pass
    if cells and numbers == len(cells):
        raise ValueError(f"particle CSV '{path}' has no header line: its first line ({header.strip()[:60]}) is "
                         f"numbers; put a header first, e.g. {','.join(CSV_COLUMNS[:4])}")
    unknown = [c for c in cells if c not in CSV_COLUMNS]
    if unknown:
        raise ValueError(f"particle CSV '{path}' has column(s) {unknown} that minidem does not read (they would "
                         f"be ignored); valid columns (lower case): {', '.join(CSV_COLUMNS)}")
    repeated = sorted({c for c in cells if cells.count(c) > 1})
    if repeated:
        raise ValueError(f"particle CSV '{path}' has column(s) {repeated} more than once")


def read_particles(path: str | Path) -> dict[str, np.ndarray]:
    """Particles from a file: CSV with a header naming at least x, y, z, radius (and
    optionally vx, vy, vz, wx, wy, wz), or any point file meshio reads (.vtu, .vtk, ...)
    with a point array ``radius`` (and optionally ``velocity``, ``angular_velocity``),
    such as a frame minidem wrote. Returns position, radius, velocity, angular_velocity."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"no such particle file '{path}'")
    if path.is_dir():
        raise ValueError(f"particle file '{path}' is a directory; give a CSV or point file (.vtu, .vtk, ...)")
    if path.suffix.lower() == ".csv":
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "Empty input file": refused below, by name
                table = np.genfromtxt(path, delimiter=",", names=True, dtype=np.float64, encoding="utf-8")
        except ValueError as exc:
            raise ValueError(f"cannot read particle CSV '{path}': {exc}") from None
        table = np.atleast_1d(table)
        names = table.dtype.names or ()
        _check_csv_header(path)
        if names and table.size == 0:
            raise ValueError(f"particle CSV '{path}' has a header ({','.join(names)}) but no data rows; "
                             "give one row per particle")
        # the cells as written (genfromtxt reads text that is not a number as NaN), with
        # the lines genfromtxt skips skipped the same way: blank ones, and '#' comments
        # (a whole line, or the end of one)
        with open(path, encoding="utf-8") as handle:
            lines = [line.split("#", 1)[0] for line in handle]
        cells = [row for row in csv.reader(line for line in lines if line.strip())][1:]
        missing = [c for c in ("x", "y", "z", "radius") if c not in names]
        if missing:
            raise ValueError(f"particle CSV '{path}' lacks column(s) {missing}; its header has {list(names)}")
        for triple in (("vx", "vy", "vz"), ("wx", "wy", "wz")):
            present = [k for k in triple if k in names]
            if present and len(present) < 3:
                raise ValueError(f"particle CSV '{path}' has column(s) {present} but not "
                                 f"{[k for k in triple if k not in names]}: give all of {', '.join(triple)} or none")

        def columns(keys):
            return (np.column_stack([table[k] for k in keys]) if all(k in names for k in keys)
                    else np.zeros((len(table), 3)))

        labels = {"position": ("column 'x'", "column 'y'", "column 'z'"), "radius": ("column 'radius'",),
                  "velocity": ("column 'vx'", "column 'vy'", "column 'vz'"),
                  "angular_velocity": ("column 'wx'", "column 'wy'", "column 'wz'")}
        where = lambda row: f"data row {row + 1} (counting from 1 after the header)"  # noqa: E731
        column_of = {"position": ("x", "y", "z"), "radius": ("radius",), "velocity": ("vx", "vy", "vz"),
                     "angular_velocity": ("wx", "wy", "wz")}

        def written(name, row, column):
            """The cell's text when it is not a number (genfromtxt gave NaN), else None."""
            k = names.index(column_of[name][column])
            text = cells[row][k].strip() if row < len(cells) and k < len(cells[row]) else ""
            try:
                float(text)
            except ValueError:
                return "empty" if not text else f"{text!r}, not a number"
            return None
        unit = "row"

        out = {"position": columns(("x", "y", "z")), "radius": np.asarray(table["radius"], dtype=np.float64),
               "velocity": columns(("vx", "vy", "vz")), "angular_velocity": columns(("wx", "wy", "wz"))}
    else:
        import meshio

        try:
            mesh = meshio.read(str(path))
        except Exception as exc:  # noqa: BLE001
            raise ValueError(f"cannot read particle file '{path}': {exc}") from None
        if "radius" not in mesh.point_data:
            raise ValueError(f"particle file '{path}' has no point array 'radius' (arrays: "
                             f"{', '.join(mesh.point_data) or 'none'})")
        n = len(mesh.points)
        out = {"position": np.asarray(mesh.points, dtype=np.float64).reshape(n, 3),
               "radius": np.asarray(mesh.point_data["radius"], dtype=np.float64).reshape(n),
               "velocity": np.asarray(mesh.point_data.get("velocity", np.zeros((n, 3))), dtype=np.float64).reshape(n, 3),
               "angular_velocity": np.asarray(mesh.point_data.get("angular_velocity", np.zeros((n, 3))),
                                              dtype=np.float64).reshape(n, 3)}
        labels = {"position": ("point coordinate x", "point coordinate y", "point coordinate z"),
                  "radius": ("point array 'radius'",),
                  "velocity": tuple(f"point array 'velocity' component {c}" for c in "xyz"),
                  "angular_velocity": tuple(f"point array 'angular_velocity' component {c}" for c in "xyz")}
        where = lambda row: f"point {row} (counting from 0)"  # noqa: E731
        written = lambda name, row, column: None  # noqa: E731
        unit = "point"
    for name in ("position", "radius", "velocity", "angular_velocity"):
        values = out[name].reshape(len(out[name]), -1)
        bad = ~np.isfinite(values)
        if name == "radius":
            bad |= ~(values > 0)
        if np.any(bad):
            row, column = (int(k) for k in np.argwhere(bad)[0])
            count = int(np.count_nonzero(np.any(bad, axis=1)))
            expected = "a finite number > 0 (m)" if name == "radius" else "a finite number"
            text = written(name, row, column) if np.isnan(values[row, column]) else None
            raise ValueError(f"particle file '{path}': {labels[name][column]} ({name}) of {where(row)} is "
                             f"{text or format(float(values[row, column]), 'g')}, expected {expected}"
                             + (f"; {count - 1} more {unit}(s) like it" if count > 1 else ""))
    return out
