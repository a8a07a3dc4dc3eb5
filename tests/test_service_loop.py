"""The re-measurement loop in one process: pin sets, numbered runs, status objects, robust
outputs and repeatable runs, on frames of the phantom rendered by the simulated theatre.

The views are initialised from their DICOM positioner angles (no encoder link), the pipeline
runs for real (contour extraction, joint solve, SR and SC), the sender has no destination.
"""

from __future__ import annotations

import copy
import datetime as dt
import json
import shutil
import subprocess
from dataclasses import replace

import numpy as np
import pydicom
import pytest
from service_testing import count_decoding, result_document, small_frame

from slamtka.drivers.kinematics import CArmKinematics
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.cases import CaseAssembler
from slamtka.service.config import SenderConfig
from slamtka.service.decoded import DecodedFrames
from slamtka.service.dicom_sc import ScOverlay, build_sc, render_overlay, wrap_text
from slamtka.service.dicom_sr import build_sr
from slamtka.service.frames import encode_frame
from slamtka.service.headers import sanitised_header
from slamtka.service.pinsets import PinSetStore, pin_disagreement_px
from slamtka.service.plans import PlanStore
from slamtka.service.poses import ViewGeometry
from slamtka.service.results import MeasurementResult
from slamtka.service.sender import Sender
from slamtka.service.spool import Spool
from slamtka.service.workflow import Workflow, write_request
from slamtka.sim.theatre import Theatre

pytest.importorskip("slamtka.solver.imaging.calibration")
_WHEN = dt.datetime(2026, 5, 6, 7, 8, 9, tzinfo=dt.UTC)


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """The phantom's frames: a case, its pins seen again unmoved, and turned by 2 deg."""
    th = Theatre(tmp_path_factory.mktemp("frames"), (-30.0, 30.0))
    calibration_path = th.prepare()
    case = th.make_case(0)
    again = th.repin(case, "ml", 0.0)
    turned = th.repin(case, "ap", 2.0)
    return th, calibration_path, case, again, turned


class Loop:
    """A spool, cases, the pipeline and the workflow in ``root`` (no network)."""

    def __init__(self, root, th: Theatre, calibration_path, new_set_on_new_series=False):
        from slamtka.service.pipeline import Pipeline
        from slamtka.solver.imaging.calibration_file import load_calibration

        self.root = root
        self.spool = Spool(root / "spool")
        geometry = ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)
        self.pipeline = Pipeline(self.spool, PlanStore(th.root / "plans"),
                                 load_calibration(calibration_path), geometry, root / "output")
        self.assembler = CaseAssembler(self.spool, geometry, 15.0, 6)
        self.audit = AuditLog(root / "audit.jsonl")
        sender = Sender("SLAMTKA", [], SenderConfig(), root / "queue", self.audit)
        self.workflow = Workflow(self.pipeline, sender, self.audit, root,
                                 min_separation_deg=15.0, max_views=6,
                                 new_set_on_new_series=new_set_on_new_series)

    def add(self, frame, minutes: int = 0):
        frame = replace(frame, acquisition_datetime=_WHEN + dt.timedelta(minutes=minutes))
        entry, _ = self.spool.store(encode_frame(frame))
        case, _ = self.assembler.add(entry)
        return case, self.workflow.place(case, case.views[frame.sop_instance_uid])

    def run(self, case, rerun: bool = False):
        views = self.workflow.selection(case)
        run_id, measurement, triggered = self.workflow.begin_run(case, views, rerun)
        outcome = self.pipeline.run(case, views, run_id=run_id, measurement=measurement,
                                    triggered=triggered)
        self.workflow.finish_run(case, run_id, outcome.result)
        return outcome

    def events(self, name: str) -> list[dict]:
        return [e for e in read_audit(self.audit.path) if e["event"] == name]


def _statuses(loop: Loop) -> list[str]:
    return [e["situation"] for e in loop.events("status_sent")]


def test_turned_pins_start_a_new_set_measured_from_its_own_views(rendered, tmp_path):
    th, calibration, case, again, turned = rendered
    loop = Loop(tmp_path, th, calibration)
    c, due = loop.add(case.frames[0])
    assert not due and _statuses(loop) == ["waiting"]  # the display hears: second view needed
    c, due = loop.add(case.frames[1], 1)
    assert due
    first = loop.run(c).result.to_document()
    assert first["status"] == "measured", first["reasons"]
    assert first["measurement"]["pin_set"] == 1 and first["measurement"]["number"] == 1
    assert first["measurement"]["previous"] is None
    assert 0 < first["measurement"]["pin_misfit_px"] < 1.0

    # The same pins seen again: the view joins the set (tested against its pins).
    c, due = loop.add(again.frames[0], 2)
    assert due and loop.events("pin_check")[-1]["offset_px"] < 1.0
    assert loop.workflow.store.get(c.case_id).current.number == 1
    second = loop.run(c).result.to_document()
    assert second["measurement"]["number"] == 2 and len(second["sources"]) == 3

    # Turned by 2 deg about the AP axis (CTR +2): a new set, which waits for its second view.
    c, due = loop.add(turned.frames[0], 3)
    assert not due
    started = loop.events("pin_set_started")
    assert len(started) == 1 and "pins moved" in started[0]["reason"]
    assert _statuses(loop)[-1] == "waiting"
    c, due = loop.add(turned.frames[1], 4)
    assert due
    views = loop.workflow.selection(c)
    assert {v.sop_instance_uid for v in views} == {f.sop_instance_uid for f in turned.frames}
    third = loop.run(c).result.to_document()
    assert third["status"] == "measured", third["reasons"]
    assert abs(third["angles"]["ctr_deg"] - turned.truth_ctr_deg) < 0.5
    assert abs(third["angles"]["str_deg"] - turned.truth_str_deg) < 0.5
    m = third["measurement"]
    assert (m["pin_set"], m["number"]) == (2, 1) and m["started_by"].startswith("pins moved")
    assert m["previous"]["pin_set"] == 1 and m["previous"]["number"] == 2
    assert m["previous"]["ctr_deg"] == pytest.approx(second["angles"]["ctr_deg"])

    # The SR says the same in words.
    dump = subprocess.run(["dsrdump", "+Pl", str(tmp_path / "output" / c.case_id /
                                                  third["run_id"] / "sr.dcm")],
                          capture_output=True, text=True)
    assert '"Measurement history")="pin set 2, measurement 1 (pins moved' in dump.stdout
    assert "previous: pin set 1, measurement 2: CTR" in dump.stdout

    # A restart rebuilds the same sets from disk.
    reloaded = PinSetStore.load(tmp_path / "pinsets", c.case_id)
    assert [len(s.views) for s in reloaded.sets] == [3, 2]


def test_an_operator_starts_a_new_set_and_reruns_without_new_views(rendered, tmp_path):
    th, calibration, case, again, _ = rendered
    loop = Loop(tmp_path, th, calibration)
    loop.add(case.frames[0])
    c, _ = loop.add(case.frames[1], 1)
    first = loop.run(c).result.to_document()
    write_request(tmp_path / "requests", "new-set", c.case_id, "dr who")
    write_request(tmp_path / "requests", "rerun", c.case_id, "dr who")
    write_request(tmp_path / "requests", "rerun", "case-unknown", "dr who")
    todo = loop.workflow.take_requests(loop.assembler.cases)
    assert [(case_.case_id, kind) for case_, kind in todo] == [(c.case_id, "rerun")]
    assert not list((tmp_path / "requests").glob("*.json"))  # taken
    assert [e["known_case"] for e in loop.events("operator_request")] == [True, True, False]

    rerun = loop.run(c, rerun=True).result.to_document()
    assert rerun["run_id"] != first["run_id"]  # a new run: new UIDs, never the old ones reused
    assert rerun["measurement"]["number"] == 2 and rerun["status"] == "measured"
    assert rerun["outputs"]["sr_sop_instance_uid"] != first["outputs"]["sr_sop_instance_uid"]

    c, due = loop.add(again.frames[0], 2)  # unmoved pins, but the operator asked: a new set
    assert not due and loop.workflow.store.get(c.case_id).current.started_by == \
        "operator (dr who)"


def test_a_repeated_run_rebuilds_identical_dicom_objects(rendered, tmp_path):
    th, calibration, case, _, _ = rendered
    loop = Loop(tmp_path, th, calibration)
    loop.add(case.frames[0])
    c, _ = loop.add(case.frames[1], 1)
    outcome = loop.run(c)
    folder = outcome.folder
    before = {p.name: p.read_bytes() for p in folder.glob("*.dcm")}
    (folder / "result.json").unlink()  # a crash before the run completed
    loop.pipeline._extracted.clear()  # a new process: nothing cached
    loop.spool.decoded = DecodedFrames(loop.spool)
    again = loop.run(c)
    assert again.result.run_id == outcome.result.run_id
    after = {p.name: p.read_bytes() for p in folder.glob("*.dcm")}
    assert sorted(after) == ["sc-view1.dcm", "sc-view2.dcm", "sr.dcm"]
    assert after == before  # byte for byte: tracking UIDs and dates derive from the run
    sr = pydicom.dcmread(folder / "sr.dcm")
    triggered = dt.datetime.fromisoformat(
        loop.workflow.store.get(c.case_id).sets[0].runs[0]["triggered"])
    assert sr.ContentDate == triggered.strftime("%Y%m%d")
    assert sr.InstanceCreationTime == triggered.strftime("%H%M%S.%f")


def test_a_spool_from_before_decoding_once_starts_and_is_measured(rendered, tmp_path,
                                                                   monkeypatch):
    """Sidecars holding the pairing alone, as before the decoded facts were kept: each
    instance is decoded once more, its sidecar rewritten (pairing kept), the case measured."""
    th, calibration, case, _, _ = rendered
    spool = Spool(tmp_path / "spool")
    geometry = ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)
    pairings = {}
    for k, frame in enumerate(case.frames[:2]):
        frame = replace(frame, acquisition_datetime=_WHEN + dt.timedelta(minutes=k))
        entry, _ = spool.store(encode_frame(frame))
        pairings[entry.sidecar.name] = geometry.pair(frame.header()).to_json()
        spool.write_sidecar(entry, pairings[entry.sidecar.name])
    calls = count_decoding(monkeypatch)
    loop = Loop(tmp_path, th, calibration)  # the service started on the old spool
    for entry in loop.spool.entries():
        c, _ = loop.assembler.add(entry)
        due = loop.workflow.place(c, c.views[entry.sop_instance_uid])
    assert due
    result = loop.run(c).result
    assert result.measured, result.reasons
    assert calls == {"decode_frame": 2, "decode_pixels": 2}  # once each, pixels included
    for name, pairing in pairings.items():
        sidecar = json.loads((tmp_path / "spool" / "instances" / name).read_text())
        assert sidecar["pairing"] == pairing and "frame" in sidecar


@pytest.mark.parametrize("attribute,value", [
    ("PatientBirthDate", "00000000"), ("PatientSex", "U"), ("PatientSex", "X"),
    ("PatientSex", "f"), ("PatientName", ["Doe^Jane", "Roe^Jane"]), ("StudyDate", "2024"),
    ("StudyTime", "1"), ("Laterality", "B"), ("Laterality", "U")])
def test_header_values_common_on_real_systems_still_build_the_results(attribute, value,
                                                                      tmp_path):
    ds = encode_frame(small_frame())
    setattr(ds, attribute, value)
    if attribute != "Laterality":  # (build_sc itself passes on only L and R)
        with pytest.raises((ValueError, TypeError)):  # the builders refuse the value as received ...
            build_sr([ds], None, side=None, version="t", series_uid="1.2.3",
                     sop_instance_uid="1.2.3.4",
                     uid_for=lambda what: "1.2.3.5", content_datetime=_WHEN)
    received = copy.deepcopy(ds)
    clean = sanitised_header(ds)  # ... and accept it sanitised; the received one is unchanged
    assert ds == received
    build_sr([clean], None, side=None, version="t", series_uid="1.2.3", sop_instance_uid="1.2.3.4",
             uid_for=lambda what: "1.2.3.5", content_datetime=_WHEN)
    build_sc(clean, np.zeros((8, 8, 3), np.uint8), series_uid="1.2.3", sop_instance_uid="1.2.4",
             instance_number=1, orientation=None, content_datetime=_WHEN)
    expected = {"PatientSex": {"U": "", "X": "", "f": "F"}.get(str(value)),
                "PatientName": "Doe^Jane"}.get(attribute, "")
    if attribute == "Laterality":
        assert "Laterality" not in clean
    else:
        assert str(clean[attribute].value) == expected


def test_a_run_with_unusual_headers_measures_and_sends_the_report_first(
        rendered, tmp_path, monkeypatch):
    th, calibration, case, _, _ = rendered
    loop = Loop(tmp_path, th, calibration)
    odd = [replace(f, patient_name="Doe^Jane") for f in case.frames]
    for k, frame in enumerate(odd):
        ds = encode_frame(replace(frame, acquisition_datetime=_WHEN + dt.timedelta(minutes=k)))
        ds.PatientBirthDate, ds.PatientSex, ds.StudyTime = "00000000", "u", "7"
        loop.spool.store(ds)
    for entry in loop.spool.entries():
        c, _ = loop.assembler.add(entry)
        loop.workflow.place(c, c.views[entry.sop_instance_uid])
    seen: list[list[str]] = []
    views = loop.workflow.selection(c)
    outcome = loop.pipeline.run(c, views, on_output=lambda obj: seen.append(
        sorted(p.name for p in obj.path.parent.glob("*.dcm"))))
    assert outcome.result.status == "measured"
    assert outcome.result.outputs.dicom_error is None
    # The report is handed to the sender once on disk, before the overlays are built; the
    # overlays once both are on disk.
    assert seen == [["sr.dcm"], ["sc-view1.dcm", "sc-view2.dcm", "sr.dcm"],
                    ["sc-view1.dcm", "sc-view2.dcm", "sr.dcm"]]

    # An overlay the builder fails anyway: result.json is still written, the report was sent
    # and no overlay is.
    import slamtka.service.pipeline as pipeline_module

    def broken(*args, **kwargs):
        raise ValueError("a value the builder refuses")

    monkeypatch.setattr(pipeline_module, "build_sc", broken)
    (outcome.folder / "result.json").unlink()
    seen.clear()
    failed = loop.pipeline.run(c, views, on_output=lambda obj: seen.append(obj))
    doc = json.loads((failed.folder / "result.json").read_text())
    assert doc["status"] == "measured" and "a value the builder refuses" in \
        doc["outputs"]["dicom_error"]
    assert [obj.kind for obj in seen] == ["sr"]
    loop.workflow.begin_run(c, views)
    loop.workflow.finish_run(c, doc["run_id"], MeasurementResult.from_document(doc))
    assert loop.events("output_failed")[0]["run_id"] == doc["run_id"]

    # A report the builder fails: nothing is sent.
    monkeypatch.setattr(pipeline_module, "build_sr", broken)
    (outcome.folder / "result.json").unlink()
    seen.clear()
    failed = loop.pipeline.run(c, views, on_output=lambda obj: seen.append(obj))
    assert failed.result.outputs.dicom_error and seen == []


def test_views_that_cannot_start_a_measurement_are_told_to_the_display(rendered, tmp_path):
    th, calibration, case, _, _ = rendered
    loop = Loop(tmp_path, th, calibration)
    no_geometry = replace(case.frames[0], primary_angle_deg=None, secondary_angle_deg=None,
                          sop_instance_uid="1.2.826.0.1.3680043.99.3")
    c, due = loop.add(no_geometry)
    assert not due and _statuses(loop) == ["unusable"]
    blank = replace(case.frames[1], pixels=np.full_like(case.frames[1].pixels, 1000),
                    sop_instance_uid="1.2.826.0.1.3680043.99.4")
    c, due = loop.add(blank, 1)
    assert not due and _statuses(loop)[-1] == "no_pins"
    assert loop.workflow.store.get(c.case_id).sets == []  # a view without pins starts nothing
    close = replace(case.frames[0], primary_angle_deg=case.frames[0].primary_angle_deg + 5.0,
                    sop_instance_uid="1.2.826.0.1.3680043.99.1")
    loop.add(case.frames[0], 2)
    c, due = loop.add(close, 3)
    assert not due and _statuses(loop)[-2:] == ["waiting", "too_close"]
    nobody = replace(case.frames[0], patient_id="NO-PLAN", sop_instance_uid="1.2.826.0.1.3680043.99.2")
    c, due = loop.add(nobody, 4)
    assert not due and _statuses(loop)[-1] == "no_plan"
    # Each status is an SR and an SC in the case's study, saying what to do.
    folder = tmp_path / "output" / c.case_id
    (status,) = [p for p in folder.iterdir() if p.name.startswith("status-")]
    sr = pydicom.dcmread(status / "sr.dcm")
    assert sr.StudyInstanceUID == case.study_uid and sr.SeriesDescription == "slamtka status"
    texts = {i.ConceptNameCodeSequence[0].CodeValue: str(i.TextValue)
             for i in sr.ContentSequence if i.ValueType == "TEXT"}
    assert texts["SVCSTATUS"].startswith("No plan for this patient")
    assert "re-run the case" in texts["NEXTSTEP"]
    assert pydicom.dcmread(status / "sc.dcm").BurnedInAnnotation == "YES"


def test_overlay_text_wraps_and_is_never_cut():
    long = "no plan for patient 'P-0000000001', right side: " + "word " * 40
    lines = wrap_text([long], 236, 1)
    assert len(lines) > 3 and " ".join(lines).split() == long.split()
    import cv2

    assert all(cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, 0.6, 3)[0][0] <= 236
               for line in lines)
    rgb = render_overlay(np.zeros((256, 256), np.uint16), ScOverlay({}, text=[long]))
    assert rgb[:, -8:].max() == 0  # nothing drawn into the right margin


def test_pin_disagreement_grows_with_a_turn_of_the_pins(rendered):
    from slamtka.drivers.kinematics import initial_view_poses
    from slamtka.solver.imaging.calibration_file import load_calibration
    from slamtka.solver.imaging.contours import extract_contours
    from slamtka.solver.measurement import pin_axis_points

    th, calibration_path, case, again, turned = rendered
    calibration = load_calibration(calibration_path)
    axes = [pin_axis_points(T, th.plan.pin_length())[[0, -1]] for T in case.truth_T_tibia_pin]
    (T,), _ = initial_view_poses(th.kinematics, [th.script.views[0]], case.setup)

    def offset(frame) -> float:
        found = extract_contours(frame.pixels).as_dict()
        return pin_disagreement_px(calibration.camera, T, axes, [
            calibration.undistort_points(found[label]) for label in ("pin1", "pin2")])

    assert offset(again.frames[0]) < 0.6
    assert offset(turned.frames[0]) > 1.2
    assert pin_disagreement_px(calibration.camera, T, axes, [np.zeros((0, 2))] * 2) == np.inf


def test_dates_and_names_keep_their_valid_values():
    ds = encode_frame(small_frame())
    ds.PatientBirthDate, ds.PatientSex, ds.StudyTime = "19700101", "M", "101112.5"
    clean = sanitised_header(copy.deepcopy(ds))
    assert (clean.PatientBirthDate, clean.PatientSex, clean.StudyTime) == (
        "19700101", "M", "101112.5")
    assert clean.Laterality == "R"


needs_dsrdump = pytest.mark.skipif(shutil.which("dsrdump") is None, reason="DCMTK not installed")
test_turned_pins_start_a_new_set_measured_from_its_own_views = needs_dsrdump(
    test_turned_pins_start_a_new_set_measured_from_its_own_views)


def test_a_configured_rule_starts_a_set_on_each_new_series(rendered, tmp_path):
    th, calibration, case, again, _ = rendered
    loop = Loop(tmp_path, th, calibration, new_set_on_new_series=True)
    loop.add(case.frames[0])
    c, due = loop.add(case.frames[1], 1)
    assert due
    loop.run(c)
    assert again.frames[0].series_uid != case.frames[0].series_uid
    c, due = loop.add(again.frames[0], 2)  # the same pins, but a new series: a new set
    assert not due
    sets = loop.workflow.store.get(c.case_id).sets
    assert [s.started_by for s in sets] == ["first view", "new DICOM series"]
    assert not loop.events("pin_check")  # the rule decided; no comparison needed


def test_the_overlay_and_report_say_what_changed_since_the_previous_measurement():
    from slamtka.service.display import change_line
    from slamtka.service.pipeline import Pipeline

    doc = result_document(
        angles={"ctr_deg": 0.4, "str_deg": 5.1, "ctr_sigma_deg": 0.1, "str_sigma_deg": 0.2},
        target={"ctr_deg": 0.0, "str_deg": 3.0, "tolerance_deg": 3.0},
        measurement={"pin_set": 2, "number": 1, "started_by": "pins moved",
                     "previous": {"run_id": "r1", "pin_set": 1, "number": 1,
                                  "ctr_deg": 0.4, "str_deg": 6.7, "verdict": "fail"}})
    result = MeasurementResult.from_document(doc)
    assert result.measurement is not None
    line = change_line(result.measurement.previous, result)
    assert line == "STR +6.7 -> +5.1, now within +-3 (was outside)"
    lines = Pipeline._summary_lines(result, 15.0)
    assert "Pin set 2, measurement 1" in lines and line in lines
    notes = dict(Pipeline._notes(result, 15.0))
    assert notes["history"].startswith("pin set 2, measurement 1 (pins moved); previous: pin set "
                                       "1, measurement 1: CTR +0.4, STR +6.7 deg, fail")
    assert change_line(None, result) is None
