"""Small linear algebra for the time-stepper, compiled with numba: the LTDL factor of M
(Featherstone's, with the sparsity of the kinematic tree) and its solves, and a dense
Cholesky factor (G_BB of the direct bilateral method).

The matrices here are small (M is 18 x 18 for the minimal coordinates), where a call into
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


# -- Featherstone's LTDL: M = Lᵀ D L with the sparsity of the kinematic tree ------------------
# (Featherstone, Rigid Body Dynamics Algorithms, 2008, §6.3-6.5.) With the velocities numbered
# parents first, dof_parent[k] < k is the dof that k hangs from (−1 at a root); row k of M has
# nonzeros only at k's ancestors and descendants ("branch-induced sparsity"), and L keeps that
# pattern: no fill-in. L is stored in one matrix: D on the diagonal, the unit lower factor's
# entries L[k, i] at k's ancestors i; nothing else is read or written.

@nb.njit(cache=True)
def ltdl(A, dof_parent, L):
    """The LTDL factor of the SPD matrix A (M of a forest: only its entries A[i, k], i an
    ancestor of k or i = k, are read, the upper triangle) into L (see above). Returns False if A is
    not positive definite (or not finite)."""
    n = A.shape[0]
    for k in range(n):
        L[k, k] = A[k, k]
        i = dof_parent[k]
        while i != -1:
            L[k, i] = A[i, k]
            i = dof_parent[i]
    for k in range(n - 1, -1, -1):
        d = L[k, k]
        if not (d > 0.0):  # catches NaN too
            return False
        i = dof_parent[k]
        while i != -1:
            a = L[k, i] / d
            j = i
            while j != -1:
                L[i, j] -= a * L[k, j]
                j = dof_parent[j]
            L[k, i] = a
            i = dof_parent[i]
    return True


@nb.njit(cache=True)
def ltdl_solve_vec(L, dof_parent, b):
    """Solve (Lᵀ D L) x = b in place for an LTDL factor (ltdl)."""
    n = b.shape[0]
    for k in range(n - 1, -1, -1):      # Lᵀ y = b: leaves to roots (a zero adds nothing)
        x = b[k]
        if x != 0.0:
            j = dof_parent[k]
            while j != -1:
                b[j] -= L[k, j] * x
                j = dof_parent[j]
    for k in range(n):                  # D z = y, L x = z: roots to leaves
        b[k] /= L[k, k]
    for k in range(n):
        j = dof_parent[k]
        while j != -1:
            b[k] -= L[k, j] * b[j]
            j = dof_parent[j]


@nb.njit(cache=True)
def ltdl_solve_cols(L, dof_parent, B):
    """Solve (Lᵀ D L) X = B in place for every column of B (ltdl_solve_vec's operations for
    each column, in the same order, so the same result bit for bit). The trees of the forest
    (contiguous dofs, each starting at a root: dof_parent −1) are solved one by one, each for
    the columns that are not zero over its dofs (the others stay zero: a contact's W column
    touches one or two trees), along the contiguous rows of B."""
    n, m = B.shape
    cols = np.empty(m, dtype=np.int64)
    o = 0
    while o < n:
        e = o + 1
        while e < n and dof_parent[e] != -1:
            e += 1
        nc = 0
        for c in range(m):
            for i in range(o, e):
                if B[i, c] != 0.0:
                    cols[nc] = c
                    nc += 1
                    break
        if nc != 0:
            _ltdl_solve_tree_cols(L, dof_parent, B, o, e, cols[:nc])
        o = e


@nb.njit(cache=True, inline="always")
def _ltdl_solve_tree_cols(L, dof_parent, B, o, e, cols):
    """ltdl_solve_cols for the tree of dofs o..e−1 and the given columns."""
    nc = cols.shape[0]
    for k in range(e - 1, o - 1, -1):  # (a W column is zero on the legs of other contacts)
        for p in range(nc):
            c = cols[p]
            x = B[k, c]
            if x != 0.0:
                j = dof_parent[k]
                while j != -1:
                    B[j, c] -= L[k, j] * x
                    j = dof_parent[j]
    if nc == B.shape[1]:    # every column: contiguous rows (vectorized)
        for k in range(o, e):
            d = L[k, k]
            row = B[k]
            for c in range(nc):
                row[c] /= d
            j = dof_parent[k]
            while j != -1:
                lkj = L[k, j]
                up = B[j]
                for c in range(nc):
                    row[c] -= lkj * up[c]
                j = dof_parent[j]
        return
    for k in range(o, e):
        d = L[k, k]
        for p in range(nc):
            B[k, cols[p]] /= d
        j = dof_parent[k]
        while j != -1:
            lkj = L[k, j]
            for p in range(nc):
                B[k, cols[p]] -= lkj * B[j, cols[p]]
            j = dof_parent[j]
