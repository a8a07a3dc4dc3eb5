"""A Secondary Capture image per view: the X-ray with its contours and the projected plane.

What the surgeon sees on the OR display: the received frame (windowed to 8 bit), the bone
and pin contours the solver used, each posed pin axis and the resection plane projected
into that view with the solved poses, and the angles (or the refusal reason) burned in.
Everything is drawn in the frame's own (distorted) pixel coordinates, so it overlays the
original image exactly. Colours: bone yellow, pin 1 cyan, pin 2 magenta, plane green
(red when outside the plan's tolerance).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime

import cv2
import highdicom as hd
import numpy as np
from pydicom.dataset import Dataset
from pydicom.valuerep import DA, TM

from slamtka.service.headers import image_laterality, stamp_dates

__all__ = ["ScOverlay", "render_overlay", "wrap_text", "build_sc", "patient_orientation", "SC_SERIES_NUMBER"]

SC_SERIES_NUMBER = 9702
_COLOURS = {"bone": (255, 220, 0), "pin1": (0, 230, 255), "pin2": (255, 60, 255)}
_PASS, _FAIL = (60, 230, 60), (255, 60, 60)


@dataclass
class ScOverlay:
    """What to draw on one view, in the frame's pixel coordinates (u = column, v = row)."""

    contours: dict[str, np.ndarray]  # label -> (N, 2)
    plane_px: np.ndarray | None = None  # (M, 2) closed polygon of the projected plane patch
    pin_axes_px: list[np.ndarray] = field(default_factory=list)  # (2, 2) tip, end per pin
    within_tolerance: bool | None = None
    text: list[str] = field(default_factory=list)


def _window(pixels: np.ndarray) -> np.ndarray:
    """uint16 X-ray to uint8 grey with a robust (1-99 percentile) window."""
    low, high = np.percentile(pixels, (1.0, 99.0))
    scaled = (pixels.astype(np.float32) - low) / max(float(high - low), 1.0)
    return (np.clip(scaled, 0.0, 1.0) * 255.0).astype(np.uint8)


def _dots(rgb: np.ndarray, points: np.ndarray, colour: tuple[int, int, int], radius: int) -> None:
    h, w = rgb.shape[:2]
    pix = np.round(np.asarray(points, float).reshape(-1, 2)).astype(np.int64)
    ok = (pix[:, 0] >= 0) & (pix[:, 0] < w) & (pix[:, 1] >= 0) & (pix[:, 1] < h)
    mask: np.ndarray = np.zeros((h, w), np.uint8)
    mask[pix[ok, 1], pix[ok, 0]] = 255
    if radius > 0:
        mask = cv2.dilate(mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                          (2 * radius + 1, 2 * radius + 1)))
    rgb[mask > 0] = colour


def wrap_text(lines: list[str], width_px: int, scale: int) -> list[str]:
    """``lines`` broken at spaces so that none is wider than ``width_px`` as drawn (a word
    longer than the width is cut into pieces): the overlay never loses text at the edge."""
    def fits(text: str) -> bool:
        (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, 3 * scale)
        return w <= width_px

    out: list[str] = []
    for line in lines:
        current = ""
        for word in line.split():
            while not fits(word) and len(word) > 1:  # longer than the width: cut it
                cut = max(k for k in range(1, len(word)) if fits(word[:k]) or k == 1)
                if current:
                    out.append(current)
                    current = ""
                out.append(word[:cut])
                word = word[cut:]
            candidate = f"{current} {word}".strip()
            if fits(candidate):
                current = candidate
            else:
                out.append(current)
                current = word
        out.append(current)
    return out


def render_overlay(pixels: np.ndarray, overlay: ScOverlay) -> np.ndarray:
    """The annotated view as an (H, W, 3) uint8 RGB image."""
    grey = _window(pixels)
    rgb = np.repeat(grey[:, :, None], 3, axis=2)
    scale = max(1, round(min(grey.shape) / 512))  # line widths and text grow with the image
    for label, points in overlay.contours.items():
        _dots(rgb, points, _COLOURS.get(label, (255, 255, 255)), scale)
    plane_colour = _FAIL if overlay.within_tolerance is False else _PASS
    if overlay.plane_px is not None and len(overlay.plane_px) >= 2:
        poly = np.round(overlay.plane_px).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(rgb, [poly], True, plane_colour, scale, cv2.LINE_AA)
    for label, axis in zip(("pin1", "pin2"), overlay.pin_axes_px):
        a, b = np.round(np.asarray(axis, float)).astype(int)
        cv2.line(rgb, tuple(map(int, a)), tuple(map(int, b)), _COLOURS[label], scale, cv2.LINE_AA)
    for i, line in enumerate(wrap_text(overlay.text, rgb.shape[1] - 20 * scale, scale)):
        origin = (10 * scale, (22 + 22 * i) * scale)
        cv2.putText(rgb, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (0, 0, 0),
                    3 * scale, cv2.LINE_AA)
        cv2.putText(rgb, line, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (255, 255, 255),
                    scale, cv2.LINE_AA)
    return rgb


def patient_orientation(R_anat_cam: np.ndarray) -> tuple[str, str]:
    """DICOM Patient Orientation letters of the image rows and columns.

    ``R_anat_cam`` rotates camera-frame directions into the anatomical frame (+x the
    patient's right, +y anterior, +z proximal/head): image rows run along camera +x, columns
    along camera +y. Components above 0.3 contribute a letter, largest first.
    """
    letters = np.array([["R", "A", "H"], ["L", "P", "F"]])

    def describe(direction: np.ndarray) -> str:
        order = np.argsort(-np.abs(direction))
        return "".join(letters[int(direction[i] < 0), i] for i in order if abs(direction[i]) > 0.3)

    return describe(R_anat_cam[:, 0]), describe(R_anat_cam[:, 1])


def build_sc(source: Dataset, rgb: np.ndarray, *, series_uid: str, sop_instance_uid: str,
             instance_number: int, orientation: tuple[str, str] | None,
             content_datetime: datetime, manufacturer: str = "slamtka",
             institution: str = "", description: str = "slamtka contours and resection plane",
             series_number: int = SC_SERIES_NUMBER) -> Dataset:
    """A Secondary Capture instance of ``rgb`` in the study and patient of ``source`` (its
    header sanitised, :mod:`service.headers`); dated ``content_datetime`` (the run's), so
    the same run built again is the same object.

    ``orientation`` (from the solved or initial view pose) may be None when no pose is known:
    Patient Orientation is then left empty (type 2: unknown).
    """
    sc = hd.sc.SCImage.from_ref_dataset(
        ref_dataset=source, pixel_array=rgb, photometric_interpretation="RGB", bits_allocated=8,
        coordinate_system="PATIENT",
        patient_orientation=(orientation[0][0], orientation[1][0]) if orientation else ("A", "F"),
        series_instance_uid=series_uid, series_number=series_number,
        sop_instance_uid=sop_instance_uid, instance_number=instance_number,
        manufacturer=manufacturer, laterality=image_laterality(source.get("Laterality")),
        series_description=description)
    # highdicom takes single letters; DICOM allows the oblique combinations too.
    sc.PatientOrientation = list(orientation) if orientation else []
    sc.BurnedInAnnotation = "YES"
    sc.ImageType = ["DERIVED", "SECONDARY"]
    sc.DerivationDescription = "X-ray with measured contours, pin axes and resection plane"
    reference = Dataset()
    reference.ReferencedSOPClassUID = source.SOPClassUID
    reference.ReferencedSOPInstanceUID = source.SOPInstanceUID
    sc.SourceImageSequence = [reference]
    if institution:
        sc.InstitutionName = institution
    stamp_dates(sc, content_datetime)
    sc.DateOfSecondaryCapture = DA(content_datetime.strftime("%Y%m%d"))
    sc.TimeOfSecondaryCapture = TM(content_datetime.strftime("%H%M%S.%f"))
    return sc
