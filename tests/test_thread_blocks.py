"""The serial work between the kernel's calls, shared or cached: each particle's first
partner computed once per neighbour list (``neighbours.reverse_index``, kept in
``State.first_partner``), the thread blocks' bounds summed in parallel by pieces
(``blocks.balanced_bounds``) and the blow-up guard's survey by blocks
(``blowup.survey``, ``blowup.survey_threads``); at list builds, the planes near each
sphere (``neighbours.near_planes``). The references here are plain numpy written from
the definitions, not minidem's own output."""

import numba
import numpy as np
import pytest

from minidem.engine import blocks, blowup, integrate, simulation
from minidem.geometry import neighbours
from minidem.scene import scenario

# a 100-sphere pile: falls, touches the floor and each other, rebuilds its list
PILE = ["fill.0.count=100", "walls.0.upper=[0.02, 0.02, 1.0]", "fill.0.upper=[0.02, 0.02, 1.0]",
        "run.threads=1", "output.vtk=false"]


def first_partners_by_definition(offsets, partners, n):
    """The smallest i whose row lists p, p itself if none (numpy: a minimum over the
    entries, each entry's row from the CSR offsets)."""
    rows = np.repeat(np.arange(n), np.diff(offsets))
    first = np.arange(n)
    np.minimum.at(first, partners.astype(np.int64), rows)
    return first


def test_reverse_index_gives_each_particles_first_partner():
    positions, radii = neighbours._random_packing(3000, seed=4)
    offsets, partners = neighbours.build_pairs(positions, radii, 0.2e-3)
    partners = partners.astype(np.int32)
    reverse_offsets, slot, first = neighbours.reverse_index(offsets, partners, 3000)
    expected = first_partners_by_definition(offsets, partners, 3000)
    assert first.dtype == np.int64 and np.array_equal(first, expected)
    # some particles are listed by an earlier row and some by none (their own index)
    assert (first < np.arange(3000)).sum() > 1000 and (first == np.arange(3000)).sum() > 10
    # the transposed order: p's first slot holds the entry of row first[p]
    rows = np.repeat(np.arange(3000), np.diff(offsets))
    listed = np.diff(reverse_offsets) > 0
    entry_at_slot = np.empty_like(slot)
    entry_at_slot[slot] = np.arange(slot.shape[0])
    assert np.array_equal(rows[entry_at_slot[reverse_offsets[:-1][listed]]], first[listed])


def test_cached_first_partners_follow_the_list_through_rebuilds_and_restores():
    # The first partners change only with the list: the state keeps them from the last
    # build (or restore) and every chunk's blocks read them. After a run with several
    # rebuilds they must be those of the list in the state; after a restore from a
    # capture taken with another list, those of the restored list.
    scene = scenario.load_scene("scenarios/bench/settle.toml", PILE + ["run.end_time=0.03"])
    sim = simulation.Simulation(scene)
    early = {}
    def keep_early(steps, total, contacts):
        if sim.state.builds == 1 and steps > 0 and "copy" not in early:
            early["copy"], early["list"] = sim.state.capture(), [a.copy() for a in sim.state.pairs[:2]]

    sim.run(progress=keep_early)
    state, n = sim.state, scene.n_particles
    assert state.builds >= 3 and state.count_contacts() > 50
    offsets, partners = state.pairs[:2]
    assert np.array_equal(state.first_partner, first_partners_by_definition(offsets, partners, n))
    later_list = partners.copy()
    # a capture holds no list (State._LISTS): the one of its position at build is made
    # again for a file, and by a restore; it must be the list the state had then
    assert "pair_neighbours" not in early["copy"]
    made = state.lists_of(early["copy"])
    assert np.array_equal(made["pair_offsets"], early["list"][0])
    assert np.array_equal(made["pair_neighbours"], early["list"][1])
    # a copy of now: the live lists, also while a rebuild has let go of them (an interrupt's
    # checkpoint is written from the copy then)
    now, live = state.capture(), state.pairs
    state.pairs = None
    made = state.lists_of(now)
    state.pairs = live
    assert np.array_equal(made["pair_offsets"], offsets) and np.array_equal(made["pair_neighbours"], partners)
    state.first_partner[:] = -7  # a restore must not keep the live ones: they are recomputed
    state.restore(early["copy"])
    offsets, partners = state.pairs[:2]
    assert not np.array_equal(partners, later_list)  # another list
    assert np.array_equal(offsets, early["list"][0]) and np.array_equal(partners, early["list"][1])
    assert np.array_equal(state.first_partner, first_partners_by_definition(offsets, partners, n))


def work_by_definition(pair_offsets, pair_overlap, near_offsets, wall_overlap):
    """Each particle's estimated work (blocks.PARTICLE_COST, LISTED_COST, CONTACT_COST):
    its listed pairs, and its touching pairs and near planes (per near-plane entry)."""
    n = pair_offsets.shape[0] - 1

    def touching(offsets, overlap):
        rows = np.repeat(np.arange(n), np.diff(offsets))
        return np.bincount(rows[overlap > 0.0], minlength=n)

    return (blocks.PARTICLE_COST + blocks.LISTED_COST * np.diff(pair_offsets)
            + blocks.CONTACT_COST * (touching(pair_offsets, pair_overlap) + touching(near_offsets, wall_overlap)))


@pytest.mark.parametrize("threads", [2, 3, 5])
@pytest.mark.parametrize("measured", [False, True])
def test_balanced_bounds_are_where_the_prefix_sum_of_the_work_reaches_each_share(threads, measured):
    # The bounds are summed by pieces of ENERGY_BLOCK particles in parallel, then found
    # within one piece: they must be those of one prefix sum over every particle, the
    # first particle whose preceding work reaches b / threads of the total. Several
    # pieces and a short last one; the touching contacts crowded in the first piece.
    # Measured: each particle's work weighted by the rate of the block it was in at the
    # measurement (BlockTiming), blocks whose bounds fall inside pieces, one empty.
    rng = np.random.default_rng(7)
    n = 3 * integrate.ENERGY_BLOCK + 123
    pair_offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 9, n))]).astype(np.int64)
    pair_overlap = rng.normal(-1.0, 1.0, pair_offsets[-1])
    pair_overlap[:pair_offsets[integrate.ENERGY_BLOCK // 2]] = 1.0
    near_offsets = np.concatenate([[0], np.cumsum(rng.integers(0, 3, n))]).astype(np.int64)  # 0-2 planes near each
    wall_overlap = rng.normal(-1.0, 1.0, near_offsets[-1])
    pairs, planes = (pair_offsets, None, None, pair_overlap), (None, None, None, None, wall_overlap, near_offsets)
    rate_bounds, rates = np.array([0, n]), np.ones(1, dtype=np.int64)
    weight = np.ones(n, dtype=np.int64)
    if measured:
        rate_bounds = np.array([0, 700, 700, 2 * integrate.ENERGY_BLOCK + 5, n])
        rates = np.array([1500, 900, 700, 1100])
        weight = rates[np.searchsorted(rate_bounds, np.arange(n), side="right") - 1]
    work = work_by_definition(pair_offsets, pair_overlap, near_offsets, wall_overlap)
    work_before = np.concatenate([[0], np.cumsum(weight * work)])
    shares = np.arange(threads + 1) * work_before[-1] // threads
    expected = np.searchsorted(work_before, shares, side="left")
    expected[-1] = n
    previous = numba.get_num_threads()
    try:
        for numba_threads in {1, min(2, numba.config.NUMBA_NUM_THREADS)}:
            numba.set_num_threads(numba_threads)
            bounds, block_work = blocks.balanced_bounds(threads, planes, pairs, n, rate_bounds, rates)
            assert bounds.tolist() == expected.tolist()
            # and each block's work unweighted, against which its cycles are measured
            assert block_work.tolist() == [work[expected[b]:expected[b + 1]].sum() for b in range(threads)]
    finally:
        numba.set_num_threads(previous)
    # the first block holds the crowded contacts: fewer particles than an equal split
    assert expected[1] < n // threads


def test_measured_blocks_even_out_the_cost_the_estimate_gets_wrong():
    # Two threads, 20,000 particles with 3 listed pairs each, a third of them touching in
    # the lower half of the indices (a pile's lower layers). The work estimate's contact
    # cost is CONTACT_COST; here a touching contact "really" costs half of that, so the
    # estimate's blocks give the first thread too little. Each call's block cycles are
    # what those costs sum to; the timing of the calls before must bring the two
    # threads' costs together, from 18 % apart with the estimate alone, up to what the
    # bounds can resolve: whole particles, and rates in steps of 1 / RATE_UNIT.
    n = 20_000
    pair_offsets = np.arange(n + 1, dtype=np.int64) * 3
    pair_overlap = np.full(3 * n, -1.0)
    pair_overlap[: 3 * n // 2: 3] = 1.0
    near_offsets = np.zeros(n + 1, dtype=np.int64)
    planes = (None, None, None, None, np.zeros(0), near_offsets)
    pairs = (pair_offsets, None, None, pair_overlap)
    touching = np.add.reduceat(pair_overlap > 0.0, pair_offsets[:-1])
    true_cost = blocks.PARTICLE_COST + 3 * blocks.LISTED_COST + 0.5 * blocks.CONTACT_COST * touching
    timing = blocks.BlockTiming()

    def call():
        bounds, _, cycles = blocks.blocks(2, planes, pairs, np.arange(n), timing)
        # a thousand cycles a unit of cost: a call's measurement is long enough to be used
        cycles[:] = [1000 * true_cost[bounds[b]:bounds[b + 1]].sum() for b in range(2)]
        return cycles / cycles.mean()

    alone = call()
    assert alone[1] / alone[0] > 1.15
    for _ in range(3):
        spread = call()
    resolution = 2.0 / blocks.BlockTiming.RATE_UNIT + true_cost.max() / (0.5 * true_cost.sum())
    assert abs(spread[1] / spread[0] - 1.0) < resolution < 0.003
    # a call too short to be measured (MIN_CYCLES) leaves the rates found before
    bounds_before = blocks.blocks(2, planes, pairs, np.arange(n), timing)[0]
    assert blocks.blocks(2, planes, pairs, np.arange(n), timing)[0].tolist() == bounds_before.tolist()


def test_block_rates_are_kept_within_their_spread():
    # A thread descheduled for a moment measures many more cycles than its work took:
    # its rate relative to the other's is capped at RATE_SPREAD, so a bound moves
    # at most as far as that ratio of costs would move it
    timing = blocks.BlockTiming()
    work = np.array([1000, 1000])
    timing.measure(2, np.array([0, 50, 100]), work)[:] = [10**8, 10**10]
    bounds, rates = timing.rates(2, 100)
    assert bounds.tolist() == [0, 50, 100]
    assert rates[1] / rates[0] == pytest.approx(blocks.BlockTiming.RATE_SPREAD, rel=2e-3)
    # no counter (cycles 0: a processor without one) or another particle count: equal rates
    timing.measure(2, np.array([0, 50, 100]), work)
    assert timing.rates(2, 100)[1].tolist() == rates.tolist()  # the last good ones stay
    assert timing.rates(2, 101)[1].tolist() == [1]


def test_thread_blocks_mark_a_copy_of_the_lists_first_partners():
    # thread_blocks takes the list's first partners and returns them with the marks of
    # defer_finishing (-1: finished in the second pass) on a copy: the state's stay as
    # they are, for the next chunk's blocks
    n = 40
    pair_offsets = np.zeros(n + 1, dtype=np.int64)
    pair_offsets[1:] = 2 * np.minimum(np.arange(1, n + 1), n - 2)  # rows 0..n-3 list 2 each
    partners = np.array([j for i in range(n - 2) for j in (i + 1, i + 2)], dtype=np.int32)
    list_first = first_partners_by_definition(pair_offsets, partners, n)
    kept = list_first.copy()
    planes = (None, None, None, None, np.zeros(0), np.zeros(n + 1, dtype=np.int64))  # no plane near any
    pairs = (pair_offsets, partners, None, np.zeros(partners.shape[0]))
    bounds, first, _ = blocks.blocks(2, planes, pairs, list_first)
    assert np.array_equal(list_first, kept) and first is not list_first
    assert bounds[0] == 0 and bounds[2] == n and 0 < bounds[1] < n
    marked = first == -1
    assert np.array_equal(first[~marked], list_first[~marked])
    # each block leaves as many to the second pass: block 1's two listed by block 0's last
    # row(s), and as many of block 0's last particles
    second = [[p for p in range(bounds[b], bounds[b + 1]) if first[p] < bounds[b]] for b in range(2)]
    assert len(second[0]) == len(second[1]) == 2


def survey_arrays(n, seed):
    rng = np.random.default_rng(seed)
    position = rng.normal(0.0, 1.0, (n, 3))
    return (position, rng.normal(0.0, 1.0, (n, 3)), rng.normal(0.0, 10.0, (n, 3)), rng.normal(0.0, 1.0, (n, 3)),
            rng.normal(0.0, 1.0, (n, 3)), rng.uniform(1.0, 2.0, n), rng.uniform(0.1, 0.2, n),
            position + rng.normal(0.0, 0.1, (n, 3)), np.array([0.0, 0.0, -9.81]), np.full(3, -2.0), np.full(3, 2.0))


def test_guard_survey_by_blocks_is_the_same_on_any_thread_count_and_agrees_with_numpy():
    n = 2 * integrate.ENERGY_BLOCK + 1000
    arrays = survey_arrays(n, 3)
    position, velocity, angular_velocity, _, _, mass, inertia, initial, gravity, lower, upper = arrays
    energy = 0.5 * (mass * (velocity ** 2).sum(axis=1) + inertia * (angular_velocity ** 2).sum(axis=1))
    outside = np.maximum(lower - position, position - upper).max(axis=1)
    work = mass * ((position - initial) @ gravity)
    previous = numba.get_num_threads()
    results = []
    try:
        for threads in {1, min(2, numba.config.NUMBA_NUM_THREADS)}:
            numba.set_num_threads(threads)
            results += [blowup.survey(*arrays), blowup.survey_threads(*arrays)]
    finally:
        numba.set_num_threads(previous)
    assert all(result == results[0] for result in results)  # bit for bit
    bad, kinetic, top, gravity_work, far, distance = results[0]
    assert bad == -1 and top == np.argmax(energy) and far == np.argmax(outside) and distance == outside.max()
    # the kinetic energy: the blocked sum of the kernel's samples (integrate.kinetic_energy)
    assert kinetic == integrate.kinetic_energy(mass, inertia, velocity, angular_velocity)
    assert kinetic == pytest.approx(energy.sum(), rel=1e-12)
    assert gravity_work == pytest.approx(work.sum(), rel=1e-9, abs=1e-9 * np.abs(work).sum())
    # a non-finite value: the first such particle, on one thread or several
    for later, first in ((n - 5, 2 * integrate.ENERGY_BLOCK + 3), (n - 5, 17)):
        arrays[3][later, 1] = np.inf
        arrays[2][first, 0] = np.nan
        assert blowup.survey(*arrays)[0] == blowup.survey_threads(*arrays)[0] == first


@pytest.mark.parametrize("block", [None, 777])
def test_near_planes_are_those_within_radius_plus_margin(block, monkeypatch):
    # Definition: plane w is listed for sphere i when (x_i - p_w) . n_w < r_i + margin,
    # ascending w per sphere (CSR). Axis-aligned planes (a box: the zero components of the
    # normal are skipped) and tilted ones, spheres on both sides and a few exactly at the
    # limit (not listed: strictly closer). Spheres are taken a block at a time: also with
    # blocks that do not divide the count.
    if block is not None:
        monkeypatch.setattr(neighbours, "_PLANE_BLOCK", block)
    rng = np.random.default_rng(5)
    n, margin = 5000, 0.5e-3
    positions = rng.uniform(-0.01, 0.11, (n, 3))
    radii = rng.uniform(0.5e-3, 1e-3, n)
    tilted = np.array([[1.0, 2.0, -0.5], [0.0, -1.0, 3.0]])
    normals = np.vstack([np.eye(3), -np.eye(3)[:2], tilted / np.linalg.norm(tilted, axis=1)[:, None]])
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.1, 0.1, 0.0], [0.1, 0.1, 0.0],
                       [0.05, 0.05, 0.05], [0.02, 0.0, 0.01]])
    positions[:10, 2] = radii[:10] + margin  # at the floor's limit: not listed
    near = np.einsum("iwk,wk->iw", positions[:, None, :] - points[None, :, :], normals) < (radii + margin)[:, None]
    offsets, planes = neighbours.near_planes(positions, radii, points, normals, margin)
    assert offsets.dtype == np.int64 and planes.dtype == np.int32
    assert np.array_equal(offsets, np.concatenate([[0], np.cumsum(near.sum(axis=1))]))
    assert np.array_equal(planes, np.nonzero(near)[1])
    assert 0 < near.any(axis=1).sum() < n and not near[:10, 2].any()
    # each entry's sphere, by definition
    assert np.array_equal(neighbours.rows_of_entries(offsets), np.repeat(np.arange(n), np.diff(offsets)))
    # no margin: every plane for every sphere
    offsets, planes = neighbours.near_planes(positions, radii, points, normals, None)
    assert np.array_equal(offsets, 7 * np.arange(n + 1)) and np.array_equal(planes, np.tile(np.arange(7), n))
