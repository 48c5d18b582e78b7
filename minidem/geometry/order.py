"""The order particles are stored in: spatial, so that a particle's neighbours are its
neighbours in memory too.

The force pass walks the particles in storage order and reads each one's listed partners.
When storage order follows space (a lattice fill, x fastest, then y, then z), the partners
of the particles in flight are a few hundred places apart and stay in cache; when it does
not (a scene built from arrays in any order, particles read from a file written by another
code, a fill whose particles arrive in random order), nearly every partner read misses the
cache, and the cost per particle grows with N as the working set outgrows each cache level.
Measured on the settle scene with its particles in random order, one thread, the first 1,000
steps (docs/benchmarks.md, "Cost per particle against N"): 1.5x slower than in the fill's
order at 20,000 particles, 2.4x at 200,000.

So a scene whose order is scattered is stored sorted by cells of half the list cutoff,
layer by layer (z, then y, then x), as LAMMPS' ``atom_modify sort`` does with its bins (of
that size by default). That is nearly the order a lattice fill makes: a shuffled lattice
(spacing above the cell) sorts back to its fill's layers and rows. Coarser cells (the whole cutoff)
put two layers of the settle lattice in one cell now and then, and ran its first 400 steps
20 % slower at 200,000 particles than the fill's order. The sort is stable, so
the same scene always gives the same order and a run stays bit-for-bit repeatable. A scene
already in a spatial order is left as it is (:func:`scattered`): its order is the user's,
and its results keep their bits.
"""

from __future__ import annotations

import functools

import numpy as np

# A scene's order is taken as scattered when consecutive particles are on average this many
# times further apart than in the sorted order. The settle scene at 200,000 (0.1 m box,
# spheres of 1 mm): random order 96 mm against 4.5 mm sorted (21x); the lattice fill's own
# order 4.2 mm (0.92x: its rows' ends jump across the box, as the sorted order's do)
SCATTERED_RATIO = 4.0


def spatial_order(position: np.ndarray, cell_size: float) -> np.ndarray:
    """The permutation that sorts particles by the cell of side ``cell_size`` (m) they are
    in, cells in layers of z, rows of y, then x; ties in the given order (stable)."""
    if position.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    cell = np.floor((position - position.min(axis=0)) / cell_size).astype(np.int64)
    # lexsort: the last key is the primary one; no packed key that could overflow when a
    # particle lies far from the others
    return np.lexsort((cell[:, 0], cell[:, 1], cell[:, 2])).astype(np.int64)


# mean_step looks at this many consecutive pairs at most, drawn at random with a fixed
# seed (the same pairs every call, so the run's decisions are repeatable): the mean of a
# million steps to about 1 %, in about 1 ms. Not evenly spaced: a stride shares a factor
# with a lattice's row length now and then (12 and 45 in the settle scene at 200,000) and
# then never meets a row's end
STEP_SAMPLES = 16_384


@functools.lru_cache(maxsize=4)
def _step_samples(n: int) -> np.ndarray:
    """The first particles of the pairs mean_step looks at among ``n`` (drawn once per n:
    a run's every list build asks again, and the draw and its sort were half the call)."""
    first = np.sort(np.random.default_rng(0).integers(0, n - 1, STEP_SAMPLES))
    first.flags.writeable = False
    return first


def mean_step(position: np.ndarray) -> float:
    """The mean distance (m) between particles stored one after the other (of up to
    STEP_SAMPLES pairs)."""
    n = position.shape[0]
    if n < 2:
        return 0.0
    if n - 1 <= STEP_SAMPLES:
        step = np.diff(position, axis=0)
    else:
        first = _step_samples(n)
        step = position[first + 1] - position[first]
    return float(np.sqrt(np.einsum("ij,ij->i", step, step)).mean())


def scattered(position: np.ndarray, order: np.ndarray) -> bool:
    """Whether the particles' own order is far less local than ``order``: consecutive
    particles SCATTERED_RATIO times further apart on average."""
    return mean_step(position) > SCATTERED_RATIO * mean_step(position[order])


def permute_rows(offsets: np.ndarray, order: np.ndarray, *columns: np.ndarray):
    """A CSR list (``offsets``, one row per particle, and ``columns`` with one row per
    entry) with its particle rows put in ``order`` (``order[k]``: the old row that becomes
    row k): (new offsets, the columns' entries in the new rows' order)."""
    counts = np.diff(offsets)[order]
    new_offsets = np.zeros(offsets.shape[0], dtype=offsets.dtype)
    np.cumsum(counts, out=new_offsets[1:])
    entries = np.repeat(offsets[:-1][order] - new_offsets[:-1], counts) + np.arange(new_offsets[-1])
    return new_offsets, tuple(column[entries] for column in columns)


def exchange_pairs(offsets: np.ndarray, partners: np.ndarray, history: np.ndarray, overlap: np.ndarray,
                   order: np.ndarray, exchange_signs: np.ndarray):
    """The half list of pairs (i, j > i: row i lists j, ascending) with its particles
    renumbered by ``order`` (``order[k]``: the old particle that becomes k): each pair
    listed again under the smaller of its new numbers, rows ascending, and the history of a
    pair whose spheres' order turned over multiplied by ``exchange_signs`` (the law's
    HistorySlot.exchange per history float: the contact as seen from its other sphere).
    Returns (offsets, partners, history, overlap) of the renumbered list."""
    n = offsets.shape[0] - 1
    # in the partners' own integer type (int32 below 2**31 particles): the renumbering's
    # temporaries are a few per list entry, at the peak of a large run's rebuild
    new_number = np.empty(n, dtype=partners.dtype)
    new_number[order] = np.arange(n, dtype=partners.dtype)
    first = np.repeat(new_number, np.diff(offsets))
    second = new_number[partners]
    turned = first > second
    smaller = np.minimum(first, second)
    np.maximum(first, second, out=second)
    first = smaller
    del smaller
    entries = np.lexsort((second, first))
    new_offsets = np.zeros(n + 1, dtype=offsets.dtype)
    np.cumsum(np.bincount(first, minlength=n), out=new_offsets[1:])
    del first
    new_history = history[entries]
    turned = turned[entries]
    for column in np.flatnonzero(np.asarray(exchange_signs) < 0):
        values = new_history[:, column]
        np.negative(values, out=values, where=turned)
        # + 0.0: a zero slot stays +0.0 (a row of -0.0 would read as a contact's history)
        np.add(values, 0.0, out=values, where=turned)
    return new_offsets, second[entries], new_history, overlap[entries]
