"""DICOM frames: encode, validate with dicom3tools' dciodvfy, decode, refuse bad instances."""

from __future__ import annotations

import shutil
import subprocess
from datetime import UTC, datetime, timedelta

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset
from pydicom.uid import ExplicitVRLittleEndian

from slamtka.service.frames import (
    ENHANCED_XA_IMAGE_STORAGE,
    RF_IMAGE_STORAGE,
    XA_IMAGE_STORAGE,
    Frame,
    FrameError,
    decode_frame,
    encode_frame,
)
from slamtka.service.scp import check_instance

WHEN = datetime(2025, 3, 14, 9, 26, 53, 589793, tzinfo=UTC)


def _frame(**changes) -> Frame:
    pixels = np.random.default_rng(1).integers(0, 4096, (48, 64)).astype(np.uint16)
    fields = dict(pixels=pixels, imager_pixel_spacing_mm=(0.2246, 0.2246), primary_angle_deg=-30.0,
                  secondary_angle_deg=2.5, sid_mm=1000.0, sod_mm=620.0, acquisition_datetime=WHEN,
                  patient_id="P-0042", patient_name="Doe^Jane", laterality="R", bits_stored=12)
    fields.update(changes)
    return Frame(**fields)


def _roundtrip(frame: Frame, tmp_path) -> tuple[Frame, str]:
    path = tmp_path / f"{frame.modality}.dcm"
    encode_frame(frame).save_as(path, enforce_file_format=True)
    return decode_frame(pydicom.dcmread(path)), str(path)


def _dciodvfy_errors(path: str) -> list[str]:
    out = subprocess.run(["dciodvfy", path], capture_output=True, text=True, timeout=60)
    return [line for line in (out.stdout + out.stderr).splitlines() if line.startswith("Error")]


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools not installed")
@pytest.mark.parametrize("sop_class,modality", [(XA_IMAGE_STORAGE, "XA"), (RF_IMAGE_STORAGE, "RF")])
def test_encoded_frame_passes_dciodvfy_and_round_trips(tmp_path, sop_class, modality):
    frame = _frame(sop_class_uid=sop_class, modality=modality)
    back, path = _roundtrip(frame, tmp_path)
    assert _dciodvfy_errors(path) == []
    assert np.array_equal(back.pixels, frame.pixels) and back.pixels.dtype == np.uint16
    assert back.imager_pixel_spacing_mm == pytest.approx(frame.imager_pixel_spacing_mm)
    assert (back.primary_angle_deg, back.secondary_angle_deg) == (-30.0, 2.5)
    assert (back.sid_mm, back.sod_mm) == (1000.0, 620.0)
    assert back.acquisition_datetime == WHEN
    assert (back.patient_id, back.patient_name, back.laterality) == ("P-0042", "Doe^Jane", "R")
    assert (back.study_uid, back.series_uid, back.sop_instance_uid) == (
        frame.study_uid, frame.series_uid, frame.sop_instance_uid)
    assert (back.sop_class_uid, back.modality, back.bits_stored) == (sop_class, modality, 12)


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dicom3tools not installed")
def test_frame_without_optional_geometry_still_validates(tmp_path):
    frame = _frame(primary_angle_deg=None, secondary_angle_deg=None, sid_mm=None, sod_mm=None,
                   laterality=None, acquisition_datetime=None)
    back, path = _roundtrip(frame, tmp_path)
    assert _dciodvfy_errors(path) == []
    assert back.primary_angle_deg is None and back.sid_mm is None and back.laterality is None
    assert back.acquisition_datetime is not None  # stamped at encoding time


def test_local_time_with_offset_is_read_as_utc():
    ds = encode_frame(_frame())
    ds.AcquisitionDateTime = "20250314102653.5+0100"
    assert decode_frame(ds).acquisition_datetime == datetime(2025, 3, 14, 9, 26, 53, 500000,
                                                             tzinfo=UTC)
    del ds.AcquisitionDateTime
    ds.ContentDate, ds.ContentTime, ds.TimezoneOffsetFromUTC = "20250314", "0426", "-0500"
    assert decode_frame(ds).acquisition_datetime == WHEN.replace(second=0, microsecond=0) + timedelta(
        minutes=0)


def test_monochrome1_is_inverted_to_monochrome2():
    ds = encode_frame(_frame())
    stored = ds.pixel_array.copy()
    ds.PhotometricInterpretation = "MONOCHROME1"
    assert np.array_equal(decode_frame(ds).pixels, 4095 - stored)


def _item(**attributes) -> Dataset:
    item = Dataset()
    for keyword, value in attributes.items():
        setattr(item, keyword, value)
    return item


def _enhanced_xa(frame: Frame, frames: int = 3) -> Dataset:
    """``frame`` as frame 1 of an Enhanced XA rotational run, its geometry only in the
    functional groups (positioner per frame, geometry and spacing shared), as such C-arms send it."""
    ds = encode_frame(frame)
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = ENHANCED_XA_IMAGE_STORAGE
    for keyword in ("PositionerPrimaryAngle", "PositionerSecondaryAngle", "DistanceSourceToDetector",
                    "DistanceSourceToPatient", "ImagerPixelSpacing", "Laterality"):
        delattr(ds, keyword)
    ds.AcquisitionDateTime = "20250314000000+0000"  # of the run; frame 1 says when it was taken
    ds.NumberOfFrames = frames
    ds.PixelData = np.stack([frame.pixels + k for k in range(frames)]).astype("<u2").tobytes()
    ds.SharedFunctionalGroupsSequence = [_item(
        FramePixelDataPropertiesSequence=[_item(ImagerPixelSpacing=list(frame.imager_pixel_spacing_mm))],
        XRayGeometrySequence=[_item(DistanceSourceToIsocenter=frame.sod_mm,
                                    DistanceSourceToDetector=frame.sid_mm)],
        FrameAnatomySequence=[_item(FrameLaterality=frame.laterality)])]
    ds.PerFrameFunctionalGroupsSequence = [_item(
        PositionerPositionSequence=[_item(PositionerPrimaryAngle=frame.primary_angle_deg + 10 * k,
                                          PositionerSecondaryAngle=frame.secondary_angle_deg)],
        FrameContentSequence=[_item(FrameAcquisitionDateTime=(WHEN + timedelta(seconds=k)).strftime(
            "%Y%m%d%H%M%S.%f") + "+0000")]) for k in range(frames)]
    return ds


def test_enhanced_xa_decodes_its_first_frame_with_the_geometry_of_its_functional_groups(tmp_path):
    frame = _frame()
    path = tmp_path / "enhanced.dcm"
    _enhanced_xa(frame).save_as(path, enforce_file_format=True)
    back = decode_frame(pydicom.dcmread(path))
    assert np.array_equal(back.pixels, frame.pixels)
    assert back.imager_pixel_spacing_mm == pytest.approx(frame.imager_pixel_spacing_mm)
    assert (back.primary_angle_deg, back.secondary_angle_deg) == (-30.0, 2.5)
    assert (back.sid_mm, back.sod_mm) == (1000.0, 620.0)
    assert back.acquisition_datetime == WHEN and back.laterality == "R"
    assert (back.sop_class_uid, back.modality, back.bits_stored) == (ENHANCED_XA_IMAGE_STORAGE, "XA", 12)


def test_the_receiver_accepts_an_enhanced_xa_instance():
    ds = _enhanced_xa(_frame())
    assert check_instance(ds, ENHANCED_XA_IMAGE_STORAGE, ExplicitVRLittleEndian, ds.SOPInstanceUID) is None


def test_enhanced_xa_per_frame_groups_override_shared_and_top_level():
    ds = _enhanced_xa(_frame(), frames=2)
    ds.PerFrameFunctionalGroupsSequence[0].XRayGeometrySequence = [_item(DistanceSourceToDetector=980.0)]
    ds.DistanceSourceToDetector = "1200"
    back = decode_frame(ds)
    assert (back.sid_mm, back.sod_mm) == (980.0, 620.0)
    del ds.SharedFunctionalGroupsSequence
    ds.ImagerPixelSpacing = ["0.3", "0.3"]
    assert decode_frame(ds).imager_pixel_spacing_mm == (0.3, 0.3)


@pytest.mark.parametrize("mutate,message", [
    (lambda ds: setattr(ds, "NumberOfFrames", 4), "PixelData holds"),
    (lambda ds: ds.SharedFunctionalGroupsSequence[0].XRayGeometrySequence[0].__setattr__(
        "DistanceSourceToDetector", 5.0), "DistanceSourceToDetector"),
    (lambda ds: delattr(ds, "SharedFunctionalGroupsSequence"), "ImagerPixelSpacing is missing"),
])
def test_bad_enhanced_xa_is_refused_naming_the_attribute(mutate, message):
    ds = _enhanced_xa(_frame())
    mutate(ds)
    with pytest.raises(FrameError, match=message):
        decode_frame(ds)


def test_multi_frame_single_plane_xa_is_still_refused():
    ds = encode_frame(_frame())
    ds.NumberOfFrames = 2
    ds.PixelData = ds.PixelData * 2
    with pytest.raises(FrameError, match="single-frame"):
        decode_frame(ds)


@pytest.mark.parametrize("mutate,message", [
    (lambda ds: delattr(ds, "PatientID"), "PatientID is missing"),
    (lambda ds: delattr(ds, "ImagerPixelSpacing"), "ImagerPixelSpacing is missing"),
    (lambda ds: setattr(ds, "Modality", "CT"), "Modality CT"),
    (lambda ds: setattr(ds, "SOPClassUID", "1.2.840.10008.5.1.4.1.1.2"), "SOPClassUID"),
    (lambda ds: setattr(ds, "ImagerPixelSpacing", ["0", "0.2"]), "ImagerPixelSpacing"),
    (lambda ds: setattr(ds, "DistanceSourceToDetector", "5"), "DistanceSourceToDetector"),
    (lambda ds: setattr(ds, "PositionerPrimaryAngle", "400"), "PositionerPrimaryAngle"),
    (lambda ds: setattr(ds, "Rows", 47), "PixelData"),
    (lambda ds: delattr(ds, "PixelData"), "PixelData is missing"),
    (lambda ds: setattr(ds, "PhotometricInterpretation", "RGB"), "PhotometricInterpretation"),
    (lambda ds: setattr(ds, "Laterality", "X"), "Laterality"),
    (lambda ds: setattr(ds, "AcquisitionDateTime", "2025-03-14"), "date-time"),
])
def test_bad_instances_are_refused_naming_the_attribute(mutate, message):
    ds = encode_frame(_frame())
    mutate(ds)
    with pytest.raises(FrameError, match=message):
        decode_frame(ds)


def test_frame_refuses_bad_content():
    with pytest.raises(ValueError, match="uint16"):
        _frame(pixels=np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError, match="bits stored"):
        _frame(pixels=np.full((8, 8), 5000, np.uint16))
    with pytest.raises(ValueError, match="timezone"):
        _frame(acquisition_datetime=datetime(2025, 1, 1))
    with pytest.raises(ValueError, match="modality"):
        encode_frame(_frame(modality="RF"))
