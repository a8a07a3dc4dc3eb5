"""C-arm kinematics: joint values to source pose, initial view poses, relative motion with
covariance, and the DICOM positioner-angle cross-check."""

from __future__ import annotations

import numpy as np
import pytest

from slamtka.drivers.kinematics import (
    CArmKinematics,
    JointReading,
    PatientSetup,
    _beam,
    check_dicom_angles,
    dicom_angles,
    initial_view_poses,
)
from slamtka.sim.bone_phantom import build_phantom
from slamtka.sim.simulate import SOURCE_TO_ISOCENTRE_MM, _view_poses
from slamtka.solver.anatomy import Landmarks
from slamtka.solver.geometry import so3_log

KIN = CArmKinematics()
REST = dict(lift_mm=200.0, travel_mm=100.0)  # a typical knee position, mid-range


@pytest.fixture(scope="module")
def landmarks() -> Landmarks:
    bone = build_phantom("right")
    return Landmarks(bone.knee_centre, bone.ankle_centre, bone.anterior, "right")


class _NominalSetupRng:
    """Stands in for simulate's RNG so that its patient set-up is the nominal one:
    no extra rotation (angle 0 about any axis) and no extra translation."""

    def normal(self, loc=0.0, scale=1.0, size=None):
        return np.array([1.0, 0.0, 0.0]) if scale == 1.0 else np.zeros(size)

    def uniform(self, low, high):
        return low


class _PlanStub:
    def __init__(self, landmarks: Landmarks) -> None:
        self.landmarks = landmarks


def test_zero_joints_put_the_source_under_the_isocentre_looking_up():
    T = KIN.T_carm_cam(JointReading())
    assert np.allclose(T.R, np.eye(3)) and np.allclose(T.t, [0, 0, -620.0])
    assert np.allclose(KIN.isocentre(JointReading()), 0.0)
    assert KIN.source_to_isocentre_mm == SOURCE_TO_ISOCENTRE_MM


def test_each_joint_moves_the_beam_as_documented(landmarks):
    setup = PatientSetup(landmarks.T_tibia_anat())
    left = np.cross(setup.superior_carm, setup.anterior_carm)
    beam = lambda j: KIN.T_carm_cam(j).rotate([0.0, 0.0, 1.0])  # noqa: E731
    assert np.allclose(beam(JointReading(orbital_deg=90)), left)  # LAO 90: detector at the left
    assert np.allclose(beam(JointReading(angulation_deg=90)), setup.superior_carm)  # cranial
    assert np.allclose(KIN.T_carm_cam(JointReading(lift_mm=100)).t, [0, 0, -520.0])
    assert np.allclose(KIN.T_carm_cam(JointReading(travel_mm=50)).t, [50, 0, -620.0])
    # Wig-wag turns about the vertical through the column, 750 mm behind the isocentre.
    iso = KIN.isocentre(JointReading(wigwag_deg=10))
    assert np.isclose(np.linalg.norm(iso[:2] - [-750.0, 0.0]), 750.0) and iso[1] > 0
    # Orbital and angulation keep the isocentre (an isocentric C).
    assert np.allclose(KIN.isocentre(JointReading(orbital_deg=-40, angulation_deg=25)), 0.0)
    # A larger SID moves only the detector: the source stays.
    assert np.allclose(KIN.T_carm_cam(JointReading(sid_mm=1100.0)).t, [0, 0, -620.0])


def test_views_match_the_simulation_conventions(landmarks):
    """Orbital angles are simulate.py's view angles: same camera frame, same poses."""
    angles = (-30.0, 0.0, 30.0)
    sim = _view_poses(_PlanStub(landmarks), angles, _NominalSetupRng())
    setup = PatientSetup(landmarks.T_tibia_anat(), isocentre_in_anat_mm=(0.0, 0.0, -30.0))
    joints = [JointReading(orbital_deg=a, **REST) for a in angles]
    poses, relatives = initial_view_poses(KIN, joints, setup)
    for ours, theirs in zip(poses, sim):
        assert np.allclose(ours.matrix(), theirs.matrix(), atol=1e-9)
    # The motion between views does not depend on the patient set-up, whatever it was.
    randomised = _view_poses(_PlanStub(landmarks), angles, np.random.default_rng(4))
    for rel in relatives:
        ours = poses[rel.view_b] @ poses[rel.view_a].inverse()
        expected = randomised[rel.view_b] @ randomised[rel.view_a].inverse()
        assert np.allclose(ours.matrix(), expected.matrix(), atol=1e-9)


def test_default_joints_look_antero_posterior_at_the_knee(landmarks):
    setup = PatientSetup(landmarks.T_tibia_anat())
    (T_cam_tibia,), _ = initial_view_poses(KIN, [JointReading(**REST)], setup)
    T_cam_anat = T_cam_tibia @ landmarks.T_tibia_anat()
    assert np.allclose(T_cam_anat.rotate([0, 1, 0]), [0, 0, 1])  # anterior is away from the source
    assert np.allclose(T_cam_anat.rotate([0, 0, 1]), [0, -1, 0])  # proximal is up in the image
    assert np.allclose(T_cam_anat.t, [0, 0, 620.0])  # the knee on the beam, at the isocentre
    assert dicom_angles(KIN, JointReading(**REST), setup) == pytest.approx((0.0, 0.0), abs=1e-9)


@pytest.mark.system
def test_relative_covariance_matches_sampled_joint_noise(landmarks):
    setup = PatientSetup(landmarks.T_tibia_anat())
    views = [JointReading(orbital_deg=-25, angulation_deg=5, **REST),
             JointReading(orbital_deg=35, angulation_deg=-5, wigwag_deg=3, **REST)]
    poses, (rel,) = initial_view_poses(KIN, views, setup)
    cov = rel.covariance
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() > -1e-12
    # Monte Carlo: perturb every joint of both views by its sd and measure the error the
    # solver's relative-pose term would see.
    rng = np.random.default_rng(0)
    A = landmarks.T_tibia_anat()
    M = poses[1] @ poses[0].inverse()
    samples = []
    for _ in range(2000):
        noisy = [KIN.with_vector(j, KIN.vector(j) + rng.normal(0.0, KIN.sd())) for j in views]
        M_noisy = KIN.source_pose(noisy[1]).inverse() @ KIN.source_pose(noisy[0])
        D = A.inverse() @ poses[0].inverse() @ M_noisy.inverse() @ M @ poses[0] @ A
        samples.append(np.concatenate([D.t, so3_log(D.R)]))
    empirical = np.cov(np.array(samples).T)
    assert np.allclose(np.diag(empirical), np.diag(cov), rtol=0.12)
    assert rel.sigma_mm == pytest.approx(np.sqrt(np.linalg.eigvalsh(cov[:3, :3]).max()))
    assert 0 < rel.sigma_rad < np.radians(1.0)
    # Perfect encoders: no uncertainty at all.
    perfect = CArmKinematics.from_config({**KIN.to_config(),
                                          "chain": [{**j, "sd": 0.0} for j in KIN.to_config()["chain"]]})
    assert np.allclose(initial_view_poses(perfect, views, setup)[1][0].covariance, 0.0)


def test_dicom_angles_describe_the_beam(landmarks):
    setup = PatientSetup(landmarks.T_tibia_anat())
    rng = np.random.default_rng(2)
    L = np.cross(setup.superior_carm, setup.anterior_carm)
    basis = np.column_stack([L, setup.anterior_carm, setup.superior_carm])
    for _ in range(20):
        j = JointReading(orbital_deg=rng.uniform(-90, 90), angulation_deg=rng.uniform(-40, 40), **REST)
        d = KIN.T_carm_cam(j).rotate([0.0, 0.0, 1.0])
        assert np.allclose(basis @ _beam(*dicom_angles(KIN, j, setup)), d)


def test_dicom_cross_check_reports_disagreement(landmarks):
    setup = PatientSetup(landmarks.T_tibia_anat())
    j = JointReading(orbital_deg=30.0, **REST)
    agree = check_dicom_angles(KIN, j, setup, 30.4, 0.3, threshold_deg=1.0)
    assert agree.agrees and agree.beam_difference_deg < 1.0
    bad = check_dicom_angles(KIN, j, setup, 25.0, 0.0, threshold_deg=2.0)
    assert bad.status == "disagrees" and bad.beam_difference_deg == pytest.approx(5.0, abs=1e-6)
    assert "beyond the 2 deg threshold" in bad.message and "+30.0" in bad.message
    assert bad.to_json()["dicom_primary_deg"] == 25.0
    absent = check_dicom_angles(KIN, j, setup, None, None)
    assert absent.status == "not_available" and not absent.agrees
    with pytest.raises(ValueError, match="threshold"):
        check_dicom_angles(KIN, j, setup, 30.0, 0.0, threshold_deg=0.0)


def test_configuration_round_trips_and_rejects_nonsense():
    config = KIN.to_config()
    again = CArmKinematics.from_config(config)
    assert again == KIN
    j = JointReading(orbital_deg=12, angulation_deg=-7, wigwag_deg=2, lift_mm=150, travel_mm=80)
    assert np.allclose(again.T_carm_cam(j).matrix(), KIN.T_carm_cam(j).matrix())
    with pytest.raises(ValueError, match="unknown keys \\['colour'\\]"):
        CArmKinematics.from_config({**config, "colour": "grey"})
    with pytest.raises(ValueError, match="'tilt' is not one of"):
        CArmKinematics.from_config({"chain": [{"axis": "tilt", "direction": [1, 0, 0], "limits": [0, 1],
                                               "sd": 0}]})
    with pytest.raises(ValueError, match="must not be the zero vector"):
        CArmKinematics.from_config({"chain": [{"axis": "lift", "direction": [0, 0, 0], "limits": [0, 1],
                                               "sd": 0}]})
    with pytest.raises(ValueError, match="lacks 'sd'"):
        CArmKinematics.from_config({"chain": [{"axis": "lift", "direction": [0, 0, 1], "limits": [0, 1]}]})
    with pytest.raises(ValueError, match="drives an axis twice"):
        CArmKinematics.from_config({"chain": [config["chain"][0], config["chain"][0]]})
    with pytest.raises(ValueError, match="between the source and the detector"):
        CArmKinematics.from_config({"source_to_isocentre_mm": 950})
    with pytest.raises(ValueError, match="must be a number"):
        CArmKinematics.from_config({"sid_nominal_mm": "far"})
    with pytest.raises(ValueError, match="orbital = 120 deg is outside"):
        KIN.T_carm_cam(JointReading(orbital_deg=120))
    with pytest.raises(ValueError, match="unknown C-arm axes \\['tilt'\\]"):
        JointReading.from_axes({"tilt": 1.0})
    with pytest.raises(ValueError, match="not a finite number"):
        JointReading(orbital_deg=float("nan"))


def test_patient_setup_validation(landmarks):
    with pytest.raises(ValueError, match="perpendicular"):
        PatientSetup(landmarks.T_tibia_anat(), superior_carm=(0, -1, 0), anterior_carm=(0, 1, 1))
    with pytest.raises(ValueError, match="unknown keys"):
        PatientSetup.from_config(landmarks, {"prone": True})
    setup = PatientSetup.from_config(landmarks, {"superior_carm": [0, 2, 0], "reference_view": 1})
    assert setup.superior_carm == (0.0, 1.0, 0.0)
    with pytest.raises(ValueError, match="reference view 1 is not one of the 1 views"):
        initial_view_poses(KIN, [JointReading(**REST)], setup)
    # The reference view's isocentre holds the knee even after lift and travel moved.
    joints = [JointReading(**REST), JointReading(lift_mm=260, travel_mm=90, orbital_deg=20)]
    poses, _ = initial_view_poses(KIN, joints, setup)
    knee_in_cam = (poses[1] @ landmarks.T_tibia_anat()).t
    assert np.allclose(knee_in_cam, [0, 0, 620.0])
    # View 0 (orbital 0: camera axes along the C-arm's) sees it where its own isocentre would
    # be after 60 mm more lift (up the beam) and 10 mm less travel (-x).
    assert np.allclose((poses[0] @ landmarks.T_tibia_anat()).t, [-10.0, 0.0, 680.0])
