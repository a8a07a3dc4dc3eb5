"""The C-arm clock against the encoder stream (service.clock): each symptom of an offset is
corrected within the bound, falls back to the header's angles, or leaves the view unused,
and never passes silently."""

from __future__ import annotations

import datetime as dt

import pytest

from slamtka.drivers.kinematics import CArmKinematics, JointReading, PatientSetup, dicom_angles
from slamtka.drivers.protocol import StatusFlags
from slamtka.drivers.reading_history import EncoderReading, ReadingHistory
from slamtka.service.clock import review_pairing
from slamtka.solver.anatomy import Landmarks

T0 = dt.datetime(2026, 1, 2, 3, 4, 5, tzinfo=dt.UTC)
KIN = CArmKinematics()
SETUP = PatientSetup.from_config(Landmarks.nominal(), {})


class Stream:
    """The encoder link's history of one scripted C-arm motion: held at -30 deg for 1 s,
    moving for 1 s, held at +30 deg (readings every 50 ms); what ``EncoderLink`` keeps."""

    def __init__(self):
        self.history = ReadingHistory(200)
        for k in range(80):
            t = T0 + dt.timedelta(seconds=0.05 * k)
            s = 0.05 * k
            orbital = -30.0 if s < 1.0 else 30.0 if s >= 2.0 else -30.0 + 60.0 * (s - 1.0)
            moving = 1.0 <= s < 2.0
            reading = EncoderReading(k, int(s * 1e6), t, t, s, JointReading(orbital_deg=orbital),
                                     int(StatusFlags.MOVING) if moving else 0)
            self.history.append(reading, t.timestamp())

    def readings_between(self, t0, t1):
        return [r for _, r in self.history.between(t0.timestamp(), t1.timestamp())]

    def at(self, seconds: float) -> EncoderReading:
        return self.history.nearest((T0 + dt.timedelta(seconds=seconds)).timestamp(), 0.03)


def _header(orbital: float) -> tuple[float, float]:
    return dicom_angles(KIN, JointReading(orbital_deg=orbital), SETUP)


def _review(stream, frame_s, header, taken=(), bound=2.0, reading="nearest"):
    when = T0 + dt.timedelta(seconds=frame_s)
    found = stream.at(frame_s) if reading == "nearest" else reading
    return review_pairing(stream, KIN, SETUP, when, found, *header, set(taken), 3.0, bound)


def test_a_frame_paired_well_needs_no_review():
    stream = Stream()
    assert _review(stream, 0.5, _header(-30.0)) is None
    assert _review(stream, 2.5, _header(30.0)) is None


def test_a_frame_time_in_the_arm_s_motion_is_corrected_to_the_still_reading_that_agrees():
    stream = Stream()  # the view at +30 deg, but the C-arm's clock says 0.6 s earlier
    check = _review(stream, 1.6, _header(30.0))
    assert check.note["status"] == "corrected" and check.reading.joints.orbital_deg == 30.0
    assert check.note["offset_s"] == pytest.approx(0.4, abs=0.03)
    assert "moving" in check.note["symptoms"] and "+0.40 s" in check.note["message"]


def test_two_views_on_one_reading_and_a_frame_ahead_of_the_stream_are_corrected():
    stream = Stream()
    first = stream.at(0.5)
    check = _review(stream, 0.5, _header(-30.0), taken={first.sequence})
    assert check.note["status"] == "corrected" and check.reading.sequence != first.sequence
    ahead = _review(stream, 4.5, _header(30.0), reading=None)  # no reading that late yet
    assert ahead.note["status"] == "corrected" and ahead.note["offset_s"] < -0.5


def test_beyond_the_bound_the_header_angles_are_used_and_said():
    stream = Stream()
    check = _review(stream, 1.6, _header(30.0), bound=0.2)
    assert check.reading is None and check.note["status"] == "header_angles"
    assert "header's positioner angles are used" in check.note["message"]


def test_encoders_and_header_far_apart_with_no_offset_to_explain_it_leave_the_view_unused():
    stream = Stream()
    check = _review(stream, 0.5, _header(30.0 + 60.0))
    assert check.reading is None and check.note["status"] == "unusable"
    assert "disagree" in check.note["message"] and "not used" in check.note["message"]


def test_without_header_angles_a_shared_reading_cannot_be_corrected():
    stream = Stream()
    first = stream.at(0.5)
    check = _review(stream, 0.5, (None, None), taken={first.sequence})
    assert check.reading is None and check.note["status"] == "unusable"
