/* What the prox iterations (prox.c: the JOR and SOR sweeps) share with the adaptive α
 * (prox_alpha.c): the Delassus operator as the adaptive α reads it, and the adaptive α's
 * steps between the sweeps. */
#ifndef STARLETH_PROX_H
#define STARLETH_PROX_H

#include "core.h"

/* The Delassus operator the adaptive α reads: (form, G, Wt, MinvW, pat) of the Python; the
 * Delassus-form kernels pass G for Wt, the velocity-form ones Wt for G, as the Python does. */
typedef struct {
    i64 form;
    const double *G, *Wt, *MinvW;
    const patterns_t *pat;
    i64 m, nv;
} dop_t;

/* auto_setup's work arrays */
typedef struct {
    double *rk, *rs, *lam0, *hist, *tmp1, *tmp2, *dsave, *xsave;
} auto_t;

/* auto_setup: with a fixed α, rk and rs are r itself (no copies, never written); adaptive:
 * rk a copy of the spectral step rs, Λ^0, hist = [inf, 0, rs/r] and work arrays */
auto_t auto_setup(const settings_t *s, const dop_t *D, i64 nc, const double *r, const double *lam,
                  arena_t *ar);

/* auto_restart: after a non-finite sweep, Λ back to Λ^0 and rk back to rs */
void auto_restart(double *hist, double *lam, const double *lam0, double *rk, const double *rs,
                  i64 m);

/* auto_jor_save: rk = rs; after even sweeps d and ξ^k saved for the next long step */
int auto_jor_save(i64 k, const double *old, const double *new_, const double *xi, double res,
                  const double *rs, double *rk, double *hist, double *dsave, double *xsave, i64 m);

/* auto_jor_long_step: rk = rs θ from the saved d and Gd = ξ − ξ_saved */
void auto_jor_long_step(const settings_t *s, i64 nc, const double *xi, const double *rs, double *rk,
                        const double *dsave, const double *xsave, i64 m);

/* auto_next: rk of the sweep after sweep k: BB step after even sweeps, else rs */
void auto_next(const settings_t *s, const dop_t *D, i64 nc, i64 k, const double *old,
               const double *new_, double res, const double *rs, double *rk, double *hist,
               double *tmp1, double *tmp2);

#endif
