"""The rerun recording of a run: written to a file, read back headless, checked."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest
from service_testing import result_document, small_frame

from slamtka.service.recording import CaseRecorder
from slamtka.service.replay import check_recording, read_recording, recorded_edge_searches
from slamtka.service.results import MeasurementResult
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import default_camera
from slamtka.sim.xray import default_distortion
from slamtka.solver.imaging.calibration_file import calibration_document
from slamtka.solver.imaging.edges import BoneEdgeSearch
from slamtka.solver.optimizer import IterationInfo, State
from slamtka.solver.variables import pin_key, view_key


@pytest.fixture(scope="module")
def plan():
    return phantom_plan("right")


def _record(path, plan, result: dict) -> None:
    rec = CaseRecorder(path, "case-x", "run-y")
    rec.stage("frames", "1 view")
    rec.frame("view1", small_frame(), {"primary_angle_deg": -30.0, "secondary_angle_deg": 0.0,
                                       "sid_mm": 1000.0, "sod_mm": None})
    rec.encoder("view1", "encoders", {"joints": {"orbital": -30.0}})
    rec.stage("calibration", "carm-1")
    rec.calibration({"id": "carm-1", "sha256": "ab" * 32})
    rec.plan(plan)
    rec.stage("contours")
    rec.contours("view1", {"bone": np.random.default_rng(0).random((40, 2)) * 60,
                           "pin1": np.zeros((5, 2)), "pin2": np.ones((7, 2))}, "extracted")
    rec.stage("solve")
    poses = dict.fromkeys((view_key(0), pin_key("pin1"), pin_key("pin2")), plan.landmarks.T_tibia_anat())
    for k, cost in enumerate((10.0, 4.0, 3.5)):
        rec.iteration("joint", IterationInfo(k, cost, {"E_rp": cost / 2}, 1e-3,
                                             State(poses, np.zeros((0, 3)))))
    rec.stage("results")
    rec.result(result)
    rec.close()


def test_a_recording_reads_back_stage_by_stage(tmp_path, plan):
    path = tmp_path / "recording.rrd"
    result = {"case_id": "case-x", "status": "not_measured", "angles": None}
    _record(path, plan, result)
    rec = read_recording(path)
    assert rec.recording_id == "case-x-run-y"
    assert rec.texts["pipeline/stages"] == ["frames: 1 view", "calibration: carm-1", "contours",
                                            "solve", "results"]
    assert rec.views() == ["view1"]
    assert rec.points == {"views/view1/contours/bone": 40, "views/view1/contours/pin1": 5,
                          "views/view1/contours/pin2": 7}
    assert rec.scalars["solver/cost"] == [10.0, 4.0, 3.5]
    assert rec.documents["views/view1/encoder"]["initialisation"] == "encoders"
    assert rec.result == result and rec.documents["calibration"]["id"] == "carm-1"
    # Meshes come back exactly as float32 vertices and the same triangles.
    assert np.array_equal(rec.meshes["plan/tibia"].faces, plan.tibia.faces)
    assert np.array_equal(rec.meshes["plan/tibia"].vertices,
                          plan.tibia.vertices.astype(np.float32).astype(float))


def test_check_names_every_difference(tmp_path, plan):
    path = tmp_path / "recording.rrd"
    result = result_document(False, reason="r")
    _record(path, plan, result)
    rec = read_recording(path)
    assert check_recording(rec, MeasurementResult.from_document(result)) == []
    changed = {**result, "reason": "other",
               "sources": [{**result["sources"][0], "sop_instance_uid": "1.3"}]}
    problems = check_recording(rec, MeasurementResult.from_document(changed))
    assert any(p.startswith("reason:") for p in problems)
    assert "source SOP Instance UIDs differ" in problems


def test_unreadable_recordings_are_refused_clearly(tmp_path):
    with pytest.raises(ValueError, match="no such recording"):
        read_recording(tmp_path / "none.rrd")
    junk = tmp_path / "junk.rrd"
    junk.write_bytes(b"not a recording at all")
    with pytest.raises(ValueError, match="cannot be read as a rerun recording"):
        read_recording(junk)


def test_a_runs_bone_edge_searches_read_back_through_its_calibration(tmp_path):
    """A run that sought the bone's edges near the model records each view's search, and
    the replay rebuilds it through the recorded calibration: the same edges are found."""
    camera = default_camera()
    distortion = default_distortion(camera)
    v, u = np.mgrid[0:camera.height, 0:camera.width].astype(np.float32)
    disk = np.clip(1.0 - np.hypot(u - 500.0, v - 520.0) / 200.0, 0.0, None) ** 0.5
    search = replace(BoneEdgeSearch.of_frame(disk.astype(np.float32), np.ones(disk.shape, bool), 0.001, 0.0),
                     distort=distortion.distort, undistort=distortion.undistort)
    path = tmp_path / "recording.rrd"
    rec = CaseRecorder(path, "case-x", "run-y")
    rec.calibration(calibration_document(camera, "carm-1", "test", distortion))
    rec.bone_edge_searches({"view1": search.to_json()})
    rec.close()
    searches = recorded_edge_searches(read_recording(path))
    assert list(searches) == ["view1"]
    again = searches["view1"]
    footprint = np.zeros(disk.shape, np.uint8)
    cv2.circle(footprint, (500, 520), 205, 1, -1)
    edges, share = search(footprint, 12.0)
    edges_again, share_again = again(footprint, 12.0)
    assert len(edges) > 100 and np.array_equal(edges, edges_again) and share == share_again
