"""The blocks of particles the kernel's threads work on (``minidem.engine.kernel``,
``compute_forces`` and ``finish_kick_drift``), chosen before each call of its ``advance``.

Not part of the kernel: these functions depend on neither the contact law nor the
scene shape, so numba compiles them once and caches them for every kernel (a kernel
that compiled its own copy paid ~0.8 s of CPU for it in every first run, even on one
thread, where the blocks are trivial and need no compiled code: ``blocks``).
"""

from __future__ import annotations

import numba
import numpy as np


def blocks(threads: int, planes, pairs, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(bounds, first partner) of the kernel's ``advance`` for the given thread count
    (see ``thread_blocks``). One thread is one block, all particles, and it is finished
    in the force pass whatever its first partner: any index in 0..n-1 (here the particle
    itself, as ``thread_blocks`` would give a particle no row lists) gives the same
    operations in the same order."""
    if threads > 1:
        return thread_blocks(threads, planes, pairs, n)
    return np.array([0, n], dtype=np.int64), np.arange(n, dtype=np.int64)


# Relative cost of the force pass per particle (gravity, the plane checks), per listed
# pair and per touching contact (pair or wall), for the blocks of the kernel's
# compute_forces. From the settle scene at N = 20,000, one thread: ~20 ns a particle,
# ~60 ns a touching contact, a few ns a listed pair apart.
PARTICLE_COST, LISTED_COST, CONTACT_COST = 4, 1, 12


@numba.njit(cache=True)
def thread_blocks(threads, planes, pairs, n):
    """More than one thread: (bounds of ``threads`` blocks of consecutive particles with
    equal estimated work in the force pass, counting the contacts touching at the last
    step; the first partner of each particle: the smallest i whose row lists it, itself
    if none).

    Equal particle counts were unequal work: the settle scene's lower layers (the low
    indices) touch first and most, e.g. 18,401 against 10,723 touching pairs in the two
    halves of N = 20,000 at step 3,000 (jitter). Which thread computes a particle does
    not change a bit of the result."""
    offsets, neighbours = pairs[0], pairs[1]
    first_partner = np.arange(n)
    for i in range(n):
        for e in range(offsets[i], offsets[i + 1]):
            first_partner[neighbours[e]] = min(first_partner[neighbours[e]], i)
    bounds = balanced_bounds(threads, planes, pairs, n)
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


@numba.njit(cache=True)
def balanced_bounds(threads, planes, pairs, n):
    """Block bounds of thread_blocks for more than one thread."""
    offsets, pair_overlap, wall_overlap, near_offsets = pairs[0], pairs[3], planes[4], planes[5]
    work_before = np.empty(n + 1, dtype=np.int64)  # estimated work of particles 0..i-1
    work_before[0] = 0
    for i in range(n):
        work = PARTICLE_COST + LISTED_COST * (offsets[i + 1] - offsets[i])
        for e in range(offsets[i], offsets[i + 1]):
            work += CONTACT_COST * (pair_overlap[e] > 0.0)
        for k in range(near_offsets[i], near_offsets[i + 1]):  # the planes near i (State.list_near_planes)
            work += CONTACT_COST * (wall_overlap[k] > 0.0)
        work_before[i + 1] = work_before[i] + work
    bounds = np.empty(threads + 1, dtype=np.int64)
    i = 0
    for block in range(threads + 1):
        # the first particle whose preceding work reaches the block's share (a loop, not
        # np.searchsorted: the same index, for a fraction of the compile time)
        share = block * work_before[n] // threads
        while i < n and work_before[i] < share:
            i += 1
        bounds[block] = i
    bounds[threads] = n
    return bounds
