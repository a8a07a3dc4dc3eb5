"""Bad inputs are refused with a clear message naming the file, key or DICOM attribute."""

from __future__ import annotations

import json
import logging
import math
import socket

import numpy as np
import pytest
from pydicom.datadict import dictionary_VR
from pydicom.dataelem import RawDataElement
from pydicom.tag import Tag
from pydicom.uid import RLELossless

from slamtka.drivers.encoder_link import LinkConfig
from slamtka.drivers.kinematics import CArmKinematics
from slamtka.service.calibrate import read_phantom_image as read_calibration_image
from slamtka.service.cli import main
from slamtka.service.config import ConfigError, config_from_dict
from slamtka.service.frames import Frame, FrameError, decode_frame, encode_frame
from slamtka.sim.bone_phantom import phantom_plan
from slamtka.sim.simulate import default_camera
from slamtka.solver.camera import Camera
from slamtka.solver.case import load_case, write_case
from slamtka.solver.geometry import Pose
from slamtka.solver.imaging.calibration_file import (
    CalibrationError,
    _digest,
    load_calibration,
    write_calibration,
)
from slamtka.solver.observations import ViewObservation
from slamtka.solver.slam import InitialGuess

CAMERA = default_camera()


@pytest.fixture(scope="module")
def valid_case(tmp_path_factory):
    """A small, loadable case folder (the phantom plan, two views, identity poses)."""
    folder = tmp_path_factory.mktemp("case") / "case"
    square = np.array([[300.0, 300.0], [700.0, 300.0], [700.0, 700.0], [300.0, 700.0]])
    views = [ViewObservation(f"view{k}", CAMERA, {"bone": square, "pin1": square + 5, "pin2": square - 5})
             for k in (1, 2)]
    initial = InitialGuess((Pose.identity(), Pose.identity()), (Pose.identity(), Pose.identity()), None)
    write_case(folder, "bad-inputs", phantom_plan("right"), views, initial, "cal")
    return folder


@pytest.fixture
def case(valid_case, tmp_path):
    import shutil
    folder = tmp_path / "case"
    shutil.copytree(valid_case, folder)
    return folder


def _edit(path, change):
    doc = json.loads(path.read_text())
    change(doc)
    path.write_text(json.dumps(doc))


def test_the_valid_case_loads(case):
    assert [v.view_id for v in load_case(case).views] == ["view1", "view2"]


@pytest.mark.parametrize("change, message", [
    (lambda d: d["views"].append(dict(d["views"][0])), "view 'view1' is given twice"),
    (lambda d: d["views"][1].__setitem__("pin3", [[1, 2]]), r"view 'view2': unknown contour labels \['pin3'\]"),
])
def test_a_repeated_view_or_an_unknown_label_is_refused(case, change, message):
    _edit(case / "contours.json", change)
    with pytest.raises(ValueError, match=f"contours.json: {message}"):
        load_case(case)


# -- 1. wrong JSON types ----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["case.json", "contours.json", "initial.json"])
def test_a_json_list_instead_of_an_object_names_the_file(case, name):
    (case / name).write_text("[1, 2, 3]")
    with pytest.raises(ValueError, match=f"{name}: must hold a JSON object, not list"):
        load_case(case)


@pytest.mark.parametrize("file, change, message", [
    ("contours.json", lambda d: d.__setitem__("views", {"view1": []}), "contours.json: 'views' must be a list"),
    ("case.json", lambda d: d.__setitem__("plan", None), "case.json: 'plan' must be a file name"),
    ("case.json", lambda d: d.__setitem__("contours", 5), "case.json: 'contours' must be a file name"),
    ("initial.json", lambda d: d.__setitem__("views", []), "initial.json: 'views' must be an object"),
])
def test_wrong_json_types_name_the_file_and_key(case, file, change, message):
    _edit(case / file, change)
    with pytest.raises(ValueError, match=message):
        load_case(case)


def _recalibrate(path, change):
    doc = json.loads(path.read_text())
    change(doc)
    doc["sha256"] = _digest({k: v for k, v in doc.items() if k != "sha256"})
    path.write_text(json.dumps(doc))


def test_a_distortion_string_is_a_malformed_calibration(tmp_path):
    path = tmp_path / "cal.json"
    write_calibration(path, CAMERA, None, "test")
    _recalibrate(path, lambda d: d.__setitem__("distortion", "none"))
    with pytest.raises(CalibrationError, match="cal.json: malformed calibration .*distortion must be an object"):
        load_calibration(path)


# -- 2. contour values ------------------------------------------------------------------------

@pytest.mark.parametrize("points, message", [
    ([["a", "b"], [1.0, 2.0]], "bone contour must be a list of"),
    ([[1.0, 2.0], [1.0]], "bone contour must be a list of"),
    ([[5300.0, 5300.0], [5400.0, 5300.0]], "bone contour has points outside the 1024x1024 image"),
])
def test_bad_contour_values_name_the_file_view_and_label(case, points, message):
    _edit(case / "contours.json", lambda d: d["views"][0].__setitem__("bone", points))
    with pytest.raises(ValueError, match=f"contours.json: view 'view1': {message}"):
        load_case(case)


def test_binary_contours_name_the_file(case):
    (case / "contours.json").write_bytes(bytes(range(128, 256)) * 8)
    with pytest.raises(ValueError, match="contours.json: not a text"):
        load_case(case)


# -- 3. camera values -------------------------------------------------------------------------

@pytest.mark.parametrize("change, message", [
    ({"fx": math.nan}, "focal lengths must be finite"),
    ({"cx": math.nan}, "principal point must be finite"),
    ({"fov_radius_px": -5.0}, "fov_radius_px must be finite and positive"),
    ({"width": 200000, "height": 200000}, "width 200000 px is outside 16..16384"),
    ({"width": 1024.7}, "width must be a whole number of pixels, got 1024.7"),
])
def test_bad_camera_values_are_refused(change, message):
    with pytest.raises(ValueError, match=message):
        Camera.from_json({**CAMERA.to_json(), **change})


def test_an_integral_float_width_is_still_accepted():
    assert Camera.from_json({**CAMERA.to_json(), "width": 1024.0}) == CAMERA


# -- 4. initial poses -------------------------------------------------------------------------

def test_a_nan_initial_pose_names_the_file(case):
    _edit(case / "initial.json", lambda d: d["views"]["view1"][0].__setitem__(0, float("nan")))
    with pytest.raises(ValueError, match="initial.json: view 'view1': not a valid pose .*non-finite"):
        load_case(case)


# -- 5. the command line ----------------------------------------------------------------------

def test_a_missing_file_is_a_clean_cli_error(tmp_path, capsys):
    assert main(["plan", "add", "--plans", str(tmp_path / "plans"), "--patient-id", "P1", "--side",
                 "right", "--tibia", str(tmp_path / "tibia.stl"),
                 "--landmarks", str(tmp_path / "nonexist.json")]) == 2
    err = capsys.readouterr().err
    assert "slamtka: error:" in err and "Traceback" not in err


def test_binary_landmarks_are_named_by_plan_add(tmp_path, capsys):
    binary = tmp_path / "landmarks.json"
    binary.write_bytes(b"\xff\xfe\x00junk")
    tibia = tmp_path / "tibia.stl"
    phantom_plan().tibia.to_trimesh().export(tibia)
    assert main(["plan", "add", "--plans", str(tmp_path / "plans"), "--patient-id", "P1",
                 "--side", "right", "--tibia", str(tibia), "--landmarks", str(binary)]) == 2
    assert f"{binary}: not a text (UTF-8) file" in capsys.readouterr().err


def test_binary_config_and_truncated_status_name_the_file(tmp_path, capsys):
    config = tmp_path / "svc.toml"
    config.write_bytes(b"\xff\xfe\x00")
    assert main(["status", "--config", str(config)]) == 2
    assert f"{config}: not a text (UTF-8) file" in capsys.readouterr().err
    config.write_text(f'data_dir = "{tmp_path}"\n[dicom]\nallowed_calling_ae_titles = ["C"]\n'
                      '[carm]\ncalibration = "cal.json"\n')
    (tmp_path / "status.json").write_text('{"state": "runn')
    assert main(["status", "--config", str(config)]) == 2
    assert "status.json: not valid JSON" in capsys.readouterr().err


# -- 6. DICOM decoding ------------------------------------------------------------------------

def _dataset():
    pixels = np.random.default_rng(1).integers(0, 4096, (48, 64)).astype(np.uint16)
    return encode_frame(Frame(pixels, (0.2246, 0.2246), bits_stored=12))


@pytest.mark.parametrize("changes, message", [
    ({"Rows": 0, "PixelData": b""}, "Rows/Columns 0/64"),
    ({"TimezoneOffsetFromUTC": "+2500", "AcquisitionDateTime": "20250314092653"},
     "TimezoneOffsetFromUTC offset '\\+2500'"),
    ({"InstanceNumber": "12abc"}, "InstanceNumber '12abc' is not an integer"),
])
def test_decode_problems_are_frame_errors_naming_the_attribute(changes, message):
    ds = _dataset()
    for keyword, value in changes.items():
        if isinstance(value, str):  # as received: raw bytes, converted (or not) on access
            tag = Tag(keyword)
            ds[tag] = RawDataElement(tag, dictionary_VR(tag), len(value), value.encode(), 0, False, True)
        else:
            setattr(ds, keyword, value)
    with pytest.raises(FrameError, match=message):
        decode_frame(ds)


def test_calibrate_names_the_file_of_a_one_row_image(tmp_path):
    ds = _dataset()
    ds.Rows, ds.PixelData = 1, ds.PixelData[:64 * 2]
    path = tmp_path / "one-row.dcm"
    ds.save_as(path, enforce_file_format=True)
    with pytest.raises(ValueError, match="one-row.dcm: Rows/Columns 1/64"):
        read_calibration_image(path)


def test_undecodable_compressed_pixels_log_no_traceback(caplog):
    ds = _dataset()
    ds.file_meta.TransferSyntaxUID = RLELossless
    ds.PixelData = b"\xff" * 64
    with caplog.at_level(logging.DEBUG), pytest.raises(FrameError, match="cannot be decoded"):
        decode_frame(ds)
    assert not [r for r in caplog.records if r.name.startswith("pydicom.pixels")]
    assert not logging.getLogger("pydicom.pixels.decoders.base").disabled


# -- 7. serve start-up ------------------------------------------------------------------------

def _minimal(tmp_path, **carm):
    return {"data_dir": str(tmp_path / "data"), "dicom": {"allowed_calling_ae_titles": ["CARM"]},
            "carm": {"calibration": str(tmp_path / "cal.json"), **carm}}


def test_bind_address_must_be_an_ip(tmp_path):
    table = _minimal(tmp_path)
    table["dicom"]["bind_address"] = "not-an-ip"
    with pytest.raises(ConfigError, match="dicom.bind_address: 'not-an-ip' is not an IP address"):
        config_from_dict(table, environ={})


def _serve(tmp_path, data_dir, port=0):
    write_calibration(tmp_path / "cal.json", CAMERA, None, "test")
    (tmp_path / "svc.toml").write_text(
        f'data_dir = "{data_dir}"\n[dicom]\nport = {port}\nallowed_calling_ae_titles = ["CARM"]\n'
        f'[carm]\ncalibration = "{tmp_path / "cal.json"}"\n')
    return main(["serve", "--config", str(tmp_path / "svc.toml")])


def test_serve_refuses_a_data_dir_that_is_a_file(tmp_path, capsys):
    (tmp_path / "afile").write_text("")
    assert _serve(tmp_path, tmp_path / "afile") == 2
    assert "afile: cannot create the service folder" in capsys.readouterr().err


def test_serve_reports_a_port_in_use(tmp_path, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        assert _serve(tmp_path, tmp_path / "data", taken.getsockname()[1]) == 2
    assert "cannot listen for DICOM on 127.0.0.1:" in capsys.readouterr().err


# -- 8. driver configuration ------------------------------------------------------------------

@pytest.mark.parametrize("section, values, message", [
    ("setup", {"rot_sd_deg": "x"}, "carm.setup: rot_sd_deg = 'x' is not of type float"),
    ("setup", {"rot_sd_deg": -5}, "carm.setup: rot_sd_deg must be positive"),
    ("setup", {"trans_sd_mm": math.nan}, "carm.setup: trans_sd_mm = nan is not finite"),
    ("setup", {"reference_view": 7}, "carm.setup: reference_view 7 must be 0 or 1"),
    ("setup", {"reference_view": -1}, "carm.setup: reference_view must be a view index"),
    ("link", {"rate_hz": True}, "carm.link: link.rate_hz: expected an integer, got True"),
    ("link", {"rate_hz": 100.7}, "carm.link: link.rate_hz: expected an integer, got 100.7"),
    ("kinematics", {"name": 5}, "carm.kinematics: .*name must be a string"),
])
def test_driver_configuration_is_checked_naming_the_key(tmp_path, section, values, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(_minimal(tmp_path, **{section: values}), environ={})


def test_valid_driver_configuration_keeps_its_values():
    assert LinkConfig.from_config({"rate_hz": 50, "max_age_s": 1}) == LinkConfig(rate_hz=50, max_age_s=1.0)
    assert CArmKinematics.from_config({"name": "OR3"}).name == "OR3"
