import numpy as np
import pytest

from solver.anatomy import Landmarks, plane_normal_from_angles, resection_angles
from solver.geometry import Pose, so3_exp, so3_log


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
