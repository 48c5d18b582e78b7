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
threads the whole was 18 ms of serial work before every chunk of 50 steps). The bounds
weigh that estimate by what each thread's block took in the calls before
(:class:`BlockTiming`).
"""

from __future__ import annotations

import llvmlite.binding
import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

from minidem.engine.integrate import ENERGY_BLOCK, block_particles, energy_blocks


def blocks(threads: int, planes, pairs, first_partner: np.ndarray,
           timing: BlockTiming | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bounds, first partner, block cycles) of the kernel's ``advance`` for the given
    thread count (see ``thread_blocks``); ``first_partner``: the list's
    (``State.first_partner``), not written into; ``timing``: the run's measurements of
    its earlier calls, which correct the estimated work (:class:`BlockTiming`), and which
    the kernel's block cycles (zeros, one per block) join for the next call. One thread
    is one block, all particles, and it is finished in the force pass whatever its first
    partner: any index in 0..n-1 gives the same operations in the same order, so the
    list's own is passed as it is."""
    n = first_partner.shape[0]
    if threads > 1:
        timing = timing or BlockTiming()
        rate_bounds, rates = timing.rates(threads, n)
        bounds, first, work = thread_blocks(threads, planes, pairs, first_partner, rate_bounds, rates)
        return bounds, first, timing.measure(threads, bounds, work)
    return np.array([0, n], dtype=np.int64), first_partner, np.zeros(1, dtype=np.int64)


@intrinsic
def cycle_counter(typingctx):
    """The processor's time-stamp counter (x86-64 ``rdtsc``, a constant rate on current
    processors, read in a few nanoseconds without a system call); 0 on other processors,
    whose counters may not be readable from user code (AArch64's PMCCNTR_EL0 traps by
    default): their blocks are balanced by the estimate alone."""
    def codegen(context, builder, signature, args):
        if llvmlite.binding.get_process_triple().startswith(("x86_64", "amd64")):
            counter = builder.module.declare_intrinsic("llvm.readcyclecounter", fnty=ir.FunctionType(ir.IntType(64), []))
            return builder.call(counter, [])
        return ir.Constant(ir.IntType(64), 0)
    return types.int64(), codegen


class BlockTiming:
    """The cost of each thread's block as measured, for the blocks of the next call.

    The estimated work (PARTICLE_COST, LISTED_COST, CONTACT_COST) is a fixed model: its
    contact cost depends on the law (a rolling and a twisting part cost more than Hertz
    alone), on whether the tile runs as vector code, and on the processor. On the settle
    scene at N = 200,000 (lattice, two threads, hm) the second thread's force pass took
    9 % more cycles than the first's, and the first waited for it at every step. So the
    kernel counts the cycles of each block's force pass (``cycle_counter``), and the next
    call's blocks weigh the estimated work of the particles each block held by that
    block's measured cycles per unit of it: the costs the model gets wrong are then
    spread as measured, as LAMMPS' ``balance ... weight time`` does across processes.

    Only the bounds change, and which thread computes a particle changes no bit of the
    result; a measurement too short to tell (MIN_CYCLES), or none (one thread, another
    processor), leaves the last good rates, and the rates of the blocks are kept within
    RATE_SPREAD of each other, so a thread descheduled for a moment cannot move a bound
    far."""

    # below this many cycles in all (a few milliseconds) a call's measurement is not used
    MIN_CYCLES = 10_000_000
    # the largest ratio of two blocks' rates
    RATE_SPREAD = 2.0
    # rates are integers in units of 1 / RATE_UNIT: the weighted work is summed exactly
    # in int64, so the bounds do not depend on the order of the sums
    RATE_UNIT = 1024

    def __init__(self):
        # thread count -> the last call's (bounds, estimated work per block, cycles per block)
        self._measured: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        # thread count -> (the bounds the rates were measured on, the rates)
        self._rates: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def rates(self, threads: int, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(bounds, rates) for ``thread_blocks``: each block's measured cycles per unit
        of estimated work in the last call that was measured long enough, relative to
        the others, on the blocks it had then; equal rates before any."""
        measured = self._measured.pop(threads, None)
        if measured is not None:
            bounds, work, cycles = measured
            if cycles.min() > 0 and work.min() > 0 and cycles.sum() >= self.MIN_CYCLES and bounds[-1] == n:
                rate = cycles / work
                rate /= np.exp(np.log(rate).mean())
                limit = np.sqrt(self.RATE_SPREAD)
                rate = np.clip(rate, 1.0 / limit, limit)
                self._rates[threads] = (bounds, np.round(rate * self.RATE_UNIT).astype(np.int64))
        found = self._rates.get(threads)
        if found is None or found[0][-1] != n:
            return np.array([0, n], dtype=np.int64), np.ones(1, dtype=np.int64)
        return found

    def measure(self, threads: int, bounds: np.ndarray, work: np.ndarray) -> np.ndarray:
        """The block cycles the kernel's call with these blocks fills (read by the next
        :meth:`rates`)."""
        cycles = np.zeros(threads, dtype=np.int64)
        self._measured[threads] = (bounds, work, cycles)
        return cycles


# Relative cost of the force pass per particle (gravity, the plane checks), per listed
# pair and per touching contact (pair or wall), for the blocks of the kernel's
# compute_forces. From the settle scene at N = 20,000, one thread: ~20 ns a particle,
# ~60 ns a touching contact, a few ns a listed pair apart.
PARTICLE_COST, LISTED_COST, CONTACT_COST = 4, 1, 12


@numba.njit(cache=True)
def thread_blocks(threads, planes, pairs, list_first_partner, rate_bounds, rates):
    """More than one thread: (bounds of ``threads`` blocks of consecutive particles with
    equal estimated work in the force pass, counting the contacts touching at the last
    step and weighted by the measured rates (``balanced_bounds``); the first partner of
    each particle: the list's, ``list_first_partner`` (the smallest i whose row lists it,
    itself if none), copied, with the marks of ``defer_finishing``; the estimated work of
    each block, unweighted, against which its cycles are measured).

    Equal particle counts were unequal work: the settle scene's lower layers (the low
    indices) touch first and most, e.g. 18,401 against 10,723 touching pairs in the two
    halves of N = 20,000 at step 3,000 (jitter). Which thread computes a particle does
    not change a bit of the result."""
    bounds, work = balanced_bounds(threads, planes, pairs, list_first_partner.shape[0], rate_bounds, rates)
    first_partner = list_first_partner.copy()
    defer_finishing(bounds, first_partner)
    return bounds, first_partner, work


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


@numba.njit(cache=True, inline="always")
def weighted_work(first, last, offsets, pair_overlap, near_offsets, wall_overlap, rate_bounds, rates):
    """(weighted, plain): range_work of particles first..last-1, each particle's weighted
    by the rate of the block (rate_bounds) it was in when the rates were measured, and
    unweighted."""
    block = 0
    while block + 1 < rates.shape[0] and rate_bounds[block + 1] <= first:
        block += 1
    weighted, plain, start = 0, 0, first
    while start < last:
        stop = last if block + 1 >= rates.shape[0] else max(start, min(last, rate_bounds[block + 1]))
        work = range_work(start, stop, offsets, pair_overlap, near_offsets, wall_overlap)
        weighted += rates[block] * work
        plain += work
        start, block = stop, block + 1
    return weighted, plain


@numba.njit(cache=True, parallel=True)
def balanced_bounds(threads, planes, pairs, n, rate_bounds, rates):
    """(bounds, work) of thread_blocks for more than one thread: bounds[b] is the first
    particle whose preceding work (particles 0..i-1) reaches b / threads of the total,
    each particle's estimated work weighted by the rate of the block it was in when the
    rates were measured (rate_bounds, rates: integers, see ``BlockTiming``; one block of
    rate 1 weighs nothing); work[b], the estimated work of block b, unweighted.

    The work is summed in parallel by pieces of consecutive particles (the energy
    blocks, ``minidem.engine.integrate.block_particles``); each bound is then found by
    walking the pieces' sums, and particle by particle only within the piece where it
    falls: the same bounds as one serial prefix sum over every particle, in a fraction
    of its time (the sums are integers: their order changes nothing)."""
    offsets, pair_overlap, wall_overlap, near_offsets = pairs[0], pairs[3], planes[4], planes[5]
    pieces = energy_blocks(n)
    piece_work = np.zeros(pieces, dtype=np.int64)
    piece_plain = np.zeros(pieces, dtype=np.int64)
    for piece in numba.prange(pieces):
        particles = block_particles(piece, n)
        piece_work[piece], piece_plain[piece] = weighted_work(particles.start, particles.stop, offsets, pair_overlap,
                                                              near_offsets, wall_overlap, rate_bounds, rates)
    total, total_plain = 0, 0
    for piece in range(pieces):
        total += piece_work[piece]
        total_plain += piece_plain[piece]
    bounds = np.empty(threads + 1, dtype=np.int64)
    plain_before = np.empty(threads + 1, dtype=np.int64)  # the unweighted work before each bound
    for block in range(threads + 1):
        share = block * total // threads
        # the whole pieces before the bound, then its piece particle by particle
        piece, before, plain = 0, 0, 0
        while piece < pieces and before + piece_work[piece] < share:
            before += piece_work[piece]
            plain += piece_plain[piece]
            piece += 1
        i = min(piece * ENERGY_BLOCK, n)
        while i < n and before < share:
            weighted, particle = weighted_work(i, i + 1, offsets, pair_overlap, near_offsets, wall_overlap,
                                               rate_bounds, rates)
            before += weighted
            plain += particle
            i += 1
        bounds[block], plain_before[block] = i, plain
    bounds[threads], plain_before[threads] = n, total_plain
    work = np.empty(threads, dtype=np.int64)
    for block in range(threads):
        work[block] = plain_before[block + 1] - plain_before[block]
    return bounds, work
