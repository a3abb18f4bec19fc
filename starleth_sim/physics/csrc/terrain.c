/* The contact query against the terrain (terrain.py): the ground plane, yawed boxes and a
 * bilinear heightfield, packed into one float array by terrain.pack_terrain:
 *   header (TERRAIN_HEADER): n_box, nx, ny, x0, y0, cell, μ of the heightfield, μ of the
 *                            plane, the bins' bx0, by0, size, nbx, nby, n_items, 1 if
 *                            the contacts have a second surface each (else 0), and the
 *                            top (the highest z of the boxes and the heightfield)
 *   boxes (n_box x BOX_STRIDE): centre (3), half sizes (3), cos ψ, sin ψ, μ, and the half
 *                               sizes of the box's axis-aligned bounds in x and y
 *   bins (with boxes: nbx x nby + 1 starts, then n_items box indices): the boxes whose
 *        bounds, grown by terrain.BOX_REACH, overlap bin (i, j) of the xy grid of squares of
 *        `size` from (bx0, by0); a contact tests the boxes of its centre's bin only
 *   heights (nx x ny): h[ix * ny + iy] at (x0 + ix cell, y0 + iy cell)
 * The surface rule: each contact sphere takes the surface with the smallest gap; a tie goes
 * to the first in the order plane, boxes (as listed), heightfield. Its second surface (the
 * other side of a concave corner: a tread and its riser, the floor and a box's side) is
 * the nearest of the others that make a concave corner with the first (second_ok), when
 * both are within SECOND_SURFACE_REACH; a sphere has none elsewhere. */
#include "core.h"

#define TERRAIN_HEADER 16
#define TERRAIN_SECOND 14 /* header entries (terrain.SECOND_SURFACES, terrain.TOP) */
#define TERRAIN_TOP    15
#define BOX_STRIDE     11
/* terrain.BOX_REACH: the boxes of a bin are those within this of it in xy; a contact whose
 * lowest point is more than this above the terrain's top meets the plane alone [m] */
#define BOX_REACH 0.1
/* a contact's second surface (terrain.py SECOND_SURFACE_*): its normal more than 20° from
 * the first's (cos 20°), the two facing each other by more than 1 nm (second_ok), its gap
 * within the reach of the first's and its own [m]; none: a gap of SECOND_SURFACE_NONE */
#define SECOND_SURFACE_COS    0.9396926207859084
#define SECOND_SURFACE_REACH  0.1
#define SECOND_SURFACE_NONE   1000.0
#define SECOND_SURFACE_FACING 1e-9

int terrain_is_flat(const ground_t *g) {
    return g->n_terrain < TERRAIN_HEADER || (g->terrain[0] == 0.0 && g->terrain[1] == 0.0);
}

int terrain_has_second_surfaces(const ground_t *g) {
    return g->n_terrain >= TERRAIN_HEADER && g->terrain[TERRAIN_SECOND] != 0.0;
}

double terrain_plane_mu(const ground_t *g) {
    return g->n_terrain >= TERRAIN_HEADER ? g->terrain[7] : 0.0;
}

/* frame_of: (n, t1, t2, μ) into out; t1 the projection of the world x axis (y if n is
 * nearly parallel to x) onto the tangent plane, t2 = n × t1 (contact.tangent_basis) */
static void frame_of(const double *n, double mu, double *out) {
    double rx = 1.0, ry = 0.0;
    if (!(fabs(n[0]) < 0.9)) {
        rx = 0.0;
        ry = 1.0;
    }
    double d = rx * n[0] + ry * n[1];
    double a0 = rx - n[0] * d, a1 = ry - n[1] * d, a2 = 0.0 - n[2] * d;
    double s = sqrt(a0 * a0 + a1 * a1 + a2 * a2);
    a0 /= s;
    a1 /= s;
    a2 /= s;
    out[0] = n[0];
    out[1] = n[1];
    out[2] = n[2];
    out[3] = a0;
    out[4] = a1;
    out[5] = a2;
    out[6] = n[1] * a2 - n[2] * a1;
    out[7] = n[2] * a0 - n[0] * a2;
    out[8] = n[0] * a1 - n[1] * a0;
    out[9] = mu;
}

/* g_N of the sphere (centre c, radius r) to the ground plane */
static double plane_gap(const ground_t *g, const double *c, double r) {
    const double *n = g->n;
    return n[0] * c[0] + n[1] * c[1] + n[2] * c[2] - g->offset - r;
}

/* the surface codes of frame entry 10 (FRAME_STRIDE): 0 none (or not known), the plane,
 * the heightfield, box k */
static double surface_code(i64 id) {
    return id == -1 ? 1.0 : id == -2 ? 2.0 : 3.0 + (double)id;
}

/* box_distance: the signed distance of c to box b (negative inside) and the outward unit
 * normal at the closest point (inside: of the nearest face) */
static double box_distance(const double *b, const double *c, double *n) {
    double dx = c[0] - b[0], dy = c[1] - b[1], dz = c[2] - b[2];
    double cs = b[6], sn = b[7];
    double p[3] = {cs * dx + sn * dy, -sn * dx + cs * dy, dz};
    double l[3], out2 = 0.0;
    int outside = 0;
    for (int k = 0; k < 3; k++) {
        double h = b[3 + k], e = fabs(p[k]) - h;
        if (e > 0.0) {
            l[k] = p[k] > 0.0 ? e : -e;
            out2 += e * e;
            outside = 1;
        } else {
            l[k] = 0.0;
        }
    }
    double d;
    if (outside) {
        d = sqrt(out2);
        for (int k = 0; k < 3; k++) l[k] /= d;
    } else { /* inside: the nearest face (ties: z, then x, then y, so a top face wins) */
        static const int order[3] = {2, 0, 1};
        int best = 2;
        d = fabs(p[2]) - b[5];
        for (int o = 1; o < 3; o++) {
            int k = order[o];
            double e = fabs(p[k]) - b[3 + k];
            if (e > d) {
                d = e;
                best = k;
            }
        }
        l[best] = p[best] >= 0.0 ? 1.0 : -1.0;
    }
    n[0] = cs * l[0] - sn * l[1];
    n[1] = sn * l[0] + cs * l[1];
    n[2] = l[2];
    return d;
}

/* heightfield: whether (c_x, c_y) lies over the grid; then h there (bilinear in the cell)
 * and the unit normal of the cell's surface at that point */
static int heightfield(const double *hdr, const double *hs, const double *c, double *h, double *n) {
    i64 nx = (i64)hdr[1], ny = (i64)hdr[2];
    double x0 = hdr[3], y0 = hdr[4], cell = hdr[5];
    double u = (c[0] - x0) / cell, v = (c[1] - y0) / cell;
    if (!(u >= 0.0 && v >= 0.0 && u <= (double)(nx - 1) && v <= (double)(ny - 1))) return 0;
    i64 i = (i64)u, j = (i64)v;
    if (i > nx - 2) i = nx - 2;
    if (j > ny - 2) j = ny - 2;
    double fx = u - (double)i, fy = v - (double)j;
    double h00 = hs[i * ny + j], h01 = hs[i * ny + j + 1], h10 = hs[(i + 1) * ny + j],
           h11 = hs[(i + 1) * ny + j + 1];
    /* (in this form, equal corners give exactly their height, a flat grid exactly a plane) */
    double a = h00 + fy * (h01 - h00), b = h10 + fy * (h11 - h10);
    *h = a + fx * (b - a);
    double gx = ((1.0 - fy) * (h10 - h00) + fy * (h11 - h01)) / cell;
    double gy = ((1.0 - fx) * (h01 - h00) + fx * (h11 - h10)) / cell;
    double s = sqrt(gx * gx + gy * gy + 1.0);
    n[0] = -gx / s + 0.0; /* (+ 0.0: no negative zero) */
    n[1] = -gy / s + 0.0;
    n[2] = 1.0 / s;
    return 1;
}

/* second_ok: whether a surface of gap gk and normal nk (its closest point to the sphere
 * pk = c − (gk + r) nk) makes a concave corner with the first surface (normal n1, closest
 * point p1): its normal more than 20° from n1, and each closest point in front of the
 * other surface's tangent plane (by more than SECOND_SURFACE_FACING), so the two face each
 * other across the sphere (not two faces side by side, as two tiles at one height). */
static int second_ok(const double *c, double r, double gk, const double *nk, const double *n1,
                     const double *p1) {
    if (!(nk[0] * n1[0] + nk[1] * n1[1] + nk[2] * n1[2] < SECOND_SURFACE_COS)) return 0;
    double pk[3], a = 0.0, b = 0.0;
    for (int k = 0; k < 3; k++) {
        pk[k] = c[k] - (gk + r) * nk[k];
        a += n1[k] * (pk[k] - p1[k]);
        b += nk[k] * (p1[k] - pk[k]);
    }
    return a > SECOND_SURFACE_FACING && b > SECOND_SURFACE_FACING;
}

/* nearest: the surface with the smallest gap among the plane, the boxes of c's bin and the
 * heightfield; with n1 given, among those (other than surface `skip`) that make a concave
 * corner with the first surface (normal n1, closest point p1: second_ok) and have a gap
 * within `reach` only, and none (SECOND_SURFACE_NONE) if there is no such surface.
 * Surfaces: −1 the plane, k ≥ 0 box k, −2 the heightfield. Its gap is returned, its
 * normal, μ and number go to n_out, mu_out, id_out. A tie goes to the first of plane,
 * boxes (in their order), heightfield. */
static double nearest(const ground_t *g, const double *c, double r, const double *n1,
                      const double *p1, i64 skip, double reach, double *n_out, double *mu_out,
                      i64 *id_out) {
    const double *T = g->terrain, *n = g->n;
    double best = SECOND_SURFACE_NONE;
    *id_out = -3;
    double gp = plane_gap(g, c, r);
    if (!n1 || (skip != -1 && gp <= reach && second_ok(c, r, gp, n, n1, p1))) {
        best = gp;
        for (int k = 0; k < 3; k++) n_out[k] = n[k];
        *mu_out = T[7];
        *id_out = -1;
    }
    i64 nbox = (i64)T[0], nbx = (i64)T[11], nby = (i64)T[12];
    const double *boxes = T + TERRAIN_HEADER, *bins = boxes + BOX_STRIDE * nbox;
    const double *items = bins + (nbox ? nbx * nby + 1 : 0), *heights = items + (i64)T[13];
    i64 first = 0, last = 0;
    if (nbox) {
        double u = floor((c[0] - T[8]) / T[10]), v = floor((c[1] - T[9]) / T[10]);
        if (u >= 0.0 && v >= 0.0 && u < (double)nbx && v < (double)nby) {
            i64 bin = (i64)u * nby + (i64)v;
            first = (i64)bins[bin];
            last = (i64)bins[bin + 1];
        }
    }
    for (i64 it = first; it < last; it++) {
        i64 id = (i64)items[it];
        if (id == skip) continue;
        const double *b = boxes + BOX_STRIDE * id;
        /* a lower bound of the distance: outside the box's axis-aligned bounds */
        double lb = py_max(py_max(fabs(c[0] - b[0]) - b[9], fabs(c[1] - b[1]) - b[10]),
                           fabs(c[2] - b[2]) - b[5]);
        if (lb - r >= best || (n1 && lb - r > reach)) continue;
        double nk[3];
        double gk = box_distance(b, c, nk) - r;
        if (gk < best && (!n1 || (gk <= reach && second_ok(c, r, gk, nk, n1, p1)))) {
            best = gk;
            for (int k = 0; k < 3; k++) n_out[k] = nk[k];
            *mu_out = b[8];
            *id_out = id;
        }
    }
    if (T[1] > 0.0 && skip != -2) {
        double h, nh[3];
        if (heightfield(T, heights, c, &h, nh)) {
            double gh = (c[2] - h) * nh[2] - r;
            if (gh < best && (!n1 || (gh <= reach && second_ok(c, r, gh, nh, n1, p1)))) {
                best = gh;
                for (int k = 0; k < 3; k++) n_out[k] = nh[k];
                *mu_out = T[6];
                *id_out = -2;
            }
        }
    }
    return best;
}

/* the frame of surface `id` of normal nb and μ into out: the plane's own tangents, or
 * frame_of's; and its code */
static void surface_frame(const ground_t *g, i64 id, const double *nb, double mu, double *out) {
    if (id == -1) {
        for (int k = 0; k < 3; k++) {
            out[k] = g->n[k];
            out[3 + k] = g->t1[k];
            out[6 + k] = g->t2[k];
        }
        out[9] = mu;
    } else {
        frame_of(nb, mu, out);
    }
    out[10] = surface_code(id);
}

/* no second surface: the first's frame (finite), surface 0, gap SECOND_SURFACE_NONE */
static double no_second_surface(const double *out, double *second) {
    for (int k = 0; k < FRAME_STRIDE; k++) second[k] = out[k];
    second[10] = 0.0;
    return SECOND_SURFACE_NONE;
}

double terrain_contact(const ground_t *g, const double *c, double r, double *out, double *second,
                       double *second_gap) {
    double nb[3], mu, n2[3], mu2;
    i64 id, id2;
    if (c[2] - r > g->terrain[TERRAIN_TOP] + BOX_REACH) {
        /* far above the terrain (more than BOX_REACH over its top): the plane alone */
        surface_frame(g, -1, g->n, g->terrain[7], out);
        if (second) *second_gap = no_second_surface(out, second);
        return plane_gap(g, c, r);
    }
    double best = nearest(g, c, r, NULL, NULL, -3, 0.0, nb, &mu, &id);
    surface_frame(g, id, nb, mu, out);
    if (!second) return best;
    /* the second surface: only near the first (a concave corner), else none */
    double g2 = SECOND_SURFACE_NONE;
    if (best <= SECOND_SURFACE_REACH) {
        double p1[3];
        for (int k = 0; k < 3; k++) p1[k] = c[k] - (best + r) * nb[k];
        g2 = nearest(g, c, r, nb, p1, id, SECOND_SURFACE_REACH, n2, &mu2, &id2);
    }
    if (g2 < SECOND_SURFACE_NONE)
        surface_frame(g, id2, n2, mu2, second);
    else
        no_second_surface(out, second);
    *second_gap = g2;
    return best;
}
