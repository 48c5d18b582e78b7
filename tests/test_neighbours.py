"""Cell-list Verlet search against an O(N^2) brute force."""

import numba
import numpy as np
import pytest

from minidem.geometry.neighbours import (
    MAX_CELLS_PER_PARTICLE,
    NeighbourList,
    _cell_grid,
    _random_packing,
    ROW_SCRATCH,
    build_pairs,
    max_displacement_exceeded,
)

SKIN = 0.2e-3
# Pairs this close (relative) to the cutoff may fall either way under rounding.
RELATIVE_TOLERANCE = 1e-12


def brute_force_distances(positions, radii, skin):
    """Centre distance and cutoff of every pair i < j."""
    pair_i, pair_j = np.triu_indices(len(positions), k=1)
    distance = np.linalg.norm(positions[pair_i] - positions[pair_j], axis=1)
    cutoff = radii[pair_i] + radii[pair_j] + skin
    return pair_i, pair_j, distance, cutoff


def csr_to_pairs(offsets, neighbours):
    pair_i = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    return pair_i, neighbours


def assert_matches_brute_force(positions, radii, skin=SKIN):
    offsets, neighbours = build_pairs(positions, radii, skin)
    n = len(positions)
    assert offsets.shape == (n + 1,) and offsets[0] == 0
    assert offsets.dtype == np.int64 and neighbours.dtype == np.int32
    assert len(neighbours) == offsets[-1]
    assert np.all(np.diff(offsets) >= 0)
    listed_i, listed_j = csr_to_pairs(offsets, neighbours)
    assert np.all(listed_j > listed_i)
    # Rows strictly ascending: sorted and no pair listed twice.
    same_row = listed_i[1:] == listed_i[:-1]
    assert np.all(np.diff(listed_j)[same_row] > 0)

    pair_i, pair_j, distance, cutoff = brute_force_distances(positions, radii, skin)
    listed = np.zeros((n, n), dtype=bool)
    listed[listed_i, listed_j] = True
    is_listed = listed[pair_i, pair_j]
    margin = RELATIVE_TOLERANCE * cutoff
    assert np.all(is_listed[distance < cutoff - margin]), "pair inside cutoff missing"
    assert np.all(~is_listed[distance > cutoff + margin]), "pair outside cutoff listed"
    return offsets, neighbours


def polydisperse_packing(n, seed, size_ratio=4.0, volume_fraction=0.3):
    rng = np.random.default_rng(seed)
    radii = 1e-3 * rng.uniform(1.0 / size_ratio, 1.0, n)
    side = (np.sum(4.0 / 3.0 * np.pi * radii**3) / volume_fraction) ** (1.0 / 3.0)
    return rng.uniform(-side / 2, side / 2, (n, 3)), radii


@pytest.mark.parametrize("seed", range(5))
def test_random_polydisperse(seed):
    positions, radii = polydisperse_packing(1000, seed)
    offsets, _ = assert_matches_brute_force(positions, radii)
    assert offsets[-1] > 500  # the packing is dense enough to exercise the search


def test_equal_radii():
    # Equal radii are stored once (build_pairs' radius_index_mask): the same pairs as the
    # brute force, and as the general path, taken when one radius differs by one ulp.
    positions, radii = polydisperse_packing(1000, seed=12, size_ratio=1.0, volume_fraction=0.4)
    assert np.all(radii == radii[0])
    offsets, neighbours = assert_matches_brute_force(positions, radii)
    assert offsets[-1] > 1000
    nudged = radii.copy()
    nudged[-1] = np.nextafter(nudged[-1], 1.0)
    offsets_general, neighbours_general = build_pairs(positions, nudged, SKIN)
    assert np.array_equal(offsets, offsets_general) and np.array_equal(neighbours, neighbours_general)


def test_one_large_sphere_among_small_ones():
    positions, radii = polydisperse_packing(800, seed=7, size_ratio=2.0)
    radii[0] = 20 * radii.max()
    positions[0] = 0.0
    offsets, _ = assert_matches_brute_force(positions, radii)
    # row 0 is longer than the build's scratch row: it is scanned a second time, straight
    # into the list, while most rows beside it are copied from the scratch
    assert offsets[1] > 50 > ROW_SCRATCH and (np.diff(offsets)[1:] <= ROW_SCRATCH).mean() > 0.5


def test_zero_skin_lists_only_overlaps():
    positions, radii = polydisperse_packing(600, seed=3, volume_fraction=0.4)
    assert_matches_brute_force(positions, radii, skin=0.0)


def test_particles_in_a_line():
    # Zero extent along y and z: a single layer of cells along x.
    n = 500
    radii = np.full(n, 1e-3)
    positions = np.zeros((n, 3))
    positions[:, 0] = np.sort(np.random.default_rng(1).uniform(0.0, 0.5, n))
    assert_matches_brute_force(positions, radii)


def test_all_in_one_cell():
    rng = np.random.default_rng(2)
    radii = rng.uniform(0.5e-3, 1e-3, 200)
    positions = rng.uniform(0.0, 0.5e-3, (200, 3))
    offsets, _ = assert_matches_brute_force(positions, radii)
    assert offsets[-1] == 200 * 199 // 2


def test_sparse_box_two_far_clusters():
    positions_a, radii_a = polydisperse_packing(400, seed=4)
    positions_b, radii_b = polydisperse_packing(400, seed=5)
    positions = np.vstack([positions_a, positions_b + [1e3, -2e3, 5e2]])
    radii = np.concatenate([radii_a, radii_b])
    offsets, neighbours = assert_matches_brute_force(positions, radii)
    listed_i, listed_j = csr_to_pairs(offsets, neighbours)
    assert np.all((listed_i < 400) == (listed_j < 400))

    max_cells = MAX_CELLS_PER_PARTICLE * len(positions)
    _, cells_per_axis, _ = _cell_grid(positions, 2 * radii.max() + SKIN, max_cells)
    assert np.prod(cells_per_axis) <= max_cells


def test_cell_count_cap_and_minimum_cell_width():
    positions, radii = polydisperse_packing(1000, seed=6)
    positions[0] = [1e9, 0.0, 0.0]
    cell_size = 2 * radii.max() + SKIN
    max_cells = MAX_CELLS_PER_PARTICLE * len(positions)
    lower, cells_per_axis, inverse_cell_width = _cell_grid(positions, cell_size, max_cells)
    assert np.prod(cells_per_axis) <= max_cells
    assert np.all(inverse_cell_width <= 1.0 / cell_size)
    # A dense box is not coarsened.
    positions, radii = polydisperse_packing(1000, seed=6)
    _, cells_per_axis, inverse_cell_width = _cell_grid(positions, cell_size, max_cells)
    extent = positions.max(axis=0) - positions.min(axis=0)
    assert np.array_equal(cells_per_axis, np.floor(extent / cell_size).astype(np.int64))


@pytest.mark.parametrize("n", [0, 1])
def test_trivial_sizes(n):
    offsets, neighbours = build_pairs(np.zeros((n, 3)), np.full(n, 1e-3), SKIN)
    assert np.array_equal(offsets, np.zeros(n + 1, dtype=np.int64))
    assert len(neighbours) == 0


def test_invalid_input_raises():
    positions, radii = polydisperse_packing(10, seed=0)
    positions[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        build_pairs(positions, radii, SKIN)
    with pytest.raises(ValueError, match="skin"):
        build_pairs(np.zeros((2, 3)), np.ones(2), -1.0)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 threads")
def test_identical_on_one_and_two_threads():
    positions, radii = _random_packing(20_000, seed=11)
    previous = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        offsets_1, neighbours_1 = build_pairs(positions, radii, SKIN)
        numba.set_num_threads(2)
        offsets_2, neighbours_2 = build_pairs(positions, radii, SKIN)
    finally:
        numba.set_num_threads(previous)
    assert np.array_equal(offsets_1, offsets_2)
    assert np.array_equal(neighbours_1, neighbours_2)


def test_independent_of_particle_order_up_to_relabelling():
    positions, radii = polydisperse_packing(700, seed=8)
    permutation = np.random.default_rng(0).permutation(700)
    offsets, neighbours = build_pairs(positions, radii, SKIN)
    offsets_p, neighbours_p = build_pairs(positions[permutation], radii[permutation], SKIN)

    def pair_set(offsets, neighbours, labels):
        i, j = csr_to_pairs(offsets, neighbours)
        i, j = labels[i], labels[j]
        return set(zip(np.minimum(i, j).tolist(), np.maximum(i, j).tolist()))

    assert pair_set(offsets, neighbours, np.arange(700)) == pair_set(
        offsets_p, neighbours_p, permutation)


def test_displacement_criterion_is_half_the_skin():
    positions = np.zeros((5, 3))
    moved = positions.copy()
    direction = np.array([1.0, 2.0, -2.0]) / 3.0
    moved[2] = 0.49 * SKIN * direction
    assert not max_displacement_exceeded(moved, positions, SKIN)
    moved[2] = 0.51 * SKIN * direction
    assert max_displacement_exceeded(moved, positions, SKIN)
    assert not max_displacement_exceeded(positions, positions, 0.0)


def test_neighbour_list_never_misses_a_contact():
    """Random walk: every overlapping pair must be in the list at every step, and the
    list must not be rebuilt more often than the skin criterion demands."""
    rng = np.random.default_rng(9)
    positions, radii = polydisperse_packing(400, seed=9, volume_fraction=0.4)
    neighbour_list = NeighbourList(SKIN)
    assert neighbour_list.update(positions, radii)
    assert not neighbour_list.update(positions, radii)
    step = 0.05 * SKIN
    for _ in range(60):
        positions = positions + rng.normal(0.0, step, positions.shape)
        neighbour_list.update(positions, radii)
        listed_i, listed_j = csr_to_pairs(neighbour_list.offsets, neighbour_list.neighbours)
        listed = set(zip(listed_i.tolist(), listed_j.tolist()))
        pair_i, pair_j, distance, _ = brute_force_distances(positions, radii, 0.0)
        in_contact = distance < radii[pair_i] + radii[pair_j]
        assert set(zip(pair_i[in_contact].tolist(), pair_j[in_contact].tolist())) <= listed
    assert 1 < neighbour_list.n_builds < 60


def test_neighbour_list_rebuilds_when_a_radius_grows():
    positions, radii = polydisperse_packing(50, seed=10)
    neighbour_list = NeighbourList(SKIN)
    neighbour_list.update(positions, radii)
    assert not neighbour_list.update(positions, 0.9 * radii)
    radii = radii.copy()
    radii[7] *= 1.01
    assert neighbour_list.update(positions, radii)


def test_callable_from_compiled_code():
    @numba.njit
    def engine_step(positions, positions_at_build, radii, skin):
        if max_displacement_exceeded(positions, positions_at_build, skin):
            offsets, neighbours = build_pairs(positions, radii, skin)
            return offsets[-1]
        return -1

    positions, radii = polydisperse_packing(300, seed=12)
    assert engine_step(positions, positions, radii, SKIN) == -1
    expected = build_pairs(positions, radii, SKIN)[0][-1]
    assert engine_step(positions, positions + SKIN, radii, SKIN) == expected


@pytest.mark.parametrize("threads", [1, 2])
def test_carry_history_is_a_merge_of_the_old_list_into_the_new(threads):
    """carry_history's contract, against a dictionary: every (row, key) of the new list
    that the old list holds takes its overlap, and its history where that row was in use
    (the rows not given are zero); every other entry keeps what the caller put there.
    Rows span several of its blocks, empty rows and rows in use at a block's edge
    included."""
    from minidem.engine.state import rows_in_use
    from minidem.geometry.neighbours import _CARRY_BLOCK, carry_history

    rng = np.random.default_rng(11)
    n_rows = 3 * _CARRY_BLOCK + 17
    edges = [row for block in range(1, 4) for row in (block * _CARRY_BLOCK - 1, block * _CARRY_BLOCK)] + [0]

    def random_rows():
        rows = [np.sort(rng.choice(8, k, replace=False)) for k in rng.integers(0, 6, n_rows)]
        for row in rng.choice(n_rows, n_rows // 5, replace=False):
            rows[row] = rows[row][:0]
        return rows

    def csr(rows):
        offsets = np.concatenate([[0], np.cumsum([len(r) for r in rows])]).astype(np.int64)
        return offsets, np.concatenate(rows).astype(np.int32)

    old_row_keys, new_row_keys = random_rows(), random_rows()
    for row in edges:  # the rows at the blocks' edges: carried whole
        old_row_keys[row] = new_row_keys[row] = np.array([2, 5])
    old_offsets, old_keys = csr(old_row_keys)
    new_offsets, new_keys = csr(new_row_keys)
    old_history = rng.normal(size=(old_keys.shape[0], 3))
    old_history[rng.random(old_keys.shape[0]) < 0.5] = 0.0  # contacts that ended: no history
    old_history[old_offsets[edges]] = 1.0  # in use at the edges
    old_overlap = rng.normal(size=old_keys.shape[0])
    history = np.zeros((new_keys.shape[0], 3))
    overlap = np.full(new_keys.shape[0], -1.0)
    previous = numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        carry_history(old_offsets, old_keys, *rows_in_use(old_history), old_overlap, new_offsets, new_keys, history,
                      overlap)
    finally:
        numba.set_num_threads(previous)

    old = {(row, int(old_keys[e])): e for row in range(n_rows) for e in range(old_offsets[row], old_offsets[row + 1])}
    carried = np.zeros(n_rows // _CARRY_BLOCK + 1, dtype=int)
    for row in range(n_rows):
        for e in range(new_offsets[row], new_offsets[row + 1]):
            a = old.get((row, int(new_keys[e])))
            if a is None:
                assert overlap[e] == -1.0 and not history[e].any()
            else:
                carried[row // _CARRY_BLOCK] += 1
                assert overlap[e] == old_overlap[a]
                np.testing.assert_array_equal(history[e], old_history[a])
    assert carried.min() > 5  # the merge is exercised in every block, the last, partial one too
