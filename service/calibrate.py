"""``slamtka calibrate IMAGE... --grid 5x5 --pitch 25 --out CALIB.json``: calibrate a C-arm.

Reads phantom frames (DICOM), finds the ball grid in each, estimates the intrinsics and the
image-intensifier distortion (``solver.imaging.calibration``) and writes the versioned
calibration file. Frames where the grid is not found are listed by name; they do not stop
the calibration unless too few usable frames remain.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pydicom
from pydicom.errors import InvalidDicomError

from solver.imaging.calibration import CalibrationError, CalibrationImage, CalibrationOptions, calibrate
from solver.imaging.phantom import PhantomSpec

from .frames import decode_frame

__all__ = ["add_calibrate_parser", "cmd_calibrate"]


def _grid(text: str) -> tuple[int, int]:
    try:
        rows, cols = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"grid must look like 5x5, got {text!r}") from None
    return rows, cols


def _read(path: Path) -> CalibrationImage:
    try:
        frame = decode_frame(pydicom.dcmread(path))
    except (InvalidDicomError, OSError) as exc:
        raise ValueError(f"{path}: not a readable DICOM file ({exc})") from None
    except ValueError as exc:  # a FrameError, or a frame the decoded values cannot make
        raise ValueError(f"{path}: {exc}") from None
    return CalibrationImage(path.name, frame.pixels, frame.imager_pixel_spacing_mm, frame.sid_mm)


def cmd_calibrate(args: argparse.Namespace) -> int:
    rows, cols = args.grid
    spec = PhantomSpec(rows, cols, args.pitch, args.ball_diameter)
    images = [_read(Path(p)) for p in args.images]
    try:
        calibration, report = calibrate(images, spec, CalibrationOptions(min_images=args.min_images),
                                        args.id or args.out.stem, args.description)
    except CalibrationError as exc:
        raise ValueError(f"calibration failed: {exc}") from None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(calibration.document(), indent=2))
    c = calibration.camera
    for item in report["images"]:
        print(f"  {item['image']}: {item['balls']} balls, tilt {item['tilt_deg']:.0f} deg, "
              f"RMS {item['rms_px']:.3f} px")
    for item in report["rejected"]:
        print(f"  {item['image']}: not used ({item['reason']})")
    print(f"calibration {calibration.calibration_id}: f {c.fx:.1f} px, principal point "
          f"({c.cx:.1f}, {c.cy:.1f}){' (held at the field centre)' if report['principal_held'] else ''}, "
          f"RMS {report['rms_px']:.3f} px over {report['used']} images -> {args.out}")
    return 0


def add_calibrate_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate a C-arm from ball-grid phantom images")
    p.add_argument("images", nargs="+", type=Path, help="phantom frames (DICOM)")
    p.add_argument("--grid", type=_grid, default=(5, 5), help="balls per row x column (5x5)")
    p.add_argument("--pitch", type=float, default=25.0, help="ball spacing, mm")
    p.add_argument("--ball-diameter", type=float, default=3.0, help="mm")
    p.add_argument("--min-images", type=int, default=CalibrationOptions().min_images)
    p.add_argument("--id", help="calibration id (default: the output file's name)")
    p.add_argument("--description", default="", help="free text stored in the file")
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=cmd_calibrate)
