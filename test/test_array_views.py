"""array_views: views without numba's reshape, and borrowed arrays (no reference counting)
whose owners keep_alive holds. The one-kernel steps rely on both; test_bitexact checks that
those steps give the phase-by-phase path's results bit for bit."""
import numba as nb
import numpy as np
import pytest
from numba.core.errors import TypingError

from starleth_sim.physics.array_views import borrowed, keep_alive, view2, view3


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
