"""Whether a READING frame's content may be used.

A frame whose CRCs hold can still be impossible: a wrong payload size, joints outside the
axis ranges the device declared, or a move faster than the declared axis rates since the
previous reading (two bit errors that cancel in a CRC). Those are rejected. A genuine frame
is merely not used when the device flags its values invalid, or when it repeats the
previous reading. After a run of implausible readings the rate check is re-anchored (the
values really jumped: the device was re-homed).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from enum import Enum

import numpy as np

from slamtka.drivers.kinematics import JOINT_FIELD, JointReading
from slamtka.drivers.protocol import INVALID_FLAGS, DeviceIdentity, ProtocolError, SerialFrame, decode_reading

__all__ = ["AxisScale", "Judgement", "ReadingValidator", "RejectionCounts", "Verdict",
           "IMPLAUSIBLE_RUN_RESET"]

log = logging.getLogger("slamtka.link")

IMPLAUSIBLE_RUN_RESET = 10  # after this many rejections in a row, re-anchor the rate check
_INVALID_FLAGS = int(INVALID_FLAGS)


class Verdict(Enum):
    USE = "use"  # a new, plausible reading
    SKIP = "skip"  # a genuine frame, not used (flagged invalid by the device, a repeat)
    REJECT = "reject"  # impossible content that slipped through the CRCs


@dataclass
class RejectionCounts:
    """Frames not used, by reason; and restarts of the device's clock."""

    malformed: int = 0  # valid frame, wrong payload for a reading
    invalid: int = 0  # the device flagged the values invalid
    range: int = 0  # outside the declared axis range
    rate: int = 0  # moved faster than the declared axis rate
    duplicate: int = 0  # a sequence number or timestamp seen already
    clock_resets: int = 0  # the device clock went backwards (device restarted)


@dataclass(frozen=True)
class Judgement:
    verdict: Verdict
    flags: int = 0
    joints: JointReading | None = None  # with USE
    clock_restarted: bool = False  # the device's clock went backwards: map it afresh


class AxisScale:
    """A device's declared axes in encoder counts, for cheap per-reading checks."""

    def __init__(self, identity: DeviceIdentity) -> None:
        res = np.array([a.resolution for a in identity.axes])
        self.resolution = res
        self.lo = np.array([a.minimum for a in identity.axes]) / res
        self.hi = np.array([a.maximum for a in identity.axes]) / res
        self.rate = np.array([a.max_rate for a in identity.axes]) / res  # counts per second
        known = [(k, a.name) for k, a in enumerate(identity.axes) if a.name in JOINT_FIELD]
        self.index = np.array([k for k, _ in known], dtype=np.int64)
        self.fields = tuple(JOINT_FIELD[name] for _, name in known)

    def out_of_range(self, counts: np.ndarray) -> bool:
        return bool(((counts < self.lo) | (counts > self.hi)).any())

    def too_fast(self, counts: np.ndarray, previous: np.ndarray, seconds: float) -> bool:
        """Moved more than the declared rate allows in ``seconds`` (plus 2 counts of rounding)."""
        return bool((np.abs(counts - previous) > self.rate * seconds + 2).any())

    def joints(self, counts: np.ndarray) -> JointReading:
        values = (counts[self.index] * self.resolution[self.index]).tolist()
        return JointReading(**dict(zip(self.fields, values)))


class ReadingValidator:
    """The checks of one session's readings against the device's declared axes."""

    def __init__(self, identity: DeviceIdentity, rate_margin: float, port: str,
                 counts: RejectionCounts) -> None:
        """``counts``: the link's tally of frames not used, kept across sessions."""
        self.identity, self.rate_margin, self.port = identity, rate_margin, port
        self.axes = AxisScale(identity)
        self.counts = counts
        self._previous: tuple[int, int, np.ndarray] | None = None  # sequence, device us, counts
        self._implausible_run = 0

    def judge(self, frame: SerialFrame) -> Judgement:
        """What to do with a READING frame; a USE is remembered as the previous reading."""
        counts_seen = self.counts
        try:
            flags, _, counts = decode_reading(frame.payload, self.identity)
        except ProtocolError:
            counts_seen.malformed += 1
            return Judgement(Verdict.REJECT)
        if flags & _INVALID_FLAGS:
            counts_seen.invalid += 1
            self._previous = None  # values may jump when the device recovers (re-homing)
            return Judgement(Verdict.SKIP, flags)
        if self.axes.out_of_range(counts):
            counts_seen.range += 1
            return Judgement(Verdict.REJECT, flags)
        restarted = False
        if self._previous is not None:
            sequence, device_us, previous_counts = self._previous
            dt = (frame.device_time_us - device_us) * 1e-6
            if dt < 0:
                counts_seen.clock_resets += 1  # the device restarted: new clock, new sequence
                restarted = True
            elif dt == 0 or frame.sequence == sequence:
                counts_seen.duplicate += 1
                return Judgement(Verdict.SKIP, flags)
            elif self.axes.too_fast(counts, previous_counts, dt * self.rate_margin):
                counts_seen.rate += 1
                self._implausible_run += 1
                if self._implausible_run >= IMPLAUSIBLE_RUN_RESET:
                    log.warning("encoder link %s: values jumped; re-anchoring the rate check", self.port)
                    self._previous = None
                return Judgement(Verdict.REJECT, flags)
        self._implausible_run = 0
        self._previous = frame.sequence, frame.device_time_us, counts
        return Judgement(Verdict.USE, flags, self.axes.joints(counts), restarted)
