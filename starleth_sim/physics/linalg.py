"""Small dense linear algebra for the time-stepper, compiled with numba.

The mass matrices here are small (18 x 18 for the minimal coordinates), where a call into
numpy/LAPACK costs more in overhead (5-6 µs for np.linalg.cholesky, measured) than the
arithmetic. Only the upper triangle of the symmetric input is read, matching what
``pin.crba`` fills.
"""
from __future__ import annotations

import numpy as np
import numba as nb


@nb.njit(cache=True)
def cholesky_upper_input(A, L):
    """L L^T = A (A symmetric positive definite, only its upper triangle is read).

    Returns False (and leaves L partially written) if A is not positive definite or not finite.
    """
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):  # catches NaN too
            return False
        d = np.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[j, i]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@nb.njit(cache=True)
def cholesky_solve_vec(L, b):
    """Solve (L L^T) x = b in place (b is overwritten with x)."""
    n = L.shape[0]
    for i in range(n):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * b[k]
        b[i] = s / L[i, i]
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


@nb.njit(cache=True)
def cholesky_blocks(A, blocks, L):
    """Cholesky factor of a block-diagonal SPD matrix, block by block (blocks: rows of
    (start, size)); only the upper triangle of each diagonal block is read, the rest of L is
    zero. Returns False if a block is not positive definite."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    for b in range(blocks.shape[0]):
        o = blocks[b, 0]
        nb_ = blocks[b, 1]
        for j in range(o, o + nb_):
            s = A[j, j]
            for k in range(o, j):
                s -= L[j, k] * L[j, k]
            if not (s > 0.0):
                return False
            d = np.sqrt(s)
            L[j, j] = d
            for i in range(j + 1, o + nb_):
                s = A[j, i]
                for k in range(o, j):
                    s -= L[i, k] * L[j, k]
                L[i, j] = s / d
    return True


@nb.njit(cache=True)
def cholesky_blocks_solve_vec(L, blocks, b):
    """Solve (L L^T) x = b in place for a block-diagonal factor."""
    for bb in range(blocks.shape[0]):
        o = blocks[bb, 0]
        e = o + blocks[bb, 1]
        for i in range(o, e):
            s = b[i]
            for k in range(o, i):
                s -= L[i, k] * b[k]
            b[i] = s / L[i, i]
        for i in range(e - 1, o - 1, -1):
            s = b[i]
            for k in range(i + 1, e):
                s -= L[k, i] * b[k]
            b[i] = s / L[i, i]


@nb.njit(cache=True)
def cholesky_blocks_solve_cols(L, blocks, B):
    """Solve (L L^T) X = B in place for every column of B, block-diagonal factor; rows of a
    column that are zero over a whole block stay zero (sparse W columns are cheap).

    Row-oriented: each substitution step updates the columns of one block together, along
    the contiguous rows of B (the column-by-column loops strode through B), with every
    column's operations in the same order as a column-by-column substitution (so the same
    result bit for bit)."""
    m = B.shape[1]
    cols = np.empty(m, dtype=np.int64)
    for bb in range(blocks.shape[0]):
        o = blocks[bb, 0]
        e = o + blocks[bb, 1]
        nc = 0
        for c in range(m):
            for i in range(o, e):
                if B[i, c] != 0.0:
                    cols[nc] = c
                    nc += 1
                    break
        if nc == 0:
            continue
        if nc == m:     # every column: contiguous inner loops
            for i in range(o, e):
                for k in range(o, i):
                    lik = L[i, k]
                    for c in range(m):
                        B[i, c] -= lik * B[k, c]
                d = L[i, i]
                for c in range(m):
                    B[i, c] /= d
            for i in range(e - 1, o - 1, -1):
                for k in range(i + 1, e):
                    lki = L[k, i]
                    for c in range(m):
                        B[i, c] -= lki * B[k, c]
                d = L[i, i]
                for c in range(m):
                    B[i, c] /= d
        else:
            for i in range(o, e):
                for k in range(o, i):
                    lik = L[i, k]
                    for j in range(nc):
                        B[i, cols[j]] -= lik * B[k, cols[j]]
                d = L[i, i]
                for j in range(nc):
                    B[i, cols[j]] /= d
            for i in range(e - 1, o - 1, -1):
                for k in range(i + 1, e):
                    lki = L[k, i]
                    for j in range(nc):
                        B[i, cols[j]] -= lki * B[k, cols[j]]
                d = L[i, i]
                for j in range(nc):
                    B[i, cols[j]] /= d
