"""The kernels' array arguments: a numpy array of the kind asked is read from the array
itself (numpy's C API, where the build had its headers), any other buffer object through the
buffer protocol, with the same results; an array of the wrong kind, layout or writeability
gets the one clear error either way (csrc/bind.c)."""
import array

import numpy as np
import pytest

from starleth_sim.physics import linalg


def _factored(n=6):
    """An SPD matrix on a chain of n dofs, its LTDL factor, the chain and a right-hand side."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((n, n))
    M = A @ A.T + n * np.eye(n)
    par = np.arange(-1, n - 1, dtype=np.int64)
    L = np.zeros((n, n))
    assert linalg.ltdl(M, par, L)
    return M, L, par, rng.standard_normal(n)


def test_a_buffer_object_gives_what_the_numpy_array_gives():
    M, L, par, b = _factored()
    x = b.copy()
    linalg.ltdl_solve_vec(L, par, x)
    np.testing.assert_allclose(M @ x, b, rtol=0, atol=1e-12)
    buf = array.array("d", b.tolist())             # not a numpy array: the buffer protocol
    linalg.ltdl_solve_vec(L, par, buf)
    assert np.frombuffer(buf).tobytes() == x.tobytes()


@pytest.mark.parametrize("bad, message", [
    (lambda b: b.astype(np.int64), "must be an array of float64"),
    (lambda b: np.repeat(b, 2)[::2], "must be a C-contiguous, writeable numpy array"),
    (lambda b: np.lib.stride_tricks.as_strided(b, writeable=False),
     "must be a C-contiguous, writeable numpy array"),
    (lambda b: list(b), "must be a C-contiguous, writeable numpy array of float64, got list"),
])
def test_an_argument_of_the_wrong_kind_is_refused_by_name(bad, message):
    _, L, par, b = _factored()
    with pytest.raises(ValueError, match=message) as e:
        linalg.ltdl_solve_vec(L, par, bad(b))
    assert "ltdl_solve_vec: b " in str(e.value)


def test_the_kernels_read_numpy_arrays_directly_where_numpy_was_there_to_build_with():
    from starleth_sim.physics.kernels import _kernels
    from starleth_sim.physics.kernels import build as kernel_build
    assert _kernels.NUMPY_C_API == (kernel_build.numpy_headers() is not None) == 1
