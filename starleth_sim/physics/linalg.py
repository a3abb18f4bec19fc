"""Small linear algebra for the time-stepper, compiled with numba: the LTDL factor of M
(Featherstone's, with the sparsity of the kinematic tree) and its solves, and a Cholesky
factor with the envelope of its matrix (G_BB of the direct bilateral method).

The matrices here are small (M is 18 x 18 for the minimal coordinates), where a call into
numpy/LAPACK costs more in overhead (5-6 µs for np.linalg.cholesky, measured) than the
arithmetic. Only the upper triangle of the symmetric input is read, matching what
``pin.crba`` fills.
"""
from __future__ import annotations

import numpy as np
import numba as nb

from .kernel_cache import KERNEL
from .array_views import arena_floats, arena_ints, view2


@nb.njit(**KERNEL)
def cholesky_upper_input(A, o, L, first):
    """L L^T = A[o:, o:] (A symmetric positive definite, only its upper triangle is read;
    o: the offset of the block factored, e.g. G_BB in G), with its
    envelope: row i of L is zero left of first[i], the first nonzero column of row i of A's
    lower triangle (Cholesky keeps fill-in inside the envelope), so its sums start there.
    Every sum runs over the same nonzero terms, in the same order, as the dense loops
    would (a term with a zero factor is ±0 and leaves a sum as it is), so L is the dense
    algorithm's bit for bit (but for the sign of a zero left of the envelope where A holds
    a -0.0, which the Delassus sums never give: 0.0 + -0.0 is +0.0). G_BB of the maximal
    coordinates (60 x 60) has 822 entries in its envelope out of 1,830 (factor 22 -> 10
    µs). L must come in zeroed; `first` (n int64) receives the envelope, for
    cholesky_solve_vec.

    Returns False (and leaves L partially written) if A is not positive definite or not finite.
    """
    n = A.shape[0] - o
    for i in range(n):
        f = i
        for k in range(i):
            if A[o + k, o + i] != 0.0:
                f = k
                break
        first[i] = f
    for j in range(n):
        s = A[o + j, o + j]
        for k in range(first[j], j):
            s -= L[j, k] * L[j, k]
        if not (s > 0.0):  # catches NaN too
            return False
        d = np.sqrt(s)
        L[j, j] = d
        fj = first[j]
        for i in range(j + 1, n):
            fi = first[i]
            if fi > j:      # outside the envelope: stays 0
                continue
            s = A[o + j, o + i]
            for k in range(max(fi, fj), j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
    return True


@nb.njit(**KERNEL, inline="always")
def _cholesky_forward(L, first, b):
    """L y = b in place (the forward pass of cholesky_solve_vec / cholesky_solve_envelope),
    by rows within the envelope `first`."""
    for i in range(L.shape[0]):
        s = b[i]
        for k in range(first[i], i):
            s -= L[i, k] * b[k]
        b[i] = s / L[i, i]


@nb.njit(**KERNEL)
def cholesky_solve_vec(L, first, b):
    """Solve (L L^T) x = b in place (b is overwritten with x), L with the envelope `first`
    of cholesky_upper_input (all zeros: a dense L)."""
    n = L.shape[0]
    _cholesky_forward(L, first, b)
    for i in range(n - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, n):
            if first[k] <= i:
                s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


@nb.njit(**KERNEL)
def envelope_columns(first):
    """The envelope of a Cholesky factor (`first`, see cholesky_upper_input) by columns: for
    each column i, the rows k > i whose envelope reaches it (first[k] ≤ i), ascending, as a
    CSR pair (ptr, idx), for cholesky_solve_envelope's backward pass."""
    n = first.shape[0]
    ptr = np.zeros(n + 1, dtype=np.int64)
    for k in range(n):
        for i in range(first[k], k):
            ptr[i + 1] += 1
    for i in range(n):
        ptr[i + 1] += ptr[i]
    idx = np.empty(ptr[n], dtype=np.int64)
    fill = ptr[:n].copy()
    for k in range(n):     # (k ascending: each column's rows come out ascending)
        for i in range(first[k], k):
            idx[fill[i]] = k
            fill[i] += 1
    return ptr, idx


@nb.njit(**KERNEL)
def cholesky_solve_envelope(L, first, col_ptr, col_idx, b):
    """cholesky_solve_vec with the envelope's columns (envelope_columns(first)): the
    backward pass visits only the rows inside the envelope, in the same order, so the same
    result bit for bit, without testing all n² - n pairs (G_BB of the maximal coordinates:
    760 terms instead of 1,770 tests)."""
    n = L.shape[0]
    _cholesky_forward(L, first, b)
    for i in range(n - 1, -1, -1):
        s = b[i]
        for p in range(col_ptr[i], col_ptr[i + 1]):
            k = col_idx[p]
            s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


# -- Featherstone's LTDL: M = Lᵀ D L with the sparsity of the kinematic tree ------------------
# (Featherstone, Rigid Body Dynamics Algorithms, 2008, §6.3-6.5.) With the velocities numbered
# parents first, dof_parent[k] < k is the dof that k hangs from (−1 at a root); row k of M has
# nonzeros only at k's ancestors and descendants ("branch-induced sparsity"), and L keeps that
# pattern: no fill-in. L is stored in one matrix: D on the diagonal, the unit lower factor's
# entries L[k, i] at k's ancestors i; nothing else is read or written.

@nb.njit(**KERNEL)
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


@nb.njit(**KERNEL)
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


@nb.njit(**KERNEL)
def ltdl_solve_cols(L, dof_parent, B, arena=None):
    """Solve (Lᵀ D L) X = B in place for every column of B (ltdl_solve_vec's operations for
    each column, in the same order, so the same result bit for bit). The trees of the forest
    (contiguous dofs, each starting at a root: dof_parent −1) are solved one by one, each for
    the columns that are not zero over its dofs (the others stay zero: a contact's W column
    touches one or two trees), along the contiguous rows of B. (arena: see
    array_views.arena_ints.)"""
    n, m = B.shape
    cols = arena_ints(arena, m)
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


@nb.njit(**KERNEL)
def ltdl_solve_cols_pattern(L, dof_parent, B, ptr, idx, arena=None):
    """ltdl_solve_cols for a B whose nonzero rows of each column are known (ptr, idx: CSR
    by column; for B = W, the row pattern of W^T), and the same pattern of the solution
    X = M^{-1}B, without scanning B for either: the trees a column touches come from its
    pattern, the solve is ltdl_solve_cols' (the same trees, columns and operations, so the
    same X bit for bit), and a column's nonzero rows are looked for in its trees only (the
    other trees' rows stay the zeros they were). Returns (ptr, idx) of X's nonzero rows by
    column, ascending: prox.col_pattern(X). Each tree is solved on a contiguous copy of its
    columns (_ltdl_solve_tree_block). Its work arrays and the pattern come from a step's
    arena (array_views.arena_ints, arena_floats; three parts) or are new."""
    n, m = B.shape
    nnz = max(ptr[m], 1)
    work = arena_ints(arena, 4 * n + 3 + (m + 1) + 2 * nnz)
    tree = work[:n]                         # dof -> its tree (trees: contiguous dofs)
    starts = work[n:2 * n + 1]
    nt = 0
    for k in range(n):
        if dof_parent[k] == -1 or k == 0:
            starts[nt] = k
            nt += 1
        tree[k] = nt - 1
    starts[nt] = n
    # the trees of each column (ascending) and the columns of each tree (ascending)
    ct_ptr = work[2 * n + 1:2 * n + m + 2]
    ct_idx = work[2 * n + m + 2:2 * n + m + 2 + nnz]
    t_count = work[2 * n + m + 2 + nnz:3 * n + m + 3 + nnz][:nt + 1]
    t_count[:] = 0
    fill = work[3 * n + m + 3 + nnz:4 * n + m + 3 + nnz][:nt]
    t_cols = work[4 * n + m + 3 + nnz:]
    k = 0
    for c in range(m):
        ct_ptr[c] = k
        last = -1
        for p in range(ptr[c], ptr[c + 1]):
            t = tree[idx[p]]
            if t != last:
                ct_idx[k] = t
                k += 1
                t_count[t + 1] += 1
                last = t
    ct_ptr[m] = k
    for t in range(nt):
        t_count[t + 1] += t_count[t]
    fill[:] = t_count[:nt]
    for c in range(m):
        for p in range(ct_ptr[c], ct_ptr[c + 1]):
            t = ct_idx[p]
            t_cols[fill[t]] = c
            fill[t] += 1
    size = 1
    for t in range(nt):
        size = max(size, (starts[t + 1] - starts[t]) * (t_count[t + 1] - t_count[t]))
    block = arena_floats(arena, size)
    for t in range(nt):
        if t_count[t + 1] > t_count[t]:
            _ltdl_solve_tree_block(L, dof_parent, B, starts[t], starts[t + 1],
                                   t_cols[t_count[t]:t_count[t + 1]], block)
    # the nonzero rows of X by column, within the column's trees
    size = 0
    for p in range(k):
        t = ct_idx[p]
        size += starts[t + 1] - starts[t]
    out = arena_ints(arena, m + 1 + size)
    out_ptr = out[:m + 1]
    out_idx = out[m + 1:]
    cnt = 0
    for c in range(m):
        out_ptr[c] = cnt
        for p in range(ct_ptr[c], ct_ptr[c + 1]):
            t = ct_idx[p]
            for i in range(starts[t], starts[t + 1]):
                if B[i, c] != 0.0:
                    out_idx[cnt] = i
                    cnt += 1
    out_ptr[m] = cnt
    return out_ptr, out_idx[:cnt]


@nb.njit(**KERNEL, inline="always")
def _ltdl_solve_tree_block(L, dof_parent, B, o, e, cols, block):
    """_ltdl_solve_tree_cols for the tree of dofs o..e−1 and some columns of B, on a
    contiguous copy of those columns' rows (`block`: scratch of (e − o)·len(cols) floats), so
    that both passes run along rows (vectorized) where the columns of B are strided: the
    same operations on each entry in the same order (the Lᵀ pass still leaves an entry as it
    is where the row below is zero), so the same X bit for bit."""
    nct = cols.shape[0]
    X = view2(block[:(e - o) * nct], (e - o, nct))
    for i in range(e - o):
        Bi = B[o + i]
        Xi = X[i]
        for p in range(nct):
            Xi[p] = Bi[cols[p]]
    for k in range(e - 1, o - 1, -1):          # Lᵀ y = b: leaves to roots
        Xk = X[k - o]
        j = dof_parent[k]
        while j != -1:
            lkj = L[k, j]
            Xj = X[j - o]
            for p in range(nct):
                x = Xk[p]
                Xj[p] = Xj[p] - lkj * x if x != 0.0 else Xj[p]
            j = dof_parent[j]
    for k in range(o, e):                      # D z = y, L x = z: roots to leaves
        d = L[k, k]
        Xk = X[k - o]
        for p in range(nct):
            Xk[p] /= d
        j = dof_parent[k]
        while j != -1:
            lkj = L[k, j]
            Xj = X[j - o]
            for p in range(nct):
                Xk[p] -= lkj * Xj[p]
            j = dof_parent[j]
    for i in range(e - o):
        Bi = B[o + i]
        Xi = X[i]
        for p in range(nct):
            Bi[cols[p]] = Xi[p]


@nb.njit(**KERNEL, inline="always")
def _ltdl_transpose_pass_cols(L, dof_parent, B, o, e, cols):
    """The Lᵀ pass of _ltdl_solve_tree_cols for some columns of B, skipping their zeros (a W
    column is zero on the legs of other contacts)."""
    for k in range(e - 1, o - 1, -1):
        for p in range(cols.shape[0]):
            c = cols[p]
            x = B[k, c]
            if x != 0.0:
                j = dof_parent[k]
                while j != -1:
                    B[j, c] -= L[k, j] * x
                    j = dof_parent[j]


@nb.njit(**KERNEL, inline="always")
def _ltdl_solve_tree_cols(L, dof_parent, B, o, e, cols):
    """ltdl_solve_cols for the tree of dofs o..e−1 and the given columns. With every
    column of B (one tree, as in the minimal coordinates) both passes run along the rows of
    B, over all columns at once (vectorized); the Lᵀ pass then also subtracts the zero
    entries of a row (L[k, j]·0 = ±0 changes no nonzero value, so the result differs at most
    in the sign of an exact zero)."""
    nc = cols.shape[0]
    if nc == B.shape[1]:    # every column: contiguous rows (vectorized)
        for k in range(e - 1, o - 1, -1):      # Lᵀ y = b: leaves to roots
            row = B[k]
            j = dof_parent[k]
            while j != -1:
                lkj = L[k, j]
                up = B[j]
                for c in range(nc):
                    up[c] -= lkj * row[c]
                j = dof_parent[j]
        for k in range(o, e):                  # D z = y, L x = z: roots to leaves
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
    _ltdl_transpose_pass_cols(L, dof_parent, B, o, e, cols)
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
