"""The compiled Schur complement against the dense algebra it replaces."""

import numpy as np

from slamtka.solver.optimizer import _POINT_REGULARISATION, NormalEquations, _reduced_system


def test_schur_complement_equals_dense_elimination_of_the_damped_points():
    rng = np.random.default_rng(3)
    P, X, lam = 4, 50, 0.01
    # Points coupled to one pose (bone points: a view) or two (pin points: view and pin).
    pair_point, pair_pose, H_px = [], [], []
    for x in range(X):
        for pose in ([x % 2] if x % 3 else [x % 2, 2 + x % 2]):
            pair_point.append(x)
            pair_pose.append(pose)
            H_px.append(rng.normal(size=(6, 3)))
    A = rng.normal(size=(X, 3, 3))
    H_xx = A @ A.transpose(0, 2, 1) + np.eye(3)
    B = rng.normal(size=(6 * P, 6 * P))
    ne = NormalEquations(H_pp=B @ B.T, g_p=rng.normal(size=6 * P), H_xx=H_xx,
                         g_x=rng.normal(size=(X, 3)), pair_point=np.array(pair_point),
                         pair_pose=np.array(pair_pose), H_px=np.array(H_px))
    S, rhs, V_inv = _reduced_system(ne, P, lam)

    # Dense: the full damped system, points eliminated by block inversion.
    H_px_dense = np.zeros((6 * P, 3 * X))
    for x, pose, block in zip(pair_point, pair_pose, H_px):
        H_px_dense[6 * pose:6 * pose + 6, 3 * x:3 * x + 3] += block
    V = np.zeros((3 * X, 3 * X))
    for x in range(X):
        block = H_xx[x] + np.diag(lam * np.diag(H_xx[x])
                                  + _POINT_REGULARISATION * np.trace(H_xx[x]))
        V[3 * x:3 * x + 3, 3 * x:3 * x + 3] = block
    V_dense_inv = np.linalg.inv(V)
    H_pp = ne.H_pp + np.diag(lam * np.diag(ne.H_pp))
    expected_S = H_pp - H_px_dense @ V_dense_inv @ H_px_dense.T
    expected_rhs = -ne.g_p + H_px_dense @ V_dense_inv @ ne.g_x.reshape(-1)
    np.testing.assert_allclose(S, expected_S, rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(rhs, expected_rhs, rtol=1e-9, atol=1e-9)
    for x in range(X):
        np.testing.assert_allclose(V_inv[x], V_dense_inv[3 * x:3 * x + 3, 3 * x:3 * x + 3],
                                   rtol=1e-9, atol=1e-12)
