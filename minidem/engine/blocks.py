"""The blocks of particles the kernel's threads work on (``minidem.engine.kernel``,
``compute_forces`` and ``finish_kick_drift``), chosen before each call of its ``advance``.

Not part of the kernel: these functions depend on neither the contact law nor the
scene shape, so numba compiles them once and caches them for every kernel (a kernel
that compiled its own copy paid ~0.8 s of CPU for it in every first run, even on one
thread, where the blocks are trivial and need no compiled code: ``blocks``).

What depends on the neighbour list alone, each particle's first partner, is computed
once per list (``minidem.geometry.neighbours.reverse_index``, at each list build and
restore: ``State.first_partner``); only the bounds, which count the contacts touching
now, are found before every call, their sums in parallel (at N = 1,000,000 on two
threads the whole was 18 ms of serial work before every chunk of 50 steps).
"""

from __future__ import annotations

import numba
import numpy as np

from minidem.engine.integrate import ENERGY_BLOCK, block_particles, energy_blocks


def blocks(threads: int, planes, pairs, first_partner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bounds, first partner) of the kernel's ``advance`` for the given thread count
    (see ``thread_blocks``); ``first_partner``: the list's (``State.first_partner``), not
    written into. One thread is one block, all particles, and it is finished in the
    force pass whatever its first partner: any index in 0..n-1 gives the same operations
    in the same order, so the list's own is passed as it is."""
    n = first_partner.shape[0]
    if threads > 1:
        return thread_blocks(threads, planes, pairs, first_partner)
    return np.array([0, n], dtype=np.int64), first_partner


# Relative cost of the force pass per particle (gravity, the plane checks), per listed
# pair and per touching contact (pair or wall), for the blocks of the kernel's
# compute_forces. From the settle scene at N = 20,000, one thread: ~20 ns a particle,
# ~60 ns a touching contact, a few ns a listed pair apart.
PARTICLE_COST, LISTED_COST, CONTACT_COST = 4, 1, 12


@numba.njit(cache=True)
def thread_blocks(threads, planes, pairs, list_first_partner):
    """More than one thread: (bounds of ``threads`` blocks of consecutive particles with
    equal estimated work in the force pass, counting the contacts touching at the last
    step; the first partner of each particle: the list's, ``list_first_partner`` (the
    smallest i whose row lists it, itself if none), copied, with the marks of
    ``defer_finishing``).

    Equal particle counts were unequal work: the settle scene's lower layers (the low
    indices) touch first and most, e.g. 18,401 against 10,723 touching pairs in the two
    halves of N = 20,000 at step 3,000 (jitter). Which thread computes a particle does
    not change a bit of the result."""
    bounds = balanced_bounds(threads, planes, pairs, list_first_partner.shape[0])
    first_partner = list_first_partner.copy()
    defer_finishing(bounds, first_partner)
    return bounds, first_partner


@numba.njit(cache=True)
def defer_finishing(bounds, first_partner):
    """Even out the second pass. Block b must leave to finish_kick_drift its particles
    with a partner in an earlier block (none in the first block, about a layer of a pile
    in the others): the other threads would wait for those at the second join. Each
    block therefore also leaves its last particles, as many as the block with the most
    such particles leaves, so every thread finishes as many in the second pass and as
    many fewer in the first (the bounds balance the total work). Marked by
    first_partner = -1 (earlier than any block): which pass finishes a particle does not
    change a bit of the result (its reactions are all stored by then)."""
    blocks = bounds.shape[0] - 1
    left = np.zeros(blocks, dtype=np.int64)
    for block in range(blocks):
        for p in range(bounds[block], bounds[block + 1]):
            left[block] += first_partner[p] < bounds[block]
    most = left.max()
    for block in range(blocks):
        p = bounds[block + 1] - 1
        while left[block] < most and p >= bounds[block]:
            if first_partner[p] >= bounds[block]:
                first_partner[p] = -1
                left[block] += 1
            p -= 1


@numba.njit(cache=True, inline="always")
def range_work(first, last, offsets, pair_overlap, near_offsets, wall_overlap):
    """The estimated work of particles first..last-1 in the force pass (the costs
    above): their list entries and their touching contacts are contiguous ranges of the
    list's and the near planes' arrays (State.list_near_planes), counted flat, without a
    loop per particle's row."""
    touching = 0
    for e in range(offsets[first], offsets[last]):
        touching += pair_overlap[e] > 0.0
    for k in range(near_offsets[first], near_offsets[last]):
        touching += wall_overlap[k] > 0.0
    return (PARTICLE_COST * (last - first) + LISTED_COST * (offsets[last] - offsets[first])
            + CONTACT_COST * touching)


@numba.njit(cache=True, parallel=True)
def balanced_bounds(threads, planes, pairs, n):
    """Block bounds of thread_blocks for more than one thread: bounds[b] is the first
    particle whose preceding work (particles 0..i-1) reaches b / threads of the total.

    The work is summed in parallel by pieces of consecutive particles (the energy
    blocks, ``minidem.engine.integrate.block_particles``); each bound is then found by
    walking the pieces' sums, and particle by particle only within the piece where it
    falls: the same bounds as one serial prefix sum over every particle, in a fraction
    of its time (the sums are integers: their order changes nothing)."""
    offsets, pair_overlap, wall_overlap, near_offsets = pairs[0], pairs[3], planes[4], planes[5]
    pieces = energy_blocks(n)
    piece_work = np.zeros(pieces, dtype=np.int64)
    for piece in numba.prange(pieces):
        particles = block_particles(piece, n)
        piece_work[piece] = range_work(particles.start, particles.stop, offsets, pair_overlap, near_offsets,
                                       wall_overlap)
    total = 0
    for piece in range(pieces):
        total += piece_work[piece]
    bounds = np.empty(threads + 1, dtype=np.int64)
    for block in range(threads + 1):
        share = block * total // threads
        # the whole pieces before the bound, then its piece particle by particle
        piece, before = 0, 0
        while piece < pieces and before + piece_work[piece] < share:
            before += piece_work[piece]
            piece += 1
        i = min(piece * ENERGY_BLOCK, n)
        while i < n and before < share:
            before += range_work(i, i + 1, offsets, pair_overlap, near_offsets, wall_overlap)
            i += 1
        bounds[block] = i
    bounds[threads] = n
    return bounds
