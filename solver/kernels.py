"""Compiled (C) kernels for per-point loops that numpy expresses only as many small batched
products or passes over temporaries.

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
silhouette term's residual rows and their gradients (projection, lookups and nearest-pair
distances: some fifteen array passes per evaluation, several hundred evaluations per
solve), and the points' blocks of the normal equations and their sums by key. So are the
seating of edge points on their rays (some 25 field lookups per ray, each a dozen array
passes over every ray's samples in numpy), every term's robust cost, the Jacobian rows of
the poses and the back-projection term's rows (a few hundred of each per solve, where
numpy's per-call overhead was most of their cost), and each trial step's
back-substitution of the points' increments.

The loops are C (``solver/_kernels.c``), built with the package: nothing is compiled or
loaded at run time, so a process's first solve costs what its later ones do, whoever owns
the install. This module is their Python face: it converts the arguments to the element
types and layout the C expects (a no-op for the solver's own arrays) and allocates the
outputs; the C checks shapes and indices, so bad input raises, never crashes. Kernels are
called thousands of times per solve, so these wrappers stay thin.
"""

from __future__ import annotations

import numpy as np

from slamtka.solver import _kernels as _c

__all__ = ["bilinear", "contour_generators", "coupling_blocks", "footprint_mask", "in_field", "nearest_points",
           "outline_samples", "pinhole", "point_blocks", "point_steps", "pose_rows", "ray_minima",
           "robust_cost", "scatter_add", "schur_complement", "silhouette_rows", "squared_norms", "surface_rows",
           "trilinear"]

_GRID_TYPES = (np.dtype(np.float32), np.dtype(np.float64))


def _floats(a: np.ndarray) -> np.ndarray:
    """``a`` as a C-contiguous float64 array (itself when it is one)."""
    return np.ascontiguousarray(a, np.float64)


def _indices(a: np.ndarray, name: str) -> np.ndarray:
    """Integer (or empty) ``a`` as a C-contiguous int64 array; anything else is refused,
    not rounded."""
    a = np.asarray(a)
    if a.dtype.kind not in "iu" and a.size:
        raise TypeError(f"{name}: indices must be integers, not {a.dtype}")
    return np.ascontiguousarray(a, np.int64)


def _grid(values: np.ndarray) -> np.ndarray:
    """Samples ``values`` as C-contiguous float32 or float64 (kept as given: a field is
    large, and its lookups read it in either); other types as float64."""
    values = np.asarray(values)
    return np.ascontiguousarray(values, values.dtype if values.dtype in _GRID_TYPES else np.float64)


def _mask(a: np.ndarray) -> np.ndarray:
    """A mask as C-contiguous uint8 or bool (nonzero: set)."""
    a = np.asarray(a)
    return np.ascontiguousarray(a if a.dtype in (np.uint8, np.bool_) else a != 0)


def schur_complement(H_xx: np.ndarray, g_x: np.ndarray, W: np.ndarray, pose_of: np.ndarray,
                     n_poses: int, lam: float, regularisation: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point ``x``: its block damped (``lam`` times its diagonal, plus
    ``regularisation`` times its trace) and inverted, ``V_inv`` (X, 3, 3); the sums over
    points of ``W_a V_inv W_b^T`` into the pose-pair blocks (P, P, 6, 6) and of
    ``W_a V_inv g_x`` into each pose (P, 6). ``W`` (X, k, 6, 3) holds each point's
    couplings, ``pose_of`` (X, k) their poses (``n_poses`` marks an empty slot)."""
    H_xx = _floats(H_xx)
    blocks, shift = np.zeros((n_poses, n_poses, 6, 6)), np.zeros((n_poses, 6))
    V_inv = np.empty((len(H_xx), 3, 3))
    _c.schur_complement(H_xx, _floats(g_x), _floats(W), _indices(pose_of, "pose_of"), lam, regularisation,
                        blocks, shift, V_inv)
    return blocks, shift, V_inv


def point_steps(W: np.ndarray, pose_of: np.ndarray, d_p: np.ndarray, V_inv: np.ndarray,
                g_x: np.ndarray) -> np.ndarray:
    """The points' increments (X, 3) back-substituted from the poses' ``d_p`` (6P,):
    ``-V_inv (g_x + sum over the point's couplings of W_a^T d_p[pose_a])``, with ``W``,
    ``pose_of`` and ``V_inv`` as in :func:`schur_complement`. One pass instead of two
    batched products and a gather per trial step."""
    d_x = np.empty((len(pose_of), 3))
    _c.point_steps(_floats(W), _indices(pose_of, "pose_of"), _floats(d_p), _floats(V_inv), _floats(g_x), d_x)
    return d_x


def in_field(uv: np.ndarray, width: int, height: int, margin: float, radius: float) -> np.ndarray:
    """Mask (N,) of the pixels ``uv`` (N, 2) inside the image and its circular field of view
    of ``radius`` (inf: none), ``margin`` pixels in from their edges."""
    inside = np.empty(len(uv), np.bool_)
    _c.in_field(_floats(uv), width, height, margin, radius, inside)
    return inside


def outline_samples(uv_a: np.ndarray, uv_delta: np.ndarray, spacing: float, width: int, height: int,
                    margin: float, radius: float, interior: np.ndarray, downscale: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Samples along projected edges from ``uv_a`` (E, 2) by ``uv_delta`` (E, 2), at the
    centres of ``ceil(length / spacing)`` (at least one) equal sub-segments, kept when in
    the field of view (:func:`in_field`) and, when ``interior`` (h, w) is not empty, on a
    zero pixel of that mask at 1/``downscale`` resolution. Each kept sample's edge and
    fraction along it, in edge order."""
    uv_delta = _floats(uv_delta)
    total = _c.outline_total(uv_delta, spacing)
    edge, frac = np.empty(total, np.int64), np.empty(total)
    kept = _c.outline_samples(_floats(uv_a), uv_delta, spacing, width, height, margin, radius, _mask(interior),
                              downscale, edge, frac)
    return edge[:kept], frac[:kept]


def pinhole(p_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, min_depth: float,
            jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of camera-frame points (N, 3), their depth floored at ``min_depth``,
    and when ``jacobian`` the projection's Jacobian (N, 2, 3) (else an empty (0, 2, 3))."""
    n = len(p_cam)
    uv, J = np.empty((n, 2)), np.empty((n if jacobian else 0, 2, 3))
    _c.pinhole(_floats(p_cam), fx, fy, cx, cy, min_depth, uv, J)
    return uv, J


def bilinear(values: np.ndarray, origin: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear interpolation of the image ``values`` (h, w), whose pixel (0, 0) lies at
    ``origin`` (u, v), at ``uv`` (N, 2), and the interpolant's gradient (N, 2) in d/du,
    d/dv. Beyond the image the distance to it is added and its direction becomes the
    gradient along the clamped axes (see ``DistanceMap.query``)."""
    n = len(uv)
    value, grad = np.empty(n), np.empty((n, 2))
    _c.bilinear(_grid(values), _floats(origin), _floats(uv), value, grad)
    return value, grad


def contour_generators(front: np.ndarray, adjacent_faces: np.ndarray, adjacent_edges: np.ndarray
                       ) -> np.ndarray:
    """The shared edges (E, 2) of ``adjacent_edges`` (A, 2) whose two faces
    (``adjacent_faces``, A, 2) are one front-facing (``front``, F) and one not, in their
    order, each run as its front face runs it (reversed where that is the second face)."""
    out = np.empty((len(adjacent_edges), 2), np.int64)
    kept = _c.contour_generators(_mask(front), _indices(adjacent_faces, "adjacent_faces"),
                                 _indices(adjacent_edges, "adjacent_edges"), out)
    return out[:kept]


def pose_rows(G_cam: np.ndarray, X: np.ndarray, R_view: np.ndarray, R_body: np.ndarray, t_body: np.ndarray,
              with_body: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jacobians (N, m, 6) with respect to the view's pose and, ``with_body``, the body's
    pose (``R_body``, ``t_body``: body to tibia; else an empty (0, m, 6)) of quantities whose
    gradients with respect to the camera-frame point are ``G_cam`` (N, m, 3), at body-frame
    points ``X`` (N, 3), and their gradients (N, m, 3) with respect to ``X`` (see
    ``terms.pose_increments``). One pass instead of the rotations, moments and reshapes of
    every term's linearisation."""
    G_cam = _floats(G_cam)
    n, m = G_cam.shape[:2]
    J_view, J_body = np.empty((n, m, 6)), np.empty((n if with_body else 0, m, 6))
    G_x = np.empty((n, m, 3))
    _c.pose_rows(G_cam, _floats(X), _floats(R_view), _floats(R_body), _floats(t_body), J_view, J_body, G_x)
    return J_view, J_body, G_x


def silhouette_rows(p_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float, min_depth: float,
                    values: np.ndarray, origin: np.ndarray, charged: np.ndarray, nearest: np.ndarray,
                    observed: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray]:
    """A silhouette term's residuals (C + M, 1): the distance-map value (``values``,
    ``origin`` as in :func:`bilinear`) at each ``charged`` outline point, then each observed
    pixel's (M, 2) distance to its ``nearest`` outline point, for camera-frame outline points
    ``p_cam`` (N, 3) projected by :func:`pinhole`; with ``jacobian`` also each residual's
    gradient (C + M, 3) with respect to its camera-frame point (else an empty (0, 3)). The
    arithmetic of the numpy path, to the last bit, in one pass."""
    rows = len(charged) + len(nearest)
    r, J_cam = np.empty((rows, 1)), np.empty((rows if jacobian else 0, 3))
    _c.silhouette_rows(_floats(p_cam), fx, fy, cx, cy, min_depth, _grid(values), _floats(origin),
                       _indices(charged, "charged"), _indices(nearest, "nearest"), _floats(observed), r, J_cam)
    return r, J_cam


def point_blocks(Jx: np.ndarray, w: np.ndarray, residuals: np.ndarray, x_idx: np.ndarray,
                 H_xx: np.ndarray, g_x: np.ndarray) -> np.ndarray:
    """One term's share of the points' normal equations, added in place: per residual row
    ``n`` of point ``x_idx[n]``, ``w Jx^T Jx`` to ``H_xx`` (X, 3, 3) and ``w Jx^T r`` to
    ``g_x`` (X, 3) (both C-contiguous float64, or a TypeError: a copy would lose the sums),
    for its point Jacobian ``Jx`` (N, m, 3), weight ``w`` (N,) and residuals (N, m).
    Returns the weighted Jacobians ``w Jx`` (N, m, 3)."""
    Jx = _floats(Jx)
    Jx_w = np.empty_like(Jx)
    _c.point_blocks(Jx, _floats(w), _floats(residuals), _indices(x_idx, "x_idx"), H_xx, g_x, Jx_w)
    return Jx_w


def coupling_blocks(Ja: np.ndarray, Jx_w: np.ndarray) -> np.ndarray:
    """Per residual row, ``Ja^T Jx_w`` (N, 6, 3) of a pose Jacobian ``Ja`` (N, m, 6) and the
    weighted point Jacobian ``Jx_w`` (N, m, 3)."""
    out = np.empty((len(Ja), 6, 3))
    _c.coupling_blocks(_floats(Ja), _floats(Jx_w), out)
    return out


def scatter_add(keys: np.ndarray, values: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``values`` (K, D) summed by their ``keys`` (K,) in 0..``n_keys`` - 1, in the
    order given: the sums (n_keys, D) and which keys occurred (n_keys,)."""
    values = _floats(values)
    sums, seen = np.zeros((n_keys, values.shape[-1])), np.zeros(n_keys, np.bool_)
    _c.scatter_add(_indices(keys, "keys"), values, sums, seen)
    return sums, seen


def squared_norms(residuals: np.ndarray) -> np.ndarray:
    """(N,) squared norm of each residual block (row) of ``residuals`` (N, m)."""
    out = np.empty(len(residuals))
    _c.squared_norms(_floats(residuals), out)
    return out


def robust_cost(s: np.ndarray, kind: int, scale: float) -> float:
    """The sum over the squared norms ``s`` (N,) of the robust loss ``rho(s)``: ``kind`` 0
    is least squares (``s``), 1 Huber's (``s`` up to ``scale``, then ``2 scale sqrt(s) -
    scale^2``), 2 Cauchy's (``scale^2 log(1 + s / scale^2)``). Several hundred terms'
    costs per solve, each a few passes over a few hundred rows in numpy."""
    return _c.robust_cost(_floats(s), kind, scale)


def trilinear(values: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray,
              gradient: bool) -> tuple[np.ndarray, np.ndarray]:
    """Trilinear interpolation of the grid ``values`` (nx, ny, nz) at ``origin + spacing *
    (i, j, k)`` at ``points`` (N, 3), and the interpolant's exact gradient (N, 3) when
    ``gradient`` (else an empty (0, 3)). Beyond the grid the distance to it is added and
    its direction becomes the gradient along the clamped axes (see
    ``SignedDistanceField.query``)."""
    n = len(points)
    value, grad = np.empty(n), np.empty((n if gradient else 0, 3))
    _c.trilinear(_grid(values), _floats(origin), spacing, _floats(points), value, grad)
    return value, grad


def surface_rows(values: np.ndarray, origin: np.ndarray, spacing: float, points: np.ndarray,
                 ids: np.ndarray, seated: np.ndarray, directions: np.ndarray, jacobian: bool
                 ) -> tuple[np.ndarray, np.ndarray]:
    """A back-projection term's residuals (N, 2) for the points ``points[ids]``: the field's
    value there (see :func:`trilinear`) and the distance moved along ``directions`` (N, 3)
    from ``seated`` (N, 3); with ``jacobian`` their gradients (N, 2, 3) with respect to the
    point (the field's gradient, the direction), else an empty (0, 2, 3). One pass instead
    of a gather, a lookup and three stacks per evaluation."""
    n = len(ids)
    r, J = np.empty((n, 2)), np.empty((n if jacobian else 0, 2, 3))
    _c.surface_rows(_grid(values), _floats(origin), spacing, _floats(points), _indices(ids, "ids"),
                    _floats(seated), _floats(directions), r, J)
    return r, J


def ray_minima(values: np.ndarray, origin: np.ndarray, spacing: float, R: np.ndarray, t: np.ndarray,
               rays: np.ndarray, min_depth: float, step: float, coarse: int) -> np.ndarray:
    """Depth (N,) along each camera ray ``depth * rays[n]`` (unit depth, carried into the
    field's frame by ``R``, ``t``) where the field (see :func:`trilinear`) is least: sampled
    where the ray crosses the field's box (slab test, floored at ``min_depth``; a ray that
    misses it gets the empty interval at its closest approach to the box's centre) every
    ``coarse * step`` from its near end up to its far end (itself the last sample), then
    every ``step`` within ``coarse`` steps either side of the least sample, then moved by at
    most one step to the vertex of the parabola through the least fine sample (kept off the
    ends) and its neighbours, when that parabola opens upwards. The first least sample wins
    ties. One pass per ray: some 25 lookups, no temporaries."""
    found = np.empty(len(rays))
    _c.ray_minima(_grid(values), _floats(origin), spacing, _floats(R), _floats(t), _floats(rays), min_depth,
                  step, coarse, found)
    return found


def footprint_mask(a: np.ndarray, b: np.ndarray, height: int, width: int) -> np.ndarray:
    """Binary mask (height, width) of the region an outline encloses, and of the pixels it
    passes through: ``a``, ``b`` (E, 2) are its directed edges' ends in mask pixels (see
    ``ContourGenerator.footprint``). The winding number is accumulated along each row of
    the outline's bounding box from the signed crossings of the edges with the rows'
    centres; then every edge is walked in unit steps."""
    mask = np.zeros((height, width), np.uint8)
    _c.footprint_mask(_floats(a), _floats(b), mask)
    return mask


def nearest_points(points: np.ndarray, queries: np.ndarray, cell: float) -> np.ndarray:
    """Index (M,) of the nearest of ``points`` (N >= 1, 2) to each of ``queries`` (M, 2),
    exactly: the points are binned on a grid of ``cell``-sized squares, and each query
    visits the rings of cells around its own until no closer point can lie further out
    (a point in ring r + 1 is at least r cells away)."""
    found = np.empty(len(queries), np.int64)
    _c.nearest_points(_floats(points), _floats(queries), cell, found)
    return found
