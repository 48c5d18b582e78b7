"""Cell-list Verlet neighbour search for spheres.

A pair (i, j) is listed when its centre distance is below ``r_i + r_j + skin``. The
list stays valid for contact detection until some particle has moved more than
``skin / 2`` since the build (see :func:`max_displacement_exceeded`).

The result is a half list in CSR form: the neighbours j > i of particle i are
``neighbours[offsets[i]:offsets[i + 1]]``, sorted ascending. Every pair appears exactly
once, so a contact loop ``for i in prange(n)`` owns row i and can accumulate into
particle i without races, and the content does not depend on the thread count or on
the cell grid.

All heavy functions are ``numba.njit`` with plain-array signatures, so an engine can
call them from its own compiled loop. :class:`NeighbourList` is the convenience wrapper
for Python callers.
"""

import time

import numba
import numpy as np

from minidem import compile_speed
from minidem.geometry.primitives import triangle_closest_point

# the check of a scene for overlapping spheres compiles the search before the engine is
# imported: numba's compiles made faster from the first (minidem.compile_speed)
compile_speed.install()

# Cells per particle allowed before the cell size is enlarged. Bounds memory by O(N)
# when a few far-apart particles would otherwise span a huge, almost empty grid.
MAX_CELLS_PER_PARTICLE = 8

# Neighbours of a particle kept from the list build's one scan (int32 each, 4 bytes a
# particle apiece while the list is built, at the peak of a large run's memory); a longer
# row is scanned again. A falling column of equal spheres has 3 a particle (half list:
# j > i), a settled pile 4.8 on average, 58 % of its rows more than 4 and 1 % more than 8:
# with 8, its build takes 87 ms instead of 130 (N = 200,000, one thread), for 16 bytes a
# particle more while a list is built.
ROW_SCRATCH = 8

# Relative margin on the cell size so that rounding in the binning can never place two
# particles closer than the cutoff more than one cell apart.
_CELL_SIZE_MARGIN = 1e-9


@numba.njit(cache=True)
def _cell_grid(positions, cell_size, max_cells):
    """Grid over the bounding box of ``positions`` with cells no smaller than
    ``cell_size`` and at most ``max_cells`` cells.

    Returns (lower_corner (3,), cells_per_axis (3,) int64, inverse_cell_width (3,)).
    """
    n_particles = positions.shape[0]
    lower = np.empty(3)
    upper = np.empty(3)
    for axis in range(3):
        lower[axis] = np.inf
        upper[axis] = -np.inf
    for p in range(n_particles):
        for axis in range(3):
            x = positions[p, axis]
            if not np.isfinite(x):
                # An exploded simulation should stop loudly, not be binned silently.
                raise ValueError("neighbour search: non-finite particle position")
            lower[axis] = min(lower[axis], x)
            upper[axis] = max(upper[axis], x)
    extent = np.empty(3)
    for axis in range(3):
        if n_particles == 0:
            lower[axis] = 0.0
            upper[axis] = 0.0
        extent[axis] = upper[axis] - lower[axis]

    cells_per_axis = np.ones(3, dtype=np.int64)
    while True:
        total = 1.0
        for axis in range(3):
            # Floor, so the actual cell width extent / n is never below cell_size.
            # Capping in float before the int cast avoids overflow for huge boxes.
            n = max(1.0, min(np.floor(extent[axis] / cell_size), float(max_cells)))
            cells_per_axis[axis] = np.int64(n)
            total *= n
        if total <= max_cells:
            break
        # Shrink the cell count towards the cap in one step (at least halve it).
        cell_size *= max(1.26, (total / max_cells) ** (1.0 / 3.0))

    inverse_cell_width = np.zeros(3)
    for axis in range(3):
        if extent[axis] > 0.0:
            inverse_cell_width[axis] = cells_per_axis[axis] / extent[axis]
    return lower, cells_per_axis, inverse_cell_width


@numba.njit(cache=True, parallel=True)
def _bin_particles(positions, lower, cells_per_axis, inverse_cell_width):
    """Counting sort of particles into cells.

    Returns (cell_of_particle (N,), cell_start (n_cells + 1,), particles_by_cell (N,)):
    the particles of cell c are ``particles_by_cell[cell_start[c]:cell_start[c + 1]]``,
    in ascending index order.
    """
    n_particles = positions.shape[0]
    nx, ny, nz = cells_per_axis[0], cells_per_axis[1], cells_per_axis[2]
    # int32, as particles_by_cell: build_pairs caps the cells below 2**31
    cell_of_particle = np.empty(n_particles, dtype=np.int32)
    for p in numba.prange(n_particles):
        # Clamp: the particle on the upper bounding face floors to index n.
        cx = min(np.int64((positions[p, 0] - lower[0]) * inverse_cell_width[0]), nx - 1)
        cy = min(np.int64((positions[p, 1] - lower[1]) * inverse_cell_width[1]), ny - 1)
        cz = min(np.int64((positions[p, 2] - lower[2]) * inverse_cell_width[2]), nz - 1)
        cell_of_particle[p] = (cx * ny + cy) * nz + cz

    cell_start = np.zeros(nx * ny * nz + 1, dtype=np.int64)
    for p in range(n_particles):
        cell_start[cell_of_particle[p] + 1] += 1
    for c in range(nx * ny * nz):
        cell_start[c + 1] += cell_start[c]
    # element by element, here and below: slice and whole-array expressions compile numba's
    # general array machinery (0.4 s of CPU in every first compile of build_pairs)
    next_slot = np.empty(nx * ny * nz, dtype=np.int64)
    for c in range(nx * ny * nz):
        next_slot[c] = cell_start[c]
    # int32: the neighbours' type (build_pairs); 4 bytes a particle less at a rebuild's peak
    particles_by_cell = np.empty(n_particles, dtype=np.int32)
    for p in range(n_particles):
        c = cell_of_particle[p]
        particles_by_cell[next_slot[c]] = p
        next_slot[c] += 1
    return cell_of_particle, cell_start, particles_by_cell


@numba.njit(cache=True)
def _scan_neighbourhood(i, cell, cells_per_axis, cell_start, particles_by_cell,
                        sorted_positions, sorted_radii, radius_index_mask, radius_i, position_i, skin, out):
    """Count the neighbours j > i of particle i found in the up to 27 cells around
    ``cell``, and store them in ``out`` in scan order: all of them if they fit, else the
    first ``len(out) - 1`` (those past them are written over its last slot). The radius
    of the particle at cell-order position k is ``sorted_radii[k & radius_index_mask]``."""
    nx, ny, nz = cells_per_axis[0], cells_per_axis[1], cells_per_axis[2]
    last = out.shape[0] - 1
    cz = cell % nz
    cy = (cell // nz) % ny
    cx = cell // (nz * ny)
    found = 0
    # Clamping the stencil to the grid (no periodicity) also prevents visiting a cell
    # twice when an axis has fewer than three cells.
    z_first = max(cz - 1, 0)
    z_last = min(cz + 1, nz - 1)
    for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
        for ay in range(max(cy - 1, 0), min(cy + 2, ny)):
            # Cells adjacent along z are adjacent in memory: one contiguous run of
            # particles per (x, y) column instead of three short ones.
            column = (ax * ny + ay) * nz
            for k in range(cell_start[column + z_first], cell_start[column + z_last + 1]):
                j = particles_by_cell[k]
                dx = sorted_positions[k, 0] - position_i[0]
                dy = sorted_positions[k, 1] - position_i[1]
                dz = sorted_positions[k, 2] - position_i[2]
                cutoff = radius_i + sorted_radii[k & radius_index_mask] + skin
                # One combined, rarely true test instead of an early `j <= i` skip:
                # index order is random within a cell, so that branch would be
                # mispredicted about half the time, costing more than the distance.
                # (Storing every candidate unconditionally at the count, advanced only
                # by a neighbour, was 30 % slower: the store waits on the count.)
                if (j > i) & (dx * dx + dy * dy + dz * dz < cutoff * cutoff):
                    out[min(found, last)] = j
                    found += 1
    return found


@numba.njit(cache=True, parallel=True)
def build_pairs(positions, radii, skin):
    """Verlet half list of all pairs with centre distance < r_i + r_j + skin.

    Parameters
    ----------
    positions : (N, 3) float64, m
    radii : (N,) float64, m
    skin : float, m, >= 0

    Returns
    -------
    offsets : (N + 1,) int64
    neighbours : (offsets[N],) int32
        Neighbours j > i of particle i are ``neighbours[offsets[i]:offsets[i + 1]]``,
        sorted ascending.
    """
    n_particles = positions.shape[0]
    if skin < 0.0:
        raise ValueError("neighbour search: skin must be >= 0")
    if n_particles >= 2**31:
        raise ValueError("neighbour search: more than 2**31 - 1 particles (int32 indices)")
    max_radius = 0.0
    for p in range(n_particles):
        max_radius = max(max_radius, radii[p])
    # The largest possible cutoff fits in one cell, so the 27-cell stencil is complete
    # for every particle, however polydisperse the packing.
    cell_size = (2.0 * max_radius + skin) * (1.0 + _CELL_SIZE_MARGIN)
    if n_particles > 0 and cell_size <= 0.0:
        raise ValueError("neighbour search: 2 * max(radii) + skin must be > 0")

    max_cells = min(max(MAX_CELLS_PER_PARTICLE * n_particles, 1), 2**31 - 1)
    lower, cells_per_axis, inverse_cell_width = _cell_grid(positions, cell_size, max_cells)
    cell_of_particle, cell_start, particles_by_cell = _bin_particles(
        positions, lower, cells_per_axis, inverse_cell_width)

    # Cell-ordered copies: the inner loop then streams through contiguous memory, and
    # the outer loop walks particles in cell order so neighbouring iterations share
    # cache lines whatever the input ordering.
    # Equal radii (a monodisperse packing) are one value, read at index k & 0 = 0: 8 bytes a
    # particle less at the build, the peak of a large run's memory; else k & -1 = k.
    equal_radii = True
    for p in range(n_particles):
        equal_radii &= radii[p] == radii[0]
    radius_index_mask = 0 if equal_radii else -1
    sorted_positions = np.empty((n_particles, 3))
    sorted_radii = np.empty(1 if equal_radii else n_particles)
    if equal_radii and n_particles > 0:
        sorted_radii[0] = radii[0]
    for k in numba.prange(n_particles):
        p = particles_by_cell[k]
        sorted_positions[k, 0] = positions[p, 0]
        sorted_positions[k, 1] = positions[p, 1]
        sorted_positions[k, 2] = positions[p, 2]
        if not equal_radii:
            sorted_radii[k] = radii[p]

    # One scan: each row's count goes straight into the offsets (summed in place after),
    # and its first ROW_SCRATCH neighbours into a scratch row, from which the list is
    # filled at the prefix-sum offsets: no per-thread buffers or atomics, and the layout
    # is independent of the thread count. Only a longer row is scanned a second time.
    scratch = np.empty((n_particles, ROW_SCRATCH), dtype=np.int32)
    offsets = np.zeros(n_particles + 1, dtype=np.int64)
    for k in numba.prange(n_particles):
        i = particles_by_cell[k]
        offsets[i + 1] = _scan_neighbourhood(
            i, cell_of_particle[i], cells_per_axis, cell_start, particles_by_cell,
            sorted_positions, sorted_radii, radius_index_mask, sorted_radii[k & radius_index_mask],
            sorted_positions[k], skin, scratch[k])
    for i in range(n_particles):
        offsets[i + 1] += offsets[i]

    neighbours = np.empty(offsets[n_particles], dtype=np.int32)
    for k in numba.prange(n_particles):
        i = particles_by_cell[k]
        row = neighbours[offsets[i]:offsets[i + 1]]
        length = row.shape[0]
        if length <= ROW_SCRATCH:
            for a in range(length):
                row[a] = scratch[k, a]
        else:
            _scan_neighbourhood(
                i, cell_of_particle[i], cells_per_axis, cell_start, particles_by_cell,
                sorted_positions, sorted_radii, radius_index_mask, sorted_radii[k & radius_index_mask],
                sorted_positions[k], skin, row)
        # Ascending j makes the list canonical (independent of the grid, which moves
        # with the bounding box) and gives the contact loop increasing memory access.
        # insertion sort: rows are a few dozen entries at most, and the same order as
        # row.sort(), whose quicksort cost 1.7 s of CPU in every first compile
        for a in range(1, length):
            value = row[a]
            b = a - 1
            while b >= 0 and row[b] > value:
                row[b + 1] = row[b]
                b -= 1
            row[b + 1] = value
    return offsets, neighbours


@numba.njit(cache=True)
def max_displacement_exceeded(positions, positions_at_build, skin):
    """True when any particle has moved more than skin / 2 since the list was built.

    Half the skin, because two particles approaching head-on each close the gap by
    their own displacement: if neither moved more than skin / 2, a pair that was not
    listed (distance >= r_i + r_j + skin at build) is still at distance >= r_i + r_j,
    so no contact can be missing from the list.
    """
    limit_squared = (0.5 * skin) ** 2
    for p in range(positions.shape[0]):
        dx = positions[p, 0] - positions_at_build[p, 0]
        dy = positions[p, 1] - positions_at_build[p, 1]
        dz = positions[p, 2] - positions_at_build[p, 2]
        # Serial with early exit: after a rebuild-worthy step the answer usually comes
        # within a few particles, and the full scan is cheap next to a build.
        if dx * dx + dy * dy + dz * dz > limit_squared:
            return True
    return False


class NeighbourList:
    """Verlet list that rebuilds itself only when the skin criterion requires it.

    ``offsets`` and ``neighbours`` hold the current CSR half list (see
    :func:`build_pairs`).
    """

    def __init__(self, skin):
        if skin < 0.0:
            raise ValueError("skin must be >= 0")
        self.skin = float(skin)
        self.offsets = None
        self.neighbours = None
        self.positions_at_build = None
        self.radii_at_build = None
        self.n_builds = 0

    def update(self, positions, radii):
        """Rebuild if needed; return True when the list was rebuilt."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        radii = np.ascontiguousarray(radii, dtype=np.float64)
        stale = (
            self.positions_at_build is None
            or positions.shape != self.positions_at_build.shape
            # A growing radius eats into the skin just like a displacement; shrinking
            # ones only leave the list a larger superset than needed.
            or bool(np.any(radii > self.radii_at_build))
            or max_displacement_exceeded(positions, self.positions_at_build, self.skin)
        )
        if not stale:
            return False
        self.offsets, self.neighbours = build_pairs(positions, radii, self.skin)
        self.positions_at_build = positions.copy()
        self.radii_at_build = radii.copy()
        self.n_builds += 1
        return True


def _random_packing(n_particles, volume_fraction=0.3, seed=0):
    """Uniformly random centres in a cube, radii uniform in [0.5, 1] mm, with the cube
    sized for the given solid volume fraction (overlaps allowed)."""
    rng = np.random.default_rng(seed)
    radii = rng.uniform(0.5e-3, 1.0e-3, n_particles)
    box_side = (np.sum(4.0 / 3.0 * np.pi * radii**3) / volume_fraction) ** (1.0 / 3.0)
    positions = rng.uniform(0.0, box_side, (n_particles, 3))
    return positions, radii


def benchmark_scaling(n_values=(2_000, 20_000, 200_000), thread_counts=(1, 2),
                      repeats=3, skin=0.2e-3):
    """Median wall time of :func:`build_pairs` on random packings at fixed density.

    Returns {(n_particles, n_threads): seconds}. Compilation is excluded by a warm-up
    call. A measurement, not a test: constant seconds / n_particles means linear cost.
    """
    previous_threads = numba.get_num_threads()
    times = {}
    try:
        warm_positions, warm_radii = _random_packing(100)
        build_pairs(warm_positions, warm_radii, skin)
        for n_particles in n_values:
            positions, radii = _random_packing(int(n_particles))
            for n_threads in thread_counts:
                numba.set_num_threads(min(n_threads, numba.config.NUMBA_NUM_THREADS))
                samples = []
                for _ in range(repeats):
                    start = time.perf_counter()
                    build_pairs(positions, radii, skin)
                    samples.append(time.perf_counter() - start)
                times[(int(n_particles), n_threads)] = float(np.median(samples))
    finally:
        numba.set_num_threads(previous_threads)
    return times


# ---------------------------------------------------------------------------------
# per-contact state across rebuilds
# ---------------------------------------------------------------------------------
_CARRY_BLOCK = 1024  # rows of a carry_history block


@numba.njit(cache=True, parallel=True)
def carry_history(old_offsets, old_keys, old_rows, old_values, old_overlap, new_offsets, new_keys, history,
                  overlap):
    """Per-entry contact state of a rebuilt CSR list, taken over from the old one.

    Both lists have the same rows (``old_offsets`` and ``new_offsets`` are each N + 1
    long: the same particles) and hold, per row, ascending keys (partner particles j > i, triangle ids or
    plane indices); a merge of the two sorted rows copies the history and last overlap
    of every (row, key) present in both. The old histories come as their rows in use
    alone (``old_rows``, ascending entry indices, and ``old_values``; the other rows are
    zero: ``minidem.engine.state.rows_in_use``), so that a rebuild can release the old
    array before it makes the new one (24 bytes a list entry of a pile's peak, the
    history of every listed pair, touching or not). ``history`` (one row per new entry)
    must hold zeros: the carried rows are written into it, the others left alone, so an
    array from the operating system's zeroed pages (numpy's np.zeros) stays unwritten,
    and not resident, where no contact was carried (24 bytes a list entry of a loose or
    falling phase). ``overlap`` (one per new entry) holds, on entry, the last overlap a
    new entry starts with (the caller's: -1 for pairs and mesh candidates, the current
    overlap for planes); the carried entries' are written over it. The list's margin (the
    Verlet skin, plus the law's reach) guarantees that a contact absent from the old list
    was not engaged, so no live contact loses its history. Rows are independent, so the
    result does not depend on the thread count.
    """
    n_rows = new_offsets.shape[0] - 1
    width = old_values.shape[1]
    in_use = old_rows.shape[0]
    # Rows by blocks: the first history in use of a block's first row is searched for,
    # and followed up the rows from there (the entries in use, as the rows, ascend): one
    # binary search a row cost as much as the merge itself (the settled pile of 200,000,
    # 970,000 entries: 20 ms against 10 on one thread, 10 against 5 on two)
    for block in numba.prange((n_rows + _CARRY_BLOCK - 1) // _CARRY_BLOCK):
        first_row = block * _CARRY_BLOCK
        c = np.searchsorted(old_rows, old_offsets[first_row]) if in_use else 0
        for row in range(first_row, min(first_row + _CARRY_BLOCK, n_rows)):
            a, a_end = old_offsets[row], old_offsets[row + 1]
            for b in range(new_offsets[row], new_offsets[row + 1]):
                key = new_keys[b]
                while a < a_end and old_keys[a] < key:
                    a += 1
                if a < a_end and old_keys[a] == key:
                    while c < in_use and old_rows[c] < a:
                        c += 1
                    if c < in_use and old_rows[c] == a:
                        for k in range(width):
                            history[b, k] = old_values[c, k]
                    overlap[b] = old_overlap[a]


def reverse_index(offsets, neighbours, n_particles):
    """The transposed half list: for each particle p the entries (i, p) naming it as the
    partner, in ascending i (a counting sort, O(N + M)).

    Returns (reverse_offsets (N + 1,) int64, slot (M,) of the neighbours' type,
    first_partner (N,) int64): p's entries occupy positions
    reverse_offsets[p]..reverse_offsets[p + 1] of the transposed order, and entry e is
    at position slot[e]. The engine stores each pair's reaction at its slot, so p reads
    its reactions contiguously and adds them in a fixed order whatever the thread count.
    first_partner[p] is the row of p's first transposed entry, the smallest i whose row
    lists p (p itself if none): the kernel's thread blocks need it
    (``minidem.engine.blocks``), and it changes only with the list, so it is found here,
    in the pass that visits the entries in ascending i anyway.

    The arrays are numpy's, filled by compiled code (``fill_reverse_index``): numpy asks
    for transparent huge pages for arrays of 4 MiB and more, which the force pass reads
    every step (``minidem.engine.state.numpy_owned``), and no copy of them is made at
    a list rebuild, the peak of a large run's memory.
    """
    reverse_offsets = np.zeros(n_particles + 1, dtype=np.int64)
    # the partners' integer type (int32 in the engine's lists): a slot is below the
    # number of entries, which the engine keeps in that type's range
    slot = np.empty(neighbours.shape[0], dtype=neighbours.dtype)
    first_partner = np.arange(n_particles, dtype=np.int64)
    fill_reverse_index(offsets, neighbours, reverse_offsets, slot, first_partner)
    return reverse_offsets, slot, first_partner


@numba.njit(cache=True)
def fill_reverse_index(offsets, neighbours, reverse_offsets, slot, first_partner):
    """``reverse_index`` into its arrays: reverse_offsets zero, first_partner[p] = p."""
    n_particles = reverse_offsets.shape[0] - 1
    for e in range(neighbours.shape[0]):
        reverse_offsets[neighbours[e] + 1] += 1
    for p in range(n_particles):
        reverse_offsets[p + 1] += reverse_offsets[p]
    # each particle's next free position, counted up in place from its start (no array of
    # its own: 8 bytes a particle less at a rebuild), and shifted back to the starts after
    for i in range(n_particles):
        for e in range(offsets[i], offsets[i + 1]):
            j = neighbours[e]
            if first_partner[j] == j:  # j's first entry (a row i lists only j > i): i is the smallest
                first_partner[j] = i
            slot[e] = reverse_offsets[j]
            reverse_offsets[j] += 1
    for p in range(n_particles, 0, -1):
        reverse_offsets[p] = reverse_offsets[p - 1]
    reverse_offsets[0] = 0


_PLANE_BLOCK = 1 << 16  # spheres near_planes takes at a time


def near_planes(positions, radii, wall_point, wall_normal, margin):
    """The planes each sphere may touch before the next list build, as CSR: (offsets
    (N + 1,) int64, planes int32), sphere i's ascending in ``planes[offsets[i]:offsets[i +
    1]]``; ``margin=None``: every plane for every sphere.

    A plane is listed while the sphere's centre is closer to it than its radius plus
    ``margin`` (the skin plus the longest reach of the law): the list is rebuilt when a
    sphere has moved half the skin, so one farther away cannot come within reach first.
    In a box only the spheres along its faces are listed (the settle pile at 20,000: the
    floor layer and the side rows, about a seventh of the spheres); the others skip the
    plane checks, 23 of the force pass's instructions per sphere and plane.

    numpy, not compiled: one pass per plane, O(N x planes) at each list build, and no
    compile time in a first run."""
    n, n_planes = positions.shape[0], wall_point.shape[0]
    if margin is None:
        return (np.arange(n + 1, dtype=np.int64) * n_planes,
                np.tile(np.arange(n_planes, dtype=np.int32), n))
    offsets = np.zeros(n + 1, dtype=np.int64)
    planes = []
    # a block of spheres at a time: whole-column temporaries (the reach, each plane's
    # distances and flags, the counts: 37 bytes a sphere) were the peak of a large run's
    # list rebuild, which holds the old and the new pair list then (docs/benchmarks.md)
    for start in range(0, n, _PLANE_BLOCK):
        stop = min(start + _PLANE_BLOCK, n)
        reach = radii[start:stop] + margin
        near = []  # per plane: which spheres of the block are near it
        counts = np.zeros(stop - start, dtype=np.int64)
        for w in range(n_planes):
            # distance of the centre from the plane, one column of positions at a time (no
            # (N, 3) temporary), the normal's zero components skipped (a box's planes are
            # axis-aligned: a third of the work); a product of zero would add only a signed
            # zero, which changes no comparison
            distance = None
            for k in range(3):
                if wall_normal[w, k] != 0.0:
                    term = positions[start:stop, k] - wall_point[w, k]
                    term *= wall_normal[w, k]
                    if distance is None:
                        distance = term
                    else:
                        distance += term
            near.append(distance < reach)
            counts += near[-1]
        np.cumsum(counts, out=offsets[start + 1:stop + 1])
        offsets[start + 1:stop + 1] += offsets[start]
        # the planes of the spheres near any (a few per cent of a large pile) from those
        # rows alone: numpy's sum and nonzero along the short axis of a whole (N, planes)
        # array were 30 of the 55 ms at N = 1,000,000 (17 ms in all after)
        rows = np.flatnonzero(counts)
        listed = np.empty((rows.shape[0], n_planes), dtype=bool)
        for w in range(n_planes):
            listed[:, w] = near[w][rows]
        planes.append(np.nonzero(listed)[1].astype(np.int32))
    return offsets, np.concatenate(planes) if planes else np.zeros(0, dtype=np.int32)


def rows_of_entries(offsets, entries=None):
    """The row of each entry of a CSR list (offsets (N + 1,)), or of each of ``entries``
    (indices into it), without a temporary of N (np.repeat of np.diff): a binary search per
    entry, for the short lists (the planes near each sphere) a large run makes at every
    list build, and for a few entries of the long ones (State.deepest_contact)."""
    entries = np.arange(offsets[-1]) if entries is None else entries
    return np.searchsorted(offsets, entries, side="right") - 1


@numba.njit(cache=True)
def _triangle_box_distance_squared(p, radius_plus_skin, lower, upper):
    # products, not ** 2 (a call of the C library's pow in numba's code)
    d = 0.0
    for axis in range(3):
        if p[axis] < lower[axis]:
            d += (lower[axis] - p[axis]) * (lower[axis] - p[axis])
        elif p[axis] > upper[axis]:
            d += (p[axis] - upper[axis]) * (p[axis] - upper[axis])
    return d


@numba.njit(cache=True)
def _scan_triangles(point, reach, triangles, lower, upper, out, write):
    """Count (and, if ``write``, store into ``out``) the triangles whose closest point
    is within ``reach`` of ``point``, in ascending id; bounding boxes first."""
    found = 0
    for t in range(triangles.shape[0]):
        if _triangle_box_distance_squared(point, reach, lower[t], upper[t]) < reach * reach:
            cx, cy, cz, feature = triangle_closest_point(point[0], point[1], point[2], triangles, t)
            dx, dy, dz = point[0] - cx, point[1] - cy, point[2] - cz
            if dx * dx + dy * dy + dz * dz < reach * reach:
                if write:
                    out[found] = t
                found += 1
    return found


@numba.njit(cache=True, parallel=True)
def mesh_candidates(positions, radii, skin, triangles):
    """Triangles within r_i + skin of each particle (closest point), as a CSR list of
    ascending triangle ids; valid for contact detection under the same half-skin
    displacement rule as :func:`build_pairs`.

    Every particle tests every triangle's bounding box, then the close ones exactly:
    O(N T) per build, linear in N for a given mesh. Enough for hoppers and silos of up
    to a few thousand triangles; a cell grid over triangles would remove the T factor.
    """
    n_particles, n_triangles = positions.shape[0], triangles.shape[0]
    lower = np.empty((n_triangles, 3))
    upper = np.empty((n_triangles, 3))
    for t in range(n_triangles):
        for axis in range(3):
            lower[t, axis] = min(triangles[t, 0, axis], triangles[t, 1, axis], triangles[t, 2, axis])
            upper[t, axis] = max(triangles[t, 0, axis], triangles[t, 1, axis], triangles[t, 2, axis])
    # pass 1 counts, pass 2 fills at prefix-sum offsets (few triangles: the scan is cheap
    # enough to run twice, unlike build_pairs' cell scans)
    no_output = np.empty(0, dtype=np.int64)
    counts = np.zeros(n_particles, dtype=np.int64)
    for p in numba.prange(n_particles):
        counts[p] = _scan_triangles(positions[p], radii[p] + skin, triangles, lower, upper, no_output, False)
    offsets = np.zeros(n_particles + 1, dtype=np.int64)
    for p in range(n_particles):
        offsets[p + 1] = offsets[p] + counts[p]
    found = np.empty(offsets[n_particles], dtype=np.int64)
    for p in numba.prange(n_particles):
        _scan_triangles(positions[p], radii[p] + skin, triangles, lower, upper, found[offsets[p]:offsets[p + 1]], True)
    return offsets, found
