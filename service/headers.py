"""Patient and study attributes as the results repeat them: valid, whatever the C-arm sent.

The receiver accepts what real systems send (PatientBirthDate 00000000, PatientSex U or
lower case, a two-valued PatientName, partial dates and times, Laterality B): rejecting a
frame over a type-2 demographic would lose the measurement. The SR and SC copy these
attributes into new objects, whose builders validate them, so they are normalised here
first: a value that can be read as a valid one is rewritten (``m`` -> ``M``, the first of two
names), anything else is blanked (type 2: present, empty = unknown). The received instance
itself is never changed.
"""

from __future__ import annotations

import copy
import re
from datetime import date, datetime

from pydicom.dataset import Dataset

__all__ = ["sanitised_header", "image_laterality", "stamp_dates"]

_SEX = {"M": "M", "F": "F", "O": "O"}
_DATES = ("PatientBirthDate", "StudyDate", "SeriesDate", "AcquisitionDate", "ContentDate")
_TIMES = ("StudyTime", "SeriesTime", "AcquisitionTime", "ContentTime", "PatientBirthTime")
_TIME = re.compile(r"^([01]\d|2[0-3])([0-5]\d([0-5]\d(\.\d{1,6})?)?)?$")


def _valid_date(text: str) -> bool:
    if not re.fullmatch(r"\d{8}", text):
        return False
    try:
        date(int(text[:4]), int(text[4:6]), int(text[6:]))
    except ValueError:
        return False
    return True


def image_laterality(value) -> str | None:
    """``L`` or ``R`` of a Laterality value, else None (B, U and blanks name no one side)."""
    text = str(value or "").strip().upper()
    return text if text in ("L", "R") else None


def sanitised_header(ds: Dataset) -> Dataset:
    """A copy of ``ds`` whose patient, study and laterality attributes the result builders
    accept (see the module docstring); ``ds`` is not changed."""
    out = copy.deepcopy(ds)
    if "PatientName" in out:
        element = out["PatientName"]
        if element.VM > 1:  # two names (e.g. alphabetic twice): the first one
            element.value = str(element.value[0])
        name = str(out.PatientName or "")
        if len(name.encode("ascii", "replace")) > 64 * 5:
            out.PatientName = name[:64]
    if "PatientSex" in out:
        out.PatientSex = _SEX.get(str(out.PatientSex or "").strip().upper(), "")
    for keyword in _DATES:
        if keyword in out and not _valid_date(str(out.get(keyword) or "")):
            setattr(out, keyword, "")
    for keyword in _TIMES:
        if keyword in out and not _TIME.match(str(out.get(keyword) or "").strip()):
            setattr(out, keyword, "")
    if "Laterality" in out and image_laterality(out.Laterality) is None:
        del out.Laterality
    for keyword in ("PatientAge",):
        if keyword in out and not re.fullmatch(r"\d{3}[DWMY]", str(out.get(keyword) or "")):
            setattr(out, keyword, "")
    return out


def stamp_dates(ds: Dataset, when: datetime,
                keywords: tuple[str, ...] = ("InstanceCreation", "Content")) -> None:
    """Set the ``<keyword>Date`` / ``<keyword>Time`` pairs of a built result, and the dates of
    its contributing equipment, to ``when`` (the run's time) instead of the builder's clock,
    so that a run built again is the same object."""
    for keyword in keywords:
        setattr(ds, f"{keyword}Date", when.strftime("%Y%m%d"))
        setattr(ds, f"{keyword}Time", when.strftime("%H%M%S.%f"))
    for item in ds.get("ContributingEquipmentSequence", []):
        if "ContributionDateTime" in item:
            item.ContributionDateTime = when.strftime("%Y%m%d%H%M%S.%f")
