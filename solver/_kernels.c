/* The solver's per-point loops in C (see solver/kernels.py, their Python face, for why).
 *
 * Each kernel is a plain C function over contiguous arrays, run without the GIL, and a
 * glue function that takes its arguments' buffers (PEP 3118: numpy arrays, no numpy
 * headers), checks their element types and shapes, and maps the kernel's error code to a
 * Python exception. Outputs are allocated by the caller (kernels.py) and written here.
 *
 * The arithmetic is that of the numba kernels it replaces, operation for operation and in
 * the same order (Python's min/max, int() as truncation, x**2 as x*x), and is built
 * without floating-point contraction or fast-math (setup.py), so results are bit-identical
 * on every machine. Index arguments are checked, and non-finite coordinates that would
 * index outside an array are refused or give NaN: bad input raises, it never crashes.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef int64_t i64;

enum status { OK = 0, BAD_INDEX, NOT_FINITE, NO_MEMORY, BAD_SHAPE };

/* Python's max(a, b) and min(a, b): the first argument unless the second compares
 * greater (less); NaN arguments propagate as they do in Python. */
static inline double pmax(double a, double b) { return b > a ? b : a; }
static inline double pmin(double a, double b) { return b < a ? b : a; }
static inline i64 imax(i64 a, i64 b) { return b > a ? b : a; }
static inline i64 imin(i64 a, i64 b) { return b < a ? b : a; }

/* int(x) as compiled code does it on x86-64 (truncation; NaN and out-of-range values give
 * the minimum integer), without C's undefined behaviour. */
static inline i64 trunc_int(double x)
{
    if (x >= -9223372036854775808.0 && x < 9223372036854775808.0)
        return (i64)x;
    return INT64_MIN;
}

/* A grid of samples in float32 or float64, read as double. */
typedef struct {
    const void *data;
    int single;
} grid_t;

static inline double grid_at(grid_t g, i64 i)
{
    return g.single ? (double)((const float *)g.data)[i] : ((const double *)g.data)[i];
}

/* a - b of two samples of the grid, in its precision: float32 samples subtract as float32
 * (as the numba kernels did, which kept a float32 sample's type until it met a double). */
static inline double grid_sub(grid_t g, double a, double b)
{
    return g.single ? (double)((float)a - (float)b) : a - b;
}

/* ---------------------------------------------------------------- normal equations */

/* out = inverse of the 3x3 M from its cofactors (as the numpy path does). */
static void inverse_3x3(const double *M, double *out)
{
    double c00 = M[4] * M[8] - M[5] * M[7];
    double c01 = M[5] * M[6] - M[3] * M[8];
    double c02 = M[3] * M[7] - M[4] * M[6];
    double det = M[0] * c00 + M[1] * c01 + M[2] * c02;
    out[0] = c00 / det;
    out[3] = c01 / det;
    out[6] = c02 / det;
    out[1] = (M[7] * M[2] - M[8] * M[1]) / det;
    out[4] = (M[8] * M[0] - M[6] * M[2]) / det;
    out[7] = (M[6] * M[1] - M[7] * M[0]) / det;
    out[2] = (M[1] * M[5] - M[2] * M[4]) / det;
    out[5] = (M[2] * M[3] - M[0] * M[5]) / det;
    out[8] = (M[0] * M[4] - M[1] * M[3]) / det;
}

static int schur_complement(const double *H_xx, const double *g_x, const double *W, const i64 *pose_of,
                            i64 X, i64 k, i64 P, double lam, double regularisation,
                            double *blocks, double *shift, double *V_inv)
{
    double V[9], Y[18];
    for (i64 x = 0; x < X; x++) {
        const double *H = H_xx + 9 * x, *Vi = V_inv + 9 * x, *g = g_x + 3 * x;
        double trace = H[0] + H[4] + H[8];
        double reg = regularisation * pmax(trace, 1e-9);
        for (int i = 0; i < 9; i++)
            V[i] = H[i];
        for (int i = 0; i < 3; i++)
            V[4 * i] += lam * H[4 * i] + reg;
        inverse_3x3(V, V_inv + 9 * x);
        for (i64 a = 0; a < k; a++) {
            i64 pa = pose_of[x * k + a];
            if (pa < 0)
                return BAD_INDEX;
            if (pa >= P)
                continue;
            const double *Wa = W + (x * k + a) * 18;
            for (int r = 0; r < 6; r++) {
                for (int j = 0; j < 3; j++)
                    Y[3 * r + j] = Wa[3 * r] * Vi[j] + Wa[3 * r + 1] * Vi[3 + j] + Wa[3 * r + 2] * Vi[6 + j];
                shift[6 * pa + r] += Y[3 * r] * g[0] + Y[3 * r + 1] * g[1] + Y[3 * r + 2] * g[2];
            }
            for (i64 b = 0; b < k; b++) {
                i64 pb = pose_of[x * k + b];
                if (pb < 0)
                    return BAD_INDEX;
                if (pb >= P)
                    continue;
                const double *Wb = W + (x * k + b) * 18;
                double *block = blocks + (pa * P + pb) * 36;
                for (int r = 0; r < 6; r++)
                    for (int c = 0; c < 6; c++)
                        block[6 * r + c] += (Y[3 * r] * Wb[3 * c] + Y[3 * r + 1] * Wb[3 * c + 1]
                                             + Y[3 * r + 2] * Wb[3 * c + 2]);
            }
        }
    }
    return OK;
}

static int point_steps(const double *W, const i64 *pose_of, const double *d_p, const double *V_inv,
                       const double *g_x, i64 X, i64 k, i64 n_poses, double *d_x)
{
    for (i64 x = 0; x < X; x++) {
        double c[3] = {g_x[3 * x], g_x[3 * x + 1], g_x[3 * x + 2]};
        for (i64 a = 0; a < k; a++) {
            i64 pose = pose_of[x * k + a];
            if (pose < 0)
                return BAD_INDEX;
            if (pose >= n_poses)
                continue;
            const double *Wa = W + (x * k + a) * 18;
            for (int i = 0; i < 6; i++) {
                double step = d_p[6 * pose + i];
                for (int j = 0; j < 3; j++)
                    c[j] += Wa[3 * i + j] * step;
            }
        }
        const double *Vi = V_inv + 9 * x;
        for (int i = 0; i < 3; i++)
            d_x[3 * x + i] = -(Vi[3 * i] * c[0] + Vi[3 * i + 1] * c[1] + Vi[3 * i + 2] * c[2]);
    }
    return OK;
}

static int point_blocks(const double *Jx, const double *w, const double *residuals, const i64 *x_idx,
                        i64 n_rows, i64 m, i64 X, double *H_xx, double *g_x, double *Jx_w)
{
    for (i64 n = 0; n < n_rows; n++) {
        i64 x = x_idx[n];
        if (x < 0 || x >= X)
            return BAD_INDEX;
        const double *J = Jx + n * m * 3;
        double *Jw = Jx_w + n * m * 3;
        for (i64 k = 0; k < m; k++)
            for (int i = 0; i < 3; i++)
                Jw[3 * k + i] = w[n] * J[3 * k + i];
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                double acc = 0.0;
                for (i64 k = 0; k < m; k++)
                    acc += Jw[3 * k + i] * J[3 * k + j];
                H_xx[9 * x + 3 * i + j] += acc;
            }
            double acc = 0.0;
            for (i64 k = 0; k < m; k++)
                acc += J[3 * k + i] * (w[n] * residuals[n * m + k]);
            g_x[3 * x + i] += acc;
        }
    }
    return OK;
}

static int coupling_blocks(const double *Ja, const double *Jx_w, i64 n_rows, i64 m, double *out)
{
    for (i64 n = 0; n < n_rows; n++)
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < 3; j++) {
                double acc = 0.0;
                for (i64 k = 0; k < m; k++)
                    acc += Ja[(n * m + k) * 6 + i] * Jx_w[(n * m + k) * 3 + j];
                out[n * 18 + 3 * i + j] = acc;
            }
    return OK;
}

static int scatter_add(const i64 *keys, const double *values, i64 K, i64 D, i64 n_keys,
                       double *sums, unsigned char *seen)
{
    for (i64 r = 0; r < K; r++) {
        i64 key = keys[r];
        if (key < 0 || key >= n_keys)
            return BAD_INDEX;
        seen[key] = 1;
        for (i64 d = 0; d < D; d++)
            sums[key * D + d] += values[r * D + d];
    }
    return OK;
}

static int squared_norms(const double *residuals, i64 N, i64 m, double *out)
{
    for (i64 n = 0; n < N; n++) {
        double acc = 0.0;
        for (i64 k = 0; k < m; k++)
            acc += residuals[n * m + k] * residuals[n * m + k];
        out[n] = acc;
    }
    return OK;
}

static double robust_cost(const double *s, i64 N, long kind, double scale)
{
    double c2 = scale * scale, total = 0.0;
    for (i64 n = 0; n < N; n++) {
        if (kind == 0) {
            total += s[n];
        } else if (kind == 1) {
            double r = sqrt(s[n]);
            total += r <= scale ? s[n] : 2.0 * scale * r - c2;
        } else {
            total += c2 * log1p(s[n] / c2);
        }
    }
    return total;
}

/* out (6) = [g, p x g]: the Jacobian row of a right pose increment for the gradient g
 * (with respect to the posed point, rotated back) at the source point p. */
static inline void twist_row(double g0, double g1, double g2, double p0, double p1, double p2, double *out)
{
    out[0] = g0, out[1] = g1, out[2] = g2;
    out[3] = p1 * g2 - p2 * g1;
    out[4] = p2 * g0 - p0 * g2;
    out[5] = p0 * g1 - p1 * g0;
}

static int pose_rows(const double *G_cam, const double *X, i64 n, i64 m, const double *Rv, const double *Rb,
                     const double *tb, double *J_view, double *J_body, double *G_x)
{
    for (i64 i = 0; i < n; i++) {
        double x0 = X[3 * i], x1 = X[3 * i + 1], x2 = X[3 * i + 2], p0 = x0, p1 = x1, p2 = x2;
        if (J_body) {
            p0 = Rb[0] * x0 + Rb[1] * x1 + Rb[2] * x2 + tb[0];
            p1 = Rb[3] * x0 + Rb[4] * x1 + Rb[5] * x2 + tb[1];
            p2 = Rb[6] * x0 + Rb[7] * x1 + Rb[8] * x2 + tb[2];
        }
        for (i64 k = 0; k < m; k++) {
            const double *c = G_cam + 3 * (i * m + k);
            double g0 = c[0] * Rv[0] + c[1] * Rv[3] + c[2] * Rv[6];
            double g1 = c[0] * Rv[1] + c[1] * Rv[4] + c[2] * Rv[7];
            double g2 = c[0] * Rv[2] + c[1] * Rv[5] + c[2] * Rv[8];
            twist_row(g0, g1, g2, p0, p1, p2, J_view + 6 * (i * m + k));
            if (J_body) {
                double b0 = g0 * Rb[0] + g1 * Rb[3] + g2 * Rb[6];
                double b1 = g0 * Rb[1] + g1 * Rb[4] + g2 * Rb[7];
                double b2 = g0 * Rb[2] + g1 * Rb[5] + g2 * Rb[8];
                twist_row(b0, b1, b2, x0, x1, x2, J_body + 6 * (i * m + k));
                g0 = b0, g1 = b1, g2 = b2;
            }
            double *g = G_x + 3 * (i * m + k);
            g[0] = g0, g[1] = g1, g[2] = g2;
        }
    }
    return OK;
}

/* ---------------------------------------------------------------- camera and images */

/* Whether pixel (u, v) lies inside the image and its circular field of view of radius
 * (inf: none), margin pixels in from their edges. */
static inline int in_field_at(double u, double v, i64 width, i64 height, double margin, double radius)
{
    if (!(u >= margin && v >= margin && u <= (double)(width - 1) - margin && v <= (double)(height - 1) - margin))
        return 0;
    double du = u - (double)(width - 1) / 2.0, dv = v - (double)(height - 1) / 2.0;
    return sqrt(du * du + dv * dv) <= radius - margin;
}

static int in_field(const double *uv, i64 N, i64 width, i64 height, double margin, double radius,
                    unsigned char *inside)
{
    for (i64 p = 0; p < N; p++)
        inside[p] = (unsigned char)in_field_at(uv[2 * p], uv[2 * p + 1], width, height, margin, radius);
    return OK;
}

/* The number of equal sub-segments, of at most spacing, of each projected edge. */
static i64 edge_samples(double du, double dv, double spacing)
{
    return imax(1, trunc_int(ceil(sqrt(du * du + dv * dv) / spacing)));
}

static i64 outline_total(const double *uv_delta, i64 E, double spacing)
{
    i64 total = 0;
    for (i64 e = 0; e < E; e++)
        total += edge_samples(uv_delta[2 * e], uv_delta[2 * e + 1], spacing);
    return total;
}

static int outline_samples(const double *uv_a, const double *uv_delta, i64 E, double spacing, i64 width,
                           i64 height, double margin, double radius, const unsigned char *interior,
                           i64 h, i64 w, i64 downscale, i64 capacity, i64 *edge, double *frac, i64 *kept_out)
{
    i64 kept = 0;
    for (i64 e = 0; e < E; e++) {
        i64 count = edge_samples(uv_delta[2 * e], uv_delta[2 * e + 1], spacing);
        for (i64 place = 0; place < count; place++) {
            double s = ((double)place + 0.5) / (double)count;
            double u = uv_a[2 * e] + s * uv_delta[2 * e];
            double v = uv_a[2 * e + 1] + s * uv_delta[2 * e + 1];
            if (!in_field_at(u, v, width, height, margin, radius))
                continue;
            if (h > 0) {
                i64 iu = imin(imax(trunc_int(rint(u / (double)downscale)), 0), w - 1);
                i64 iv = imin(imax(trunc_int(rint(v / (double)downscale)), 0), h - 1);
                if (interior[iv * w + iu] != 0)
                    continue;
            }
            if (kept == capacity)
                return BAD_SHAPE;
            edge[kept] = e;
            frac[kept] = s;
            kept++;
        }
    }
    *kept_out = kept;
    return OK;
}

/* Pixel of one camera-frame point p (depth floored at min_depth) and, with J (6 values),
 * the projection's Jacobian (2, 3) there. */
static inline void project(const double *p, double fx, double fy, double cx, double cy, double min_depth,
                           double *uv, double *J)
{
    double x = p[0], y = p[1], z = pmax(p[2], min_depth);
    if (J) {
        double inv_z = 1.0 / z;
        uv[0] = fx * x * inv_z + cx;
        uv[1] = fy * y * inv_z + cy;
        J[0] = fx * inv_z;
        J[1] = 0.0;
        J[2] = -fx * x * (inv_z * inv_z);
        J[3] = 0.0;
        J[4] = fy * inv_z;
        J[5] = -fy * y * (inv_z * inv_z);
    } else {
        uv[0] = fx * x / z + cx;
        uv[1] = fy * y / z + cy;
    }
}

static int pinhole(const double *p_cam, i64 N, double fx, double fy, double cx, double cy, double min_depth,
                   double *uv, double *J)
{
    for (i64 p = 0; p < N; p++)
        project(p_cam + 3 * p, fx, fy, cx, cy, min_depth, uv + 2 * p, J ? J + 6 * p : NULL);
    return OK;
}

/* The bilinear interpolant of the image values (h, w) whose pixel (0, 0) lies at origin,
 * at (u, v), and its gradient; beyond the image the distance to it is added. */
static inline double bilinear_at(grid_t values, i64 h, i64 w, const double *origin, double u_in, double v_in,
                                 double *grad)
{
    double lu = u_in - origin[0], lv = v_in - origin[1];
    double u = pmin(pmax(lu, 0.0), (double)(w - 1) - 1e-9);
    double v = pmin(pmax(lv, 0.0), (double)(h - 1) - 1e-9);
    i64 iu = u == u ? (i64)u : 0, iv = v == v ? (i64)v : 0; /* floor: both are >= 0 (NaN: NaN out) */
    double fu = u - (double)iu, fv = v - (double)iv;
    double v00 = grid_at(values, iv * w + iu), v10 = grid_at(values, iv * w + iu + 1);
    double v01 = grid_at(values, (iv + 1) * w + iu), v11 = grid_at(values, (iv + 1) * w + iu + 1);
    double top = v00 * (1 - fu) + v10 * fu;
    double bottom = v01 * (1 - fu) + v11 * fu;
    double value = top * (1 - fv) + bottom * fv;
    grad[0] = grid_sub(values, v10, v00) * (1 - fv) + grid_sub(values, v11, v01) * fv;
    grad[1] = bottom - top;
    double out_u = lu - u, out_v = lv - v;
    if (out_u != 0.0 || out_v != 0.0) {
        double dist_out = sqrt(out_u * out_u + out_v * out_v);
        value += dist_out;
        if (out_u != 0.0)
            grad[0] = out_u / dist_out;
        if (out_v != 0.0)
            grad[1] = out_v / dist_out;
    }
    return value;
}

static int bilinear(grid_t values, i64 h, i64 w, const double *origin, const double *uv, i64 N,
                    double *value, double *grad)
{
    for (i64 p = 0; p < N; p++)
        value[p] = bilinear_at(values, h, w, origin, uv[2 * p], uv[2 * p + 1], grad + 2 * p);
    return OK;
}

static int silhouette_rows(const double *p_cam, i64 N, double fx, double fy, double cx, double cy,
                           double min_depth, grid_t values, i64 h, i64 w, const double *origin,
                           const i64 *charged, i64 n_c, const i64 *nearest, const double *observed, i64 n_o,
                           double *r, double *J_cam)
{
    double uv[2], J[6], grad[2];
    for (i64 c = 0; c < n_c; c++) {
        i64 q = charged[c];
        if (q < 0 || q >= N)
            return BAD_INDEX;
        project(p_cam + 3 * q, fx, fy, cx, cy, min_depth, uv, J_cam ? J : NULL);
        r[c] = bilinear_at(values, h, w, origin, uv[0], uv[1], grad);
        if (J_cam)
            for (int j = 0; j < 3; j++)
                J_cam[3 * c + j] = grad[0] * J[j] + grad[1] * J[3 + j];
    }
    for (i64 o = 0; o < n_o; o++) {
        i64 q = nearest[o];
        if (q < 0 || q >= N)
            return BAD_INDEX;
        project(p_cam + 3 * q, fx, fy, cx, cy, min_depth, uv, J_cam ? J : NULL);
        double du = uv[0] - observed[2 * o], dv = uv[1] - observed[2 * o + 1];
        double d = sqrt(du * du + dv * dv);
        r[n_c + o] = d;
        if (J_cam) {
            double m = pmax(d, 1e-9), eu = du / m, ev = dv / m;
            for (int j = 0; j < 3; j++)
                J_cam[3 * (n_c + o) + j] = eu * J[j] + ev * J[3 + j];
        }
    }
    return OK;
}

/* ---------------------------------------------------------------- outlines and footprints */

static int contour_generators(const unsigned char *front, i64 F, const i64 *adjacent_faces,
                              const i64 *adjacent_edges, i64 A, i64 *out, i64 *kept_out)
{
    i64 kept = 0;
    for (i64 e = 0; e < A; e++) {
        i64 f0 = adjacent_faces[2 * e], f1 = adjacent_faces[2 * e + 1];
        if (f0 < 0 || f0 >= F || f1 < 0 || f1 >= F)
            return BAD_INDEX;
        int first = front[f0] != 0;
        if (first == (front[f1] != 0))
            continue;
        out[2 * kept] = adjacent_edges[2 * e + (first ? 0 : 1)];
        out[2 * kept + 1] = adjacent_edges[2 * e + (first ? 1 : 0)];
        kept++;
    }
    *kept_out = kept;
    return OK;
}

/* int(min(max(ceil(x), lo), hi)): a row or column bound clamped to [lo, hi]. */
static inline i64 ceil_within(double x, i64 lo, i64 hi)
{
    return trunc_int(pmin(pmax(ceil(x), (double)lo), (double)hi));
}

static int footprint_mask(const double *a, const double *b, i64 n, i64 height, i64 width, unsigned char *mask)
{
    if (n == 0)
        return OK;
    double lo_u = INFINITY, lo_v = INFINITY, hi_u = -INFINITY, hi_v = -INFINITY;
    for (i64 e = 0; e < n; e++) {
        if (!(isfinite(a[2 * e]) && isfinite(a[2 * e + 1]) && isfinite(b[2 * e]) && isfinite(b[2 * e + 1])))
            return NOT_FINITE;
        lo_u = pmin(pmin(lo_u, a[2 * e]), b[2 * e]);
        hi_u = pmax(pmax(hi_u, a[2 * e]), b[2 * e]);
        lo_v = pmin(pmin(lo_v, a[2 * e + 1]), b[2 * e + 1]);
        hi_v = pmax(pmax(hi_v, a[2 * e + 1]), b[2 * e + 1]);
    }
    i64 left = ceil_within(lo_u, 0, width), right = ceil_within(hi_u, 0, width);
    i64 upper = ceil_within(lo_v, 0, height), lower = ceil_within(hi_v, 0, height);
    i64 box_w = right - left, box_h = imax(lower - upper, 0);
    i64 *crossings = calloc((size_t)(box_h * (box_w + 1)) + 1, sizeof(i64));
    if (!crossings)
        return NO_MEMORY;
    for (i64 e = 0; e < n; e++) {
        double tu, tv, bu, bv;
        i64 sign;
        if (b[2 * e + 1] > a[2 * e + 1]) {
            tu = a[2 * e], tv = a[2 * e + 1], bu = b[2 * e], bv = b[2 * e + 1], sign = 1;
        } else {
            tu = b[2 * e], tv = b[2 * e + 1], bu = a[2 * e], bv = a[2 * e + 1], sign = -1;
        }
        i64 first = ceil_within(tv, 0, height), last = ceil_within(bv, 0, height);
        for (i64 row = first; row < last; row++) {
            double x = tu + ((double)row - tv) / (bv - tv) * (bu - tu);
            i64 column = ceil_within(x, left, right) - left;
            crossings[(row - upper) * (box_w + 1) + column] += sign;
        }
    }
    for (i64 r = 0; r < box_h; r++) {
        i64 winding = 0;
        for (i64 c = 0; c < box_w; c++) {
            winding += crossings[r * (box_w + 1) + c];
            if (winding != 0)
                mask[(upper + r) * width + left + c] = 1;
        }
    }
    free(crossings);
    for (i64 e = 0; e < n; e++) {
        double du = b[2 * e] - a[2 * e], dv = b[2 * e + 1] - a[2 * e + 1];
        i64 steps = trunc_int(ceil(pmax(fabs(du), fabs(dv)))) + 1;
        for (i64 place = 0; place < steps; place++) {
            double s = (double)place / (double)imax(steps - 1, 1);
            i64 u = trunc_int(rint(a[2 * e] + s * du));
            i64 v = trunc_int(rint(a[2 * e + 1] + s * dv));
            if (0 <= u && u < width && 0 <= v && v < height)
                mask[v * width + u] = 1;
        }
    }
    return OK;
}

static int nearest_points(const double *points, i64 n, const double *queries, i64 M, double cell, i64 *found)
{
    double lo_u = points[0], lo_v = points[1], hi_u = lo_u, hi_v = lo_v;
    for (i64 k = 0; k < n; k++) {
        if (!(isfinite(points[2 * k]) && isfinite(points[2 * k + 1])))
            return NOT_FINITE;
        lo_u = pmin(lo_u, points[2 * k]), hi_u = pmax(hi_u, points[2 * k]);
        lo_v = pmin(lo_v, points[2 * k + 1]), hi_v = pmax(hi_v, points[2 * k + 1]);
    }
    double span_u = (hi_u - lo_u) / cell, span_v = (hi_v - lo_v) / cell;
    if (!(span_u < 1e9 && span_v < 1e9 && span_u * span_v < 1e9))
        return NO_MEMORY; /* a grid of a billion cells */
    i64 cols = trunc_int(span_u) + 1, rows = trunc_int(span_v) + 1;
    i64 *bin_of = malloc(sizeof(i64) * (size_t)n), *order = malloc(sizeof(i64) * (size_t)n);
    i64 *start = calloc((size_t)(cols * rows + 1), sizeof(i64)), *filled = malloc(sizeof(i64) * (size_t)(cols * rows));
    int status = OK;
    if (!bin_of || !order || !start || !filled) {
        status = NO_MEMORY;
        goto done;
    }
    for (i64 k = 0; k < n; k++) {
        bin_of[k] = trunc_int((points[2 * k + 1] - lo_v) / cell) * cols + trunc_int((points[2 * k] - lo_u) / cell);
        start[bin_of[k] + 1] += 1;
    }
    for (i64 b = 0; b < cols * rows; b++)
        start[b + 1] += start[b];
    memcpy(filled, start, sizeof(i64) * (size_t)(cols * rows));
    for (i64 k = 0; k < n; k++)
        order[filled[bin_of[k]]++] = k;
    for (i64 q = 0; q < M; q++) {
        double u = queries[2 * q], v = queries[2 * q + 1];
        double grid_u = floor((u - lo_u) / cell), grid_v = floor((v - lo_v) / cell);
        if (!(fabs(grid_u) < 1e15 && fabs(grid_v) < 1e15)) {
            status = NOT_FINITE;
            goto done;
        }
        i64 cu = (i64)grid_u, cv = (i64)grid_v;
        /* Rings beyond this reach lie wholly outside the grid. */
        i64 reach = imax(imax(imax(imax(cu, cols - 1 - cu), cv), rows - 1 - cv), 0);
        i64 best = -1;
        double best_d2 = INFINITY;
        for (i64 r = 0; r <= reach; r++) {
            for (i64 gv = imax(cv - r, 0); gv <= imin(cv + r, rows - 1); gv++) {
                i64 step = (gv == cv - r || gv == cv + r) ? 1 : 2 * r;
                for (i64 gu = cu - r; gu <= cu + r; gu += step) {
                    if (gu < 0 || gu >= cols)
                        continue;
                    i64 b = gv * cols + gu;
                    for (i64 j = start[b]; j < start[b + 1]; j++) {
                        i64 k = order[j];
                        double du = points[2 * k] - u, dv = points[2 * k + 1] - v;
                        double d2 = du * du + dv * dv;
                        if (d2 < best_d2 || (d2 == best_d2 && k < best))
                            best = k, best_d2 = d2;
                    }
                }
            }
            double reach_mm = (double)r * cell;
            if (best >= 0 && best_d2 <= reach_mm * reach_mm)
                break;
        }
        found[q] = best;
    }
done:
    free(bin_of), free(order), free(start), free(filled);
    return status;
}

/* ---------------------------------------------------------------- distance fields */

/* A field of samples (nx, ny, nz) at origin + spacing (i, j, k). */
typedef struct {
    grid_t values;
    i64 shape[3];
    const double *origin;
    double spacing;
} field_t;

/* Along one axis of the field: the cell of the coordinate (clamped to the grid), the
 * fraction across it, and how far (mm) the coordinate lies beyond the grid. A NaN
 * coordinate gets cell 0 and NaN fractions (a NaN value), never an index outside. */
static inline i64 grid_axis(double coordinate, double origin, double spacing, i64 size, double *frac,
                            double *out)
{
    double g = (coordinate - origin) / spacing;
    double clamped = pmin(pmax(g, 0.0), (double)(size - 1) - 1e-9);
    i64 cell = clamped == clamped ? (i64)floor(clamped) : 0;
    *frac = clamped - (double)cell;
    *out = (g - clamped) * spacing;
    return cell;
}

/* The trilinear interpolant of the field at (p0, p1, p2); with grad its exact gradient. */
static inline double trilinear_at(const field_t *f, double p0, double p1, double p2, double *grad)
{
    double fx, fy, fz, out_x, out_y, out_z;
    i64 x = grid_axis(p0, f->origin[0], f->spacing, f->shape[0], &fx, &out_x);
    i64 y = grid_axis(p1, f->origin[1], f->spacing, f->shape[1], &fy, &out_y);
    i64 z = grid_axis(p2, f->origin[2], f->spacing, f->shape[2], &fz, &out_z);
    double dist_out = sqrt(out_x * out_x + out_y * out_y + out_z * out_z);
    i64 sy = f->shape[2], sx = f->shape[1] * sy, i = x * sx + y * sy + z;
    double c000 = grid_at(f->values, i), c001 = grid_at(f->values, i + 1);
    double c010 = grid_at(f->values, i + sy), c011 = grid_at(f->values, i + sy + 1);
    double c100 = grid_at(f->values, i + sx), c101 = grid_at(f->values, i + sx + 1);
    double c110 = grid_at(f->values, i + sx + sy), c111 = grid_at(f->values, i + sx + sy + 1);
    grid_t g = f->values;
    double dz00 = grid_sub(g, c001, c000), dz01 = grid_sub(g, c011, c010);
    double dz10 = grid_sub(g, c101, c100), dz11 = grid_sub(g, c111, c110);
    double cz00 = c000 + dz00 * fz, cz01 = c010 + dz01 * fz;
    double cz10 = c100 + dz10 * fz, cz11 = c110 + dz11 * fz;
    double dy0 = cz01 - cz00, dy1 = cz11 - cz10;
    double cy0 = cz00 + dy0 * fy, cy1 = cz10 + dy1 * fy;
    double dx = cy1 - cy0;
    if (grad) {
        double slope_z0 = dz00 + grid_sub(g, dz01, dz00) * fy;
        double slope_z1 = dz10 + grid_sub(g, dz11, dz10) * fy;
        grad[0] = dx / f->spacing;
        grad[1] = (dy0 * (1 - fx) + dy1 * fx) / f->spacing;
        grad[2] = (slope_z0 * (1 - fx) + slope_z1 * fx) / f->spacing;
        if (out_x != 0.0)
            grad[0] = out_x / dist_out;
        if (out_y != 0.0)
            grad[1] = out_y / dist_out;
        if (out_z != 0.0)
            grad[2] = out_z / dist_out;
    }
    return cy0 + dx * fx + dist_out;
}

static int trilinear(const field_t *f, const double *points, i64 N, double *value, double *grad)
{
    for (i64 p = 0; p < N; p++)
        value[p] = trilinear_at(f, points[3 * p], points[3 * p + 1], points[3 * p + 2], grad ? grad + 3 * p : NULL);
    return OK;
}

static int surface_rows(const field_t *f, const double *points, i64 P, const i64 *ids, i64 N,
                        const double *seated, const double *directions, double *r, double *J)
{
    for (i64 i = 0; i < N; i++) {
        i64 id = ids[i];
        if (id < 0 || id >= P)
            return BAD_INDEX;
        const double *x = points + 3 * id;
        r[2 * i] = trilinear_at(f, x[0], x[1], x[2], J ? J + 6 * i : NULL);
        double along = 0.0;
        for (int k = 0; k < 3; k++) {
            along += (x[k] - seated[3 * i + k]) * directions[3 * i + k];
            if (J)
                J[6 * i + 3 + k] = directions[3 * i + k];
        }
        r[2 * i + 1] = along;
    }
    return OK;
}

/* The field's value at the point R (depth ray) + t. */
static inline double field_on_ray(const field_t *f, const double *R, const double *t, const double *ray,
                                  double depth)
{
    double q0 = ray[0] * depth, q1 = ray[1] * depth, q2 = ray[2] * depth;
    return trilinear_at(f, R[0] * q0 + R[1] * q1 + R[2] * q2 + t[0], R[3] * q0 + R[4] * q1 + R[5] * q2 + t[1],
                        R[6] * q0 + R[7] * q1 + R[8] * q2 + t[2], NULL);
}

/* Depth interval in which the ray depth * ray (carried by R, t) crosses the box (2, 3)
 * (slab test); a ray that misses it gets the empty interval at its closest approach to
 * the box's centre. */
static inline void depths_in_box(const double *box, const double *R, const double *t, const double *ray,
                                 double *near_out, double *far_out)
{
    double near = -INFINITY, far = INFINITY, square = 0.0, towards = 0.0;
    for (int k = 0; k < 3; k++) {
        double direction = R[3 * k] * ray[0] + R[3 * k + 1] * ray[1] + R[3 * k + 2] * ray[2];
        square += direction * direction;
        towards += direction * (0.5 * (box[k] + box[3 + k]) - t[k]);
        if (direction == 0.0) { /* parallel: the slab holds the whole ray or none of it */
            if (!(box[k] <= t[k] && t[k] <= box[3 + k]))
                near = INFINITY, far = -INFINITY;
            continue;
        }
        double enter = (box[k] - t[k]) / direction, leave = (box[3 + k] - t[k]) / direction;
        near = pmax(near, pmin(enter, leave));
        far = pmin(far, pmax(enter, leave));
    }
    if (!(far >= near))
        near = far = towards / square;
    *near_out = near;
    *far_out = far;
}

static int ray_minima(const field_t *f, const double *R, const double *t, const double *rays, i64 N,
                      double min_depth, double step, i64 coarse, double *found)
{
    double box[6];
    for (int k = 0; k < 3; k++)
        box[k] = f->origin[k], box[3 + k] = f->origin[k] + f->spacing * (double)(f->shape[k] - 1);
    double *fine = malloc(sizeof(double) * (size_t)(2 * coarse + 1));
    if (!fine)
        return NO_MEMORY;
    for (i64 r = 0; r < N; r++) {
        const double *ray = rays + 3 * r;
        double near, far;
        depths_in_box(box, R, t, ray, &near, &far);
        near = pmax(near, min_depth), far = pmax(far, min_depth);
        if (isinf(far)) { /* a zero ray inside the box: no end to sample up to */
            found[r] = NAN;
            continue;
        }
        double best_z = near, best_d = INFINITY;
        for (i64 k = 0;; k++) {
            double z = pmin(near + (double)coarse * step * (double)k, far);
            double d = field_on_ray(f, R, t, ray, z);
            if (d < best_d)
                best_z = z, best_d = d;
            if (!(z < far)) /* at the far end (or NaN depths: one sample) */
                break;
        }
        i64 best = 0;
        for (i64 j = 0; j < 2 * coarse + 1; j++) {
            fine[j] = field_on_ray(f, R, t, ray, best_z + (double)(j - coarse) * step);
            if (fine[j] < fine[best])
                best = j;
        }
        best = imin(imax(best, 1), 2 * coarse - 1);
        double d_minus = fine[best - 1], d_0 = fine[best], d_plus = fine[best + 1];
        double curvature = d_plus - 2.0 * d_0 + d_minus;
        double shift = curvature > 1e-9 ? 0.5 * (d_minus - d_plus) / pmax(curvature, 1e-9) : 0.0;
        found[r] = best_z + (double)(best - coarse) * step + pmin(pmax(shift, -1.0), 1.0) * step;
    }
    free(fine);
    return OK;
}

/* ================================================================ Python glue */

/* The buffers an entry point holds, released together. */
typedef struct {
    Py_buffer views[12];
    int count;
} held_t;

static void release(held_t *held)
{
    for (int i = 0; i < held->count; i++)
        PyBuffer_Release(&held->views[i]);
    held->count = 0;
}

static Py_ssize_t format_size(char code)
{
    switch (code) {
    case 'd': case 'l': case 'q': return 8;
    case 'f': return 4;
    case 'B': case '?': return 1;
    default: return 0;
    }
}

/* The C-contiguous buffer of obj, of ndim dimensions and one of the element formats in
 * formats ("d" float64, "f" float32, "lq" int64, "B?" uint8 or bool); NULL with an
 * exception naming the argument when it is not. */
static Py_buffer *take(held_t *held, PyObject *obj, const char *name, const char *formats, int ndim,
                       int writable)
{
    if (held->count == (int)(sizeof held->views / sizeof held->views[0])) {
        PyErr_SetString(PyExc_SystemError, "too many array arguments");
        return NULL;
    }
    Py_buffer *view = &held->views[held->count];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s array, got %.100s", name,
                     writable ? " writable" : "", Py_TYPE(obj)->tp_name);
        return NULL;
    }
    held->count++;
    const char *code = view->format;
    if (*code == '@' || *code == '=' || *code == '<')
        code++;
    if (!code[0] || code[1] || !strchr(formats, code[0]) || view->itemsize != format_size(code[0])) {
        PyErr_Format(PyExc_TypeError, "%s: element type '%s' is not one of '%s'", name, view->format, formats);
        return NULL;
    }
    if (view->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: %d dimensions, expected %d", name, view->ndim, ndim);
        return NULL;
    }
    return view;
}

/* Whether view's shape is dims (-1: any), else a ValueError naming the argument. */
static int shaped(const Py_buffer *view, const char *name, const Py_ssize_t *dims)
{
    for (int i = 0; i < view->ndim; i++)
        if (dims[i] >= 0 && view->shape[i] != dims[i]) {
            PyErr_Format(PyExc_ValueError, "%s: axis %d has %zd elements, expected %zd", name, i,
                         view->shape[i], dims[i]);
            return 0;
        }
    return 1;
}

#define TAKE(var, obj, formats, ndim, writable)                       \
    Py_buffer *var = take(held, obj, #var, formats, ndim, writable);  \
    if (!var)                                                         \
        return NULL
#define SHAPE(var, ...)                                               \
    do {                                                              \
        const Py_ssize_t dims_[] = {__VA_ARGS__};                     \
        if (!shaped(var, #var, dims_))                                \
            return NULL;                                              \
    } while (0)
#define REQUIRE(cond, message)                                        \
    do {                                                              \
        if (!(cond)) {                                                \
            PyErr_SetString(PyExc_ValueError, message);               \
            return NULL;                                              \
        }                                                             \
    } while (0)
/* The kernel call, without the GIL; its error as an exception named after the kernel
 * (the glue function's name without "glue_"). */
#define RUN(call)                                                     \
    do {                                                              \
        int status_;                                                  \
        Py_BEGIN_ALLOW_THREADS                                        \
        status_ = (call);                                             \
        Py_END_ALLOW_THREADS                                          \
        if (!raise_status(status_, __func__ + 5))                     \
            return NULL;                                              \
    } while (0)

/* The entry point py_name: glue_name with the buffers it took released, however it ends. */
#define ENTRY(name)                                                   \
    static PyObject *py_##name(PyObject *self, PyObject *args)        \
    {                                                                 \
        held_t held = {.count = 0};                                   \
        PyObject *result = glue_##name(args, &held);                  \
        release(&held);                                               \
        return result;                                                \
    }

#define F64 "d"
#define I64 "lq"
#define GRID "df"

static int raise_status(int status, const char *kernel)
{
    switch (status) {
    case OK: return 1;
    case BAD_INDEX: PyErr_Format(PyExc_IndexError, "%s: an index is out of range", kernel); break;
    case NOT_FINITE: PyErr_Format(PyExc_ValueError, "%s: coordinates are not finite", kernel); break;
    case NO_MEMORY: PyErr_Format(PyExc_MemoryError, "%s: no memory for its working arrays", kernel); break;
    default: PyErr_Format(PyExc_ValueError, "%s: inconsistent shapes", kernel); break;
    }
    return 0;
}

static grid_t grid_of(const Py_buffer *view)
{
    grid_t g = {view->buf, view->itemsize == 4};
    return g;
}

static PyObject *glue_schur_complement(PyObject *args, held_t *held)
{
    PyObject *o[7];
    double lam, regularisation;
    if (!PyArg_ParseTuple(args, "OOOOddOOO", &o[0], &o[1], &o[2], &o[3], &lam, &regularisation, &o[4], &o[5], &o[6]))
        return NULL;
    TAKE(H_xx, o[0], F64, 3, 0);
    TAKE(g_x, o[1], F64, 2, 0);
    TAKE(W, o[2], F64, 4, 0);
    TAKE(pose_of, o[3], I64, 2, 0);
    TAKE(blocks, o[4], F64, 4, 1);
    TAKE(shift, o[5], F64, 2, 1);
    TAKE(V_inv, o[6], F64, 3, 1);
    Py_ssize_t X = pose_of->shape[0], k = pose_of->shape[1], P = blocks->shape[0];
    SHAPE(H_xx, X, 3, 3);
    SHAPE(g_x, X, 3);
    SHAPE(W, X, k, 6, 3);
    SHAPE(blocks, P, P, 6, 6);
    SHAPE(shift, P, 6);
    SHAPE(V_inv, X, 3, 3);
    RUN(schur_complement(H_xx->buf, g_x->buf, W->buf, pose_of->buf, X, k, P, lam, regularisation, blocks->buf,
                         shift->buf, V_inv->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_point_steps(PyObject *args, held_t *held)
{
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "OOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    TAKE(W, o[0], F64, 4, 0);
    TAKE(pose_of, o[1], I64, 2, 0);
    TAKE(d_p, o[2], F64, 1, 0);
    TAKE(V_inv, o[3], F64, 3, 0);
    TAKE(g_x, o[4], F64, 2, 0);
    TAKE(d_x, o[5], F64, 2, 1);
    Py_ssize_t X = pose_of->shape[0], k = pose_of->shape[1];
    SHAPE(W, X, k, 6, 3);
    SHAPE(V_inv, X, 3, 3);
    SHAPE(g_x, X, 3);
    SHAPE(d_x, X, 3);
    RUN(point_steps(W->buf, pose_of->buf, d_p->buf, V_inv->buf, g_x->buf, X, k, d_p->shape[0] / 6, d_x->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_point_blocks(PyObject *args, held_t *held)
{
    PyObject *o[7];
    if (!PyArg_ParseTuple(args, "OOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6]))
        return NULL;
    TAKE(Jx, o[0], F64, 3, 0);
    TAKE(w, o[1], F64, 1, 0);
    TAKE(residuals, o[2], F64, 2, 0);
    TAKE(x_idx, o[3], I64, 1, 0);
    TAKE(H_xx, o[4], F64, 3, 1);
    TAKE(g_x, o[5], F64, 2, 1);
    TAKE(Jx_w, o[6], F64, 3, 1);
    Py_ssize_t n = Jx->shape[0], m = Jx->shape[1], X = H_xx->shape[0];
    SHAPE(Jx, n, m, 3);
    SHAPE(w, n);
    SHAPE(residuals, n, m);
    SHAPE(x_idx, n);
    SHAPE(H_xx, X, 3, 3);
    SHAPE(g_x, X, 3);
    SHAPE(Jx_w, n, m, 3);
    RUN(point_blocks(Jx->buf, w->buf, residuals->buf, x_idx->buf, n, m, X, H_xx->buf, g_x->buf, Jx_w->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_coupling_blocks(PyObject *args, held_t *held)
{
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2]))
        return NULL;
    TAKE(Ja, o[0], F64, 3, 0);
    TAKE(Jx_w, o[1], F64, 3, 0);
    TAKE(out, o[2], F64, 3, 1);
    Py_ssize_t n = Ja->shape[0], m = Ja->shape[1];
    SHAPE(Ja, n, m, 6);
    SHAPE(Jx_w, n, m, 3);
    SHAPE(out, n, 6, 3);
    RUN(coupling_blocks(Ja->buf, Jx_w->buf, n, m, out->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_scatter_add(PyObject *args, held_t *held)
{
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "OOOO", &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    TAKE(keys, o[0], I64, 1, 0);
    TAKE(values, o[1], F64, 2, 0);
    TAKE(sums, o[2], F64, 2, 1);
    TAKE(seen, o[3], "?", 1, 1);
    Py_ssize_t K = keys->shape[0], D = values->shape[1], n_keys = sums->shape[0];
    SHAPE(values, K, D);
    SHAPE(sums, n_keys, D);
    SHAPE(seen, n_keys);
    RUN(scatter_add(keys->buf, values->buf, K, D, n_keys, sums->buf, seen->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_squared_norms(PyObject *args, held_t *held)
{
    PyObject *o[2];
    if (!PyArg_ParseTuple(args, "OO", &o[0], &o[1]))
        return NULL;
    TAKE(residuals, o[0], F64, 2, 0);
    TAKE(out, o[1], F64, 1, 1);
    SHAPE(out, residuals->shape[0]);
    RUN(squared_norms(residuals->buf, residuals->shape[0], residuals->shape[1], out->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_robust_cost(PyObject *args, held_t *held)
{
    PyObject *o[1];
    long kind;
    double scale, total = 0.0;
    if (!PyArg_ParseTuple(args, "Old", &o[0], &kind, &scale))
        return NULL;
    TAKE(s, o[0], F64, 1, 0);
    Py_BEGIN_ALLOW_THREADS
    total = robust_cost(s->buf, s->shape[0], kind, scale);
    Py_END_ALLOW_THREADS
    return PyFloat_FromDouble(total);
}

static PyObject *glue_in_field(PyObject *args, held_t *held)
{
    PyObject *o[2];
    long long width, height;
    double margin, radius;
    if (!PyArg_ParseTuple(args, "OLLddO", &o[0], &width, &height, &margin, &radius, &o[1]))
        return NULL;
    TAKE(uv, o[0], F64, 2, 0);
    TAKE(inside, o[1], "?", 1, 1);
    SHAPE(uv, -1, 2);
    SHAPE(inside, uv->shape[0]);
    RUN(in_field(uv->buf, uv->shape[0], width, height, margin, radius, inside->buf));
    Py_RETURN_NONE;
}

/* outline_total(uv_delta, spacing): the number of samples before the tests (the length
 * of the outputs outline_samples needs); outline_samples(...) -> the number kept. */
static PyObject *glue_outline_total(PyObject *args, held_t *held)
{
    PyObject *o[1];
    double spacing;
    i64 total = 0;
    if (!PyArg_ParseTuple(args, "Od", &o[0], &spacing))
        return NULL;
    TAKE(uv_delta, o[0], F64, 2, 0);
    SHAPE(uv_delta, -1, 2);
    Py_BEGIN_ALLOW_THREADS
    total = outline_total(uv_delta->buf, uv_delta->shape[0], spacing);
    Py_END_ALLOW_THREADS
    return PyLong_FromLongLong(total);
}

static PyObject *glue_outline_samples(PyObject *args, held_t *held)
{
    PyObject *o[5];
    double spacing, margin, radius;
    long long width, height, downscale;
    i64 kept = 0;
    if (!PyArg_ParseTuple(args, "OOdLLddOLOO", &o[0], &o[1], &spacing, &width, &height, &margin, &radius, &o[2],
                          &downscale, &o[3], &o[4]))
        return NULL;
    TAKE(uv_a, o[0], F64, 2, 0);
    TAKE(uv_delta, o[1], F64, 2, 0);
    TAKE(interior, o[2], "B?", 2, 0);
    TAKE(edge, o[3], I64, 1, 1);
    TAKE(frac, o[4], F64, 1, 1);
    Py_ssize_t E = uv_a->shape[0], h = interior->shape[0], w = interior->shape[1];
    SHAPE(uv_a, E, 2);
    SHAPE(uv_delta, E, 2);
    REQUIRE((h > 0) == (w > 0), "outline_samples: the interior mask is empty in one axis only");
    REQUIRE(downscale >= 1, "outline_samples: downscale must be at least 1");
    SHAPE(frac, edge->shape[0]);
    RUN(outline_samples(uv_a->buf, uv_delta->buf, E, spacing, width, height, margin, radius, interior->buf, h, w,
                        downscale, edge->shape[0], edge->buf, frac->buf, &kept));
    return PyLong_FromLongLong(kept);
}

static PyObject *glue_pinhole(PyObject *args, held_t *held)
{
    PyObject *o[3];
    double fx, fy, cx, cy, min_depth;
    if (!PyArg_ParseTuple(args, "OdddddOO", &o[0], &fx, &fy, &cx, &cy, &min_depth, &o[1], &o[2]))
        return NULL;
    TAKE(p_cam, o[0], F64, 2, 0);
    TAKE(uv, o[1], F64, 2, 1);
    TAKE(J, o[2], F64, 3, 1);
    Py_ssize_t n = p_cam->shape[0];
    int jacobian = J->shape[0] > 0;
    SHAPE(p_cam, n, 3);
    SHAPE(uv, n, 2);
    SHAPE(J, jacobian ? n : 0, 2, 3);
    RUN(pinhole(p_cam->buf, n, fx, fy, cx, cy, min_depth, uv->buf, jacobian ? J->buf : NULL));
    Py_RETURN_NONE;
}

static PyObject *glue_bilinear(PyObject *args, held_t *held)
{
    PyObject *o[5];
    if (!PyArg_ParseTuple(args, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    TAKE(values, o[0], GRID, 2, 0);
    TAKE(origin, o[1], F64, 1, 0);
    TAKE(uv, o[2], F64, 2, 0);
    TAKE(value, o[3], F64, 1, 1);
    TAKE(grad, o[4], F64, 2, 1);
    Py_ssize_t n = uv->shape[0];
    SHAPE(origin, 2);
    SHAPE(uv, n, 2);
    SHAPE(value, n);
    SHAPE(grad, n, 2);
    REQUIRE(values->shape[0] >= 2 && values->shape[1] >= 2, "bilinear: the image needs 2 x 2 pixels or more");
    RUN(bilinear(grid_of(values), values->shape[0], values->shape[1], origin->buf, uv->buf, n, value->buf,
                 grad->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_silhouette_rows(PyObject *args, held_t *held)
{
    PyObject *o[8];
    double fx, fy, cx, cy, min_depth;
    if (!PyArg_ParseTuple(args, "OdddddOOOOOOO", &o[0], &fx, &fy, &cx, &cy, &min_depth, &o[1], &o[2], &o[3],
                          &o[4], &o[5], &o[6], &o[7]))
        return NULL;
    TAKE(p_cam, o[0], F64, 2, 0);
    TAKE(values, o[1], GRID, 2, 0);
    TAKE(origin, o[2], F64, 1, 0);
    TAKE(charged, o[3], I64, 1, 0);
    TAKE(nearest, o[4], I64, 1, 0);
    TAKE(observed, o[5], F64, 2, 0);
    TAKE(r, o[6], F64, 2, 1);
    TAKE(J_cam, o[7], F64, 2, 1);
    Py_ssize_t n = p_cam->shape[0], n_c = charged->shape[0], n_o = nearest->shape[0];
    int jacobian = J_cam->shape[0] > 0;
    SHAPE(p_cam, n, 3);
    SHAPE(origin, 2);
    SHAPE(observed, n_o, 2);
    SHAPE(r, n_c + n_o, 1);
    SHAPE(J_cam, jacobian ? n_c + n_o : 0, 3);
    REQUIRE(values->shape[0] >= 2 && values->shape[1] >= 2, "silhouette_rows: the image needs 2 x 2 pixels or more");
    RUN(silhouette_rows(p_cam->buf, n, fx, fy, cx, cy, min_depth, grid_of(values), values->shape[0],
                        values->shape[1], origin->buf, charged->buf, n_c, nearest->buf, observed->buf, n_o, r->buf,
                        jacobian ? J_cam->buf : NULL));
    Py_RETURN_NONE;
}

static PyObject *glue_contour_generators(PyObject *args, held_t *held)
{
    PyObject *o[4];
    i64 kept = 0;
    if (!PyArg_ParseTuple(args, "OOOO", &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    TAKE(front, o[0], "?B", 1, 0);
    TAKE(adjacent_faces, o[1], I64, 2, 0);
    TAKE(adjacent_edges, o[2], I64, 2, 0);
    TAKE(out, o[3], I64, 2, 1);
    Py_ssize_t A = adjacent_edges->shape[0];
    SHAPE(adjacent_faces, A, 2);
    SHAPE(adjacent_edges, A, 2);
    SHAPE(out, A, 2);
    RUN(contour_generators(front->buf, front->shape[0], adjacent_faces->buf, adjacent_edges->buf, A, out->buf,
                           &kept));
    return PyLong_FromLongLong(kept);
}

static PyObject *glue_footprint_mask(PyObject *args, held_t *held)
{
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO", &o[0], &o[1], &o[2]))
        return NULL;
    TAKE(a, o[0], F64, 2, 0);
    TAKE(b, o[1], F64, 2, 0);
    TAKE(mask, o[2], "B", 2, 1);
    Py_ssize_t n = a->shape[0];
    SHAPE(a, n, 2);
    SHAPE(b, n, 2);
    RUN(footprint_mask(a->buf, b->buf, n, mask->shape[0], mask->shape[1], mask->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_nearest_points(PyObject *args, held_t *held)
{
    PyObject *o[3];
    double cell;
    if (!PyArg_ParseTuple(args, "OOdO", &o[0], &o[1], &cell, &o[2]))
        return NULL;
    TAKE(points, o[0], F64, 2, 0);
    TAKE(queries, o[1], F64, 2, 0);
    TAKE(found, o[2], I64, 1, 1);
    SHAPE(points, -1, 2);
    SHAPE(queries, -1, 2);
    SHAPE(found, queries->shape[0]);
    REQUIRE(points->shape[0] >= 1, "nearest_points: no points to search");
    REQUIRE(cell > 0.0, "nearest_points: the cell must be positive");
    RUN(nearest_points(points->buf, points->shape[0], queries->buf, queries->shape[0], cell, found->buf));
    Py_RETURN_NONE;
}

/* The field's buffers (values, origin) taken and checked into f. */
static int take_field(held_t *held, PyObject *values_obj, PyObject *origin_obj, double spacing, field_t *f)
{
    Py_buffer *values = take(held, values_obj, "values", GRID, 3, 0);
    if (!values)
        return 0;
    Py_buffer *origin = take(held, origin_obj, "origin", F64, 1, 0);
    if (!origin)
        return 0;
    const Py_ssize_t three[] = {3};
    if (!shaped(origin, "origin", three))
        return 0;
    for (int k = 0; k < 3; k++) {
        if (values->shape[k] < 2) {
            PyErr_SetString(PyExc_ValueError, "values: the field needs 2 samples or more along each axis");
            return 0;
        }
        f->shape[k] = values->shape[k];
    }
    f->values = grid_of(values);
    f->origin = origin->buf;
    f->spacing = spacing;
    return 1;
}

static PyObject *glue_trilinear(PyObject *args, held_t *held)
{
    PyObject *o[5];
    double spacing;
    field_t f;
    if (!PyArg_ParseTuple(args, "OOdOOO", &o[0], &o[1], &spacing, &o[2], &o[3], &o[4]))
        return NULL;
    if (!take_field(held, o[0], o[1], spacing, &f))
        return NULL;
    TAKE(points, o[2], F64, 2, 0);
    TAKE(value, o[3], F64, 1, 1);
    TAKE(grad, o[4], F64, 2, 1);
    Py_ssize_t n = points->shape[0];
    int gradient = grad->shape[0] > 0;
    SHAPE(points, n, 3);
    SHAPE(value, n);
    SHAPE(grad, gradient ? n : 0, 3);
    RUN(trilinear(&f, points->buf, n, value->buf, gradient ? grad->buf : NULL));
    Py_RETURN_NONE;
}

static PyObject *glue_surface_rows(PyObject *args, held_t *held)
{
    PyObject *o[8];
    double spacing;
    field_t f;
    if (!PyArg_ParseTuple(args, "OOdOOOOOO", &o[0], &o[1], &spacing, &o[2], &o[3], &o[4], &o[5], &o[6], &o[7]))
        return NULL;
    if (!take_field(held, o[0], o[1], spacing, &f))
        return NULL;
    TAKE(points, o[2], F64, 2, 0);
    TAKE(ids, o[3], I64, 1, 0);
    TAKE(seated, o[4], F64, 2, 0);
    TAKE(directions, o[5], F64, 2, 0);
    TAKE(r, o[6], F64, 2, 1);
    TAKE(J, o[7], F64, 3, 1);
    Py_ssize_t n = ids->shape[0];
    int jacobian = J->shape[0] > 0;
    SHAPE(points, -1, 3);
    SHAPE(seated, n, 3);
    SHAPE(directions, n, 3);
    SHAPE(r, n, 2);
    SHAPE(J, jacobian ? n : 0, 2, 3);
    RUN(surface_rows(&f, points->buf, points->shape[0], ids->buf, n, seated->buf, directions->buf, r->buf,
                     jacobian ? J->buf : NULL));
    Py_RETURN_NONE;
}

static PyObject *glue_ray_minima(PyObject *args, held_t *held)
{
    PyObject *o[6];
    double spacing, min_depth, step;
    long long coarse;
    field_t f;
    if (!PyArg_ParseTuple(args, "OOdOOOddLO", &o[0], &o[1], &spacing, &o[2], &o[3], &o[4], &min_depth, &step,
                          &coarse, &o[5]))
        return NULL;
    if (!take_field(held, o[0], o[1], spacing, &f))
        return NULL;
    TAKE(R, o[2], F64, 2, 0);
    TAKE(t, o[3], F64, 1, 0);
    TAKE(rays, o[4], F64, 2, 0);
    TAKE(found, o[5], F64, 1, 1);
    SHAPE(R, 3, 3);
    SHAPE(t, 3);
    SHAPE(rays, -1, 3);
    SHAPE(found, rays->shape[0]);
    REQUIRE(coarse >= 1 && coarse <= 1000000, "ray_minima: coarse must be a positive number of steps");
    REQUIRE(step > 0.0 && isfinite(step), "ray_minima: the step must be positive");
    RUN(ray_minima(&f, R->buf, t->buf, rays->buf, rays->shape[0], min_depth, step, coarse, found->buf));
    Py_RETURN_NONE;
}

static PyObject *glue_pose_rows(PyObject *args, held_t *held)
{
    PyObject *o[8];
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7]))
        return NULL;
    TAKE(G_cam, o[0], F64, 3, 0);
    TAKE(X, o[1], F64, 2, 0);
    TAKE(R_view, o[2], F64, 2, 0);
    TAKE(R_body, o[3], F64, 2, 0);
    TAKE(t_body, o[4], F64, 1, 0);
    TAKE(J_view, o[5], F64, 3, 1);
    TAKE(J_body, o[6], F64, 3, 1);
    TAKE(G_x, o[7], F64, 3, 1);
    Py_ssize_t n = G_cam->shape[0], m = G_cam->shape[1];
    int with_body = J_body->shape[0] > 0;
    SHAPE(G_cam, n, m, 3);
    SHAPE(X, n, 3);
    SHAPE(R_view, 3, 3);
    SHAPE(R_body, 3, 3);
    SHAPE(t_body, 3);
    SHAPE(J_view, n, m, 6);
    SHAPE(J_body, with_body ? n : 0, m, 6);
    SHAPE(G_x, n, m, 3);
    RUN(pose_rows(G_cam->buf, X->buf, n, m, R_view->buf, R_body->buf, t_body->buf, J_view->buf,
                  with_body ? J_body->buf : NULL, G_x->buf));
    Py_RETURN_NONE;
}

ENTRY(schur_complement)
ENTRY(point_steps)
ENTRY(point_blocks)
ENTRY(coupling_blocks)
ENTRY(scatter_add)
ENTRY(squared_norms)
ENTRY(robust_cost)
ENTRY(in_field)
ENTRY(outline_total)
ENTRY(outline_samples)
ENTRY(pinhole)
ENTRY(bilinear)
ENTRY(silhouette_rows)
ENTRY(contour_generators)
ENTRY(footprint_mask)
ENTRY(nearest_points)
ENTRY(trilinear)
ENTRY(surface_rows)
ENTRY(ray_minima)
ENTRY(pose_rows)

static PyMethodDef methods[] = {
    {"schur_complement", py_schur_complement, METH_VARARGS, NULL},
    {"point_steps", py_point_steps, METH_VARARGS, NULL},
    {"point_blocks", py_point_blocks, METH_VARARGS, NULL},
    {"coupling_blocks", py_coupling_blocks, METH_VARARGS, NULL},
    {"scatter_add", py_scatter_add, METH_VARARGS, NULL},
    {"squared_norms", py_squared_norms, METH_VARARGS, NULL},
    {"robust_cost", py_robust_cost, METH_VARARGS, NULL},
    {"in_field", py_in_field, METH_VARARGS, NULL},
    {"outline_total", py_outline_total, METH_VARARGS, NULL},
    {"outline_samples", py_outline_samples, METH_VARARGS, NULL},
    {"pinhole", py_pinhole, METH_VARARGS, NULL},
    {"bilinear", py_bilinear, METH_VARARGS, NULL},
    {"silhouette_rows", py_silhouette_rows, METH_VARARGS, NULL},
    {"contour_generators", py_contour_generators, METH_VARARGS, NULL},
    {"footprint_mask", py_footprint_mask, METH_VARARGS, NULL},
    {"nearest_points", py_nearest_points, METH_VARARGS, NULL},
    {"trilinear", py_trilinear, METH_VARARGS, NULL},
    {"surface_rows", py_surface_rows, METH_VARARGS, NULL},
    {"ray_minima", py_ray_minima, METH_VARARGS, NULL},
    {"pose_rows", py_pose_rows, METH_VARARGS, NULL},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_kernels",
    "The solver's compiled kernels; call them through slamtka.solver.kernels, which checks and allocates.",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
