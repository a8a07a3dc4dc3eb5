"""The versioned C-arm calibration file: what the service and ``slamtka solve`` load.

``slamtka-calibration/2``: id, description, creation time, detector (size, pixel spacing,
field size when known), camera (K and field radius), distortion, RMS overall and per image,
rejected images with their reason, the phantom, the estimated plate error, the intrinsics'
standard deviations, optionally the C-arm it belongs to (``device``), and a sha256 over the
rest. Version 1 files (no distortion, no pixel spacing) still load. Estimating a calibration
from phantom frames is :mod:`slamtka.solver.imaging.calibration`'s; loading one needs none
of it (nor its optimiser), so a measurement starts quickly.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.imaging.distortion import Distortion
from slamtka.solver.jsonfile import read_json_object

__all__ = ["Calibration", "CalibrationError", "load_calibration", "calibration_document", "calibration_from_document",
           "write_calibration", "assign_device", "FORMAT", "FORMAT_V1"]

FORMAT = "slamtka-calibration/2"
FORMAT_V1 = "slamtka-calibration/1"


class CalibrationError(ValueError):
    """A calibration set, file or frame that cannot be used, with the reason; a refused
    calibration run also carries its report (``report``)."""

    def __init__(self, message: str, report: dict | None = None):
        super().__init__(message)
        self.report = report


# -- the calibration as the pipeline uses it ------------------------------------------------

@dataclass
class Calibration:
    """One C-arm's intrinsics, distortion and detector, as loaded from its file."""

    camera: Camera
    distortion: Distortion | None  # None: images carry no distortion (or are corrected)
    calibration_id: str
    sha256: str
    pixel_spacing_mm: tuple[float, float] | None
    _document: dict = field(repr=False, default_factory=dict)

    def document(self) -> dict:
        """The calibration file's content (for audit records)."""
        return self._document

    @property
    def device(self) -> dict[str, str]:
        """The C-arm this calibration belongs to (identity key -> value), if assigned."""
        return dict(self._document.get("device") or {})

    @property
    def field_mm(self) -> float | None:
        """The detector field (intensifier size / zoom) it was made for, when known."""
        value = (self._document.get("detector") or {}).get("field_mm")
        return None if value is None else float(value)

    def undistort_points(self, uv: np.ndarray) -> np.ndarray:
        """Ideal pinhole pixel positions (N, 2) of raw observed positions (N, 2)."""
        uv = self._points(uv)
        return uv if self.distortion is None or len(uv) == 0 else self.distortion.undistort(uv)

    def distort_points(self, uv: np.ndarray) -> np.ndarray:
        """Raw (as imaged) pixel positions (N, 2) of ideal pinhole positions (N, 2)."""
        uv = self._points(uv)
        return uv if self.distortion is None or len(uv) == 0 else self.distortion.distort(uv)

    @staticmethod
    def _points(uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, float)
        if uv.size == 0:
            return np.zeros((0, 2))
        if uv.ndim != 2 or uv.shape[1] != 2 or not np.all(np.isfinite(uv)):
            raise CalibrationError(f"pixel positions must be finite (N, 2), got shape {uv.shape}")
        return uv.copy()

    def check_frame(self, frame_or_width, height: int | None = None,
                    pixel_spacing: tuple[float, float] | None = None) -> str | None:
        """Why a frame must be refused with this calibration, or None when it matches.

        Takes a frame (anything with ``width``, ``height`` and ``imager_pixel_spacing_mm``,
        such as ``service.frames.Frame``) or its width, height and pixel spacing (mm).
        """
        if height is None:
            frame = frame_or_width
            width, height = frame.width, frame.height
            pixel_spacing = frame.imager_pixel_spacing_mm
        else:
            width = frame_or_width
        if (width, height) != (self.camera.width, self.camera.height):
            return (f"frame is {width}x{height} px but calibration {self.calibration_id} is for "
                    f"{self.camera.width}x{self.camera.height} px")
        if self.pixel_spacing_mm is not None and pixel_spacing is not None and not np.allclose(
                pixel_spacing, self.pixel_spacing_mm, rtol=1e-3, atol=1e-5):
            return (f"frame pixel spacing {list(pixel_spacing)} mm differs from calibration "
                    f"{self.calibration_id} ({list(self.pixel_spacing_mm)} mm)")
        return None


def _digest(body: dict) -> str:
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def calibration_document(camera: Camera, calibration_id: str, description: str,
                         distortion: Distortion | None = None,
                         pixel_spacing_mm: tuple[float, float] | None = None,
                         extra: dict | None = None, field_mm: float | None = None) -> dict:
    """The versioned, checksummed calibration file content."""
    body = {"format": FORMAT, "id": calibration_id, "description": description,
            "created": datetime.now(UTC).isoformat(timespec="seconds"),
            "detector": {"width": camera.width, "height": camera.height,
                         "pixel_spacing_mm": None if pixel_spacing_mm is None else list(pixel_spacing_mm),
                         "field_mm": field_mm},
            "camera": camera.to_json(),
            "distortion": {"model": "none"} if distortion is None else distortion.to_json(),
            **(extra or {})}
    return {**body, "sha256": _digest(body)}


def assign_device(document: dict, device: dict[str, str], field_mm: float | None) -> dict:
    """The calibration document bound to one C-arm (``device``: its identity, e.g. Device
    Serial Number) and detector field, re-checksummed; the original checksum is kept."""
    body = {k: v for k, v in document.items() if k != "sha256"}
    detector = dict(body.get("detector") or {})
    if field_mm is not None:
        detector["field_mm"] = float(field_mm)
    body.update(detector=detector, device=dict(device),
                assigned={"at": datetime.now(UTC).isoformat(timespec="seconds"),
                          "original_sha256": document.get("sha256")})
    return {**body, "sha256": _digest(body)}


def write_calibration(path: str | Path, camera: Camera, distortion: Distortion | None,
                      description: str, calibration_id: str | None = None,
                      pixel_spacing_mm: tuple[float, float] | None = None,
                      extra: dict | None = None) -> Calibration:
    """Write a calibration file (whole, then renamed into place) and return it as loaded."""
    path = Path(path)
    doc = calibration_document(camera, calibration_id or path.stem, description, distortion,
                               pixel_spacing_mm, extra)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(doc, indent=2))
    temporary.replace(path)
    return load_calibration(path)


def load_calibration(path: str | Path) -> Calibration:
    """Read and verify a calibration file (version 2, or version 1 without distortion)."""
    path = Path(path)
    try:
        doc = read_json_object(path)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from None
    return calibration_from_document(doc, str(path))


def calibration_from_document(doc: dict, where: str) -> Calibration:
    """A calibration file's content (as read, or as a run recorded it), verified; ``where``
    names it in errors."""
    if doc.get("format") not in (FORMAT, FORMAT_V1):
        raise CalibrationError(f"{where}: format {doc.get('format')!r} "
                               f"is not {FORMAT!r} or {FORMAT_V1!r}")
    body = {k: v for k, v in doc.items() if k != "sha256"}
    if doc.get("sha256") != _digest(body):
        raise CalibrationError(f"{where}: calibration checksum does not match its content")
    try:
        camera = Camera.from_json(doc["camera"])
        distortion_doc = doc.get("distortion") or {"model": "none"}
        if not isinstance(distortion_doc, dict):
            raise TypeError(f"distortion must be an object with a model, "
                            f"not {type(distortion_doc).__name__}")
        distortion = None if distortion_doc.get("model") == "none" else Distortion.from_json(distortion_doc)
        spacing = (doc.get("detector") or {}).get("pixel_spacing_mm")
        spacing = None if spacing is None else (float(spacing[0]), float(spacing[1]))
        calibration_id = str(doc["id"])
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise CalibrationError(f"{where}: malformed calibration ({exc})") from None
    return Calibration(camera, distortion, calibration_id, doc["sha256"], spacing, doc)
