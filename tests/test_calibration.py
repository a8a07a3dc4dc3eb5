"""C-arm calibration on real-world phantom sets, its refusals, and calibrations per C-arm."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid
from pynetdicom import AE
from service_testing import free_port, small_frame

from slamtka.drivers.kinematics import CArmKinematics
from slamtka.service.audit import AuditLog
from slamtka.service.calibrations import CalibrationSet, CalibrationStore, device_identity
from slamtka.service.cases import CaseAssembler
from slamtka.service.cli import main
from slamtka.service.config import DicomConfig
from slamtka.service.frames import encode_frame
from slamtka.service.pipeline import Pipeline
from slamtka.service.plans import PlanStore
from slamtka.service.poses import ViewGeometry
from slamtka.service.scp import DicomReceiver
from slamtka.service.spool import Spool
from slamtka.sim.plate_images import plate_offsets, simulate_phantom_set
from slamtka.sim.simulate import default_camera
from slamtka.sim.xray import default_distortion
from slamtka.solver.camera import Camera
from slamtka.solver.imaging.calibration import CalibrationImage, CalibrationOptions, calibrate
from slamtka.solver.imaging.calibration_file import CalibrationError, load_calibration, write_calibration
from slamtka.solver.imaging.plate import PhantomSpec

SPACING = (230 / 1024, 230 / 1024)


@pytest.fixture(scope="module")
def real_set():
    """A set as a hospital collects it: plate 0.25 mm off grid, two specks per frame (one
    continuing the grid), a ball missing, an empty frame, a duplicate."""
    nominal = default_camera()
    true = Camera(nominal.fx * 0.99, nominal.fx * 0.99, nominal.cx - 5.0, nominal.cy + 7.0,
                  nominal.width, nominal.height, nominal.fov_radius_px)
    distortion = default_distortion(true)
    rng = np.random.default_rng(11)
    spec = PhantomSpec()
    phantom = simulate_phantom_set(true, distortion, spec, 10, rng, plate_offsets(spec, 0.25, rng),
                                   missing_balls=(7,), specks=2, empty_frames=1, duplicates=1)
    images = [CalibrationImage(n, im, SPACING, 1000.0) for n, im in zip(phantom.names, phantom.images)]
    return true, phantom, images


def test_a_real_world_set_calibrates_with_every_frame_that_shows_the_grid(real_set):
    true, phantom, images = real_set
    calibration, report = calibrate(images)
    entries = {e["image"]: e for e in report["images"]}
    assert "no phantom in the image" in entries["empty00"]["reason"]
    assert entries["copy00"]["reason"] == "duplicate: the same pixels as img00"
    assert all(entries[n]["used"] for n in phantom.poses), [entries[n]["reason"] for n in phantom.poses]
    c = calibration.camera
    assert abs(c.fx / true.fx - 1) < 0.005
    assert not report["principal_point"]["held_at_field_centre"]
    assert math.hypot(c.cx - true.cx, c.cy - true.cy) < 3.0
    assert 0.1 < report["plate"]["error_rms_mm"] < 0.35 and report["rms_px"] < 0.1
    assert set(report["intrinsics"]) == {"f_px", "cx_px", "cy_px", "k1", "k2", "t1_rad", "t2_rad"}
    assert all(0 < v["sd"] < math.inf for v in report["intrinsics"].values())
    # The specks: off the lattice (stray), taken for a missing ball or continuing the grid
    # (outliers, each said why); either way left out.
    used = [e for e in report["images"] if e["used"]]
    assert sum(e["stray_blobs"] + len(e["outlier_balls"]) for e in used) >= len(used)
    assert all(o["why"] for e in used for o in e["outlier_balls"])
    assert calibration.document()["plate"]["refined"] and calibration.document()["rejected"]
    # The same set with the plate taken as perfect fits several times worse.
    _, perfect = calibrate(images, options=CalibrationOptions(refine_plate=False, max_rms_px=10.0))
    assert perfect["rms_px"] > 4 * report["rms_px"]


def test_refusals_name_the_problem_and_carry_the_report(real_set):
    true, phantom, images = real_set
    with pytest.raises(CalibrationError, match="no calibration images given") as refused:
        calibrate([])
    assert refused.value.report["status"] == "refused"
    wrong_sid = [CalibrationImage(i.name, i.pixels, i.pixel_spacing_mm, 600.0) for i in images]
    with pytest.raises(CalibrationError, match=r"focal length \d+ px is \+\d+% from the nominal SID / "
                                               r"pixel spacing \d+ px: implausible") as refused:
        calibrate(wrong_sid)
    assert refused.value.report["intrinsics"]["f_px"]["sd"] > 0  # the run's figures are kept
    with pytest.raises(CalibrationError, match=r"calibration RMS 0.\d+ px exceeds 0.001 px; the images "
                                               r"that fit worst: img\d\d \(RMS 0.\d+ px, \d+ outlier balls\)"):
        calibrate(images, options=CalibrationOptions(max_rms_px=0.001))


def test_a_frame_of_another_camera_is_set_aside_by_name(real_set):
    true, phantom, images = real_set
    # Another C-arm: its intensifier distorts the other way round, its axis is elsewhere.
    other = Camera(true.fx, true.fy, true.cx + 40.0, true.cy, true.width, true.height, true.fov_radius_px)
    distortion = replace(default_distortion(other), k1=-0.04, t1=-0.01)
    stranger = simulate_phantom_set(other, distortion, PhantomSpec(), 1, np.random.default_rng(3)).images[0]
    _, report = calibrate(images + [CalibrationImage("stranger", stranger, SPACING, 1000.0)])
    entry = next(e for e in report["images"] if e["image"] == "stranger")
    assert not entry["used"] and entry["reason"].startswith("does not fit the other images (")


def test_calibrate_reads_image_files_and_always_writes_its_report(real_set, tmp_path, capsys):
    _, phantom, _ = real_set
    paths = []
    for name, image in zip(phantom.names, phantom.images):
        path = tmp_path / f"{name}.png"
        assert cv2.imwrite(str(path), image)
        paths.append(str(path))
    out = tmp_path / "carm.json"
    assert main(["calibrate", *paths, "--out", str(out)]) == 2
    assert "image files carry no pixel spacing; give --pixel-spacing MM" in capsys.readouterr().err
    damaged = tmp_path / "damaged.dcm"
    damaged.write_bytes(b"not DICOM at all")
    assert main(["calibrate", *paths, str(damaged), "--pixel-spacing", str(SPACING[0]), "--sid", "1000",
                 "--out", str(out)]) == 0
    report = json.loads((tmp_path / "carm.report.json").read_text())
    assert report["status"] == "calibrated" and load_calibration(out).pixel_spacing_mm == SPACING
    assert report["images"][-1]["image"] == "damaged.dcm"
    assert report["images"][-1]["reason"].startswith("not readable: not a readable DICOM file")
    assert "copy00.png: not used (duplicate: the same pixels as img00.png)" in capsys.readouterr().out
    refused = tmp_path / "refused.json"
    assert main(["calibrate", *paths, "--pixel-spacing", str(SPACING[0]), "--min-images", "40",
                 "--out", str(refused)]) == 2
    report = json.loads((tmp_path / "refused.report.json").read_text())
    assert report["status"] == "refused" and "only 10 usable images, need 40" in report["refusal"]
    assert not refused.exists()
    assert "REFUSED: only 10 usable images" in capsys.readouterr().out


def _config(tmp_path, match="device_serial_number", default=None) -> str:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "slamtka.toml"
    path.write_text(f'data_dir = "{tmp_path / "data"}"\n[dicom]\nallowed_calling_ae_titles = ["CARM"]\n'
                    f'[carm]\ncalibration_match = "{match}"\n'
                    + (f'calibration = "{default}"\n' if default else ""))
    return str(path)


def test_simulated_set_calibrate_install_list_and_show(tmp_path, capsys):
    folder = tmp_path / "phantom"
    assert main(["simulate", "--calibration-images", "8", "--out", str(folder), "--seed", "4"]) == 0
    frames = sorted(folder.glob("*.dcm"))
    assert len(frames) == 10 and (folder / "truth.json").is_file()
    assert (folder / "resent-img00.dcm").read_bytes() == (folder / "img00.dcm").read_bytes()
    out = tmp_path / "or3-23cm.json"
    assert main(["calibrate", *map(str, frames), "--out", str(out)]) == 0
    calibration = load_calibration(out)
    assert calibration.device == {"device_serial_number": "SIM-0001", "station_name": "SIMCARM"}
    assert calibration.field_mm == 230.0
    config = _config(tmp_path)
    capsys.readouterr()
    assert main(["calibration", "install", str(out), "--config", config]) == 0
    assert "installed or3-23cm for the C-arm with Device Serial Number 'SIM-0001'" in capsys.readouterr().out
    assert main(["calibration", "install", str(out), "--config", config]) == 2
    assert "is installed for the same id; give --replace" in capsys.readouterr().err
    assert main(["calibration", "install", str(out), "--config", config, "--replace"]) == 0
    assert main(["calibration", "list", "--config", config]) == 0
    listing = capsys.readouterr().out
    assert "or3-23cm: Device Serial Number 'SIM-0001', 1024x1024 px" in listing and "230 mm field" in listing
    assert main(["calibration", "show", "or3-23cm", "--config", config]) == 0
    assert json.loads(capsys.readouterr().out)["device"]["device_serial_number"] == "SIM-0001"
    by_ae = _config(tmp_path / "ae", match="calling_ae_title")
    assert main(["calibration", "install", str(out), "--config", by_ae]) == 2
    assert "names no calling AE title of its C-arm; give it (--calling-ae-title VALUE)" in capsys.readouterr().err
    assert main(["calibration", "install", str(out), "--config", by_ae, "--calling-ae-title", "CARM"]) == 0


def _calibration(tmp_path, name: str, device: dict, field: float | None = None, size: int = 64):
    camera = Camera(300.0, 300.0, size / 2, size / 2, size, size)
    written = write_calibration(tmp_path / f"{name}.json", camera, None, "test", name, (0.3, 0.3))
    doc = written.document()
    from slamtka.solver.imaging.calibration_file import assign_device

    (tmp_path / f"{name}.json").write_text(json.dumps(assign_device(doc, device, field)))
    return load_calibration(tmp_path / f"{name}.json")


def test_the_calibration_is_chosen_by_c_arm_and_field(tmp_path):
    or3_small = _calibration(tmp_path, "or3-15", {"device_serial_number": "OR3"}, 150.0)
    or3_large = _calibration(tmp_path, "or3-23", {"device_serial_number": "OR3"}, 230.0)
    default = _calibration(tmp_path, "site", {})
    frame = small_frame()

    def header(**attributes):
        ds = encode_frame(frame)
        for keyword, value in attributes.items():
            setattr(ds, keyword, value)
        return ds

    chosen = CalibrationSet([or3_small, or3_large], None)
    assert chosen.select(header(DeviceSerialNumber="OR3", IntensifierSize="230"), frame)[0] is or3_large
    assert chosen.select(header(DeviceSerialNumber="OR3", IntensifierSize="150"), frame)[0] is or3_small
    none, why = chosen.select(header(DeviceSerialNumber="OR3", IntensifierSize="300"), frame)
    assert none is None and why.startswith("the C-arm with Device Serial Number 'OR3' has no calibration "
                                           "for this detector field (64x64 px, 0.3 mm pixels, 300 mm field)")
    none, why = chosen.select(header(DeviceSerialNumber="OR7"), frame)
    assert why == ("no calibration for the C-arm with Device Serial Number 'OR7' (install one with "
                   "`slamtka calibration install`)")
    none, why = chosen.select(header(DeviceSerialNumber=""), frame)
    assert why == "the frame names no Device Serial Number: its C-arm's calibration cannot be chosen"
    # The single calibration of the existing configuration serves C-arms without their own.
    fallback = CalibrationSet([or3_small, or3_large], default)
    assert fallback.select(header(DeviceSerialNumber="OR7"), frame) == (default, None)
    with pytest.raises(CalibrationError, match="no calibration: set carm.calibration, or install one"):
        CalibrationSet.load(tmp_path / "empty", None, "device_serial_number")


def test_the_receiver_keeps_the_calling_ae_title_that_picks_the_calibration(tmp_path):
    spool = Spool(tmp_path / "spool")
    config = DicomConfig(ae_title="SLAMTKA", port=free_port(), allowed_calling_ae_titles=["CARM_OR3"])
    audit = AuditLog(tmp_path / "audit.jsonl")
    stored = []
    receiver = DicomReceiver(config, spool, audit, stored.append)
    receiver.start()
    try:
        ae = AE(ae_title="CARM_OR3")
        ds = encode_frame(small_frame())
        ae.add_requested_context(ds.SOPClassUID, ds.file_meta.TransferSyntaxUID)
        assoc = ae.associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert assoc.is_established and assoc.send_c_store(ds).Status == 0
        assoc.release()
    finally:
        receiver.stop()
        audit.close()
    spooled = spool.read(stored[0])
    assert device_identity(spooled)["calling_ae_title"] == "CARM_OR3"
    mine = _calibration(tmp_path, "or3", {"calling_ae_title": "CARM_OR3"})
    assert CalibrationSet([mine], None, "calling_ae_title").select(spooled, small_frame())[0] is mine


def test_a_run_leaves_out_a_frame_of_a_c_arm_without_calibration(tmp_path):
    spool = Spool(tmp_path / "spool")
    geometry = ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)
    assembler = CaseAssembler(spool, geometry, 15.0, 6)
    study = generate_uid()
    for angle in (-30.0, 30.0):
        entry, _ = spool.store(encode_frame(small_frame(study_uid=study, primary_angle_deg=angle),
                                            device_serial_number="OR7"))
        case, due = assembler.add(entry)
    assert due
    mine = _calibration(tmp_path, "or3", {"device_serial_number": "OR3"})
    pipeline = Pipeline(spool, PlanStore(tmp_path / "plans"), CalibrationSet([mine], None), geometry,
                        tmp_path / "out")
    doc = pipeline.run(case, case.selection(6)).result.to_document()
    assert doc["status"] == "not_measured" and doc["calibration"] is None
    problem = ("no calibration for the C-arm with Device Serial Number 'OR7' (install one with "
               "`slamtka calibration install`)")
    assert [s["problem"] for s in doc["sources"]] == [problem, problem]
    assert f"view1: {problem}" in doc["reasons"]
    assert pydicom.dcmread(doc["outputs"]["folder"] + "/sr.dcm").Modality == "SR"


def test_a_running_service_picks_up_an_installed_calibration_without_restart(tmp_path):
    """``calibration install`` while the service runs: the next frame is measured with it; a
    damaged file keeps the calibrations the service had, and says so."""
    made = tmp_path / "made"
    made.mkdir()
    folder = tmp_path / "calibrations"
    or3 = _calibration(made, "or3", {"device_serial_number": "OR3"})
    store_path = made / "or3.json"

    CalibrationStore(folder).install(store_path, "device_serial_number")
    told: list[tuple[str, dict]] = []
    live = CalibrationSet.load(folder, None, "device_serial_number", on_change=lambda e, f: told.append((e, f)))
    frame = small_frame()
    ds = encode_frame(frame, device_serial_number="OR7")
    assert live.select(ds, frame)[0] is None
    _calibration(made, "or7", {"device_serial_number": "OR7"})
    CalibrationStore(folder).install(made / "or7.json", "device_serial_number")
    chosen, problem = live.select(ds, frame)
    assert problem is None and chosen.calibration_id == "or7"
    assert told == [("calibrations_reloaded", {"added": ["or7"], "removed": [], "replaced": []})]
    (folder / "broken.json").write_text("{ not json")
    chosen, problem = live.select(ds, frame)
    assert chosen.calibration_id == "or7" and told[-1][0] == "calibrations_unreadable"
    assert "broken.json" in told[-1][1]["error"] and told[-1][1]["kept"] == ["or3", "or7"]
    (folder / "broken.json").unlink()
    (folder / "or7.json").unlink()
    assert live.select(ds, frame)[0] is None
    assert told[-1] == ("calibrations_reloaded", {"added": [], "removed": ["or7"], "replaced": []})
    assert [c.calibration_id for c in live.installed] == [or3.calibration_id]
    # Telling the change may fail (the audit log's disk full): the frame still gets its calibration.
    live.on_change = lambda event, fields: 1 / 0
    CalibrationStore(folder).install(made / "or7.json", "device_serial_number")
    assert live.select(ds, frame)[0].calibration_id == "or7"


def test_install_refuses_an_unsafe_id_and_a_second_calibration_of_the_same_detector(tmp_path):
    made = tmp_path / "made"
    made.mkdir()
    store = CalibrationStore(tmp_path / "calibrations")
    _calibration(made, "or3-a", {"device_serial_number": "OR3"})
    _calibration(made, "or3-b", {"device_serial_number": "OR3"})
    store.install(made / "or3-a.json", "device_serial_number")
    with pytest.raises(ValueError, match=r"calibration or3-a is installed for the same C-arm "
                                         r"\(Device Serial Number 'OR3'\) and detector; give --replace"):
        store.install(made / "or3-b.json", "device_serial_number")
    store.install(made / "or3-b.json", "device_serial_number", replace=True)
    assert [c.calibration_id for c in store.installed()] == ["or3-b"]
    bad = _calibration(made, "bad", {"device_serial_number": "OR9"})
    doc = bad.document()
    doc["calibration_id"] = "../etc/passwd"
    (made / "bad.json").write_text(json.dumps(doc))
    with pytest.raises((ValueError, CalibrationError)):
        store.install(made / "bad.json", "device_serial_number")


def test_drawn_contours_of_a_view_use_its_calibration_from_the_first_view(tmp_path):
    """Undistorted hand-drawn contours of the first view after a start: distorted with that
    view's calibration (there was none current yet: this failed); a view of a C-arm
    without calibration has none to use."""
    spool = Spool(tmp_path / "spool")
    geometry = ViewGeometry(CArmKinematics(), {}, None, 0.1, 3.0)
    assembler = CaseAssembler(spool, geometry, 15.0, 6)
    study = generate_uid()
    for serial, angle in (("OR3", -30.0), ("OR7", 30.0)):
        entry, _ = spool.store(encode_frame(small_frame(study_uid=study, primary_angle_deg=angle),
                                            device_serial_number=serial))
        case, _ = assembler.add(entry)
    mine = _calibration(tmp_path, "or3", {"device_serial_number": "OR3"})
    drawn_dir = tmp_path / "drawn"
    drawn_dir.mkdir()
    or3_view, or7_view = case.selection(6)
    drawn = {"bone": [[10.0, 12.0], [20.0, 22.0]], "pin1": [[30.0, 31.0]], "pin2": [[40.0, 41.0]]}
    (drawn_dir / "drawn.json").write_text(json.dumps({
        "format": "slamtka-contours/1", "coordinates": "undistorted",
        "views": [{"view_id": v.sop_instance_uid, **drawn} for v in (or3_view, or7_view)]}))
    pipeline = Pipeline(spool, PlanStore(tmp_path / "plans"), CalibrationSet([mine], None), geometry,
                        tmp_path / "out", manual_contours_dir=drawn_dir)
    contours, source = pipeline.view_contours(case, or3_view)
    assert source == "manual" and pipeline.calibration is mine
    for label, points in drawn.items():
        np.testing.assert_allclose(contours[label], points, atol=1e-6)
    assert pipeline.view_contours(case, or7_view) == (None, "the frame does not match the C-arm calibration")
