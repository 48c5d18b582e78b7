"""The ContactHistory a law's force function gets in the kernel (minidem.contact.history)
against the numpy array it gets from Python: the same slots for every slice."""

import numba
import numpy as np
import pytest

from minidem.contact.history import history_column

SLOTS, COLUMNS = 7, 5


@numba.njit
def _part_of_column(tile, column, start, stop):
    """Column ``column`` of the tile as a ContactHistory, sliced [start:stop]: its length
    and its slots (zero-padded to SLOTS)."""
    part = history_column(tile, column, COLUMNS)[start:stop]
    out = np.zeros(SLOTS)
    for s in range(len(part)):
        out[s] = part[s]
    return len(part), out


@numba.njit
def _fill_column(tile, column, start, stop, value):
    history = history_column(tile, column, COLUMNS)
    history[start:stop] = value


# in range, empty, reversed, negative from the end, beyond both ends
BOUNDS = [(0, 3), (3, 6), (6, 7), (0, 7), (2, 2), (5, 3), (-3, -1), (-1, 7), (-10, 2), (1, 100), (8, 10),
          (7, 7), (-7, -6), (0, -7)]


@pytest.mark.parametrize("start, stop", BOUNDS)
def test_a_slice_of_a_history_holds_the_slots_numpy_gives(start, stop):
    # expected: Python's own slicing of the same column (what a law called from Python gets)
    tile = np.arange(SLOTS * COLUMNS, dtype=float).reshape(SLOTS, COLUMNS)
    column = 2
    expected = tile[:, column][start:stop]
    length, slots = _part_of_column(tile, column, start, stop)
    assert length == len(expected)
    assert np.array_equal(slots[:length], expected)


@pytest.mark.parametrize("start, stop", BOUNDS)
def test_setting_a_slice_of_a_history_sets_the_slots_numpy_sets(start, stop):
    tile = np.arange(SLOTS * COLUMNS, dtype=float).reshape(SLOTS, COLUMNS)
    expected = tile.copy()
    expected[:, 3][start:stop] = -1.0
    _fill_column(tile, 3, start, stop, -1.0)
    assert np.array_equal(tile, expected)  # no other column, no other slot touched


@numba.njit
def _open_slices(tile):
    history = history_column(tile, 1, COLUMNS)
    tail, head, whole = history[4:], history[:-2], history[:]
    return len(tail), tail[0], len(head), head[len(head) - 1], len(whole), whole[SLOTS - 1]


def test_open_slices_of_a_history_are_numpys():
    # a slice with a bound left out, as a law may write it (expected: numpy's slicing)
    tile = np.arange(SLOTS * COLUMNS, dtype=float).reshape(SLOTS, COLUMNS)
    column = tile[:, 1]
    expected = (len(column[4:]), column[4:][0], len(column[:-2]), column[:-2][-1], len(column[:]), column[-1])
    assert _open_slices(tile) == expected
