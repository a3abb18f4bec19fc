/* Small linear algebra of the time-stepper (linalg.py): the LTDL factor of M with the sparsity
 * of the kinematic tree (Featherstone 2008, §6.3-6.5) and its solves, and a Cholesky factor
 * with the envelope of its matrix (G_BB of the direct bilateral method). Only the upper
 * triangle of a symmetric input is read. */
#include "core.h"

/* cholesky_upper_input: L L^T = A[o:, o:] (A: nA x nA, upper triangle read; L: n x n,
 * n = nA - o, zeroed by the caller), with the envelope `first` (n) of each row. 0 if A is not
 * positive definite (or not finite). */
int cholesky_upper_input(const double *A, i64 nA, i64 o, double *L, i64 *first) {
    i64 n = nA - o;
    for (i64 i = 0; i < n; i++) {
        i64 f = i;
        for (i64 k = 0; k < i; k++) {
            if (A[(o + k) * nA + (o + i)] != 0.0) {
                f = k;
                break;
            }
        }
        first[i] = f;
    }
    for (i64 j = 0; j < n; j++) {
        double s = A[(o + j) * nA + (o + j)];
        for (i64 k = first[j]; k < j; k++) s -= L[j * n + k] * L[j * n + k];
        if (!(s > 0.0)) return 0; /* catches NaN too */
        double d = sqrt(s);
        L[j * n + j] = d;
        i64 fj = first[j];
        for (i64 i = j + 1; i < n; i++) {
            i64 fi = first[i];
            if (fi > j) continue; /* outside the envelope: stays 0 */
            s = A[(o + j) * nA + (o + i)];
            for (i64 k = py_maxi(fi, fj); k < j; k++) s -= L[i * n + k] * L[j * n + k];
            L[i * n + j] = s / d;
        }
    }
    return 1;
}

/* cholesky_forward: L y = b in place, by rows within the envelope `first`. */
static void cholesky_forward(const double *L, i64 n, const i64 *first, double *b) {
    for (i64 i = 0; i < n; i++) {
        double s = b[i];
        for (i64 k = first[i]; k < i; k++) s -= L[i * n + k] * b[k];
        b[i] = s / L[i * n + i];
    }
}

/* cholesky_solve_vec: (L L^T) x = b in place, L with the envelope `first`. */
void cholesky_solve_vec(const double *L, i64 n, const i64 *first, double *b) {
    cholesky_forward(L, n, first, b);
    for (i64 i = n - 1; i >= 0; i--) {
        double s = b[i];
        for (i64 k = i + 1; k < n; k++)
            if (first[k] <= i) s -= L[k * n + i] * b[k];
        b[i] = s / L[i * n + i];
    }
}

/* envelope_columns: the envelope `first` by columns (CSR ptr: n + 1, idx: ptr[n]; rows k > i
 * with first[k] <= i, ascending), from the arena. */
void envelope_columns(const i64 *first, i64 n, arena_t *a, i64 **ptr_out, i64 **idx_out) {
    i64 *ptr = arena_i(a, n + 1);
    for (i64 i = 0; i <= n; i++) ptr[i] = 0;
    for (i64 k = 0; k < n; k++)
        for (i64 i = first[k]; i < k; i++) ptr[i + 1] += 1;
    for (i64 i = 0; i < n; i++) ptr[i + 1] += ptr[i];
    i64 *idx = arena_i(a, ptr[n]);
    i64 *fill = arena_i(a, n);
    for (i64 i = 0; i < n; i++) fill[i] = ptr[i];
    for (i64 k = 0; k < n; k++) /* (k ascending: each column's rows come out ascending) */
        for (i64 i = first[k]; i < k; i++) idx[fill[i]++] = k;
    *ptr_out = ptr;
    *idx_out = idx;
}

/* cholesky_solve_envelope: cholesky_solve_vec with the envelope's columns
 * (envelope_columns). */
void cholesky_solve_envelope(const double *L, i64 n, const i64 *first, const i64 *col_ptr,
                             const i64 *col_idx, double *b) {
    cholesky_forward(L, n, first, b);
    for (i64 i = n - 1; i >= 0; i--) {
        double s = b[i];
        for (i64 p = col_ptr[i]; p < col_ptr[i + 1]; p++) {
            i64 k = col_idx[p];
            s -= L[k * n + i] * b[k];
        }
        b[i] = s / L[i * n + i];
    }
}

void cholesky_solve_envelope_cols(const double *L, i64 n, const i64 *first, const i64 *col_ptr,
                                  const i64 *col_idx, double *X, i64 q) {
    for (i64 i = 0; i < n; i++) { /* L Y = B, by rows within the envelope */
        double *xi = X + i * q;
        for (i64 k = first[i]; k < i; k++) {
            double l = L[i * n + k];
            const double *xk = X + k * q;
            for (i64 c = 0; c < q; c++) xi[c] -= l * xk[c];
        }
        double d = L[i * n + i];
        for (i64 c = 0; c < q; c++) xi[c] /= d;
    }
    for (i64 i = n - 1; i >= 0; i--) { /* L^T X = Y, by the envelope's columns */
        double *xi = X + i * q;
        for (i64 p = col_ptr[i]; p < col_ptr[i + 1]; p++) {
            i64 k = col_idx[p];
            double l = L[k * n + i];
            const double *xk = X + k * q;
            for (i64 c = 0; c < q; c++) xi[c] -= l * xk[c];
        }
        double d = L[i * n + i];
        for (i64 c = 0; c < q; c++) xi[c] /= d;
    }
}

/* ltdl: M = L^T D L with the tree's sparsity (dof_parent[k] < k, -1 at a root), D on the
 * diagonal of L and the unit factor's entries L[k, i] at k's ancestors i. 0 if A is not
 * positive definite (or not finite). */
int ltdl(const double *A, i64 n, const i64 *dof_parent, double *L) {
    for (i64 k = 0; k < n; k++) {
        L[k * n + k] = A[k * n + k];
        i64 i = dof_parent[k];
        while (i != -1) {
            L[k * n + i] = A[i * n + k];
            i = dof_parent[i];
        }
    }
    for (i64 k = n - 1; k >= 0; k--) {
        double d = L[k * n + k];
        if (!(d > 0.0)) return 0; /* catches NaN too */
        i64 i = dof_parent[k];
        while (i != -1) {
            double a = L[k * n + i] / d;
            i64 j = i;
            while (j != -1) {
                L[i * n + j] -= a * L[k * n + j];
                j = dof_parent[j];
            }
            L[k * n + i] = a;
            i = dof_parent[i];
        }
    }
    return 1;
}

/* ltdl_solve_vec: (L^T D L) x = b in place. */
void ltdl_solve_vec(const double *L, i64 n, const i64 *dof_parent, double *b) {
    for (i64 k = n - 1; k >= 0; k--) { /* L^T y = b: leaves to roots (a zero adds nothing) */
        double x = b[k];
        if (x != 0.0) {
            i64 j = dof_parent[k];
            while (j != -1) {
                b[j] -= L[k * n + j] * x;
                j = dof_parent[j];
            }
        }
    }
    for (i64 k = 0; k < n; k++) b[k] /= L[k * n + k]; /* D z = y, L x = z: roots to leaves */
    for (i64 k = 0; k < n; k++) {
        i64 j = dof_parent[k];
        while (j != -1) {
            b[k] -= L[k * n + j] * b[j];
            j = dof_parent[j];
        }
    }
}

/* ltdl_solve_tree_cols: ltdl_solve_cols for the tree of dofs o..e-1 and the columns cols
 * (nc) of B (n x m). With every column: both passes along rows, the L^T pass without skipping
 * zeros; else the L^T pass skips the zero entries (_ltdl_transpose_pass_cols). */
static void ltdl_solve_tree_cols(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m,
                                 i64 o, i64 e, const i64 *cols, i64 nc) {
    if (nc == m) {                         /* every column: contiguous rows */
        for (i64 k = e - 1; k >= o; k--) { /* L^T y = b: leaves to roots */
            const double *row = B + k * m;
            i64 j = dof_parent[k];
            while (j != -1) {
                double lkj = L[k * n + j];
                double *up = B + j * m;
                for (i64 c = 0; c < nc; c++) up[c] -= lkj * row[c];
                j = dof_parent[j];
            }
        }
        for (i64 k = o; k < e; k++) { /* D z = y, L x = z: roots to leaves */
            double d = L[k * n + k];
            double *row = B + k * m;
            for (i64 c = 0; c < nc; c++) row[c] /= d;
            i64 j = dof_parent[k];
            while (j != -1) {
                double lkj = L[k * n + j];
                const double *up = B + j * m;
                for (i64 c = 0; c < nc; c++) row[c] -= lkj * up[c];
                j = dof_parent[j];
            }
        }
        return;
    }
    /* the transposed pass (Lᵀ), column by column */
    for (i64 k = e - 1; k >= o; k--) {
        for (i64 p = 0; p < nc; p++) {
            i64 c = cols[p];
            double x = B[k * m + c];
            if (x != 0.0) {
                i64 j = dof_parent[k];
                while (j != -1) {
                    B[j * m + c] -= L[k * n + j] * x;
                    j = dof_parent[j];
                }
            }
        }
    }
    for (i64 k = o; k < e; k++) {
        double d = L[k * n + k];
        for (i64 p = 0; p < nc; p++) B[k * m + cols[p]] /= d;
        i64 j = dof_parent[k];
        while (j != -1) {
            double lkj = L[k * n + j];
            for (i64 p = 0; p < nc; p++) B[k * m + cols[p]] -= lkj * B[j * m + cols[p]];
            j = dof_parent[j];
        }
    }
}

/* ltdl_solve_cols: (L^T D L) X = B in place, tree by tree (contiguous dofs starting at a
 * root), each for the columns not zero over its dofs. */
void ltdl_solve_cols(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m, arena_t *a) {
    i64 *cols = arena_i(a, m);
    i64 o = 0;
    while (o < n) {
        i64 e = o + 1;
        while (e < n && dof_parent[e] != -1) e++;
        i64 nc = 0;
        for (i64 c = 0; c < m; c++) {
            for (i64 i = o; i < e; i++) {
                if (B[i * m + c] != 0.0) {
                    cols[nc++] = c;
                    break;
                }
            }
        }
        if (nc != 0) ltdl_solve_tree_cols(L, dof_parent, B, n, m, o, e, cols, nc);
        o = e;
    }
}

/* ltdl_solve_tree_block: ltdl_solve_tree_cols for the tree of dofs o..e-1 and the columns
 * cols (nct) of B, on a contiguous copy X ((e - o) x nct, in block); the L^T pass leaves an
 * entry as it is where the row below is zero. */
static void ltdl_solve_tree_block(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m,
                                  i64 o, i64 e, const i64 *cols, i64 nct, double *X) {
    for (i64 i = 0; i < e - o; i++) {
        const double *Bi = B + (o + i) * m;
        double *Xi = X + i * nct;
        for (i64 p = 0; p < nct; p++) Xi[p] = Bi[cols[p]];
    }
    for (i64 k = e - 1; k >= o; k--) { /* L^T y = b: leaves to roots */
        const double *Xk = X + (k - o) * nct;
        i64 j = dof_parent[k];
        while (j != -1) {
            double lkj = L[k * n + j];
            double *Xj = X + (j - o) * nct;
            for (i64 p = 0; p < nct; p++) {
                double x = Xk[p];
                Xj[p] = x != 0.0 ? Xj[p] - lkj * x : Xj[p];
            }
            j = dof_parent[j];
        }
    }
    for (i64 k = o; k < e; k++) { /* D z = y, L x = z: roots to leaves */
        double d = L[k * n + k];
        double *Xk = X + (k - o) * nct;
        for (i64 p = 0; p < nct; p++) Xk[p] /= d;
        i64 j = dof_parent[k];
        while (j != -1) {
            double lkj = L[k * n + j];
            const double *Xj = X + (j - o) * nct;
            for (i64 p = 0; p < nct; p++) Xk[p] -= lkj * Xj[p];
            j = dof_parent[j];
        }
    }
    for (i64 i = 0; i < e - o; i++) {
        double *Bi = B + (o + i) * m;
        const double *Xi = X + i * nct;
        for (i64 p = 0; p < nct; p++) Bi[cols[p]] = Xi[p];
    }
}

/* ltdl_solve_cols_pattern: ltdl_solve_cols for a B (n x m) whose nonzero rows of each column
 * are known (ptr: m + 1, idx: CSR by column), and the pattern of X = M^{-1} B by column
 * (out_ptr: m + 1, out_idx: out_ptr[m]), looked for in the column's trees only; each tree is
 * solved on a contiguous copy of its columns. Work arrays and the pattern from the arena. */
void ltdl_solve_cols_pattern(const double *L, const i64 *dof_parent, double *B, i64 n, i64 m,
                             const i64 *ptr, const i64 *idx, arena_t *a, i64 **out_ptr,
                             i64 **out_idx) {
    i64 nnz = py_maxi(ptr[m], 1);
    i64 *work = arena_i(a, 4 * n + 3 + (m + 1) + 2 * nnz);
    i64 *tree = work; /* dof -> its tree (trees: contiguous dofs) */
    i64 *starts = work + n;
    i64 nt = 0;
    for (i64 k = 0; k < n; k++) {
        if (dof_parent[k] == -1 || k == 0) starts[nt++] = k;
        tree[k] = nt - 1;
    }
    starts[nt] = n;
    /* the trees of each column (ascending) and the columns of each tree (ascending) */
    i64 *ct_ptr = work + 2 * n + 1;
    i64 *ct_idx = work + 2 * n + m + 2;
    i64 *t_count = work + 2 * n + m + 2 + nnz; /* nt + 1 */
    for (i64 t = 0; t <= nt; t++) t_count[t] = 0;
    i64 *fill = work + 3 * n + m + 3 + nnz; /* nt */
    i64 *t_cols = work + 4 * n + m + 3 + nnz;
    i64 k = 0;
    for (i64 c = 0; c < m; c++) {
        ct_ptr[c] = k;
        i64 last = -1;
        for (i64 p = ptr[c]; p < ptr[c + 1]; p++) {
            i64 t = tree[idx[p]];
            if (t != last) {
                ct_idx[k++] = t;
                t_count[t + 1] += 1;
                last = t;
            }
        }
    }
    ct_ptr[m] = k;
    for (i64 t = 0; t < nt; t++) t_count[t + 1] += t_count[t];
    for (i64 t = 0; t < nt; t++) fill[t] = t_count[t];
    for (i64 c = 0; c < m; c++) {
        for (i64 p = ct_ptr[c]; p < ct_ptr[c + 1]; p++) {
            i64 t = ct_idx[p];
            t_cols[fill[t]++] = c;
        }
    }
    i64 size = 1;
    for (i64 t = 0; t < nt; t++)
        size = py_maxi(size, (starts[t + 1] - starts[t]) * (t_count[t + 1] - t_count[t]));
    double *block = arena_f(a, size);
    for (i64 t = 0; t < nt; t++)
        if (t_count[t + 1] > t_count[t])
            ltdl_solve_tree_block(L, dof_parent, B, n, m, starts[t], starts[t + 1],
                                  t_cols + t_count[t], t_count[t + 1] - t_count[t], block);
    /* the nonzero rows of X by column, within the column's trees */
    size = 0;
    for (i64 p = 0; p < k; p++) {
        i64 t = ct_idx[p];
        size += starts[t + 1] - starts[t];
    }
    i64 *out = arena_i(a, m + 1 + size);
    i64 *optr = out, *oidx = out + m + 1;
    i64 cnt = 0;
    for (i64 c = 0; c < m; c++) {
        optr[c] = cnt;
        for (i64 p = ct_ptr[c]; p < ct_ptr[c + 1]; p++) {
            i64 t = ct_idx[p];
            for (i64 i = starts[t]; i < starts[t + 1]; i++)
                if (B[i * m + c] != 0.0) oidx[cnt++] = i;
        }
    }
    optr[m] = cnt;
    *out_ptr = optr;
    *out_idx = oidx;
}
