/* The compliant contact law of Alg. 1 (contact.py) and the actuators' torque saturation
 * (actuator.py). */
#include "core.h"

/* compliant_contact_forces: Alg. 1 for all nc contacts at (q^M, u^S). A closed contact
 * (g_N ≤ 0) is a spring-damper between its point P and its anchor P0:
 *   λ_N = max(−c_N g_N − d_N γ_N, 0);
 *   stick: λ_T = −c_T g_T − d_T γ_T, slipping (λ_T = −μλ_N γ_T/‖γ_T‖) once ‖λ_T‖ ≥ μλ_N;
 *   slip: λ_T = −μλ_N γ_T/‖γ_T‖, sticking again (P0 ← P) once ‖γ_T‖ ≈ 0 or d_T ‖γ_T‖ ≤ μλ_N.
 * Wt: nc x 3 x nv, position and anchor nc x 3, frames nc x FRAME_STRIDE (each contact's
 * n, t1, t2 and μ: contact_points), lam (nc x 3) receives (λ_N, λ_T1, λ_T2); closed, slip
 * and anchor are updated in place. */
void compliant_contact_forces(const compliant_law_t *law, i64 nc, i64 nv, const double *gap,
                              const double *position, const double *Wt, const double *u, u8 *closed,
                              u8 *slip, double *anchor, const double *frames, double *lam) {
    (void)law->mu; /* (μ per contact: its surface's, in frames) */
    double c_n = law->c_N, d_n = law->d_N, c_t = law->c_T, d_t = law->d_T;
    double slip_velocity = law->slip_velocity;
    for (i64 i = 0; i < nc; i++) {
        double *li = lam + 3 * i;
        const double *pos = position + 3 * i;
        double *anc = anchor + 3 * i;
        const double *t1 = frames + FRAME_STRIDE * i + 3, *t2 = t1 + 3;
        double mu = frames[FRAME_STRIDE * i + 9];
        if (gap[i] > 0.0) {
            closed[i] = 0;
            slip[i] = 0;
            li[0] = 0.0;
            li[1] = 0.0;
            li[2] = 0.0;
            continue;
        }
        if (!closed[i]) {
            closed[i] = 1;
            slip[i] = 0;
            for (int k = 0; k < 3; k++) anc[k] = pos[k];
        }
        const double *W0 = Wt + (3 * i + 0) * nv, *W1 = Wt + (3 * i + 1) * nv,
                     *W2 = Wt + (3 * i + 2) * nv;
        double gn = 0.0, g1 = 0.0, g2 = 0.0;
        for (i64 j = 0; j < nv; j++) {
            gn += W0[j] * u[j];
            g1 += W1[j] * u[j];
            g2 += W2[j] * u[j];
        }
        /* γ_N = gn, γ_T = (g1, g2) */
        double ln = -c_n * gap[i] - d_n * gn;
        if (ln < 0.0) ln = 0.0;
        double vt = sqrt(g1 * g1 + g2 * g2);
        double lim = mu * ln;
        double l1, l2;
        if (slip[i]) {
            if (vt > 0.0) {
                l1 = -lim * g1 / vt;
                l2 = -lim * g2 / vt;
            } else {
                l1 = 0.0;
                l2 = 0.0;
            }
            if (vt <= slip_velocity || d_t * vt <= lim) {
                slip[i] = 0;
                for (int k = 0; k < 3; k++) anc[k] = pos[k];
            }
        } else {
            double dx0 = pos[0] - anc[0];
            double dx1 = pos[1] - anc[1];
            double dx2 = pos[2] - anc[2];
            double gt1 = t1[0] * dx0 + t1[1] * dx1 + t1[2] * dx2;
            double gt2 = t2[0] * dx0 + t2[1] * dx1 + t2[2] * dx2;
            l1 = -c_t * gt1 - d_t * g1;
            l2 = -c_t * gt2 - d_t * g2;
            if (l1 * l1 + l2 * l2 >= lim * lim) {
                if (vt > 0.0) {
                    l1 = -lim * g1 / vt;
                    l2 = -lim * g2 / vt;
                } else {
                    double s = (l1 != 0.0 || l2 != 0.0) ? lim / sqrt(l1 * l1 + l2 * l2) : 0.0;
                    l1 *= s;
                    l2 *= s;
                }
                slip[i] = 1;
            }
        }
        li[0] = ln;
        li[1] = l1;
        li[2] = l2;
    }
}

/* generalized_contact_force: out += Σ_i W_i λ_i (W_i = Wt[i]^T; Wt: nc x 3 x nv, lam: nc x 3,
 * out: nv), skipping contacts with λ_i = 0. */
void generalized_contact_force(const double *Wt, const double *lam, i64 nc, i64 nv, double *out) {
    for (i64 i = 0; i < nc; i++) {
        double a = lam[3 * i], b = lam[3 * i + 1], c = lam[3 * i + 2];
        if (a == 0.0 && b == 0.0 && c == 0.0) continue;
        const double *W0 = Wt + (3 * i + 0) * nv, *W1 = Wt + (3 * i + 1) * nv,
                     *W2 = Wt + (3 * i + 2) * nv;
        for (i64 j = 0; j < nv; j++) out[j] += W0[j] * a + W1[j] * b + W2[j] * c;
    }
}

/* saturate_torque (actuator.py): out = tau clipped to [−limit, limit], a torque driving its
 * joint (τ φ̇ > 0) beyond |φ̇| = v derated linearly to zero at 2v. 0 if tau has a non-finite
 * entry (out then not to be used). */
int saturate_torque(const double *tau, const double *limit, const double *qd,
                    const double *qd_limit, double *out, i64 n) {
    for (i64 k = 0; k < n; k++) {
        double t = tau[k];
        if (!isfinite(t)) return 0;
        t = py_min(py_max(t, -limit[k]), limit[k]);
        double w = fabs(qd[k]);
        if (w > qd_limit[k] && t * qd[k] > 0.0) t *= py_max(0.0, 2.0 - w / qd_limit[k]);
        out[k] = t;
    }
    return 1;
}
