import numpy as np
import pytest

from slamtka.solver.anatomy import Landmarks, plane_normal_from_angles, resection_angles
from slamtka.solver.geometry import Pose, so3_exp, so3_log


def test_so3_round_trip_including_near_pi():
    rng = np.random.default_rng(0)
    for phi in list(rng.normal(size=(20, 3))) + [np.array([np.pi - 1e-7, 0, 0])]:
        assert np.allclose(so3_exp(so3_log(so3_exp(phi))), so3_exp(phi), atol=1e-6)


def test_retract_and_local_are_inverse():
    rng = np.random.default_rng(1)
    T = Pose(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 100)
    xi = rng.normal(size=6) * 0.3
    assert np.allclose(T.local(T.retract(xi)), xi, atol=1e-9)


def test_pose_rejects_non_rotation():
    with pytest.raises(ValueError, match="rotation"):
        Pose(np.diag([1.0, 1.0, -1.0]), np.zeros(3))


@pytest.mark.parametrize("side", ["left", "right"])
def test_sign_conventions(side):
    """Varus (medial lower) and posterior slope (posterior lower) are positive."""
    lm = Landmarks(np.zeros(3), np.array([0, 0, -370.0]), np.array([0, 1.0, 0]), side)
    medial = np.array([lm.medial_sign, 0.0, 0.0])
    # A plane whose medial side is lower: height falls towards medial.
    pts = np.array([[0, 0, 0], medial * 10 + [0, 0, -1], [0, 10, 0]], float)
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    ctr, str_ = resection_angles(n, lm.medial_sign)
    assert ctr > 0 and abs(str_) < 1e-9
    pts = np.array([[0, 0, 0], [10, 0, 0], [0, -10, -1]], float)  # posterior side lower
    ctr, str_ = resection_angles(np.cross(pts[1] - pts[0], pts[2] - pts[0]), lm.medial_sign)
    assert str_ > 0 and abs(ctr) < 1e-9
    n = plane_normal_from_angles(0.05, -0.02, lm.medial_sign)
    assert np.allclose(resection_angles(n, lm.medial_sign), (0.05, -0.02))


def test_landmarks_refuse_nonsense():
    with pytest.raises(ValueError, match="mechanical axis"):
        Landmarks(np.zeros(3), np.array([0, 0, -0.37]), np.array([0, 1.0, 0]), "right")
    with pytest.raises(ValueError, match="laterality"):
        Landmarks(np.zeros(3), np.array([0, 0, -370.0]), np.array([0, 1.0, 0]), "up")
    with pytest.raises(ValueError, match="parallel"):
        Landmarks(np.zeros(3), np.array([0, 0, -370.0]), np.array([0, 0, 1.0]), "left")


def test_relative_pose_jacobians_far_from_agreement():
    """E_odo's analytic Jacobians hold where the views disagree with the encoders by a lot
    (the simulated cases start where they agree, which tests little of the rotation part)."""
    from slamtka.solver.optimizer import NoiseModel, State, whitened
    from slamtka.solver.terms import RelativePoseTerm
    from slamtka.solver.variables import view_key

    rng = np.random.default_rng(3)

    def random_pose() -> Pose:
        return Pose(so3_exp(rng.normal(size=3) * 0.6), rng.normal(size=3) * 50.0)

    term = RelativePoseTerm("E_odo", view_key(0), view_key(1), random_pose(), random_pose(),
                            NoiseModel((2.0,) * 3 + (0.01,) * 3))
    state = State({view_key(0): random_pose(), view_key(1): random_pose()}, np.zeros((0, 3)))
    lin = whitened(term, state)
    eps = 1e-6
    for pose, J in lin.pose_jacobians:
        for dof in range(6):
            step = np.zeros((2, 6))
            step[state.ordering.index(pose), dof] = eps
            plus = whitened(term, state.retract(step.ravel(), state.points), False).residuals
            minus = whitened(term, state.retract(-step.ravel(), state.points), False).residuals
            fd = (plus - minus)[0] / (2 * eps)
            np.testing.assert_allclose(J[0, :, dof], fd, atol=1e-5 * (1 + np.abs(fd).max()))


def test_cropped_distance_map_agrees_with_the_whole_image_map():
    """A pin's map is computed around its contour only: inside that window it is the full
    map; beyond, it still grows away from the contour (an upper bound that pulls back)."""
    from slamtka.solver.observations import DistanceMap

    t = np.linspace(0.0, 1.0, 200)[:, None]
    points = np.array([400.0, 300.0]) + t * np.array([150.0, 60.0])
    whole = DistanceMap.from_points(points, 1024, 1024)
    window = DistanceMap.from_points(points, 1024, 1024, margin_px=40)
    assert window.values.size < whole.values.size / 20
    near = np.array([[420.0, 330.0], [560.0, 340.0], [380.0, 290.0]])
    np.testing.assert_allclose(window.query(near)[0], whole.query(near)[0], atol=1e-4)
    np.testing.assert_allclose(window.query(near)[1], whole.query(near)[1], atol=1e-4)
    far = np.array([[100.0, 900.0], [1000.0, 20.0]])
    d_window, g_window = window.query(far)
    assert np.all(d_window >= whole.query(far)[0] - 1e-6)
    # The gradient still points away from the contour.
    towards = points.mean(axis=0) - far
    assert np.all(np.einsum("ij,ij->i", g_window, towards) < 0)
    # The global searches see the whole image, capped: the same from either map.
    np.testing.assert_array_equal(window.truncated(30.0), np.minimum(whole.values, 30.0))
    with pytest.raises(ValueError, match="margin"):
        window.truncated(50.0)
