"""Results and their documents against the published schema; SR and SC against dciodvfy and
dsrdump."""

from __future__ import annotations

import copy
import dataclasses
import datetime as dt
import json
import shutil
import subprocess

import highdicom as hd
import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid
from service_testing import result_document, small_frame

from slamtka.service.dicom_sc import ScOverlay, build_sc, patient_orientation, render_overlay
from slamtka.service.dicom_sr import (
    SrGeometry,
    SrMeasurement,
    build_sr,
    tibia_frame_of_reference_uid,
)
from slamtka.service.frames import encode_frame
from slamtka.service.pipeline import plane_polygon, result_uid
from slamtka.service.refusals import CODES, Refusal, RefusalCode, solver_refusal
from slamtka.service.results import (
    MeasurementResult,
    build_result,
    result_schema,
    validate_result,
)
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import SimulationConfig, simulate_case
from slamtka.solver.gates import Why
from slamtka.solver.measurement import angle_covariance, fit_resection_plane, pin_axis_points
from slamtka.solver.plan import Target
from slamtka.solver.slam import InitialGuess, SolveOutcome, SolveStart

_WHEN = dt.datetime(2026, 3, 4, 10, 11, 12, 345000, tzinfo=dt.UTC)
needs_dicom3tools = pytest.mark.skipif(shutil.which("dciodvfy") is None or
                                       shutil.which("dsrdump") is None,
                                       reason="dicom3tools/DCMTK not installed")


@pytest.fixture(scope="module")
def truth_case():
    """A simulated case and an outcome at its true poses (no solve needed for documents)."""
    plan = phantom_plan("right", Target(0.0, 3.0, 3.0))
    case = simulate_case(plan, SimulationConfig(seed=5))
    pins = case.truth_T_tibia_pin
    plane = fit_resection_plane(pins, plan.pin_length(), plan.landmarks)
    cov = angle_covariance(pins, np.eye(12) * 1e-6, plan.pin_length(), plan.landmarks)
    outcome = SolveOutcome("measured", "", None, case.truth_T_cam_tibia, pins, plane, cov,
                           {"E_rp": 1.0}, {"E_rp": 10.0}, 12, 0.4, True, "converged",
                           {"view1/bone": 300})
    return plan, case, outcome


def _sources(n: int) -> list[dict]:
    return [{"view_id": f"view{k}", "sop_instance_uid": generate_uid(), "sop_class_uid":
             "1.2.840.10008.5.1.4.1.1.12.1", "series_instance_uid": generate_uid(),
             "acquisition_datetime": "2025-03-14T09:26:53.589793+00:00",
             "positioner": {"primary_angle_deg": -30.0, "secondary_angle_deg": 0.0,
                            "sid_mm": 1000.0, "sod_mm": 620.0},
             "initialisation": "dicom_positioner", "encoder_reading": None, "angle_check": None,
             "clock": None, "contours": "extracted", "used": True, "problem": None}
            for k in range(1, n + 1)]


def _result(plan, case, outcome) -> MeasurementResult:
    return build_result(
        case_id="case-0123456789abcdef", run_id="0123456789abcdef",
        case={"patient_id": "P-1", "study_instance_uid": generate_uid(), "laterality": "R"},
        sources=_sources(2), outcome=outcome, method="slam-noenc", plan=plan, views=case.views,
        calibration={"id": "carm-1", "sha256": "ab" * 32},
        initial=InitialGuess(tuple(case.initial.T_cam_tibia), tuple(case.initial.T_tibia_pin)),
        refusal=None, reasons=[], timings={"solve_s": 0.4, "total_s": 0.9},
        outputs={"folder": "/out", "recording": "/out/recording.rrd",
                 "sr_sop_instance_uid": generate_uid(), "sc_sop_instance_uids": {}})


def _document(plan, case, outcome) -> dict:
    return _result(plan, case, outcome).to_document()


def test_the_published_schema_is_a_valid_json_schema():
    import jsonschema

    jsonschema.Draft202012Validator.check_schema(result_schema())


def test_measured_document_validates_and_carries_the_measurement(truth_case):
    plan, case, outcome = truth_case
    doc = _document(plan, case, outcome)
    assert doc["status"] == "measured" and doc["reason"] is None
    assert doc["angles"]["ctr_deg"] == pytest.approx(case.truth_ctr_deg, abs=1e-9)
    assert doc["angles"]["str_deg"] == pytest.approx(case.truth_str_deg, abs=1e-9)
    expected = ("pass" if abs(case.truth_ctr_deg) <= 3 and abs(case.truth_str_deg - 3) <= 3
                else "fail")
    assert doc["verdict"] == expected
    assert "varus" in doc["sign_convention"]["CTR"]
    assert doc["calibration"]["sha256"] == "ab" * 32 and len(doc["sources"]) == 2
    assert doc["solver"]["method"] == "slam-noenc"  # the configured method, not a default
    json.loads(json.dumps(doc))  # plain JSON all the way down


def test_refused_document_validates_with_reasons_and_no_angles():
    doc = build_result(case_id="case-x", run_id="0123456789abcdef",
                       case={"patient_id": "P-2", "study_instance_uid": "1.2.3", "laterality": None},
                       sources=_sources(2), outcome=None, method="slam", plan=None, views=[],
                       calibration=None,
                       initial=None, refusal=Refusal.of(RefusalCode.NO_PLAN,
                                                        "no plan for patient 'P-2'"),
                       reasons=["view3: not initialised, left out (no reading)"],
                       timings={"total_s": 0.1},
                       outputs={"folder": "/o", "recording": "/o/r.rrd",
                                "sr_sop_instance_uid": "1.2.3.4", "sc_sop_instance_uids": {}}
                       ).to_document()
    assert doc["status"] == "not_measured" and doc["verdict"] == "not_measured"
    assert doc["angles"] is None and doc["reason"] == "no plan for patient 'P-2'"
    assert doc["reasons"] == ["no plan for patient 'P-2'",
                              "view3: not initialised, left out (no reading)"]
    assert doc["refusal"] == {"code": "no_plan", "detail": "no plan for patient 'P-2'",
                              "may_restart": True}


def test_measured_document_has_no_refusal(truth_case):
    assert _document(*truth_case)["refusal"] is None


def test_a_solver_refusal_carries_the_kind_the_solver_named():
    refusal = solver_refusal(Why.PINS_INDISTINCT, "the two pins cannot be told apart in view view2")
    assert (refusal.code, refusal.may_restart) == (Why.PINS_INDISTINCT, False)
    assert solver_refusal(None, "something new").code is RefusalCode.OTHER


def test_the_schema_publishes_every_refusal_code():
    codes = result_schema()["properties"]["refusal"]["properties"]["code"]["enum"]
    assert sorted(codes) == sorted(CODES)


def test_the_schema_publishes_every_start_a_solve_can_have(truth_case):
    """A solve restarted from a view the encoders carried was written as its start, which
    the schema did not list: such a measured result failed its own validation."""
    assert sorted(result_schema()["properties"]["solver"]["properties"]["start"]["enum"]) == sorted(SolveStart)
    plan, case, outcome = truth_case
    for start in SolveStart:
        validate_result(_document(plan, case, dataclasses.replace(outcome, initialisation=start)))


@pytest.mark.parametrize("tamper,where", [
    (lambda d: d.pop("sources"), "(root)"),
    (lambda d: d.update(surprise=1), "(root)"),
    (lambda d: d["angles"].update(ctr_deg="3"), "angles"),
    (lambda d: d.update(status="maybe"), "status"),
    (lambda d: d["poses"]["T_tibia_pin"].pop(), "poses/T_tibia_pin"),
    (lambda d: d["sources"][0].update(sop_instance_uid="1.2.x"), "sources/0/sop_instance_uid"),
])
def test_schema_refuses_broken_documents_naming_the_place(truth_case, tamper, where):
    doc = copy.deepcopy(_document(*truth_case))
    tamper(doc)
    with pytest.raises(ValueError) as err:
        validate_result(doc)
    assert where in str(err.value)


def test_a_result_is_frozen_and_gives_back_the_document_it_was_made_from(truth_case):
    built = _result(*truth_case)
    doc = built.to_document()
    again = MeasurementResult.from_document(doc)
    assert again == built
    assert json.dumps(again.to_document()) == json.dumps(doc)  # key order included
    with pytest.raises(dataclasses.FrozenInstanceError):
        built.status = "not_measured"  # type: ignore[misc]
    doc["angles"]["ctr_deg"] = 99.0  # the object keeps its own copy of the document
    assert built.angles is not None and built.angles.ctr_deg != 99.0
    for measured in (True, False):
        stored = result_document(measured)
        assert MeasurementResult.from_document(stored).to_document() == stored


def test_a_refused_result_reads_back_its_refusal_and_side():
    result = MeasurementResult.from_document(result_document(False, inputs=None))
    assert result.refusal == solver_refusal(Why.PINS_INDISTINCT,
                                            "the two pins cannot be told apart in view view2")
    assert (result.angles, result.measured, result.side) == (None, False, "right")


def test_a_result_says_which_member_breaks_the_schema():
    with pytest.raises(ValueError, match="deviation/within_tolerance") as err:
        MeasurementResult.from_document(result_document(
            deviation={"ctr_deg": 0.0, "str_deg": 0.0, "within_tolerance": "yes"}))
    assert "breaks the schema" in str(err.value)
    with pytest.raises(ValueError, match="measurement/previous"):
        MeasurementResult.from_document(result_document(measurement={
            "pin_set": 1, "number": 2, "started_by": "first view", "previous": {"run_id": "r"}}))


def test_completing_a_result_keeps_the_rest():
    result = MeasurementResult.from_document(result_document())
    done = result.completed({"total_s": 1.5, "results_s": 0.2}, "ValueError: refused")
    doc = done.to_document()
    assert doc["timings"] == {"total_s": 1.5, "results_s": 0.2}
    assert doc["outputs"]["dicom_error"] == "ValueError: refused"
    assert "dicom_error" not in result.to_document()["outputs"]  # absent, not null
    MeasurementResult.from_document(doc)
    assert {**doc, "timings": None, "outputs": None} == {
        **result.to_document(), "timings": None, "outputs": None}


def _dciodvfy_errors(path) -> list[str]:
    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    return [line for line in (out.stdout + out.stderr).splitlines() if line.startswith("Error")]


@needs_dicom3tools
def test_sr_passes_dciodvfy_and_reads_back_with_dsrdump(truth_case, tmp_path):
    plan, case, outcome = truth_case
    result = _result(plan, case, outcome)
    doc = result.to_document()
    evidence = [encode_frame(small_frame()) for _ in range(2)]
    for ds in evidence[1:]:
        ds.StudyInstanceUID = evidence[0].StudyInstanceUID
    axes = [pin_axis_points(T, plan.pin_length())[[0, -1]] for T in outcome.T_tibia_pin]
    geometry = SrGeometry(tibia_frame_of_reference_uid("cd" * 32),
                          plane_polygon(outcome.plane.point, outcome.plane.normal), axes,
                          [88.0, 91.0], "right")
    sr = build_sr(evidence, SrMeasurement(result.angles, result.deviation, geometry),
                  side=result.side, version=result.software_version, series_uid=generate_uid(),
                  sop_instance_uid=generate_uid(),
                  uid_for=lambda what: result_uid("case-x", "run", what), content_datetime=_WHEN)
    path = tmp_path / "sr.dcm"
    sr.save_as(path, enforce_file_format=True)
    assert _dciodvfy_errors(path) == []
    dump = subprocess.run(["dsrdump", str(path)], capture_output=True, text=True, timeout=60)
    assert dump.returncode == 0, dump.stderr
    text = dump.stdout
    assert "Comprehensive 3D SR" in text and "Imaging Measurement Report" in text
    assert f'"Coronal tibial resection angle")="{doc["angles"]["ctr_deg"]:.6g}'[:45] in text
    assert "(deg,UCUM" in text and "Standard Deviation" in text and "POLYGON" in text
    assert text.count("POLYLINE") == 2 and "Trocar pin 2" in text
    # highdicom parses it back to the same numbers
    back = hd.sr.Comprehensive3DSR.from_dataset(pydicom.dcmread(path))
    groups = back.content.get_planar_roi_measurement_groups()
    values = {(m.name.meaning, m.derivation is not None): m.value for m in groups[0].get_measurements()}
    assert values[("Coronal tibial resection angle", False)] == pytest.approx(doc["angles"]["ctr_deg"])
    assert values[("Sagittal tibial resection angle", True)] == pytest.approx(doc["angles"]["str_sigma_deg"])
    region = groups[0].roi
    assert region.frame_of_reference_uid == geometry.frame_of_reference_uid
    assert np.allclose(region.value, geometry.plane_polygon, atol=1e-3)


@needs_dicom3tools
def test_not_measured_sr_and_sc_pass_dciodvfy(tmp_path):
    frame = small_frame(pixels=np.random.default_rng(2).integers(0, 4000, (256, 256)).astype(np.uint16))
    source = encode_frame(frame)
    sr = build_sr([source], None, side="right", version="0.1.0", series_uid=generate_uid(),
                  sop_instance_uid=generate_uid(),
                  uid_for=lambda what: result_uid("case-x", "run", what), content_datetime=_WHEN,
                  notes=[("reason", "no plan for patient 'P-1', right side"),
                         ("action", "add the plan, then re-run the case")])
    sr.save_as(tmp_path / "sr.dcm", enforce_file_format=True)
    assert _dciodvfy_errors(tmp_path / "sr.dcm") == []
    dump = subprocess.run(["dsrdump", "+Pl", str(tmp_path / "sr.dcm")], capture_output=True,
                          text=True)
    assert "Not measured" in dump.stdout
    # The reason and what to do are content items, not only burned into the overlay.
    assert '"Reason not measured")="no plan for patient' in dump.stdout
    assert '"What to do next")="add the plan, then re-run the case"' in dump.stdout
    t = np.linspace(0, 2 * np.pi, 400)
    overlay = ScOverlay({"bone": np.c_[128 + 60 * np.cos(t), 128 + 90 * np.sin(t)]},
                        text=["NOT MEASURED", "no plan"])
    rgb = render_overlay(frame.pixels, overlay)
    assert rgb.shape == (256, 256, 3) and rgb.dtype == np.uint8
    assert np.all(rgb[128 + 90, 128] == (255, 220, 0))  # a contour pixel in the bone colour
    for orientation in (None, ("L", "F")):
        sc = build_sc(source, rgb, series_uid=generate_uid(), sop_instance_uid=generate_uid(),
                      instance_number=1, orientation=orientation, content_datetime=_WHEN)
        sc.save_as(tmp_path / "sc.dcm", enforce_file_format=True)
        assert _dciodvfy_errors(tmp_path / "sc.dcm") == []
        back = pydicom.dcmread(tmp_path / "sc.dcm")
        assert back.PatientID == frame.patient_id and back.StudyInstanceUID == frame.study_uid
        assert back.SourceImageSequence[0].ReferencedSOPInstanceUID == frame.sop_instance_uid
        assert np.array_equal(back.pixel_array, rgb)


def test_patient_orientation_letters_follow_the_camera_axes():
    # Camera x along the patient's left, y towards the feet: rows "L", columns "F".
    R = np.column_stack([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    assert patient_orientation(R) == ("L", "F")
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    R = np.column_stack([[c, s, 0.0], [0.0, 0.0, -1.0], [-s, c, 0.0]])
    assert patient_orientation(R) == ("RA", "F")
