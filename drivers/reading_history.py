"""What the link keeps of the readings: each validated reading, a bounded history looked
up by UTC time, and the map from the device's clock to the host's.

Device timestamps are mapped to host UTC with the minimum of (host receive time - device
time) over a sliding window, the standard one-way clock estimate: it converges to the fixed
offset plus the smallest transport delay and absorbs slow drift.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from slamtka.drivers.kinematics import JointReading
from slamtka.drivers.protocol import StatusFlags

__all__ = ["EncoderReading", "ReadingHistory", "DeviceClock"]


@dataclass(frozen=True)
class EncoderReading:
    """One validated encoder reading."""

    sequence: int
    device_time_us: int  # the device's clock when it sampled the joints
    time_utc: datetime  # that instant on the host's UTC clock (see the module docstring)
    received_utc: datetime  # when the host put it in the history
    received_monotonic: float  # the same instant on time.monotonic()
    joints: JointReading
    flags: int

    @property
    def moving(self) -> bool:
        return bool(self.flags & StatusFlags.MOVING)

    def age_s(self, now_monotonic: float | None = None) -> float:
        """Seconds since the joints were sampled."""
        now = time.monotonic() if now_monotonic is None else now_monotonic
        return now - self.received_monotonic + (self.received_utc - self.time_utc).total_seconds()

    def to_json(self) -> dict:
        return {"sequence": self.sequence, "device_time_us": self.device_time_us,
                "time_utc": self.time_utc.isoformat(), "received_utc": self.received_utc.isoformat(),
                "joints": self.joints.to_json(),
                "flags": [f.name for f in StatusFlags if self.flags & f]}


class ReadingHistory:
    """A bounded, thread-safe history of readings, looked up by UTC time."""

    def __init__(self, capacity: int) -> None:
        self._times = np.full(capacity, np.nan)  # POSIX seconds of each reading's time_utc
        self._items: list[EncoderReading | None] = [None] * capacity
        self._next = 0
        self._count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._count

    @property
    def capacity(self) -> int:
        return len(self._items)

    def append(self, reading: EncoderReading, t_posix: float) -> None:
        """Add a reading sampled at ``t_posix`` (its time_utc as POSIX seconds)."""
        with self._lock:
            self._times[self._next] = t_posix
            self._items[self._next] = reading
            self._next = (self._next + 1) % len(self._items)
            self._count = min(self._count + 1, len(self._items))

    def last(self) -> EncoderReading | None:
        with self._lock:
            return self._items[self._next - 1] if self._count else None

    def between(self, t0_posix: float, t1_posix: float) -> list[tuple[float, EncoderReading]]:
        """Every reading sampled in [t0, t1], as (POSIX seconds, reading), oldest first."""
        with self._lock:
            inside = np.flatnonzero((self._times >= t0_posix) & (self._times <= t1_posix))
            found = [(float(self._times[k]), item) for k in inside if (item := self._items[k]) is not None]
        return sorted(found, key=lambda item: item[0])

    def nearest(self, t_posix: float, max_age_s: float) -> EncoderReading | None:
        """The reading sampled closest to ``t_posix``, if within ``max_age_s`` of it."""
        with self._lock:
            if not self._count:
                return None
            gaps = np.abs(self._times - t_posix)  # empty slots are NaN and never win
            k = int(np.nanargmin(gaps))
            return self._items[k] if gaps[k] <= max_age_s else None


class DeviceClock:
    """Device microseconds to host POSIX seconds: sliding-window minimum of the offset."""

    def __init__(self, window: int) -> None:
        self.window = window
        self._mins: deque[tuple[int, float]] = deque()  # (index, offset), offsets increasing
        self._n = 0

    def reset(self) -> None:
        self._mins.clear()

    def update(self, device_time_us: int, host_s: float) -> float:
        """Add one sample; return the device time mapped to host seconds."""
        device_s = device_time_us * 1e-6
        offset = host_s - device_s
        while self._mins and self._mins[-1][1] >= offset:
            self._mins.pop()
        self._mins.append((self._n, offset))
        while self._mins[0][0] <= self._n - self.window:
            self._mins.popleft()
        self._n += 1
        return device_s + self._mins[0][1]
