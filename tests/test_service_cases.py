"""Case assembly, triggering and initial poses."""

from __future__ import annotations

import numpy as np
import pytest
from pydicom.uid import generate_uid
from service_testing import small_frame

from slamtka.drivers.kinematics import CArmKinematics, JointReading, PatientSetup, initial_view_poses
from slamtka.service.cases import CaseAssembler
from slamtka.service.frames import encode_frame
from slamtka.service.poses import ViewGeometry, planned_pins, positioner_T_anat_cam
from slamtka.service.spool import Spool
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.solver.measurement import fit_resection_plane
from slamtka.solver.plan import Target


def _geometry() -> ViewGeometry:
    return ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)


def _spooled(spool: Spool, **changes):
    entry, _ = spool.store(encode_frame(small_frame(**changes)))
    return entry


def test_views_are_grouped_and_the_pipeline_is_due_on_separated_views(tmp_path):
    spool = Spool(tmp_path)
    assembler = CaseAssembler(spool, _geometry(), 15.0, 6)
    study = generate_uid()
    first = _spooled(spool, study_uid=study, primary_angle_deg=-20.0)
    case, due = assembler.add(first)
    assert not due and len(case.views) == 1
    assert assembler.add(_spooled(spool, study_uid=study, primary_angle_deg=-28.0)) == (case, False)
    case_again, due = assembler.add(_spooled(spool, study_uid=study, primary_angle_deg=25.0))
    assert case_again is case and due and case.separation_deg(case.selection(6)) == pytest.approx(53.0)
    assert assembler.add(first) == (case, False)  # the same SOP Instance UID changes nothing
    assert assembler.add(_spooled(spool, study_uid=study, primary_angle_deg=40.0))[1]  # again
    other_side, due = assembler.add(_spooled(spool, study_uid=study, laterality="L"))
    assert other_side is not case and not due
    assert len(assembler.cases) == 2


def test_a_view_without_geometry_is_kept_but_not_usable(tmp_path):
    spool = Spool(tmp_path)
    assembler = CaseAssembler(spool, _geometry(), 15.0, 6)
    study = generate_uid()
    assembler.add(_spooled(spool, study_uid=study, primary_angle_deg=-30.0))
    case, due = assembler.add(_spooled(spool, study_uid=study, primary_angle_deg=None,
                                       secondary_angle_deg=None))
    assert not due and [v.usable for v in case.ordered()].count(False) == 1
    unusable = next(v for v in case.views.values() if not v.usable)
    assert "no encoder link and no positioner angles" in unusable.pairing.problem


def test_a_restart_rebuilds_cases_from_the_spool_and_its_sidecars(tmp_path):
    spool = Spool(tmp_path)
    study = generate_uid()
    for angle in (-30.0, 30.0):
        CaseAssembler(spool, _geometry(), 15.0, 6).add(_spooled(spool, study_uid=study,
                                                               primary_angle_deg=angle))
    assert len(list((tmp_path / "instances").glob("*.json"))) == 2  # pairings persisted
    rebuilt = CaseAssembler(Spool(tmp_path), _geometry(), 15.0, 6)
    for entry in Spool(tmp_path).entries():
        rebuilt.add(entry)
    (case,) = rebuilt.cases.values()
    assert rebuilt.is_due(case) and all(v.pairing.initialisation == "dicom_positioner"
                                        for v in case.views.values())


def test_positioner_poses_agree_with_the_c_arm_kinematics():
    """Pure orbital rotation: DICOM primary angle and the orbital joint are the same thing."""
    kinematics = CArmKinematics()
    plan_frame = PatientSetup(phantom_plan().landmarks.T_tibia_anat())
    for angle in (-40.0, 0.0, 30.0):
        joints = JointReading(orbital_deg=angle)
        (T_cam_tibia,), _ = initial_view_poses(kinematics, [joints], plan_frame)
        T_anat_cam = positioner_T_anat_cam(angle, 0.0, kinematics.source_to_isocentre_mm, np.zeros(3))
        T_expected = T_anat_cam.inverse() @ plan_frame.T_tibia_anat.inverse()
        assert np.allclose(T_cam_tibia.matrix(), T_expected.matrix(), atol=1e-6)


@pytest.mark.parametrize("side", ["left", "right"])
def test_planned_pins_lie_in_the_planned_plane(side):
    plan = phantom_plan(side, Target(2.0, 5.0, 3.0))
    pins = planned_pins(plan)
    plane = fit_resection_plane(pins, plan.pin_length(), plan.landmarks)
    assert np.degrees([plane.ctr, plane.str_]) == pytest.approx([2.0, 5.0], abs=1e-6)
    sdf = plan.bone_model().sdf
    tips = np.array([T.t for T in pins])
    assert np.all(sdf.query(tips)[0] < 0)  # drilled into the bone
    assert 25.0 < np.linalg.norm(tips[0] - tips[1]) < 35.0
