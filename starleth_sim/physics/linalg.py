"""Small linear algebra for the time-stepper (C kernels, ``csrc/linalg.c``): the LTDL factor
of M (Featherstone's, with the sparsity of the kinematic tree) and its solves, and a Cholesky
factor with the envelope of its matrix (G_BB of the direct bilateral method).

The matrices here are small (M is 18 x 18 for the minimal coordinates), where a call into
numpy/LAPACK costs more in overhead than the arithmetic (doc/performance.md). Only the upper
triangle of the symmetric input is read, matching what ``pin.crba`` fills.

Featherstone's LTDL (Rigid Body Dynamics Algorithms, 2008, §6.3-6.5): with the velocities
numbered parents first, dof_parent[k] < k is the dof that k hangs from (−1 at a root); row k
of M has nonzeros only at k's ancestors and descendants ("branch-induced sparsity"), and L
keeps that pattern: no fill-in. L is stored in one matrix: D on the diagonal, the unit lower
factor's entries L[k, i] at k's ancestors i; nothing else is read or written.

The kernels:

- ``ltdl(A, dof_parent, L) -> bool``: the LTDL factor of the SPD matrix A (M of a forest:
  only its entries A[i, k], i an ancestor of k or i = k, are read) into L; False if A is not
  positive definite (or not finite).
- ``ltdl_solve_vec(L, dof_parent, b)``: (Lᵀ D L) x = b in place.
- ``ltdl_solve_cols(L, dof_parent, B)``: the same for every column of B (n x m), tree by tree
  of the forest and only for the columns that are not zero over a tree's dofs (a contact's W
  column touches one or two trees); the same operations in the same order as
  ltdl_solve_vec per column, so the same result bit for bit (but for the sign of an exact
  zero).
- ``ltdl_solve_cols_pattern(L, dof_parent, B, ptr, idx) -> (ptr, idx)``: ltdl_solve_cols for a
  B whose nonzero rows per column are known (CSR by column: for B = W, the row pattern of
  W^T), returning the pattern of X = M^{-1}B's columns (prox.col_pattern(X)) without
  scanning B: the maximal coordinates' M^{-1}W.
- ``cholesky_upper_input(A, o, L, first) -> bool``: L Lᵀ = A[o:, o:] (upper triangle read)
  with its envelope: row i of L is zero left of first[i], the first nonzero column of row i
  of A's lower triangle (Cholesky keeps fill-in inside the envelope), so every sum runs over
  the same nonzero terms, in the same order, as the dense loops would: the dense result bit
  for bit (G_BB of the maximal coordinates: 822 of its 1,830 entries in the envelope). L
  must come in zeroed; `first` receives the envelope.
- ``cholesky_solve_vec(L, first, b)``: (L Lᵀ) x = b in place.
- ``envelope_columns(first) -> (ptr, idx)``: the envelope by columns, for
  ``cholesky_solve_envelope(L, first, col_ptr, col_idx, b)``, whose backward pass visits only
  the rows inside the envelope, in the same order (760 terms instead of 1,770 tests for the
  maximal coordinates' G_BB).
"""
from __future__ import annotations

from .kernels import (
                      cholesky_solve_envelope,
                      cholesky_solve_vec,
                      cholesky_upper_input,
                      envelope_columns,
                      ltdl,
                      ltdl_solve_cols,
                      ltdl_solve_cols_pattern,
                      ltdl_solve_vec,
)

__all__ = ["cholesky_solve_envelope", "cholesky_solve_vec", "cholesky_upper_input",
           "envelope_columns", "ltdl", "ltdl_solve_cols", "ltdl_solve_cols_pattern",
           "ltdl_solve_vec"]
