/* The Delassus operator G = W^T M^{-1} W of the prox iterations (prox.py): the nonzero
 * patterns of W^T, M^{-1}W and G, G itself (over the row envelopes of M^{-1}W for large
 * problems) or its diagonal, and the prox parameters r = α / diag(G) it gives.
 * Layouts: Wt m x nv, MinvW nv x m, G m x m (row-major). */
#include "core.h"

/* The CSR pattern of the rows of the m x n matrix whose entry (r, k) is A[r * rs + k * ks]
 * (row_pattern's loop; col_pattern = row_pattern(A.T) with the strides swapped), one arena
 * buffer for ptr and idx */
static void strided_row_pattern(const double *A, i64 m, i64 n, i64 rs, i64 ks, arena_t *a,
                                i64 **ptr, i64 **idx) {
    i64 *buf = arena_i(a, m + 1 + m * n);
    i64 *p = buf, *ix = buf + m + 1;
    i64 cnt = 0;
    for (i64 r = 0; r < m; r++) {
        p[r] = cnt;
        for (i64 k = 0; k < n; k++) { /* (branch-free: the nonzeros are scattered) */
            ix[cnt] = k;
            cnt += A[r * rs + k * ks] != 0.0;
        }
    }
    p[m] = cnt;
    *ptr = p;
    *idx = ix;
}

/* row_pattern: CSR pattern of the rows of A (m x n) */
void row_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx) {
    strided_row_pattern(A, m, n, n, 1, a, ptr, idx);
}

/* col_pattern: row_pattern(A.T), the pattern of the n columns of A (m x n) */
void col_pattern(const double *A, i64 m, i64 n, arena_t *a, i64 **ptr, i64 **idx) {
    strided_row_pattern(A, n, m, 1, n, a, ptr, idx);
}

/* row_envelopes: first / one past the last nonzero column of each row k of M^{-1}W (nv
 * rows, n columns), from its column pattern */
static void row_envelopes(const i64 *mp_ptr, const i64 *mp_idx, i64 nv, i64 n, arena_t *a,
                          i64 **first_out, i64 **end_out) {
    i64 *buf = arena_i(a, 2 * nv);
    i64 *first = buf, *end = buf + nv;
    for (i64 k = 0; k < nv; k++) {
        first[k] = n;
        end[k] = 0;
    }
    for (i64 b = 0; b < n; b++)
        for (i64 p = mp_ptr[b]; p < mp_ptr[b + 1]; p++) {
            i64 k = mp_idx[p];
            if (b < first[k]) first[k] = b;
            end[k] = b + 1;
        }
    *first_out = first;
    *end_out = end;
}

/* delassus_rows: G = W^T M^{-1} W row by row (upper part, then mirrored) */
static void delassus_rows(const double *Wt, const double *MinvW, double *G, i64 m, i64 nv,
                          const i64 *wp_ptr, const i64 *wp_idx) {
    for (i64 a = 0; a < m; a++) {
        double *row = G + a * m;
        for (i64 b = a; b < m; b++) row[b] = 0.0;
        for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
            i64 k = wp_idx[p];
            double w = Wt[a * nv + k];
            const double *mk = MinvW + k * m;
            for (i64 b = a; b < m; b++) row[b] = row[b] + w * mk[b];
        }
        for (i64 b = a + 1; b < m; b++) G[b * m + a] = row[b];
    }
}

/* delassus: G = W^T M^{-1} W (both triangles); over M^{-1}W's row envelopes for m > 24 */
void delassus(const double *Wt, const double *MinvW, double *G, i64 m, i64 nv, const i64 *wp_ptr,
              const i64 *wp_idx, const i64 *mp_ptr, const i64 *mp_idx, arena_t *a) {
    if (m <= DELASSUS_ENVELOPE_ROWS) {
        delassus_rows(Wt, MinvW, G, m, nv, wp_ptr, wp_idx);
        return;
    }
    i64 *first, *end;
    row_envelopes(mp_ptr, mp_idx, nv, m, a, &first, &end);
    for (i64 t = 0; t < m * m; t++) G[t] = 0.0;
    for (i64 r = 0; r < m; r++) {
        double *row = G + r * m;
        i64 lo = m, hi = r + 1;
        for (i64 p = wp_ptr[r]; p < wp_ptr[r + 1]; p++) {
            i64 k = wp_idx[p];
            i64 b0 = py_maxi(r, first[k]);
            i64 b1 = end[k];
            if (b1 <= b0) continue;
            lo = py_mini(lo, b0);
            hi = py_maxi(hi, b1);
            double w = Wt[r * nv + k];
            const double *mk = MinvW + k * m;
            for (i64 b = b0; b < b1; b++) row[b] = row[b] + w * mk[b];
        }
        for (i64 b = py_maxi(r + 1, lo); b < hi; b++) G[b * m + r] = row[b];
    }
}

/* delassus_diagonal: diag(G) without forming G */
void delassus_diagonal(const double *Wt, const double *MinvW, double *d, i64 m, i64 nv,
                       const i64 *wp_ptr, const i64 *wp_idx) {
    for (i64 a = 0; a < m; a++) {
        double s = 0.0;
        for (i64 p = wp_ptr[a]; p < wp_ptr[a + 1]; p++) {
            i64 k = wp_idx[p];
            s = s + Wt[a * nv + k] * MinvW[k * m + a];
        }
        d[a] = s;
    }
}

/* prox_parameters: r_N = |α|/G_NN, r_T = |α|/max(G_T1T1, G_T2T2), r_B = |α|/G_BB */
void prox_parameters(const double *Gdiag, i64 m, i64 nc, double alpha, double *r) {
    alpha = fabs(alpha);
    for (i64 i = 0; i < nc; i++) {
        i64 b = 3 * i;
        r[b] = alpha / Gdiag[b];
        double rt = alpha / py_max(Gdiag[b + 1], Gdiag[b + 2]);
        r[b + 1] = rt;
        r[b + 2] = rt;
    }
    for (i64 l = 3 * nc; l < m; l++) r[l] = alpha / Gdiag[l];
}

void relax_bilateral_rows(const settings_t *s, const double *Gdiag, i64 m, i64 nc, double scale,
                          double *r) {
    double omega = s->bilateral_relaxation * scale;
    if (omega > 0.0)
        for (i64 l = 3 * nc; l < m; l++) r[l] = omega / Gdiag[l];
}
