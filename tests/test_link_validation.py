"""The checks of a reading's content (drivers.reading_validation), frame by frame."""

from __future__ import annotations

import numpy as np
import pytest

from slamtka.drivers.carm_sim import DEFAULT_IDENTITY
from slamtka.drivers.protocol import MessageType, SerialFrame, StatusFlags, encode_reading
from slamtka.drivers.reading_validation import (
    IMPLAUSIBLE_RUN_RESET,
    ReadingValidator,
    RejectionCounts,
    Verdict,
)

HOME = np.array([0, 0, 0, 100_000, 50_000, 1_000_000])  # counts of 0.001 deg / mm


def frame(sequence: int, t_ms: float, counts=HOME, flags: int = 0) -> SerialFrame:
    return SerialFrame(MessageType.READING, sequence, int(t_ms * 1000), encode_reading(flags, 0, counts))


def test_a_plausible_reading_is_used_and_its_joints_scaled():
    validator = ReadingValidator(DEFAULT_IDENTITY, 1.5, "/dev/ttyX", RejectionCounts())
    judgement = validator.judge(frame(1, 0.0, HOME + [1500, 0, 0, 0, 0, 0]))
    assert judgement.verdict is Verdict.USE and judgement.joints.orbital_deg == pytest.approx(1.5)


@pytest.mark.parametrize("second, verdict, tally", [
    (frame(2, 10.0, HOME + [500, 0, 0, 0, 0, 0]), Verdict.USE, None),  # 50 deg/s: within 60
    (frame(1, 10.0), Verdict.SKIP, "duplicate"),  # the same sequence number again
    (frame(2, 0.0), Verdict.SKIP, "duplicate"),  # the same device time again
    (frame(2, 10.0, flags=int(StatusFlags.AXIS_FAULT)), Verdict.SKIP, "invalid"),
    (frame(2, 10.0, HOME + [100_000, 0, 0, 0, 0, 0]), Verdict.REJECT, "range"),  # 100 deg orbital
    (frame(2, 10.0, HOME + [5_000, 0, 0, 0, 0, 0]), Verdict.REJECT, "rate"),  # 500 deg/s
    (SerialFrame(MessageType.READING, 2, 10_000, b"\x00" * 7), Verdict.REJECT, "malformed"),
])
def test_each_check_names_its_reason(second, verdict, tally):
    counts = RejectionCounts()
    validator = ReadingValidator(DEFAULT_IDENTITY, 1.5, "/dev/ttyX", counts)
    assert validator.judge(frame(1, 0.0)).verdict is Verdict.USE
    assert validator.judge(second).verdict is verdict
    assert {k: v for k, v in vars(counts).items() if v} == ({tally: 1} if tally else {})


def test_a_device_restart_and_a_real_jump_are_taken_up_again():
    counts = RejectionCounts()
    validator = ReadingValidator(DEFAULT_IDENTITY, 1.5, "/dev/ttyX", counts)
    validator.judge(frame(100, 5000.0))
    restarted = validator.judge(frame(1, 1.0))  # its clock went back: a new session of the device
    assert restarted.verdict is Verdict.USE and restarted.clock_restarted and counts.clock_resets == 1
    moved = HOME + [40_000, 0, 0, 0, 0, 0]  # re-homed 40 deg away: every reading "too fast" ...
    verdicts = [validator.judge(frame(2 + k, 10.0 * (k + 1), moved)).verdict
                for k in range(IMPLAUSIBLE_RUN_RESET + 1)]
    # ... until the rate check is re-anchored on the new values.
    assert verdicts == [Verdict.REJECT] * IMPLAUSIBLE_RUN_RESET + [Verdict.USE]
