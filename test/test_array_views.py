"""array_views: views without numba's reshape, borrowed arrays (no reference counting) whose
owners keep_alive holds, and the arena of a step's work arrays. The one-kernel steps rely on
them; test_bitexact checks that those steps give the phase-by-phase path's results bit for
bit."""
import numba as nb
import numpy as np
import pytest
from numba.core.errors import TypingError

from starleth_sim.physics.array_views import (ARENA_ALIGN, arena_floats, arena_ints, borrowed,
                                              keep_alive, view2, view3)


@nb.njit
def _write_through_borrowed(a, value):
    b = borrowed(a)
    m = view2(b[:6], (2, 3))
    m[1, 2] = value
    return b.shape[0], b[5]


def test_a_borrowed_array_is_the_same_memory():
    a = np.arange(8.0)
    n, seen = _write_through_borrowed(a, -1.5)
    assert n == 8 and seen == -1.5
    assert a[5] == -1.5                       # written through the borrowed 2-d view
    np.testing.assert_array_equal(np.delete(a, 5), np.delete(np.arange(8.0), 5))


@nb.njit
def _fill_borrowed_then_allocate(n, rounds):
    owner = np.empty(n)
    b = borrowed(owner)
    for k in range(n):
        b[k] = k + 0.5
    total = 0.0
    for _ in range(rounds):         # allocations of the same size while b is in use: had
        other = np.full(n, -7.0)    # owner been freed, they would reuse its memory
        total += other[0]
        for k in range(n):
            total += b[k]
    out = b.copy()
    keep_alive(owner)
    return out, total


def test_keep_alive_holds_the_owner_of_a_borrowed_array():
    n, rounds = 64, 50
    out, total = _fill_borrowed_then_allocate(n, rounds)
    want = np.arange(n) + 0.5
    np.testing.assert_array_equal(out, want)
    assert total == pytest.approx(rounds * (want.sum() - 7.0))


@nb.njit
def _views3(a):
    c = view3(borrowed(a), (2, 2, 3))
    return c[1, 0, 2] + c[0, 1, 0]


def test_view3_of_a_borrowed_array_indexes_in_c_order():
    a = np.arange(12.0)
    assert _views3(a) == a[1 * 6 + 0 * 3 + 2] + a[0 * 6 + 1 * 3 + 0]


@nb.njit
def _borrow_a_scalar(x):
    return borrowed(x)


def test_borrowed_takes_arrays_only():
    with pytest.raises(TypingError):
        _borrow_a_scalar(1.0)


@nb.njit
def _carve(floats, ints, pos, sizes):
    """arena_floats / arena_ints in turn for `sizes`; each request filled with its index.
    Returns the arrays' first entries and whether each lies in the arena's buffers."""
    arena = (floats, ints, pos)
    firsts = np.empty(sizes.shape[0])
    inside = np.empty(sizes.shape[0], dtype=np.bool_)
    for k in range(sizes.shape[0]):
        if k % 2 == 0:
            a = arena_floats(arena, sizes[k])
            a[:] = k
            firsts[k] = a[0] if a.shape[0] else -1.0
            inside[k] = a.shape[0] == 0 or (floats.ctypes.data <= a.ctypes.data
                                            < floats.ctypes.data + 8 * floats.shape[0])
        else:
            b = arena_ints(arena, sizes[k])
            b[:] = k
            firsts[k] = b[0] if b.shape[0] else -1.0
            inside[k] = b.shape[0] == 0 or (ints.ctypes.data <= b.ctypes.data
                                            < ints.ctypes.data + 8 * ints.shape[0])
    return firsts, inside


@nb.njit
def _no_arena(n):
    a = arena_floats(None, n)
    b = arena_ints(None, n)
    a[:] = 1.5
    b[:] = 2
    return a.sum() + b.sum()


def test_arena_hands_out_aligned_parts_and_allocates_when_full():
    """A step's arena (array_views.arena_floats / arena_ints): requests get parts of its
    buffers that do not overlap (writes to one do not reach another), each starting
    ARENA_ALIGN entries (64 bytes) after the last's start rounded up, while they fit; a
    request that does not fit gets an array of its own (the arena is left as it was, the
    miss counted), and without an arena every request allocates."""
    floats = np.full(24, np.nan)
    ints = np.full(16, -1, dtype=np.int64)
    pos = np.zeros(3, np.int64)
    sizes = np.array([4, 3, 5, 3, 9, 1], dtype=np.int64)   # floats 4, 5, 9; ints 3, 3, 1
    firsts, inside = _carve(floats, ints, pos, sizes)
    np.testing.assert_array_equal(firsts, np.arange(6.0))
    # floats: parts at 0 and 8, the third (9 from 16) does not fit in 24; ints: parts at 0
    # and 8, the third (1 from 16) does not fit in 16
    np.testing.assert_array_equal(inside, [True, True, True, True, False, False])
    nan = np.nan
    np.testing.assert_array_equal(floats, [0] * 4 + [nan] * 4 + [2] * 5 + [nan] * 11)
    np.testing.assert_array_equal(ints, [1] * 3 + [-1] * 5 + [3] * 3 + [-1] * 5)
    np.testing.assert_array_equal(pos, [16, 16, 2])      # the two requests that allocated
    assert ARENA_ALIGN == 8
    assert _no_arena(4) == 4 * 1.5 + 4 * 2
