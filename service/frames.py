"""X-ray frames as DICOM: encode a C-arm image, decode one received over the network.

A :class:`Frame` is one single-plane C-arm image with the geometry attributes the pipeline
cross-checks (docs/design.md): positioner angles, source distances and the imager pixel
spacing at the detector. :func:`encode_frame` writes it as X-Ray Angiographic Image Storage
(default) or X-Ray Radiofluoroscopic Image Storage, as mobile C-arms send them; the result
passes dicom3tools' ``dciodvfy``. :func:`decode_frame` accepts XA, Enhanced XA, RF, DX and
Secondary Capture instances and raises :class:`FrameError` naming the attribute that is
missing or invalid. Of an Enhanced XA instance (multi-frame, geometry in functional groups)
the first frame is used, with the geometry recorded for it.

Pixel convention: ``pixels`` is unsigned 16 bit, higher = more X-ray intensity at the detector
(bone and metal dark, as MONOCHROME2 XA stores it). The value is read from the bits BitsStored
and HighBit name (signed values shifted to offset binary); an instance stored the other way
round (Pixel Intensity Relationship Sign -1, or without it MONOCHROME1 or Presentation LUT
Shape INVERSE) is inverted on decode so downstream code sees one convention; an attribute
value outside the standard is refused by name. Uncompressed pixel data is read directly,
compressed data through pydicom's decoders.
Times are UTC-aware; an instance without a timezone offset is read as UTC.

A :class:`FrameHeader` is a frame without its pixels: what the receiver decodes once and
keeps beside the spooled instance (:mod:`service.decoded`), so that later stages and a
restart read the facts back instead of decoding the header again, and decode only the
pixels (:func:`decode_pixels`) when they need them.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime, timedelta, timezone

import numpy as np
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.pixels import pixel_array
from pydicom.uid import (
    PYDICOM_IMPLEMENTATION_UID,
    UID,
    ExplicitVRLittleEndian,
    RLELossless,
    generate_uid,
)

__all__ = ["Frame", "FrameHeader", "FrameError", "encode_frame", "decode_frame", "decode_pixels",
           "case_key", "SOP_CLASSES", "SIMULATED_SERIAL", "XA_IMAGE_STORAGE",
           "ENHANCED_XA_IMAGE_STORAGE", "RF_IMAGE_STORAGE"]

XA_IMAGE_STORAGE = UID("1.2.840.10008.5.1.4.1.1.12.1")
ENHANCED_XA_IMAGE_STORAGE = UID("1.2.840.10008.5.1.4.1.1.12.1.1")
RF_IMAGE_STORAGE = UID("1.2.840.10008.5.1.4.1.1.12.2")
DX_PRESENTATION_STORAGE = UID("1.2.840.10008.5.1.4.1.1.1.1")
DX_PROCESSING_STORAGE = UID("1.2.840.10008.5.1.4.1.1.1.1.1")
SECONDARY_CAPTURE_STORAGE = UID("1.2.840.10008.5.1.4.1.1.7")

# SOP class -> modality values accepted for it on decode.
SOP_CLASSES: dict[str, tuple[str, ...]] = {
    XA_IMAGE_STORAGE: ("XA",),
    ENHANCED_XA_IMAGE_STORAGE: ("XA",),
    RF_IMAGE_STORAGE: ("RF",),
    DX_PRESENTATION_STORAGE: ("DX",),
    DX_PROCESSING_STORAGE: ("DX",),
    SECONDARY_CAPTURE_STORAGE: ("XA", "RF", "DX", "OT"),
}
_ENCODABLE: dict[str, str] = {XA_IMAGE_STORAGE: "XA", RF_IMAGE_STORAGE: "RF"}
# Where Enhanced XA keeps, per frame, what single-frame XA has at the top level:
# (functional group sequence, attribute in it, single-frame attribute it stands for).
_FUNCTIONAL_GROUP_ATTRIBUTES = (
    ("PositionerPositionSequence", "PositionerPrimaryAngle", "PositionerPrimaryAngle"),
    ("PositionerPositionSequence", "PositionerSecondaryAngle", "PositionerSecondaryAngle"),
    ("XRayGeometrySequence", "DistanceSourceToDetector", "DistanceSourceToDetector"),
    ("XRayGeometrySequence", "DistanceSourceToIsocenter", "DistanceSourceToPatient"),
    ("FramePixelDataPropertiesSequence", "ImagerPixelSpacing", "ImagerPixelSpacing"),
    ("PixelMeasuresSequence", "PixelSpacing", "PixelSpacing"),
    ("FrameContentSequence", "FrameAcquisitionDateTime", "AcquisitionDateTime"),
    ("FrameAnatomySequence", "FrameLaterality", "ImageLaterality"),
)
_FUNCTIONAL_GROUPS = ("SharedFunctionalGroupsSequence", "PerFrameFunctionalGroupsSequence")


SIMULATED_SERIAL = "SIM-0001"  # the Device Serial Number of the simulated C-arm


class FrameError(ValueError):
    """A DICOM instance that cannot be used as an X-ray frame; the message names why."""


@dataclass
class Frame:
    """One C-arm image and the acquisition geometry recorded with it."""

    pixels: np.ndarray  # (H, W) uint16, higher = more X-ray intensity (bone dark)
    imager_pixel_spacing_mm: tuple[float, float]  # (row spacing, column spacing) at the detector
    primary_angle_deg: float | None = None  # PositionerPrimaryAngle (LAO +, RAO -)
    secondary_angle_deg: float | None = None  # PositionerSecondaryAngle (CRA +, CAU -)
    sid_mm: float | None = None  # DistanceSourceToDetector
    sod_mm: float | None = None  # DistanceSourceToPatient (isocentre)
    acquisition_datetime: datetime | None = None  # UTC-aware
    patient_id: str = "ANON"
    patient_name: str = "ANONYMOUS"
    study_uid: str = field(default_factory=generate_uid)
    series_uid: str = field(default_factory=generate_uid)
    sop_instance_uid: str = field(default_factory=generate_uid)
    sop_class_uid: str = XA_IMAGE_STORAGE
    laterality: str | None = None  # "L" or "R"
    modality: str = "XA"
    bits_stored: int = 16
    instance_number: int = 1

    def __post_init__(self) -> None:
        pixels = np.asarray(self.pixels)
        if pixels.ndim != 2 or min(pixels.shape) < 2:
            raise ValueError(f"frame pixels must be a 2-D image, got shape {pixels.shape}")
        if pixels.dtype != np.uint16:
            raise ValueError(f"frame pixels must be uint16, got {pixels.dtype}")
        if not 8 <= self.bits_stored <= 16:
            raise ValueError(f"bits stored {self.bits_stored} is outside 8-16")
        if int(pixels.max(initial=0)) >= 1 << self.bits_stored:
            raise ValueError(f"pixel values exceed {self.bits_stored} bits stored")
        spacing = tuple(float(s) for s in self.imager_pixel_spacing_mm)
        if len(spacing) != 2 or not all(0.0 < s < 10.0 for s in spacing):
            raise ValueError(f"imager pixel spacing {self.imager_pixel_spacing_mm} mm is not plausible")
        if self.laterality not in (None, "L", "R"):
            raise ValueError(f"laterality must be 'L', 'R' or None, got {self.laterality!r}")
        if self.acquisition_datetime is not None and self.acquisition_datetime.tzinfo is None:
            raise ValueError("acquisition_datetime must be timezone-aware (UTC)")
        self.pixels = pixels
        self.imager_pixel_spacing_mm = spacing

    @property
    def height(self) -> int:
        return int(self.pixels.shape[0])

    @property
    def width(self) -> int:
        return int(self.pixels.shape[1])

    def header(self) -> FrameHeader:
        """The frame without its pixels."""
        return FrameHeader(**{f.name: getattr(self, f.name) for f in fields(FrameHeader)})


@dataclass(frozen=True)
class FrameHeader:
    """What a received frame says besides its pixels: every attribute of :class:`Frame`
    but ``pixels`` and ``bits_stored`` (which come with the pixels), in JSON for the spool."""

    imager_pixel_spacing_mm: tuple[float, float]
    primary_angle_deg: float | None
    secondary_angle_deg: float | None
    sid_mm: float | None
    sod_mm: float | None
    acquisition_datetime: datetime | None
    patient_id: str
    patient_name: str
    study_uid: str
    series_uid: str
    sop_instance_uid: str
    sop_class_uid: str
    laterality: str | None
    modality: str
    instance_number: int

    def with_pixels(self, pixels: np.ndarray, bits_stored: int) -> Frame:
        """The :class:`Frame` (validated) of these facts and decoded pixels."""
        return Frame(pixels=pixels, bits_stored=bits_stored, **vars(self))

    def to_json(self) -> dict:
        doc = asdict(self)
        doc["imager_pixel_spacing_mm"] = list(self.imager_pixel_spacing_mm)
        when = self.acquisition_datetime
        doc["acquisition_datetime"] = None if when is None else when.isoformat()
        return doc

    @staticmethod
    def from_json(doc: dict) -> FrameHeader:
        """The facts of :meth:`to_json`; KeyError, TypeError or ValueError when ``doc`` is
        not such a document (a member missing, another version)."""
        names = {f.name for f in fields(FrameHeader)}
        if set(doc) != names:
            raise KeyError(f"frame facts differ in {sorted(names ^ set(doc))}")
        when = doc["acquisition_datetime"]
        row, column = doc["imager_pixel_spacing_mm"]
        return FrameHeader(**{**doc, "imager_pixel_spacing_mm": (float(row), float(column)),
                              "acquisition_datetime": None if when is None
                              else datetime.fromisoformat(when)})


def _ds(value: float) -> str:
    """A decimal string (VR DS, at most 16 characters)."""
    return f"{value:.6g}"


def encode_frame(frame: Frame, *, manufacturer: str = "slamtka", station_name: str = "SIMCARM",
                 device_serial_number: str = SIMULATED_SERIAL, intensifier_size_mm: float | None = None,
                 kvp: float = 70.0, tube_current_ma: float = 5.0, exposure_time_ms: float = 200.0,
                 study_id: str = "1", series_number: int = 1) -> Dataset:
    """The frame as an XA (default) or RF Image Storage instance with its file meta.

    Save it with ``ds.save_as(path, enforce_file_format=True)``.
    """
    if frame.sop_class_uid not in _ENCODABLE:
        raise ValueError(f"cannot encode SOP class {frame.sop_class_uid}: use XA or RF Image Storage")
    modality = _ENCODABLE[frame.sop_class_uid]
    if frame.modality != modality:
        raise ValueError(f"modality {frame.modality!r} does not match SOP class ({modality})")
    when = (frame.acquisition_datetime or datetime.now(UTC)).astimezone(UTC)
    date, time = when.strftime("%Y%m%d"), when.strftime("%H%M%S.%f")

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = UID(frame.sop_class_uid)
    meta.MediaStorageSOPInstanceUID = UID(frame.sop_instance_uid)
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SpecificCharacterSet = "ISO_IR 100"
    # SOP Common
    ds.SOPClassUID, ds.SOPInstanceUID = frame.sop_class_uid, frame.sop_instance_uid
    ds.InstanceCreationDate, ds.InstanceCreationTime = date, time
    ds.TimezoneOffsetFromUTC = "+0000"
    # Patient
    ds.PatientName, ds.PatientID = frame.patient_name, frame.patient_id
    ds.PatientBirthDate, ds.PatientSex = "", ""
    # General Study
    ds.StudyInstanceUID, ds.StudyID = frame.study_uid, study_id
    ds.StudyDate, ds.StudyTime = date, time
    ds.ReferringPhysicianName, ds.AccessionNumber = "", ""
    # General Series
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = modality, frame.series_uid, series_number
    ds.BodyPartExamined = "KNEE"
    ds.Laterality = frame.laterality or ""
    # General Equipment
    ds.Manufacturer, ds.StationName = manufacturer, station_name
    if device_serial_number:
        ds.DeviceSerialNumber = device_serial_number
    # General Image / Acquisition
    ds.InstanceNumber = frame.instance_number
    ds.PatientOrientation = ""
    ds.ContentDate, ds.ContentTime = date, time
    ds.AcquisitionDateTime = when.strftime("%Y%m%d%H%M%S.%f") + "+0000"
    ds.ImageType = ["ORIGINAL", "PRIMARY", "SINGLE PLANE"]
    ds.LossyImageCompression = "00"
    ds.PixelIntensityRelationship = "LIN"
    # Image Pixel
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = frame.height, frame.width
    ds.BitsAllocated, ds.BitsStored, ds.HighBit = 16, frame.bits_stored, frame.bits_stored - 1
    ds.PixelRepresentation = 0
    ds.PixelData = np.ascontiguousarray(frame.pixels, dtype="<u2").tobytes()
    # X-Ray Acquisition and positioner
    ds.KVP = _ds(kvp)
    ds.RadiationSetting = "GR"
    ds.XRayTubeCurrent = int(round(tube_current_ma))
    ds.ExposureTime = int(round(exposure_time_ms))
    ds.Exposure = int(round(tube_current_ma * exposure_time_ms / 1000.0))
    ds.ImagerPixelSpacing = [_ds(s) for s in frame.imager_pixel_spacing_mm]
    ds.FieldOfViewShape = "ROUND"
    if intensifier_size_mm is not None:
        ds.IntensifierSize = _ds(intensifier_size_mm)
    if frame.sid_mm is not None:
        ds.DistanceSourceToDetector = _ds(frame.sid_mm)
    if frame.sod_mm is not None:
        ds.DistanceSourceToPatient = _ds(frame.sod_mm)
    # Type 2 in the XA Positioner module: present, empty when unknown. (The RF IOD has no
    # such attributes; they are kept there too, as C-arms do, making it Standard Extended.)
    ds.PositionerPrimaryAngle = "" if frame.primary_angle_deg is None else _ds(frame.primary_angle_deg)
    ds.PositionerSecondaryAngle = "" if frame.secondary_angle_deg is None else _ds(frame.secondary_angle_deg)
    return ds


_PYDICOM_DECODERS = logging.getLogger("pydicom.pixels.decoders.base")


@contextlib.contextmanager
def _quiet(logger: logging.Logger):
    """Silence ``logger`` for the duration (restoring its previous state)."""
    disabled, logger.disabled = logger.disabled, True
    try:
        yield
    finally:
        logger.disabled = disabled


def _required(ds: Dataset, keyword: str):
    value = ds.get(keyword)
    if value is None or value == "":
        raise FrameError(f"{keyword} is missing")
    return value


def _optional_integer(ds: Dataset, keyword: str) -> int | None:
    """An integer attribute, None if absent or empty; junk names the attribute."""
    try:
        value = ds.get(keyword)  # a received value is converted on access, and may fail there
    except (TypeError, ValueError) as exc:
        raise FrameError(f"{keyword} cannot be read ({exc})") from None
    if value is None or value == "":
        return None
    try:
        return int(value)
    except (TypeError, ValueError):
        raise FrameError(f"{keyword} {str(value)!r} is not an integer") from None


def _integer(ds: Dataset, keyword: str, default: int | None = None) -> int:
    """An integer attribute (required unless it has a default)."""
    value = _optional_integer(ds, keyword)
    if value is None:
        if default is None:
            raise FrameError(f"{keyword} is missing")
        return default
    return value


def _optional_float(ds: Dataset, keyword: str, low: float, high: float) -> float | None:
    try:
        value = ds.get(keyword)
        if value is None or value == "":
            return None
        number = float(value)
    except (TypeError, ValueError):
        raise FrameError(f"{keyword} is not a number") from None
    if not (np.isfinite(number) and low <= number <= high):
        raise FrameError(f"{keyword} {number} is outside the plausible range [{low}, {high}]")
    return number


def _utc_offset(text: str, keyword: str) -> timezone:
    """A ``+HHMM``/``-HHMM`` offset from UTC."""
    if len(text) != 5 or text[0] not in "+-" or not text[1:].isdigit():
        raise FrameError(f"{keyword} offset {text!r} is not of the form +HHMM")
    hours, minutes = int(text[1:3]), int(text[3:5])
    if hours > 14 or minutes > 59:  # DICOM's offsets run from -1200 to +1400
        raise FrameError(f"{keyword} offset {text!r} is not a valid offset from UTC")
    minutes += hours * 60
    return timezone((-1 if text[0] == "-" else 1) * timedelta(minutes=minutes))


def _acquisition_datetime(ds: Dataset) -> datetime | None:
    """AcquisitionDateTime, else AcquisitionDate/Time, else ContentDate/Time, in UTC."""
    text = str(ds.get("AcquisitionDateTime", "") or "")
    if not text:
        for prefix in ("Acquisition", "Content"):
            date, time = ds.get(f"{prefix}Date", ""), ds.get(f"{prefix}Time", "")
            if date and time:
                text = f"{date}{time}"
                break
    if not text:
        return None
    offset = _utc_offset(str(ds.get("TimezoneOffsetFromUTC", "") or "+0000"), "TimezoneOffsetFromUTC")
    if len(text) > 5 and text[-5] in "+-":
        offset, text = _utc_offset(text[-5:], "AcquisitionDateTime"), text[:-5]
    fraction = 0
    if "." in text:
        text, frac = text.split(".", 1)
        fraction = int((frac + "000000")[:6]) if frac.isdigit() else -1
    try:
        if fraction < 0 or len(text) < 8:
            raise ValueError
        padded = (text + "000000")[:14]
        when = datetime.strptime(padded, "%Y%m%d%H%M%S").replace(microsecond=fraction, tzinfo=offset)
    except ValueError:
        raise FrameError(f"acquisition date-time {text!r} is not a valid DICOM date-time") from None
    return when.astimezone(UTC)


def _pixel_spacing(ds: Dataset) -> tuple[float, float]:
    for keyword in ("ImagerPixelSpacing", "PixelSpacing"):
        value = ds.get(keyword)
        if value:
            try:
                spacing = tuple(float(v) for v in value)
            except (TypeError, ValueError):
                raise FrameError(f"{keyword} {value!r} is not numeric") from None
            if len(spacing) != 2 or not all(0.0 < s < 10.0 for s in spacing):
                raise FrameError(f"{keyword} {list(spacing)} mm is not a plausible pixel spacing")
            return spacing
    raise FrameError("ImagerPixelSpacing is missing (and no PixelSpacing either)")


def _inverted(ds: Dataset, photometric: str) -> bool:
    """Whether stored values run opposite to the convention (higher = more X-ray intensity
    at the detector, bone and metal dark, as MONOCHROME2 XA stores it).

    Pixel Intensity Relationship Sign, when present, says exactly that (-1: higher values
    mean less intensity); the photometric interpretation and Presentation LUT Shape only say
    how to display, so they decide only without it. MONOCHROME1 and INVERSE are one
    inversion, not two: DX pairs them to say the same thing.
    """
    sign = _optional_integer(ds, "PixelIntensityRelationshipSign")
    if sign not in (None, 1, -1):
        raise FrameError(f"PixelIntensityRelationshipSign {sign} is not +1 or -1")
    shape = str(ds.get("PresentationLUTShape", "") or "")
    if shape not in ("", "IDENTITY", "INVERSE"):
        raise FrameError(f"PresentationLUTShape {shape!r} is not IDENTITY or INVERSE")
    if sign is not None:
        return sign == -1
    return photometric == "MONOCHROME1" or shape == "INVERSE"


def _stored_words(ds: Dataset, syntax: UID, frames: int, count: int, bits_allocated: int,
                  high_bit: int, bits_stored: int) -> np.ndarray:
    """The first frame's pixel cells as they were stored (unused bits included)."""
    if not syntax.is_encapsulated:
        return np.frombuffer(ds.PixelData, "<u1" if bits_allocated == 8 else "<u2", count)
    if syntax != RLELossless and high_bit != bits_stored - 1:
        raise FrameError(f"HighBit {high_bit} must be BitsStored - 1 ({bits_stored - 1}) in "
                         f"JPEG transfer syntax {syntax.name}")
    try:
        # pydicom logs each failed decoder's traceback; the FrameError below already says it.
        with _quiet(_PYDICOM_DECODERS):
            array = pixel_array(ds, index=0 if frames > 1 else None, correct_unused_bits=False)
    except Exception as exc:  # pydicom raises many types for bad or undecodable pixel data
        raise FrameError(f"PixelData cannot be decoded (transfer syntax {syntax}): {exc}") from None
    if array.size != count:
        raise FrameError(f"PixelData decodes to {array.size} pixels, Rows x Columns say {count}")
    return array.reshape(-1)  # signed cells wrap to their two's complement bits on astype


def _pixels(ds: Dataset) -> tuple[np.ndarray, int]:
    """The pixel matrix as uint16 in the convention of :func:`_inverted`, and its bits stored.

    The value is read from bits HighBit-BitsStored+1 .. HighBit of each cell (what lies
    outside, such as old overlay planes, is dropped); signed values are shifted to offset
    binary (-2^(n-1) becomes 0), which keeps their order.
    """
    if _integer(ds, "SamplesPerPixel") != 1:
        raise FrameError(f"SamplesPerPixel {ds.SamplesPerPixel} is not 1 (not a grey-scale X-ray)")
    photometric = str(_required(ds, "PhotometricInterpretation"))
    if photometric not in ("MONOCHROME1", "MONOCHROME2"):
        raise FrameError(f"PhotometricInterpretation {photometric} is not MONOCHROME1/2")
    try:
        frames = int(ds.get("NumberOfFrames", 1) or 1)
    except (TypeError, ValueError):
        raise FrameError(f"NumberOfFrames {ds.NumberOfFrames!r} is not a number") from None
    if frames < 1 or (frames > 1 and ds.SOPClassUID != ENHANCED_XA_IMAGE_STORAGE):
        raise FrameError(f"NumberOfFrames is {ds.NumberOfFrames}: send single-frame images")
    representation = _integer(ds, "PixelRepresentation")
    if representation not in (0, 1):
        raise FrameError(f"PixelRepresentation {representation} is not 0 (unsigned) or 1 (signed)")
    bits_allocated = _integer(ds, "BitsAllocated")
    bits_stored = _integer(ds, "BitsStored")
    if bits_allocated not in (8, 16) or not 1 <= bits_stored <= bits_allocated:
        raise FrameError(f"BitsAllocated {bits_allocated} / BitsStored {bits_stored} not supported")
    high_bit = _integer(ds, "HighBit")
    if not bits_stored - 1 <= high_bit < bits_allocated:
        raise FrameError(f"HighBit {high_bit} does not fit BitsStored {bits_stored} in "
                         f"BitsAllocated {bits_allocated}")
    inverted = _inverted(ds, photometric)
    rows, columns = _integer(ds, "Rows"), _integer(ds, "Columns")
    if rows < 2 or columns < 2:
        raise FrameError(f"Rows/Columns {rows}/{columns}: an image needs at least 2x2 pixels")
    if "PixelData" not in ds:
        raise FrameError("PixelData is missing")
    if not ds.PixelData:
        raise FrameError("PixelData is empty")
    syntax = getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", ExplicitVRLittleEndian)
    expected = frames * rows * columns * bits_allocated // 8
    if not syntax.is_compressed and len(ds.PixelData) not in (expected, expected + 1):
        raise FrameError(f"PixelData holds {len(ds.PixelData)} bytes, NumberOfFrames x Rows x "
                         f"Columns x BitsAllocated need {expected}")
    words = _stored_words(ds, syntax, frames, rows * columns, bits_allocated, high_bit,
                          bits_stored)
    mask = np.uint16((1 << bits_stored) - 1)
    pixels = words.astype(np.uint16)  # one copy, then in place: no frame-sized temporaries
    pixels >>= np.uint16(high_bit - bits_stored + 1)
    pixels &= mask
    if representation == 1:
        pixels ^= np.uint16(1 << (bits_stored - 1))  # two's complement to offset binary
    if inverted:
        np.subtract(mask, pixels, out=pixels)
    return pixels.reshape(rows, columns), bits_stored


def _first_item(ds: Dataset, keyword: str) -> Dataset | None:
    sequence = ds.get(keyword)
    return sequence[0] if sequence else None


def _first_frame_attributes(ds: Dataset) -> Dataset:
    """The attributes of an Enhanced XA instance's first frame under their single-frame names.

    Its functional groups (per-frame over shared) override the top level, so the rest of
    decoding reads one instance kind. Other instances are returned as they are.
    """
    if ds.get("SOPClassUID") != ENHANCED_XA_IMAGE_STORAGE:
        return ds
    flat = Dataset()
    for element in ds:
        if element.keyword not in ("PixelData", *_FUNCTIONAL_GROUPS):
            flat.add(element)
    for group in (_first_item(ds, keyword) for keyword in _FUNCTIONAL_GROUPS):
        for sequence, keyword, single_frame_keyword in _FUNCTIONAL_GROUP_ATTRIBUTES:
            item = _first_item(group, sequence) if group is not None else None
            value = item.get(keyword) if item is not None else None
            if value not in (None, ""):
                setattr(flat, single_frame_keyword, value)
    return flat


def _laterality(attrs: Dataset) -> str | None:
    laterality = str(attrs.get("ImageLaterality", "") or attrs.get("Laterality", "") or "") or None
    if laterality in ("B", "U"):
        laterality = None
    if laterality not in (None, "L", "R"):
        raise FrameError(f"Laterality {laterality!r} is not L or R")
    return laterality


def case_key(ds: Dataset) -> tuple[str, str, str | None]:
    """Patient ID, Study Instance UID and laterality of an instance, read from its header
    alone (pixels not needed): what groups it into a case."""
    attrs = _first_frame_attributes(ds)
    return str(attrs.get("PatientID", "")), str(attrs.get("StudyInstanceUID", "")), _laterality(attrs)


def decode_pixels(ds: Dataset) -> tuple[np.ndarray, int]:
    """The pixels of a received instance (as in :class:`Frame`) and their bits stored, or
    :class:`FrameError`: the part of :func:`decode_frame` an instance whose
    :class:`FrameHeader` is known already needs."""
    pixels, bits_stored = _pixels(ds)
    return pixels, max(8, bits_stored)


def decode_frame(ds: Dataset) -> Frame:
    """The :class:`Frame` of a received instance, or :class:`FrameError` saying what is wrong."""
    attrs = _first_frame_attributes(ds)
    sop_class = str(_required(attrs, "SOPClassUID"))
    if sop_class not in SOP_CLASSES:
        raise FrameError(f"SOPClassUID {sop_class} is not an X-ray image class "
                         "(XA, Enhanced XA, RF, DX or Secondary Capture)")
    modality = str(_required(attrs, "Modality"))
    if modality not in SOP_CLASSES[sop_class]:
        raise FrameError(f"Modality {modality} is not an X-ray modality for SOP class {sop_class}")
    pixels, bits_stored = decode_pixels(ds)
    laterality = _laterality(attrs)
    return FrameHeader(
        imager_pixel_spacing_mm=_pixel_spacing(attrs),
        primary_angle_deg=_optional_float(attrs, "PositionerPrimaryAngle", -180.0, 180.0),
        secondary_angle_deg=_optional_float(attrs, "PositionerSecondaryAngle", -180.0, 180.0),
        sid_mm=_optional_float(attrs, "DistanceSourceToDetector", 100.0, 5000.0),
        sod_mm=_optional_float(attrs, "DistanceSourceToPatient", 50.0, 5000.0),
        acquisition_datetime=_acquisition_datetime(attrs),
        patient_id=str(_required(attrs, "PatientID")),
        patient_name=str(attrs.get("PatientName", "") or ""),
        study_uid=str(_required(attrs, "StudyInstanceUID")),
        series_uid=str(_required(attrs, "SeriesInstanceUID")),
        sop_instance_uid=str(_required(attrs, "SOPInstanceUID")),
        sop_class_uid=sop_class,
        laterality=laterality,
        modality=modality,
        instance_number=_integer(attrs, "InstanceNumber", 1) or 1,
    ).with_pixels(pixels, bits_stored)
