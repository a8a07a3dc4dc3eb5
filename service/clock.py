"""The C-arm's clock against the encoder stream: detected, corrected within a bound, told.

A frame is paired with the encoder reading taken at its AcquisitionDateTime. When the
C-arm's clock is off the host's (a second is common), that reading belongs to another
moment: the arm was moving then, another view of the case was paired with the very same
reading, or the encoders' beam direction disagrees with the one the header states. Each of
these is a symptom of the offset (or of a wrong header); none may pass silently.

:func:`review_pairing` looks, within ``max_offset_s`` of the frame's time, for readings of
the arm standing still where the encoders agree with the header's positioner angles, and
takes the nearest: the offset is corrected and the view keeps its encoder pose. When none
is found, a view whose symptom is a clock's (arm moving, a shared reading, no reading) falls
back to its header angles; one whose still, own reading simply disagrees with the header
(a wrong header or wrong encoders: which, nothing tells) is not used; without header angles
to compare with, neither can be used. Every outcome carries a ``clock`` note (status,
offset, message) that is persisted with the pairing, audited and shown.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Protocol

from slamtka.drivers.kinematics import AngleCheck, CArmKinematics, PatientSetup, check_dicom_angles
from slamtka.drivers.reading_history import EncoderReading

__all__ = ["ClockCheck", "ReadingSource", "review_pairing"]


class ReadingSource(Protocol):
    """Where a frame's encoder reading comes from: the live C-arm link
    (:class:`drivers.encoder_link.EncoderLink`) or, offline, readings from a file."""

    def reading_at(self, t_utc: datetime, max_age_s: float | None = None) -> EncoderReading | None:
        ...

    def readings_between(self, t0_utc: datetime, t1_utc: datetime) -> list[EncoderReading]:
        ...


@dataclass(frozen=True)
class ClockCheck:
    """What :func:`review_pairing` decided: the reading to use (None: header angles or
    unusable), the clock note, and the angle check of the reading kept."""

    reading: EncoderReading | None
    note: dict
    check: AngleCheck | None = None


def _symptoms(reading: EncoderReading, taken: set[int], check) -> list[str]:
    found = []
    if reading.moving:
        found.append("the arm was moving at the frame's time")
    if reading.sequence in taken:
        found.append("another view of the case was paired with the same encoder reading")
    if check.status == "disagrees":
        found.append(f"encoder and header angles disagree ({check.beam_difference_deg:.1f} deg)")
    return found


def review_pairing(link: ReadingSource, kinematics: CArmKinematics, setup: PatientSetup,
                   when: datetime, reading: EncoderReading | None, primary: float | None,
                   secondary: float | None, taken: set[int], tolerance_deg: float,
                   max_offset_s: float) -> ClockCheck | None:
    """None when the reading at the frame's time shows no symptom of a clock offset; else
    the corrected reading, or none (header angles), with the note saying which and why."""
    has_angles = primary is not None and secondary is not None
    if reading is not None:
        check = check_dicom_angles(kinematics, reading.joints, setup, primary, secondary,
                                   tolerance_deg)
        symptoms = _symptoms(reading, taken, check)
        if not symptoms:
            return None
    else:
        symptoms = ["no encoder reading at the frame's time"]
        if not has_angles or max_offset_s <= 0:
            return None  # the plain "no reading" cases, reported by the pairing as before
    why = "; ".join(symptoms)
    if has_angles and max_offset_s > 0:
        window = link.readings_between(when - timedelta(seconds=max_offset_s),
                                       when + timedelta(seconds=max_offset_s))
        if reading is None and not window:
            return None  # no stream around then at all (link down, an old frame): no clock
        fits = []
        for candidate in window:
            if candidate.moving or candidate.sequence in taken:
                continue
            check = check_dicom_angles(kinematics, candidate.joints, setup, primary, secondary,
                                       tolerance_deg)
            if check.status == "agrees":
                offset = (candidate.time_utc - when).total_seconds()
                fits.append((abs(offset), offset, candidate, check))
        if fits:
            _, offset, best, check = min(fits, key=lambda f: f[0])
            return ClockCheck(best, {
                "status": "corrected", "offset_s": round(offset, 3), "symptoms": why,
                "message": f"C-arm clock {offset:+.2f} s off the encoder stream ({why}): "
                           f"corrected, the reading at the corrected time is used"}, check)
    clock_like = reading is None or reading.moving or reading.sequence in taken
    if has_angles and clock_like:
        return ClockCheck(None, {
            "status": "header_angles", "offset_s": None, "symptoms": why,
            "message": f"encoders unusable for this view ({why}; no reading within "
                       f"{max_offset_s:g} s agrees with the header): the header's positioner "
                       "angles are used"})
    if has_angles:  # still, its own reading, and yet another beam: which one is wrong?
        return ClockCheck(None, {
            "status": "unusable", "offset_s": None, "symptoms": why,
            "message": f"{why}, and no clock offset within {max_offset_s:g} s explains it: the "
                       "view is not used (check the C-arm's angles and the encoder link)"})
    return ClockCheck(None, {
        "status": "unusable", "offset_s": None, "symptoms": why,
        "message": f"encoders unusable for this view ({why}) and the header has no "
                   "positioner angles to correct the clock with"})
