"""``slamtka measure``: the service's pipeline offline on DICOM files, and its refusals."""

from __future__ import annotations

import json
from dataclasses import replace

import pydicom
import pytest

import slamtka.service.pipeline as pipeline
from slamtka.service.cli import main
from slamtka.solver.imaging.contours import ContourError


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("measure") / "case"
    assert main(["simulate", "--out", str(folder), "--images", "--seed", "2", "--patient-id", "PAT77",
                 "--patient-name", "DOE^JANE"]) == 0
    return folder


def _args(case, out, *frames, plan=None, calibration=None):
    frames = frames or (case / "frames" / "view1.dcm", case / "frames" / "view2.dcm")
    return ["measure", *map(str, frames), "--plan", str(plan or case / "plan"),
            "--calibration", str(calibration or case / "calibration.json"), "--out", str(out)]


def test_measure_writes_the_services_results_offline(case, tmp_path):
    ds = pydicom.dcmread(case / "frames" / "view1.dcm")
    assert ds.PatientID == "PAT77" and str(ds.PatientName) == "DOE^JANE"
    assert main(_args(case, tmp_path / "out")) == 0
    (result,) = (tmp_path / "out").glob("case-*/*/result.json")
    doc = json.loads(result.read_text())
    truth = json.loads((case / "ground_truth.json").read_text())
    assert doc["status"] == "measured" and doc["case"]["patient_id"] == "PAT77"
    assert abs(doc["angles"]["ctr_deg"] - truth["ctr_deg"]) < 1.0
    assert abs(doc["angles"]["str_deg"] - truth["str_deg"]) < 1.0
    names = {p.name for p in result.parent.iterdir()}
    assert {"sr.dcm", "sc-view1.dcm", "sc-view2.dcm", "recording.rrd"} <= names


def test_measure_refuses_bad_input_in_one_line_naming_the_file(case, tmp_path, capsys):
    not_dicom = tmp_path / "notes.dcm"
    not_dicom.write_text("not an image")
    other = tmp_path / "other.dcm"
    ds = pydicom.dcmread(case / "frames" / "view2.dcm")
    ds.PatientID = "SOMEONE-ELSE"
    ds.save_as(other)
    wrong_calibration = tmp_path / "calibration.json"
    doc = json.loads((case / "calibration.json").read_text())
    doc["camera"]["width"] = 512
    wrong_calibration.write_text(json.dumps(doc))
    view1 = case / "frames" / "view1.dcm"
    cases = [
        (_args(case, tmp_path / "a", view1, not_dicom), f"{not_dicom}: not a DICOM file"),
        (_args(case, tmp_path / "b", view1, other), f"{other}: Patient ID 'SOMEONE-ELSE'"),
        (_args(case, tmp_path / "c", plan=tmp_path / "no-plan"), f"{tmp_path / 'no-plan'}: no such plan"),
        (_args(case, tmp_path / "d", calibration=wrong_calibration), str(wrong_calibration)),
    ]
    for argv, message in cases:
        capsys.readouterr()
        assert main(argv) == 2, message
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, err


def _measured_with_view1_read_by(auto_read, case, tmp_path, monkeypatch) -> list[str]:
    """Run ``measure`` with view 1's own ("auto") extraction replaced by ``auto_read(pixels,
    config, **kwargs)``; assert the case measures and return the polarities asked for."""
    real = pipeline.extract_contours
    asked: list[str] = []
    view1 = pydicom.dcmread(case / "frames" / "view1.dcm").pixel_array

    def extract(pixels, config, **kwargs):
        asked.append(config.polarity)
        if config.polarity == "auto" and pixels.shape == view1.shape and (pixels == view1).all():
            return auto_read(real, pixels, config, **kwargs)
        return real(pixels, config, **kwargs)

    monkeypatch.setattr(pipeline, "extract_contours", extract)
    assert main(_args(case, tmp_path / "out")) == 0
    (result,) = (tmp_path / "out").glob("case-*/*/result.json")
    assert json.loads(result.read_text())["status"] == "measured"
    return asked


def test_a_frame_misread_inverted_is_extracted_again_as_its_partner_reads(case, tmp_path, monkeypatch):
    """The run reads a case's frames with one polarity: view 1 made to read inverted from
    weak cues (as a collimator blade's edge did in shutters seeds 14 and 23) is extracted
    again as view 2's clear reading says, and the case measures."""
    def misreading(real, pixels, config, **kwargs):
        found = real(pixels, replace(config, polarity="bright"), **kwargs)
        found.diagnostics["polarity_decisive"] = False
        return found

    assert _measured_with_view1_read_by(misreading, case, tmp_path, monkeypatch) == ["auto", "auto", "dark"]


def test_a_frame_whose_polarity_could_not_be_told_is_extracted_as_its_partner_reads(case, tmp_path,
                                                                                    monkeypatch):
    """View 1 made unreadable by its own cues (as the real tibia's operating-room seed 18
    showed no steel standing out) is extracted again with view 2's clear polarity, and the
    case measures instead of being refused for want of a view."""
    def unreadable(real, pixels, config, **kwargs):
        raise ContourError("the polarity of the frame cannot be told (no steel stands out); configure it")

    assert _measured_with_view1_read_by(unreadable, case, tmp_path, monkeypatch) == ["auto", "auto", "dark"]


def test_frames_of_a_flat_panels_larger_detector_are_measured(tmp_path):
    """A 2048 px detector over the same field (``simulate --detector-pixels``): the frames
    go through the service's pipeline at their own size (reduced for extraction only) and
    are measured; the SC shows them as they came."""
    folder = tmp_path / "case"
    assert main(["simulate", "--out", str(folder), "--images", "--seed", "2", "--detector-pixels", "2048"]) == 0
    assert pydicom.dcmread(folder / "frames" / "view1.dcm").Rows == 2048
    assert main(_args(folder, tmp_path / "out")) == 0
    (result,) = (tmp_path / "out").glob("case-*/*/result.json")
    doc = json.loads(result.read_text())
    truth = json.loads((folder / "ground_truth.json").read_text())
    assert doc["status"] == "measured"
    assert abs(doc["angles"]["ctr_deg"] - truth["ctr_deg"]) < 0.5
    assert abs(doc["angles"]["str_deg"] - truth["str_deg"]) < 0.5
    assert pydicom.dcmread(result.parent / "sc-view1.dcm").Rows == 2048


def test_a_detector_size_out_of_range_is_refused_in_one_line(tmp_path, capsys):
    assert main(["simulate", "--out", str(tmp_path / "case"), "--detector-pixels", "10"]) == 2
    assert "--detector-pixels must be 256 to 4096, got 10" in capsys.readouterr().err
