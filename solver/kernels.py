"""Compiled (numba) kernels for per-point loops that numpy expresses only as many small
batched products or passes over temporaries.

The Schur complement of an iteration eliminates each edge point's 3x3 block and folds its
one or two (6, 3) couplings into the pose blocks: with numpy that is a dozen passes over
(X, k, 6, 6) temporaries and sparse sums per trial step (a third of the joint stages'
time); one compiled pass over the points does the same arithmetic in registers. The
distance field's trilinear lookup (tens of thousands of points per seating of the edge
points) is the same story: one pass instead of some twenty array passes, and so is the
rasterisation of a model's projected footprint (every few iterations of every silhouette
term) and the search for each observed contour pixel's nearest outline point (every
iteration of every silhouette term: building and querying a KD-tree for a thousand points
cost more than the rest of the term), and the bilinear lookup of an image's distance map
(every iteration of every term on a view's contour: a few hundred points, where numpy's
per-call overhead of some twenty array passes dominated), as it does in the camera's
projection of a term's points (several times per iteration and term), the sampling of a
traced outline, the contour generators of a pose, the Jacobian rows of a pose increment, a
silhouette term's residual rows and their gradients (projection, lookups
and nearest-pair distances: some fifteen array passes per evaluation, several hundred
evaluations per solve), and the points' blocks of the normal equations and their sums by key.
So are the seating of edge points on their rays (some 25 field lookups per ray, each a dozen
array passes over every ray's samples in numpy), every term's robust cost, the Jacobian
rows of the poses and the back-projection term's rows (a few hundred of each per solve,
where numpy's per-call overhead was most of their cost), and each trial step's
back-substitution of the points' increments.
Compiled on first use and cached beside this file when it is writable (the service's
warm-up pays the first compilation, about a second).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["bilinear", "contour_generators", "coupling_blocks", "footprint_mask", "in_field", "nearest_points", "outline_samples", "pinhole", "point_blocks", "point_steps", "pose_rows", "ray_minima",
           "robust_cost", "scatter_add", "schur_complement", "silhouette_rows", "squared_norms", "surface_rows", "trilinear", "warm_up"]


@numba.njit(cache=True, nogil=True)
def _inverse_3x3(M: np.ndarray, out: np.ndarray) -> None:
    """``out`` = inverse of the 3x3 ``M`` from its cofactors (as the numpy path does)."""
    c00 = M[1, 1] * M[2, 2] - M[1, 2] * M[2, 1]
    c01 = M[1, 2] * M[2, 0] - M[1, 0] * M[2, 2]
    c02 = M[1, 0] * M[2, 1] - M[1, 1] * M[2, 0]
    det = M[0, 0] * c00 + M[0, 1] * c01 + M[0, 2] * c02
    out[0, 0] = c00 / det
    out[1, 0] = c01 / det
    out[2, 0] = c02 / det
    out[0, 1] = (M[2, 1] * M[0, 2] - M[2, 2] * M[0, 1]) / det
    out[1, 1] = (M[2, 2] * M[0, 0] - M[2, 0] * M[0, 2]) / det
    out[2, 1] = (M[2, 0] * M[0, 1] - M[2, 1] * M[0, 0]) / det
    out[0, 2] = (M[0, 1] * M[1, 2] - M[0, 2] * M[1, 1]) / det
    out[1, 2] = (M[0, 2] * M[1, 0] - M[0, 0] * M[1, 2]) / det
    out[2, 2] = (M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]) / det


@numba.njit(cache=True, nogil=True)
def schur_complement(H_xx: np.ndarray, g_x: np.ndarray, W: np.ndarray, pose_of: np.ndarray,
                     n_poses: int, lam: float, regularisation: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point ``x``: its block damped (``lam`` times its diagonal, plus
    ``regularisation`` times its trace) and inverted, ``V_inv`` (X, 3, 3); the sums over
    points of ``W_a V_inv W_b^T`` into the pose-pair blocks (P, P, 6, 6) and of
    ``W_a V_inv g_x`` into each pose (P, 6). ``W`` (X, k, 6, 3) holds each point's
    couplings, ``pose_of`` (X, k) their poses (``n_poses`` marks an empty slot)."""
    X, k = pose_of.shape
    blocks = np.zeros((n_poses, n_poses, 6, 6))
    shift = np.zeros((n_poses, 6))
    V_inv = np.empty((X, 3, 3))
    V = np.empty((3, 3))
    Y = np.empty((k, 6, 3))
    for x in range(X):
        trace = H_xx[x, 0, 0] + H_xx[x, 1, 1] + H_xx[x, 2, 2]
        reg = regularisation * max(trace, 1e-9)
        for i in range(3):
            for j in range(3):
                V[i, j] = H_xx[x, i, j]
            V[i, i] += lam * H_xx[x, i, i] + reg
        _inverse_3x3(V, V_inv[x])
        for a in range(k):
            pa = pose_of[x, a]
            if pa >= n_poses:
                continue
            for r in range(6):
                for j in range(3):
                    Y[a, r, j] = (W[x, a, r, 0] * V_inv[x, 0, j] + W[x, a, r, 1] * V_inv[x, 1, j]
                                  + W[x, a, r, 2] * V_inv[x, 2, j])
                shift[pa, r] += Y[a, r, 0] * g_x[x, 0] + Y[a, r, 1] * g_x[x, 1] + Y[a, r, 2] * g_x[x, 2]
            for b in range(k):
                pb = pose_of[x, b]
                if pb >= n_poses:
                    continue
                for r in range(6):
                    for c in range(6):
                        blocks[pa, pb, r, c] += (Y[a, r, 0] * W[x, b, c, 0] + Y[a, r, 1] * W[x, b, c, 1]
                                                 + Y[a, r, 2] * W[x, b, c, 2])
    return blocks, shift, V_inv


@numba.njit(cache=True, nogil=True)
def point_steps(W: np.ndarray, pose_of: np.ndarray, d_p: np.ndarray, V_inv: np.ndarray,
                g_x: np.ndarray) -> np.ndarray:
    """The points' increments (X, 3) back-substituted from the poses' ``d_p`` (6P,):
    ``-V_inv (g_x + sum over the point's couplings of W_a^T d_p[pose_a])``, with ``W``,
    ``pose_of`` and ``V_inv`` as in :func:`schur_complement`. One pass instead of two
    batched products and a gather per trial step."""
    X, k = pose_of.shape
    n_poses = d_p.shape[0] // 6
    d_x = np.empty((X, 3))
    c = np.empty(3)
    for x in range(X):
        for j in range(3):
            c[j] = g_x[x, j]
        for a in range(k):
            pose = pose_of[x, a]
            if pose >= n_poses:
                continue
            for i in range(6):
                step = d_p[6 * pose + i]
                for j in range(3):
                    c[j] += W[x, a, i, j] * step
        for i in range(3):
            d_x[x, i] = -(V_inv[x, i, 0] * c[0] + V_inv[x, i, 1] * c[1] + V_inv[x, i, 2] * c[2])
    return d_x


@numba.njit(cache=True, nogil=True, inline="always")
def _in_field(u: float, v: float, width: int, height: int, margin: float, radius: float) -> bool:
    """Whether pixel (u, v) lies inside the image and its circular field of view of
    ``radius`` (inf: none), ``margin`` pixels in from their edges."""
    if not (u >= margin and v >= margin and u <= width - 1 - margin and v <= height - 1 - margin):
        return False
    du, dv = u - (width - 1) / 2.0, v - (height - 1) / 2.0
    return np.sqrt(du * du + dv * dv) <= radius - margin


@numba.njit(cache=True, nogil=True)
def in_field(uv: np.ndarray, width: int, height: int, margin: float, radius: float) -> np.ndarray:
    """Mask (N,) of the pixels ``uv`` (N, 2) inside the field of view (:func:`_in_field`)."""
    inside = np.empty(uv.shape[0], np.bool_)
    for p in range(uv.shape[0]):
        inside[p] = _in_field(uv[p, 0], uv[p, 1], width, height, margin, radius)
    return inside


@numba.njit(cache=True, nogil=True)
def outline_samples(uv_a: np.ndarray, uv_delta: np.ndarray, spacing: float, width: int, height: int,
                    margin: float, radius: float, interior: np.ndarray, downscale: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Samples along projected edges from ``uv_a`` (E, 2) by ``uv_delta`` (E, 2), at the
    centres of ``ceil(length / spacing)`` (at least one) equal sub-segments, kept when in
    the field of view (:func:`_in_field`) and, when ``interior`` (h, w) is not empty, on a
    zero pixel of that mask at 1/``downscale`` resolution. Each kept sample's edge and
    fraction along it, in edge order."""
    total = 0
    counts = np.empty(uv_a.shape[0], np.int64)
    for e in range(uv_a.shape[0]):
        du, dv = uv_delta[e, 0], uv_delta[e, 1]
        counts[e] = max(1, int(np.ceil(np.sqrt(du * du + dv * dv) / spacing)))
        total += counts[e]
    edge = np.empty(total, np.int64)
    frac = np.empty(total)
    h, w = interior.shape
    kept = 0
    for e in range(uv_a.shape[0]):
        for place in range(counts[e]):
            s = (place + 0.5) / counts[e]
            u = uv_a[e, 0] + s * uv_delta[e, 0]
            v = uv_a[e, 1] + s * uv_delta[e, 1]
            if not _in_field(u, v, width, height, margin, radius):
                continue
            if h > 0:
                iu = min(max(int(np.rint(u / downscale)), 0), w - 1)
                iv = min(max(int(np.rint(v / downscale)), 0), h - 1)
                if interior[iv, iu] != 0:
                    continue
            edge[kept], frac[kept] = e, s
            kept += 1
    return edge[:kept], frac[:kept]


@numba.njit(cache=True, nogil=True)
def pinhole(p_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, min_depth: float,
            jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of camera-frame points (N, 3), their depth floored at ``min_depth``,
    and when ``jacobian`` the projection's Jacobian (N, 2, 3) (else an empty (0, 2, 3))."""
    n = p_cam.shape[0]
    uv = np.empty((n, 2))
    J = np.zeros((n if jacobian else 0, 2, 3))
    for p in range(n):
        x, y = p_cam[p, 0], p_cam[p, 1]
        z = max(p_cam[p, 2], min_depth)
        if jacobian:
            inv_z = 1.0 / z
            uv[p, 0] = fx * x * inv_z + cx
            uv[p, 1] = fy * y * inv_z + cy
            J[p, 0, 0] = fx * inv_z
            J[p, 0, 2] = -fx * x * inv_z**2
            J[p, 1, 1] = fy * inv_z
            J[p, 1, 2] = -fy * y * inv_z**2
        else:
            uv[p, 0] = fx * x / z + cx
            uv[p, 1] = fy * y / z + cy
    return uv, J


@numba.njit(cache=True, nogil=True)
def bilinear(values: np.ndarray, origin: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation of the image ``values`` (h, w), whose pixel (0, 0) lies at
    ``origin`` (u, v), at ``uv`` (N, 2), and the interpolant's gradient (N, 2) in d/du,
    d/dv. Beyond the image the distance to it is added and its direction becomes the
    gradient along the clamped axes (see ``DistanceMap.query``)."""
    n = uv.shape[0]
    h, w = values.shape
    value = np.empty(n)
    grad = np.empty((n, 2))
    upper_u, upper_v = w - 1 - 1e-9, h - 1 - 1e-9
    for p in range(n):
        lu, lv = uv[p, 0] - origin[0], uv[p, 1] - origin[1]
        u, v = min(max(lu, 0.0), upper_u), min(max(lv, 0.0), upper_v)
        iu, iv = int(u), int(v)  # floor: both are >= 0
        fu, fv = u - iu, v - iv
        v00, v10 = float(values[iv, iu]), float(values[iv, iu + 1])
        v01, v11 = float(values[iv + 1, iu]), float(values[iv + 1, iu + 1])
        top = v00 * (1 - fu) + v10 * fu
        bottom = v01 * (1 - fu) + v11 * fu
        value[p] = top * (1 - fv) + bottom * fv
        grad[p, 0] = (v10 - v00) * (1 - fv) + (v11 - v01) * fv
        grad[p, 1] = bottom - top
        out_u, out_v = lu - u, lv - v
        if out_u != 0.0 or out_v != 0.0:
            dist_out = np.sqrt(out_u * out_u + out_v * out_v)
            value[p] += dist_out
            if out_u != 0.0:
                grad[p, 0] = out_u / dist_out
            if out_v != 0.0:
                grad[p, 1] = out_v / dist_out
    return value, grad


@numba.njit(cache=True, nogil=True)
def contour_generators(front: np.ndarray, adjacent_faces: np.ndarray, adjacent_edges: np.ndarray
                       ) -> np.ndarray:
    """The shared edges (E, 2) of ``adjacent_edges`` (A, 2) whose two faces
    (``adjacent_faces``, A, 2) are one front-facing (``front``, F) and one not, in their
    order, each run as its front face runs it (reversed where that is the second face)."""
    out = np.empty(adjacent_edges.shape, adjacent_edges.dtype)
    kept = 0
    for e in range(adjacent_edges.shape[0]):
        first = front[adjacent_faces[e, 0]]
        if first == front[adjacent_faces[e, 1]]:
            continue
        a, b = (0, 1) if first else (1, 0)
        out[kept, 0], out[kept, 1] = adjacent_edges[e, a], adjacent_edges[e, b]
        kept += 1
    return out[:kept]


@numba.njit(cache=True, nogil=True, inline="always")
def _twist_row(g0: float, g1: float, g2: float, p0: float, p1: float, p2: float, out: np.ndarray) -> None:
    """``out`` (6,) = ``[g, p x g]``: the Jacobian row of a right pose increment for the
    gradient ``g`` (with respect to the posed point, rotated back) at the source point ``p``."""
    out[0], out[1], out[2] = g0, g1, g2
    out[3] = p1 * g2 - p2 * g1
    out[4] = p2 * g0 - p0 * g2
    out[5] = p0 * g1 - p1 * g0


@numba.njit(cache=True, nogil=True)
def pose_rows(G_cam: np.ndarray, X: np.ndarray, R_view: np.ndarray, R_body: np.ndarray, t_body: np.ndarray,
              with_body: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians (N, m, 6) with respect to the view's pose and, ``with_body``, the body's
    pose (``R_body``, ``t_body``: body to tibia; else an empty (0, m, 6)) of quantities whose
    gradients with respect to the camera-frame point are ``G_cam`` (N, m, 3), at body-frame
    points ``X`` (N, 3), and their gradients (N, m, 3) with respect to ``X`` (see
    ``terms.pose_increments``). One pass instead of the rotations, moments and reshapes of
    every term's linearisation."""
    n, m = G_cam.shape[0], G_cam.shape[1]
    J_view = np.empty((n, m, 6))
    J_body = np.empty((n if with_body else 0, m, 6))
    G_x = np.empty((n, m, 3))
    for i in range(n):
        x0, x1, x2 = X[i, 0], X[i, 1], X[i, 2]
        p0, p1, p2 = x0, x1, x2
        if with_body:
            p0 = R_body[0, 0] * x0 + R_body[0, 1] * x1 + R_body[0, 2] * x2 + t_body[0]
            p1 = R_body[1, 0] * x0 + R_body[1, 1] * x1 + R_body[1, 2] * x2 + t_body[1]
            p2 = R_body[2, 0] * x0 + R_body[2, 1] * x1 + R_body[2, 2] * x2 + t_body[2]
        for k in range(m):
            c0, c1, c2 = G_cam[i, k, 0], G_cam[i, k, 1], G_cam[i, k, 2]
            g0 = c0 * R_view[0, 0] + c1 * R_view[1, 0] + c2 * R_view[2, 0]
            g1 = c0 * R_view[0, 1] + c1 * R_view[1, 1] + c2 * R_view[2, 1]
            g2 = c0 * R_view[0, 2] + c1 * R_view[1, 2] + c2 * R_view[2, 2]
            _twist_row(g0, g1, g2, p0, p1, p2, J_view[i, k])
            if with_body:
                b0 = g0 * R_body[0, 0] + g1 * R_body[1, 0] + g2 * R_body[2, 0]
                b1 = g0 * R_body[0, 1] + g1 * R_body[1, 1] + g2 * R_body[2, 1]
                b2 = g0 * R_body[0, 2] + g1 * R_body[1, 2] + g2 * R_body[2, 2]
                _twist_row(b0, b1, b2, x0, x1, x2, J_body[i, k])
                g0, g1, g2 = b0, b1, b2
            G_x[i, k, 0], G_x[i, k, 1], G_x[i, k, 2] = g0, g1, g2
    return J_view, J_body, G_x


@numba.njit(cache=True, nogil=True)
def silhouette_rows(p_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, min_depth: float,
                    values: np.ndarray, origin: np.ndarray, charged: np.ndarray, nearest: np.ndarray,
                    observed: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
    """A silhouette term's residuals (C + M, 1): the distance-map value (``values``,
    ``origin`` as in :func:`bilinear`) at each ``charged`` outline point, then each observed
    pixel's (M, 2) distance to its ``nearest`` outline point, for camera-frame outline points
    ``p_cam`` (N, 3) projected by :func:`pinhole`; with ``jacobian`` also each residual's
    gradient (C + M, 3) with respect to its camera-frame point (else an empty (0, 3)). The
    arithmetic of the numpy path, to the last bit, in one pass."""
    n_c, n_o = charged.shape[0], nearest.shape[0]
    uv, J_proj = pinhole(p_cam, fx, fy, cx, cy, min_depth, jacobian)
    uv_charged = np.empty((n_c, 2))
    for c in range(n_c):
        uv_charged[c, 0], uv_charged[c, 1] = uv[charged[c], 0], uv[charged[c], 1]
    dist, grad = bilinear(values, origin, uv_charged)
    r = np.empty((n_c + n_o, 1))
    J_cam = np.empty((n_c + n_o if jacobian else 0, 3))
    for c in range(n_c):
        r[c, 0] = dist[c]
        if jacobian:
            q = charged[c]
            for j in range(3):
                J_cam[c, j] = grad[c, 0] * J_proj[q, 0, j] + grad[c, 1] * J_proj[q, 1, j]
    for o in range(n_o):
        q = nearest[o]
        du, dv = uv[q, 0] - observed[o, 0], uv[q, 1] - observed[o, 1]
        d = np.sqrt(du * du + dv * dv)
        r[n_c + o, 0] = d
        if jacobian:
            m = max(d, 1e-9)
            eu, ev = du / m, dv / m
            for j in range(3):
                J_cam[n_c + o, j] = eu * J_proj[q, 0, j] + ev * J_proj[q, 1, j]
    return r, J_cam


@numba.njit(cache=True, nogil=True)
def point_blocks(Jx: np.ndarray, w: np.ndarray, residuals: np.ndarray, x_idx: np.ndarray,
                 H_xx: np.ndarray, g_x: np.ndarray) -> np.ndarray:
    """One term's share of the points' normal equations, added in place: per residual row
    ``n`` of point ``x_idx[n]``, ``w Jx^T Jx`` to ``H_xx`` (X, 3, 3) and ``w Jx^T r`` to
    ``g_x`` (X, 3), for its point Jacobian ``Jx`` (N, m, 3), weight ``w`` (N,) and
    residuals (N, m). Returns the weighted Jacobians ``w Jx`` (N, m, 3)."""
    n_rows, m = Jx.shape[0], Jx.shape[1]
    Jx_w = np.empty_like(Jx)
    for n in range(n_rows):
        x = x_idx[n]
        for k in range(m):
            for i in range(3):
                Jx_w[n, k, i] = w[n] * Jx[n, k, i]
        for i in range(3):
            for j in range(3):
                acc = 0.0
                for k in range(m):
                    acc += Jx_w[n, k, i] * Jx[n, k, j]
                H_xx[x, i, j] += acc
            acc = 0.0
            for k in range(m):
                acc += Jx[n, k, i] * (w[n] * residuals[n, k])
            g_x[x, i] += acc
    return Jx_w


@numba.njit(cache=True, nogil=True)
def coupling_blocks(Ja: np.ndarray, Jx_w: np.ndarray) -> np.ndarray:
    """Per residual row, ``Ja^T Jx_w`` (N, 6, 3) of a pose Jacobian ``Ja`` (N, m, 6) and the
    weighted point Jacobian ``Jx_w`` (N, m, 3)."""
    n_rows, m = Ja.shape[0], Ja.shape[1]
    out = np.empty((n_rows, 6, 3))
    for n in range(n_rows):
        for i in range(6):
            for j in range(3):
                acc = 0.0
                for k in range(m):
                    acc += Ja[n, k, i] * Jx_w[n, k, j]
                out[n, i, j] = acc
    return out


@numba.njit(cache=True, nogil=True)
def scatter_add(keys: np.ndarray, values: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``values`` (K, D) summed by their ``keys`` (K,) in 0..``n_keys`` - 1, in the
    order given: the sums (n_keys, D) and which keys occurred (n_keys,)."""
    sums = np.zeros((n_keys, values.shape[1]))
    seen = np.zeros(n_keys, np.bool_)
    for r in range(keys.shape[0]):
        key = keys[r]
        seen[key] = True
        for d in range(values.shape[1]):
            sums[key, d] += values[r, d]
    return sums, seen


@numba.njit(cache=True, nogil=True)
def squared_norms(residuals: np.ndarray) -> np.ndarray:
    """(N,) squared norm of each residual block (row) of ``residuals`` (N, m)."""
    out = np.empty(residuals.shape[0])
    for n in range(residuals.shape[0]):
        acc = 0.0
        for k in range(residuals.shape[1]):
            acc += residuals[n, k] * residuals[n, k]
        out[n] = acc
    return out


@numba.njit(cache=True, nogil=True)
def robust_cost(s: np.ndarray, kind: int, scale: float) -> float:
    """The sum over the squared norms ``s`` (N,) of the robust loss ``rho(s)``: ``kind`` 0
    is least squares (``s``), 1 Huber's (``s`` up to ``scale``, then ``2 scale sqrt(s) -
    scale^2``), 2 Cauchy's (``scale^2 log(1 + s / scale^2)``). Several hundred terms'
    costs per solve, each a few passes over a few hundred rows in numpy."""
    c2 = scale * scale
    total = 0.0
    for n in range(s.shape[0]):
        if kind == 0:
            total += s[n]
        elif kind == 1:
            r = np.sqrt(s[n])
            total += s[n] if r <= scale else 2.0 * scale * r - c2
        else:
            total += c2 * np.log1p(s[n] / c2)
    return total


@numba.njit(cache=True, nogil=True, inline="always")
def _grid_axis(coordinate: float, origin: float, spacing: float, size: int) -> tuple[int, float, float]:
    """Along one axis of a grid of ``size`` samples: the cell of ``coordinate`` (clamped to
    the grid), the fraction across it, and how far (mm) the coordinate lies beyond the grid."""
    g = (coordinate - origin) / spacing
    clamped = min(max(g, 0.0), size - 1 - 1e-9)
    cell = int(np.floor(clamped))
    return cell, clamped - cell, (g - clamped) * spacing


@numba.njit(cache=True, nogil=True, inline="always")
def _trilinear_at(values: np.ndarray, origin: np.ndarray, spacing: float, p0: float, p1: float,
                  p2: float, grad: np.ndarray) -> float:
    """The trilinear interpolant of ``values`` (see :func:`trilinear`) at the point (p0, p1,
    p2); when ``grad`` has three elements (not none) its exact gradient is written there."""
    x, fx, out_x = _grid_axis(p0, origin[0], spacing, values.shape[0])
    y, fy, out_y = _grid_axis(p1, origin[1], spacing, values.shape[1])
    z, fz, out_z = _grid_axis(p2, origin[2], spacing, values.shape[2])
    dist_out = np.sqrt(out_x * out_x + out_y * out_y + out_z * out_z)
    c000, c001 = float(values[x, y, z]), float(values[x, y, z + 1])
    c010, c011 = float(values[x, y + 1, z]), float(values[x, y + 1, z + 1])
    c100, c101 = float(values[x + 1, y, z]), float(values[x + 1, y, z + 1])
    c110, c111 = float(values[x + 1, y + 1, z]), float(values[x + 1, y + 1, z + 1])
    dz00, dz01, dz10, dz11 = c001 - c000, c011 - c010, c101 - c100, c111 - c110
    cz00, cz01 = c000 + dz00 * fz, c010 + dz01 * fz
    cz10, cz11 = c100 + dz10 * fz, c110 + dz11 * fz
    dy0, dy1 = cz01 - cz00, cz11 - cz10
    cy0, cy1 = cz00 + dy0 * fy, cz10 + dy1 * fy
    dx = cy1 - cy0
    if grad.shape[0] == 3:
        slope_z0 = dz00 + (dz01 - dz00) * fy
        slope_z1 = dz10 + (dz11 - dz10) * fy
        grad[0] = dx / spacing
        grad[1] = (dy0 * (1 - fx) + dy1 * fx) / spacing
        grad[2] = (slope_z0 * (1 - fx) + slope_z1 * fx) / spacing
        if out_x != 0.0:
            grad[0] = out_x / dist_out
        if out_y != 0.0:
            grad[1] = out_y / dist_out
        if out_z != 0.0:
            grad[2] = out_z / dist_out
    return cy0 + dx * fx + dist_out


@numba.njit(cache=True, nogil=True)
def trilinear(values: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray,
              gradient: bool) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear interpolation of the grid ``values`` (nx, ny, nz) at ``origin + spacing *
    (i, j, k)`` at ``points`` (N, 3), and the interpolant's exact gradient (N, 3) when
    ``gradient`` (else an empty (0, 3)). Beyond the grid the distance to it is added and
    its direction becomes the gradient along the clamped axes (see
    ``SignedDistanceField.query``)."""
    n = points.shape[0]
    value = np.empty(n)
    grad = np.empty((n if gradient else 0, 3))
    none = np.empty(0)
    for p in range(n):
        value[p] = _trilinear_at(values, origin, spacing, points[p, 0], points[p, 1], points[p, 2],
                                 grad[p] if gradient else none)
    return value, grad


@numba.njit(cache=True, nogil=True)
def surface_rows(values: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray,
                 ids: np.ndarray, seated: np.ndarray, directions: np.ndarray, jacobian: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A back-projection term's residuals (N, 2) for the points ``points[ids]``: the field's
    value there (see :func:`trilinear`) and the distance moved along ``directions`` (N, 3)
    from ``seated`` (N, 3); with ``jacobian`` their gradients (N, 2, 3) with respect to the
    point (the field's gradient, the direction), else an empty (0, 2, 3). One pass instead
    of a gather, a lookup and three stacks per evaluation."""
    n = ids.shape[0]
    r = np.empty((n, 2))
    J = np.empty((n if jacobian else 0, 2, 3))
    none = np.empty(0)
    for i in range(n):
        x = points[ids[i]]
        r[i, 0] = _trilinear_at(values, origin, spacing, x[0], x[1], x[2], J[i, 0] if jacobian else none)
        along = 0.0
        for k in range(3):
            along += (x[k] - seated[i, k]) * directions[i, k]
            if jacobian:
                J[i, 1, k] = directions[i, k]
        r[i, 1] = along
    return r, J


@numba.njit(cache=True, nogil=True, inline="always")
def _sdf_on_ray(values: np.ndarray, origin: np.ndarray, spacing: float, R: np.ndarray, t: np.ndarray,
                ray: np.ndarray, depth: float, none: np.ndarray) -> float:
    """The field's value at the body-frame point ``R (depth ray) + t``."""
    q0, q1, q2 = ray[0] * depth, ray[1] * depth, ray[2] * depth
    return _trilinear_at(values, origin, spacing,
                         R[0, 0] * q0 + R[0, 1] * q1 + R[0, 2] * q2 + t[0],
                         R[1, 0] * q0 + R[1, 1] * q1 + R[1, 2] * q2 + t[1],
                         R[2, 0] * q0 + R[2, 1] * q1 + R[2, 2] * q2 + t[2], none)


@numba.njit(cache=True, nogil=True, inline="always")
def _depths_in_box(box: np.ndarray, R: np.ndarray, t: np.ndarray, ray: np.ndarray) -> tuple[float, float]:
    """Depth interval in which the camera ray ``depth * ray`` (unit depth, carried into the
    box's frame by ``R``, ``t``) crosses the box (2, 3) (slab test). A ray that misses it
    gets the empty interval at its closest approach to the box's centre."""
    near, far, square, towards = -np.inf, np.inf, 0.0, 0.0
    for k in range(3):
        direction = R[k, 0] * ray[0] + R[k, 1] * ray[1] + R[k, 2] * ray[2]
        square += direction * direction
        towards += direction * (0.5 * (box[0, k] + box[1, k]) - t[k])
        if direction == 0.0:  # parallel: the slab holds the whole ray or none of it
            if not box[0, k] <= t[k] <= box[1, k]:
                near, far = np.inf, -np.inf
            continue
        enter, leave = (box[0, k] - t[k]) / direction, (box[1, k] - t[k]) / direction
        near, far = max(near, min(enter, leave)), min(far, max(enter, leave))
    if not far >= near:
        near = far = towards / square
    return near, far


@numba.njit(cache=True, nogil=True)
def ray_minima(values: np.ndarray, origin: np.ndarray, spacing: float, R: np.ndarray, t: np.ndarray,
               rays: np.ndarray, min_depth: float, step: float, coarse: int) -> np.ndarray:
    """Depth (N,) along each camera ray ``depth * rays[n]`` (unit depth, carried into the
    field's frame by ``R``, ``t``) where the field (see :func:`trilinear`) is least: sampled
    where the ray crosses the field's box (:func:`_depths_in_box`, floored at ``min_depth``)
    every ``coarse * step`` from its near end up to its far end (itself the last sample),
    then every ``step`` within ``coarse`` steps either side of the least sample, then moved
    by at most one step to the vertex of the parabola through the least fine sample (kept
    off the ends) and its neighbours, when that parabola opens upwards. The first least
    sample wins ties. One pass per ray: some 25 lookups, no temporaries."""
    box = np.empty((2, 3))
    for k in range(3):
        box[0, k], box[1, k] = origin[k], origin[k] + spacing * (values.shape[k] - 1)
    none = np.empty(0)
    fine = np.empty(2 * coarse + 1)
    found = np.empty(rays.shape[0])
    for r in range(rays.shape[0]):
        near, far = _depths_in_box(box, R, t, rays[r])
        near, far = max(near, min_depth), max(far, min_depth)
        best_z, best_d = near, np.inf
        k = 0
        while True:
            z = min(near + coarse * step * k, far)
            d = _sdf_on_ray(values, origin, spacing, R, t, rays[r], z, none)
            if d < best_d:
                best_z, best_d = z, d
            if not z < far:  # at the far end (or NaN depths: one sample)
                break
            k += 1
        best = 0
        for j in range(2 * coarse + 1):
            fine[j] = _sdf_on_ray(values, origin, spacing, R, t, rays[r], best_z + (j - coarse) * step, none)
            if fine[j] < fine[best]:
                best = j
        best = min(max(best, 1), 2 * coarse - 1)
        d_minus, d_0, d_plus = fine[best - 1], fine[best], fine[best + 1]
        curvature = d_plus - 2.0 * d_0 + d_minus
        shift = 0.5 * (d_minus - d_plus) / max(curvature, 1e-9) if curvature > 1e-9 else 0.0
        found[r] = best_z + (best - coarse) * step + min(max(shift, -1.0), 1.0) * step
    return found


@numba.njit(cache=True, nogil=True)
def footprint_mask(a: np.ndarray, b: np.ndarray, height: int, width: int) -> np.ndarray:
    """Binary mask (height, width) of the region an outline encloses, and of the pixels it
    passes through: ``a``, ``b`` (E, 2) are its directed edges' ends in mask pixels (see
    ``ContourGenerator.footprint``). The winding number is accumulated along each row of
    the outline's bounding box from the signed crossings of the edges with the rows'
    centres; then every edge is walked in unit steps."""
    mask = np.zeros((height, width), np.uint8)
    n = a.shape[0]
    if n == 0:
        return mask
    lo_u, lo_v, hi_u, hi_v = np.inf, np.inf, -np.inf, -np.inf
    for e in range(n):
        lo_u = min(lo_u, a[e, 0], b[e, 0])
        hi_u = max(hi_u, a[e, 0], b[e, 0])
        lo_v = min(lo_v, a[e, 1], b[e, 1])
        hi_v = max(hi_v, a[e, 1], b[e, 1])
    left = int(min(max(np.ceil(lo_u), 0), width))
    right = int(min(max(np.ceil(hi_u), 0), width))
    upper = int(min(max(np.ceil(lo_v), 0), height))
    lower = int(min(max(np.ceil(hi_v), 0), height))
    box_w = right - left
    crossings = np.zeros((max(lower - upper, 0), box_w + 1), np.int64)
    for e in range(n):
        downwards = b[e, 1] > a[e, 1]
        if downwards:
            tu, tv, bu, bv, sign = a[e, 0], a[e, 1], b[e, 0], b[e, 1], 1
        else:
            tu, tv, bu, bv, sign = b[e, 0], b[e, 1], a[e, 0], a[e, 1], -1
        first = int(min(max(np.ceil(tv), 0), height))
        last = int(min(max(np.ceil(bv), 0), height))
        for row in range(first, last):
            x = tu + (row - tv) / (bv - tv) * (bu - tu)
            column = int(min(max(np.ceil(x), left), right)) - left
            crossings[row - upper, column] += sign
    for r in range(lower - upper):
        winding = 0
        for c in range(box_w):
            winding += crossings[r, c]
            if winding != 0:
                mask[upper + r, left + c] = 1
    for e in range(n):
        du, dv = b[e, 0] - a[e, 0], b[e, 1] - a[e, 1]
        steps = int(np.ceil(max(abs(du), abs(dv)))) + 1
        for place in range(steps):
            s = place / max(steps - 1, 1)
            u = int(np.rint(a[e, 0] + s * du))
            v = int(np.rint(a[e, 1] + s * dv))
            if 0 <= u < width and 0 <= v < height:
                mask[v, u] = 1
    return mask


@numba.njit(cache=True, nogil=True)
def nearest_points(points: np.ndarray, queries: np.ndarray, cell: float) -> np.ndarray:
    """Index (M,) of the nearest of ``points`` (N >= 1, 2) to each of ``queries`` (M, 2),
    exactly: the points are binned on a grid of ``cell``-sized squares, and each query
    visits the rings of cells around its own until no closer point can lie further out
    (a point in ring r + 1 is at least r cells away)."""
    n = points.shape[0]
    lo_u, lo_v = points[0, 0], points[0, 1]
    hi_u, hi_v = lo_u, lo_v
    for k in range(n):
        lo_u, hi_u = min(lo_u, points[k, 0]), max(hi_u, points[k, 0])
        lo_v, hi_v = min(lo_v, points[k, 1]), max(hi_v, points[k, 1])
    cols = int((hi_u - lo_u) / cell) + 1
    rows = int((hi_v - lo_v) / cell) + 1
    bin_of = np.empty(n, np.int64)
    start = np.zeros(cols * rows + 1, np.int64)
    for k in range(n):
        bin_of[k] = int((points[k, 1] - lo_v) / cell) * cols + int((points[k, 0] - lo_u) / cell)
        start[bin_of[k] + 1] += 1
    for b in range(cols * rows):
        start[b + 1] += start[b]
    order = np.empty(n, np.int64)
    filled = start[:-1].copy()
    for k in range(n):
        order[filled[bin_of[k]]] = k
        filled[bin_of[k]] += 1
    found = np.empty(queries.shape[0], np.int64)
    for q in range(queries.shape[0]):
        u, v = queries[q, 0], queries[q, 1]
        cu = int(np.floor((u - lo_u) / cell))
        cv = int(np.floor((v - lo_v) / cell))
        # Rings beyond this reach lie wholly outside the grid.
        reach = max(cu, cols - 1 - cu, cv, rows - 1 - cv, 0)
        best, best_d2 = -1, np.inf
        for r in range(reach + 1):
            for gv in range(max(cv - r, 0), min(cv + r, rows - 1) + 1):
                on_edge = gv == cv - r or gv == cv + r
                step = 1 if on_edge else 2 * r
                gu = cu - r
                while gu <= cu + r:
                    if 0 <= gu < cols:
                        b = gv * cols + gu
                        for j in range(start[b], start[b + 1]):
                            k = order[j]
                            d2 = (points[k, 0] - u) ** 2 + (points[k, 1] - v) ** 2
                            if d2 < best_d2 or (d2 == best_d2 and k < best):
                                best, best_d2 = k, d2
                    gu += step
            if best >= 0 and best_d2 <= (r * cell) ** 2:
                break
        found[q] = best
    return found


def warm_up() -> None:
    """Compile (or load from the cache) every kernel now, on a tiny problem: the first
    compilation takes about two seconds, which no case in the operating room should wait."""
    schur_complement(np.eye(3)[None], np.zeros((1, 3)), np.zeros((1, 1, 6, 3)),
                     np.zeros((1, 1), np.int64), 1, 0.0, 1e-6)
    point_steps(np.zeros((1, 1, 6, 3)), np.zeros((1, 1), np.int64), np.zeros(6), np.zeros((1, 3, 3)),
                np.zeros((1, 3)))
    footprint_mask(np.zeros((1, 2)), np.ones((1, 2)), 2, 2)
    contour_generators(np.ones(2, np.bool_), np.array([[0, 1]]), np.array([[0, 1]]))
    for with_body in (False, True):
        pose_rows(np.zeros((1, 1, 3)), np.zeros((1, 3)), np.eye(3), np.eye(3), np.zeros(3), with_body)
    nearest_points(np.zeros((1, 2)), np.zeros((1, 2)), 1.0)
    bilinear(np.zeros((2, 2), np.float32), np.zeros(2), np.zeros((1, 2)))
    in_field(np.zeros((1, 2)), 2, 2, 0.0, np.inf)
    scatter_add(np.zeros(1, np.int64), np.zeros((1, 1)), 1)
    robust_cost(squared_norms(np.zeros((1, 2))), 1, 1.0)
    Jx_w = point_blocks(np.zeros((1, 2, 3)), np.ones(1), np.zeros((1, 2)), np.zeros(1, np.int64),
                        np.zeros((1, 3, 3)), np.zeros((1, 3)))
    coupling_blocks(np.zeros((1, 2, 6)), Jx_w)
    for mask in (np.zeros((0, 0), np.uint8), np.zeros((1, 1), np.uint8)):
        outline_samples(np.zeros((1, 2)), np.ones((1, 2)), 1.0, 2, 2, 0.0, np.inf, mask, 4)
    for jacobian in (False, True):
        pinhole(np.ones((1, 3)), 1.0, 1.0, 0.0, 0.0, 1.0, jacobian)
        silhouette_rows(np.ones((1, 3)), 1.0, 1.0, 0.0, 0.0, 1.0,
                        np.zeros((2, 2), np.float32), np.zeros(2), np.zeros(1, np.int64),
                        np.zeros(1, np.int64), np.zeros((1, 2)), jacobian)
    for gradient in (False, True):
        surface_rows(np.zeros((2, 2, 2), np.float32), np.zeros(3), 1.0, np.zeros((1, 3)),
                     np.zeros(1, np.int64), np.zeros((1, 3)), np.ones((1, 3)), gradient)
        trilinear(np.zeros((2, 2, 2), np.float32), np.zeros(3), 1.0, np.zeros((1, 3)), gradient)
    ray_minima(np.zeros((2, 2, 2), np.float32), np.zeros(3), 1.0, np.eye(3), np.zeros(3),
               np.ones((1, 3)), 10.0, 1.0, 4)
