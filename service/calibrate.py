"""``slamtka calibrate IMAGE... --grid 5x5 --out CALIB.json``: calibrate a C-arm.

Reads phantom frames, DICOM (any image SOP class the service decodes) or ordinary image
files (PNG, TIFF, JPEG; their pixel spacing from ``--pixel-spacing``), estimates the
intrinsics, the image-intensifier distortion and the plate's own error
(``solver.imaging.calibration``) and writes the versioned calibration file. Every run writes
its report (``--report``, default ``CALIB.report.json`` beside the output), also when the
calibration is refused: per frame found or not and why, its residual, the outlier balls,
the estimated plate error, the final RMS and the intrinsics with their standard deviations.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import pydicom
from pydicom.errors import InvalidDicomError

from slamtka.service.atomic_files import write_json_atomic
from slamtka.service.calibrations import detector_field_mm, device_identity
from slamtka.service.frames import decode_frame
from slamtka.solver.imaging.calibration import CalibrationImage, CalibrationOptions, calibrate
from slamtka.solver.imaging.calibration_file import CalibrationError
from slamtka.solver.imaging.plate import PhantomSpec

__all__ = ["add_calibrate_parser", "cmd_calibrate", "read_phantom_image", "format_report",
           "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")


def _grid(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must look like 5x5, got {text!r}") from None
    return rows, cols


def _spacing(text: str) -> tuple[float, float]:
    """``0.2246`` or ``0.2246,0.2246`` (row, column spacing in mm)."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) == 1:
        values *= 2
    if len(values) != 2 or not all(0.0 < v < 10.0 for v in values):
        raise argparse.ArgumentTypeError(f"pixel spacing must be one or two numbers in mm "
                                         f"(0-10), e.g. 0.2246 or 0.2246,0.2246; got {text!r}")
    return values[0], values[1]


def read_phantom_image(path: Path, pixel_spacing: tuple[float, float] | None = None,
                       sid_mm: float | None = None) -> tuple[CalibrationImage, dict[str, str]]:
    """One phantom frame and the identity of the C-arm that made it (DICOM only)."""
    if path.suffix.lower() in IMAGE_SUFFIXES:
        if pixel_spacing is None:
            raise ValueError(f"{path}: an image file carries no pixel spacing; give --pixel-spacing MM")
        pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if pixels is None:
            raise ValueError(f"{path}: not a readable {path.suffix.lstrip('.').upper()} image")
        if pixels.ndim == 3:
            code = cv2.COLOR_BGRA2GRAY if pixels.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            pixels = cv2.cvtColor(pixels, code)
        return CalibrationImage(path.name, np.asarray(pixels), pixel_spacing, sid_mm), {}
    try:
        ds = pydicom.dcmread(path)
        frame = decode_frame(ds)
    except (InvalidDicomError, OSError) as exc:
        raise ValueError(f"{path}: not a readable DICOM file ({exc}); image files need one of the "
                         f"suffixes {', '.join(IMAGE_SUFFIXES)}") from None
    except ValueError as exc:  # a FrameError, or a frame the decoded values cannot make
        raise ValueError(f"{path}: {exc}") from None
    return (CalibrationImage(path.name, frame.pixels, frame.imager_pixel_spacing_mm,
                             frame.sid_mm or sid_mm, detector_field_mm(ds)), device_identity(ds))


def _number(value, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def format_report(report: dict) -> str:
    """The run's report as lines for the terminal."""
    lines = []
    for e in report["images"]:
        if e["used"]:
            outliers = ", ".join(f"ball {o['ball']} off by {o['residual_px']:.1f} px" if o["ball"] else
                                 f"blob at {o['at_px']} beyond the plate" for o in e["outlier_balls"])
            lines.append(f"  {e['image']}: {e['balls_used']} balls, tilt {e['tilt_deg']:.0f} deg, RMS "
                         f"{e['rms_px']:.3f} px" + (f"; outlier balls: {outliers}" if outliers else ""))
        else:
            lines.append(f"  {e['image']}: not used ({e['reason']})")
    plate = report.get("plate") or {}
    if plate.get("refined"):
        lines.append(f"plate error (estimated): {plate['error_rms_mm']:.3f} mm RMS, max "
                     f"{plate['error_max_mm']:.3f} mm over {plate['balls_seen']} balls")
    intrinsics = report.get("intrinsics")
    if intrinsics:
        lines.append("intrinsics: " + ", ".join(f"{k} {v['value']:.6g} +- {v['sd']:.2g}"
                                                for k, v in intrinsics.items()))
        pp = report["principal_point"]
        lines.append(f"principal point: {pp['why']}")
        lines.append(f"final RMS {_number(report.get('rms_px'), '.3f')} px over {report['used']} images")
    if report["status"] == "refused":
        lines.append(f"REFUSED: {report['refusal']}")
    return "\n".join(lines)


def _add_unreadable(report: dict, unreadable: dict[str, str]) -> None:
    """Files that could not be read, in the report as frames not used."""
    report["images"] += [{"image": name, "used": False, "reason": f"not readable: {why}",
                          "balls_found": None, "balls_used": 0, "stray_blobs": 0,
                          "outlier_balls": [], "rms_px": None, "tilt_deg": None}
                         for name, why in unreadable.items()]


def cmd_calibrate(args: argparse.Namespace) -> int:
    rows, cols = args.grid
    spec = PhantomSpec(rows, cols, args.pitch, args.ball_diameter)
    if args.pixel_spacing is None and any(p.suffix.lower() in IMAGE_SUFFIXES for p in args.images):
        raise ValueError("image files carry no pixel spacing; give --pixel-spacing MM")
    read, unreadable = [], {}
    for path in args.images:
        try:
            read.append(read_phantom_image(Path(path), args.pixel_spacing, args.sid))
        except ValueError as exc:  # one damaged file is set aside, not the run
            unreadable[Path(path).name] = str(exc).removeprefix(f"{path}: ")
    images = [image for image, _ in read]
    devices = {tuple(sorted(d.items())) for _, d in read}
    report_path = args.report or args.out.with_name(args.out.stem + ".report.json")
    calibration_id = args.id or args.out.stem
    # Frames that all name one C-arm bind the calibration to it (`calibration install` may
    # bind it to another identity).
    device = dict(next(iter(devices))) if len(devices) == 1 else {}
    try:
        calibration, report = calibrate(images, spec, CalibrationOptions(min_images=args.min_images),
                                        calibration_id, args.description, device)
    except CalibrationError as exc:
        if exc.report is not None:
            _add_unreadable(exc.report, unreadable)
            write_json_atomic(report_path, exc.report)
            print(format_report(exc.report))
            print(f"report -> {report_path}")
        raise ValueError(f"calibration failed: {exc}") from None
    _add_unreadable(report, unreadable)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out, calibration.document())
    write_json_atomic(report_path, report)
    print(format_report(report))
    c = calibration.camera
    print(f"calibration {calibration.calibration_id}: f {c.fx:.1f} px, principal point "
          f"({c.cx:.1f}, {c.cy:.1f}), RMS {report['rms_px']:.3f} px over {report['used']} images "
          f"-> {args.out} (report {report_path})")
    if device:
        print("made for the C-arm " + ", ".join(f"{k} {v!r}" for k, v in device.items()))
    return 0


def add_calibrate_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate a C-arm from ball-grid phantom images")
    p.add_argument("images", nargs="+", type=Path,
                   help=f"phantom frames: DICOM, or images ({', '.join(IMAGE_SUFFIXES)})")
    p.add_argument("--grid", type=_grid, default=(5, 5), help="balls per row x column (5x5)")
    p.add_argument("--pitch", type=float, default=25.0,
                   help="ball spacing, mm (only a scale: approximate is fine)")
    p.add_argument("--ball-diameter", type=float, default=3.0, help="mm")
    p.add_argument("--pixel-spacing", type=_spacing,
                   help="detector pixel spacing of image files, mm (row,col or one value)")
    p.add_argument("--sid", type=float, help="source-to-detector distance, mm, of frames that do not "
                                             "say (checks the focal length's plausibility)")
    p.add_argument("--min-images", type=int, default=CalibrationOptions().min_images)
    p.add_argument("--id", help="calibration id (default: the output file's name)")
    p.add_argument("--description", default="", help="free text stored in the file")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--report", type=Path, help="the run's report (default: OUT.report.json)")
    p.set_defaults(func=cmd_calibrate)
