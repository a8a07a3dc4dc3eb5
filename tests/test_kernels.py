"""Compiled kernels against the plain computations they replace."""

import numpy as np
import pytest

from slamtka.solver.kernels import (
    bilinear,
    contour_generators,
    coupling_blocks,
    footprint_mask,
    in_field,
    nearest_points,
    outline_samples,
    pinhole,
    point_blocks,
    point_steps,
    pose_rows,
    ray_minima,
    robust_cost,
    scatter_add,
    silhouette_rows,
    squared_norms,
    surface_rows,
    trilinear,
)


@pytest.mark.parametrize("n_points", [1, 7, 900])
def test_nearest_points_is_the_exact_nearest_neighbour(n_points):
    """Queries on the outline, beside it and hundreds of cells away all get the point at
    the least distance (brute force), whatever the grid's cell size."""
    rng = np.random.default_rng(n_points)
    points = rng.uniform(0.0, 300.0, (n_points, 2)) + [100.0, -50.0]
    queries = np.vstack([points + rng.normal(0.0, 2.0, points.shape),
                         rng.uniform(-2000.0, 2000.0, (200, 2))])
    brute = np.min(np.linalg.norm(queries[:, None] - points[None], axis=2), axis=1)
    for cell in (0.5, 10.0, 1000.0):
        found = nearest_points(points, queries, cell)
        np.testing.assert_allclose(np.linalg.norm(queries - points[found], axis=1), brute,
                                   rtol=0, atol=1e-9)


def test_bilinear_is_exact_on_a_plane_and_grows_by_the_distance_beyond():
    """An image of an affine function is interpolated exactly, gradient included; beyond
    the image the value at the nearest border point grows by the distance to it, and the
    clamped axes' gradient points away from the image."""
    h, w, origin = 40, 60, np.array([100.0, 200.0])
    vv, uu = np.mgrid[0:h, 0:w]
    values = (0.3 * uu - 0.7 * vv + 5.0).astype(np.float32)
    rng = np.random.default_rng(1)
    inside = origin + rng.uniform(0.0, [w - 1, h - 1], (300, 2))
    value, grad = bilinear(values, origin, inside)
    local = inside - origin
    np.testing.assert_allclose(value, 0.3 * local[:, 0] - 0.7 * local[:, 1] + 5.0, atol=1e-5)
    np.testing.assert_allclose(grad, np.tile([0.3, -0.7], (300, 1)), atol=1e-5)
    beyond = origin + np.array([[-3.0, 10.0], [w - 1 + 4.0, h - 1 + 3.0], [20.0, -2.0]])
    value, grad = bilinear(values, origin, beyond)
    border = np.array([[0.0, 10.0], [w - 1, h - 1], [20.0, 0.0]])
    plane = 0.3 * border[:, 0] - 0.7 * border[:, 1] + 5.0
    np.testing.assert_allclose(value, plane + [3.0, 5.0, 2.0], atol=1e-5)
    np.testing.assert_allclose(grad, [[-1.0, -0.7], [0.8, 0.6], [0.3, -1.0]], atol=1e-5)


def test_outline_samples_are_the_in_field_centres_of_equal_sub_segments():
    """Each edge cut into ceil(length / spacing) equal parts, sampled at their centres, in
    edge order; samples outside the (circular) field or on the interior mask are dropped."""
    rng = np.random.default_rng(3)
    uv_a = rng.uniform(-20.0, 120.0, (50, 2))
    uv_delta = rng.normal(0.0, 8.0, (50, 2))
    edge, frac = outline_samples(uv_a, uv_delta, 3.0, 100, 100, 2.0, 45.0, np.zeros((0, 0), np.uint8), 4)
    counts = np.maximum(1, np.ceil(np.linalg.norm(uv_delta, axis=1) / 3.0)).astype(int)
    every = [(e, (k + 0.5) / n) for e, n in enumerate(counts) for k in range(n)]
    all_edge, all_frac = np.array(every).T
    uv = uv_a[all_edge.astype(int)] + all_frac[:, None] * uv_delta[all_edge.astype(int)]
    inside = in_field(uv, 100, 100, 2.0, 45.0)
    assert inside.any() and not inside.all()
    np.testing.assert_array_equal(edge, all_edge[inside])
    np.testing.assert_array_equal(frac, all_frac[inside])
    mask = np.zeros((25, 25), np.uint8)
    mask[:, :12] = 1  # u < ~46 px is interior
    edge, frac = outline_samples(uv_a, uv_delta, 3.0, 100, 100, 2.0, 45.0, mask, 4)
    kept = uv_a[edge] + frac[:, None] * uv_delta[edge]
    assert len(kept) and np.all(np.round(kept[:, 0] / 4) >= 12)


def test_point_blocks_and_couplings_are_the_batched_products():
    """The points' normal-equation blocks and their couplings to a pose equal numpy's
    batched products; rows of one key are summed by the scatter-add."""
    rng = np.random.default_rng(4)
    n, m, X = 200, 2, 300
    Jx, Ja = rng.normal(size=(n, m, 3)), rng.normal(size=(n, m, 6))
    w, r = rng.uniform(0.1, 1.0, n), rng.normal(size=(n, m))
    x_idx = rng.permutation(X)[:n]
    H_xx, g_x = np.ones((X, 3, 3)), np.ones((X, 3))
    Jx_w = point_blocks(Jx, w, r, x_idx, H_xx, g_x)
    expected_H, expected_g = np.ones((X, 3, 3)), np.ones((X, 3))
    expected_H[x_idx] += (w[:, None, None] * Jx).transpose(0, 2, 1) @ Jx
    expected_g[x_idx] += np.einsum("nmi,nm->ni", Jx, w[:, None] * r)
    np.testing.assert_allclose(H_xx, expected_H, rtol=0, atol=1e-13)
    np.testing.assert_allclose(g_x, expected_g, rtol=0, atol=1e-13)
    np.testing.assert_allclose(coupling_blocks(Ja, Jx_w), Ja.transpose(0, 2, 1) @ Jx_w, rtol=0, atol=1e-14)
    keys = rng.integers(0, 7, 50)
    values = rng.normal(size=(50, 4))
    sums, seen = scatter_add(keys, values, 9)
    np.testing.assert_allclose(sums, [values[keys == k].sum(axis=0) for k in range(9)], atol=1e-14)
    np.testing.assert_array_equal(seen, [k in keys for k in range(9)])


@pytest.mark.parametrize("jacobian", [False, True])
def test_silhouette_rows_are_the_numpy_path_to_the_last_bit(jacobian):
    """Distance-map values at the charged outline points and each observed pixel's distance
    to its nearest one, with their camera-frame gradients: bit for bit the numpy
    expressions the silhouette term used before."""
    rng = np.random.default_rng(5)
    p_cam = rng.normal([0.0, 0.0, 900.0], [60.0, 60.0, 20.0], (400, 3))
    values = rng.uniform(0.0, 50.0, (300, 400)).astype(np.float32)
    origin = np.array([200.0, 180.0])
    charged = np.flatnonzero(rng.uniform(size=400) < 0.8)
    nearest = rng.integers(0, 400, 250)
    observed = rng.uniform(300.0, 700.0, (250, 2))
    intrinsics = (1100.0, 1090.0, 512.0, 500.0, 1.0)
    r, J_cam = silhouette_rows(p_cam, *intrinsics, values, origin, charged, nearest, observed, jacobian)
    uv, J_proj = pinhole(p_cam, *intrinsics, jacobian)
    dist, grad = bilinear(values, origin, uv[charged])
    offset = uv[nearest] - observed
    norms = np.sqrt(np.einsum("ij,ij->i", offset, offset))
    assert np.array_equal(r, np.concatenate([dist, norms])[:, None])
    if not jacobian:
        assert J_cam.shape == (0, 3)
        return
    J_pix = np.concatenate([grad, offset / np.maximum(norms, 1e-9)[:, None]])
    rows = np.concatenate([charged, nearest])
    assert np.array_equal(J_cam, np.einsum("nk,nkj->nj", J_pix, J_proj[rows]))


def test_contour_generators_are_the_edges_between_front_and_back_faces_run_by_the_front():
    rng = np.random.default_rng(6)
    front = rng.uniform(size=500) < 0.5
    faces = rng.integers(0, 500, (800, 2))
    edges = rng.integers(0, 300, (800, 2))
    first = front[faces[:, 0]]
    on = first != front[faces[:, 1]]
    expected = np.where(first[on, None], edges[on], edges[on][:, ::-1])
    found = contour_generators(front, faces, edges)
    assert found.dtype == edges.dtype and np.array_equal(found, expected)


def test_pose_rows_are_the_rotated_gradients_and_their_moments():
    """The view's and the body's Jacobian rows equal numpy's statement of them: the
    gradient rotated into each pose's source frame, and its moment about the source point
    (the point carried by the body's pose for the view, the point itself for the body)."""
    rng = np.random.default_rng(7)
    G_cam, X = rng.normal(size=(300, 2, 3)), rng.normal(size=(300, 3)) * 100.0
    R_view = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R_body, t_body = np.linalg.qr(rng.normal(size=(3, 3)))[0], rng.normal(size=3) * 50.0

    def rows(G: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.concatenate([G, np.cross(p[:, None, :], G)], axis=-1)

    G_view = G_cam @ R_view
    J_view, J_body, G_x = pose_rows(G_cam, X, R_view, R_body, t_body, False)
    np.testing.assert_allclose(J_view, rows(G_view, X), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(G_x, G_view, rtol=1e-12, atol=1e-12)
    assert J_body.shape == (0, 2, 6)
    G_body = G_view @ R_body
    J_view, J_body, G_x = pose_rows(G_cam, X, R_view, R_body, t_body, True)
    np.testing.assert_allclose(J_view, rows(G_view, X @ R_body.T + t_body), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(J_body, rows(G_body, X), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(G_x, G_body, rtol=1e-12, atol=1e-12)


def test_ray_minima_is_the_sampled_search_of_the_least_distance_along_each_ray():
    """The compiled search equals numpy's statement of it: each ray's interval in the
    field's box (slab test; the closest approach to its centre for a ray that misses), the
    coarse samples of it (clamped to its far end), the fine samples around the least, the
    parabola's vertex."""
    rng = np.random.default_rng(5)
    values = rng.normal(0.0, 5.0, (30, 24, 20)).astype(np.float32)
    origin, spacing, step, coarse, min_depth = np.array([-40.0, -30.0, 300.0]), 2.0, 0.7, 4, 10.0
    box = np.vstack([origin, origin + spacing * (np.array(values.shape) - 1)])
    angle = 0.3
    R = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    t = np.array([3.0, -2.0, 5.0])
    rays = np.column_stack([rng.uniform(-0.3, 0.3, (300, 2)), np.ones(300)])  # some miss the box

    direction = rays @ R.T
    t0, t1 = (box[0] - t) / direction, (box[1] - t) / direction
    near = np.max(np.minimum(t0, t1), axis=1)
    far = np.min(np.maximum(t0, t1), axis=1)
    missed = ~(far >= near)
    assert missed.any() and not missed.all()
    closest = direction @ (box.mean(axis=0) - t) / np.sum(direction**2, axis=1)
    near[missed] = far[missed] = closest[missed]
    depths = np.maximum(np.column_stack([near, far]), min_depth)

    def field(z: np.ndarray) -> np.ndarray:
        points = (rays[:, None, :] * z[:, :, None]).reshape(-1, 3) @ R.T + t
        return trilinear(values, origin, spacing, points, False)[0].reshape(z.shape)

    coarse_step = coarse * step
    samples = int(np.ceil(np.max(depths[:, 1] - depths[:, 0]) / coarse_step)) + 1
    z = np.minimum(depths[:, :1] + coarse_step * np.arange(samples), depths[:, 1:])
    rows = np.arange(len(rays))
    z_fine = z[rows, np.argmin(field(z), axis=1)][:, None] + np.arange(-coarse, coarse + 1) * step
    d = field(z_fine)
    best = np.clip(np.argmin(d, axis=1), 1, 2 * coarse - 1)
    d_minus, d_0, d_plus = d[rows, best - 1], d[rows, best], d[rows, best + 1]
    curvature = d_plus - 2.0 * d_0 + d_minus
    shift = np.where(curvature > 1e-9, 0.5 * (d_minus - d_plus) / np.maximum(curvature, 1e-9), 0.0)
    expected = z_fine[rows, best] + np.clip(shift, -1.0, 1.0) * step
    found = ray_minima(values, origin, spacing, R, t, rays, min_depth, step, coarse)
    np.testing.assert_allclose(found, expected, rtol=0, atol=1e-9)


def test_squared_norms_and_robust_costs_are_numpys_sums():
    """Each residual block's squared norm, and the sums of the robust losses over them,
    equal numpy's statements of the same maths (to rounding: the sums run in another order)."""
    rng = np.random.default_rng(11)
    for m in (1, 2, 6):
        r = rng.normal(0.0, 3.0, (500, m))
        np.testing.assert_allclose(squared_norms(r), np.sum(r**2, axis=1), rtol=1e-15, atol=0)
    s = np.sum(rng.normal(0.0, 3.0, (500, 2)) ** 2, axis=1)
    scale = 2.0
    huber = np.where(np.sqrt(s) <= scale, s, 2.0 * scale * np.sqrt(s) - scale**2)
    cauchy = scale**2 * np.log1p(s / scale**2)
    for kind, rho in enumerate((s, huber, cauchy)):
        np.testing.assert_allclose(robust_cost(s, kind, scale), np.sum(rho), rtol=1e-12)
    assert robust_cost(np.zeros(0), 1, scale) == 0.0


@pytest.mark.parametrize("jacobian", [False, True])
def test_surface_rows_are_the_lookup_and_the_distance_along_the_ray(jacobian):
    """A back-projection term's rows equal numpy's statement of them: the field's value
    and gradient at each chosen point, and its offset from the seated point along its ray."""
    rng = np.random.default_rng(13)
    values = rng.normal(0.0, 5.0, (12, 10, 8)).astype(np.float32)
    origin, spacing = np.array([-5.0, 2.0, 1.0]), 1.5
    points = rng.uniform(-10.0, 20.0, (80, 3))  # some beyond the grid
    ids = rng.choice(80, 50, replace=False)
    seated = points[ids] + rng.normal(0.0, 1.0, (50, 3))
    directions = rng.normal(size=(50, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    d, grad = trilinear(values, origin, spacing, points[ids], True)
    r, J = surface_rows(values, origin, spacing, points, ids, seated, directions, jacobian)
    expected = np.column_stack([d, np.sum((points[ids] - seated) * directions, axis=1)])
    np.testing.assert_allclose(r, expected, rtol=1e-13, atol=1e-12)
    if jacobian:
        np.testing.assert_array_equal(J, np.stack([grad, directions], axis=1))
    else:
        assert J.shape == (0, 2, 3)


def test_point_steps_are_the_back_substitution_of_the_pose_steps():
    """The points' increments equal numpy's batched statement of them, the empty coupling
    slots (pose P) moving nothing."""
    rng = np.random.default_rng(17)
    X, k, P = 200, 3, 4
    W = rng.normal(size=(X, k, 6, 3))
    pose_of = rng.integers(0, P + 1, (X, k))
    d_p, V_inv, g_x = rng.normal(size=6 * P), rng.normal(size=(X, 3, 3)), rng.normal(size=(X, 3))
    d_p_ext = np.vstack([d_p.reshape(P, 6), np.zeros((1, 6))])
    coupled = np.einsum("xaij,xai->xj", W, d_p_ext[pose_of])
    expected = -np.einsum("xij,xj->xi", V_inv, g_x + coupled)
    np.testing.assert_allclose(point_steps(W, pose_of, d_p, V_inv, g_x), expected, rtol=1e-12, atol=1e-12)


def test_bad_input_raises_named_errors_never_crashes():
    """Out-of-range indices, float indices, wrong shapes, non-finite outlines and in-place
    outputs that a copy would detach are refused with an exception; other element types
    and layouts are converted."""
    rng = np.random.default_rng(8)
    with pytest.raises(IndexError, match="scatter_add"):
        scatter_add(np.array([0, 5]), np.ones((2, 1)), 3)
    with pytest.raises(IndexError, match="silhouette_rows"):
        silhouette_rows(np.ones((2, 3)), 1.0, 1.0, 0.0, 0.0, 1.0, np.zeros((4, 4), np.float32),
                        np.zeros(2), np.array([2]), np.zeros(0, np.int64), np.zeros((0, 2)), True)
    with pytest.raises(TypeError, match="ids"):
        surface_rows(np.zeros((2, 2, 2)), np.zeros(3), 1.0, np.zeros((3, 3)), np.array([0.5]),
                     np.zeros((1, 3)), np.ones((1, 3)), False)
    with pytest.raises(ValueError, match="uv"):
        bilinear(np.zeros((4, 4)), np.zeros(2), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="not finite"):
        footprint_mask(np.array([[np.nan, 0.0]]), np.ones((1, 2)), 4, 4)
    with pytest.raises(ValueError, match="no points"):
        nearest_points(np.zeros((0, 2)), np.zeros((1, 2)), 1.0)
    with pytest.raises(TypeError, match="H_xx"):  # a converted copy would lose the sums
        point_blocks(np.ones((1, 1, 3)), np.ones(1), np.ones((1, 1)), np.zeros(1, np.int64),
                     np.ones((1, 3, 3), np.float32), np.ones((1, 3)))
    uv = rng.uniform(0.0, 3.0, (5, 4))[:, ::2]  # strided, and as float32 below
    expected = bilinear(np.arange(16.0).reshape(4, 4), np.zeros(2), np.ascontiguousarray(uv))
    for values, points in ((np.arange(16).reshape(4, 4), uv),
                           (np.arange(16.0).reshape(4, 4), uv.astype(np.float32))):
        found = bilinear(values, np.zeros(2), points)
        np.testing.assert_allclose(found[0], expected[0], rtol=1e-6)
    assert np.isnan(trilinear(np.zeros((2, 2, 2)), np.zeros(3), 1.0, np.array([[np.nan, 0.0, 0.0]]), True)[0][0])
