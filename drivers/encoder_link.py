"""The serial driver of the C-arm encoder link (pyserial).

One reader thread per link owns the port: it opens it, identifies the device, starts the
stream, parses frames and keeps a bounded history of readings; when the device vanishes
(the read fails, as it does when a USB adapter is pulled) or stays silent too long, it closes
the port and reopens it with exponential backoff until the device path is back.

A reading is only handed out when it is valid (CRCs, then :mod:`drivers.reading_validation`)
and not older than the maximum age; device timestamps are mapped to host UTC by
:class:`drivers.reading_history.DeviceClock`. Host times come from ``time.monotonic``
anchored to UTC when a session starts, so wall-clock steps do not disturb ages or
latencies. The port itself, and the errors that name what went wrong with it, are
:mod:`drivers.serial_port`.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from datetime import UTC, datetime
from pathlib import Path

import serial

from slamtka.drivers.config_tables import ConfigError, build_table
from slamtka.drivers.kinematics import AXIS_UNITS
from slamtka.drivers.protocol import (
    PROTOCOL_VERSION,
    DeviceIdentity,
    DeviceStatus,
    FrameParser,
    MessageType,
    ParserStats,
    ProtocolError,
    ResultCode,
    SerialFrame,
    decode_identity,
    decode_result,
    decode_status,
    encode_serial_frame,
    encode_stream_start,
)
from slamtka.drivers.reading_history import DeviceClock, EncoderReading, ReadingHistory
from slamtka.drivers.reading_validation import ReadingValidator, RejectionCounts, Verdict
from slamtka.drivers.serial_port import (
    DeviceLostError,
    DeviceRejectedError,
    LinkError,
    NoAnswerError,
    ProtocolVersionError,
    WrongDeviceError,
    open_port,
)

__all__ = ["LinkConfig", "EncoderLink", "LinkState", "LinkStats"]

log = logging.getLogger("slamtka.link")

READ_POLL_S = 0.005  # longest a read blocks: bounds how late silence and stop are noticed


@dataclass(frozen=True)
class LinkConfig:
    baudrate: int = 115200
    rate_hz: int = 100  # streaming rate requested from the device
    max_age_s: float = 0.1  # a reading older than this is never handed out
    history_s: float = 120.0  # how far back readings can be looked up
    silence_margin_s: float = 0.05  # silent once no frame came for one period plus this
    reopen_after_s: float = 1.0  # a port silent this long is closed and reopened
    answer_timeout_s: float = 0.25  # per request attempt (identify, stream start)
    request_attempts: int = 3
    backoff_initial_s: float = 0.02  # reconnect delays double from here ...
    backoff_max_s: float = 0.25  # ... up to here: a returning device is back within this
    clock_window: int = 500  # readings in the clock-offset minimum filter
    rate_margin: float = 1.5  # tolerated multiple of an axis' declared maximum rate
    required_axes: tuple[str, ...] = ("orbital", "angulation")

    def __post_init__(self) -> None:
        checks = {
            "baudrate": self.baudrate > 0, "rate_hz": 1 <= self.rate_hz <= 65535,
            "max_age_s": 0 < self.max_age_s <= 10, "history_s": self.history_s >= self.max_age_s,
            "silence_margin_s": self.silence_margin_s > 0,
            "reopen_after_s": self.reopen_after_s > self.silence_margin_s,
            "answer_timeout_s": self.answer_timeout_s > 0, "request_attempts": self.request_attempts >= 1,
            "backoff_initial_s": 0 < self.backoff_initial_s <= self.backoff_max_s,
            "backoff_max_s": self.backoff_max_s < 60, "clock_window": self.clock_window >= 1,
            "rate_margin": self.rate_margin >= 1,
        }
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(f"encoder link configuration: invalid {', '.join(bad)} "
                             f"({', '.join(f'{b}={getattr(self, b)!r}' for b in bad)})")
        unknown = set(self.required_axes) - set(AXIS_UNITS)
        if unknown:
            raise ConfigError(f"encoder link configuration: unknown required axes {sorted(unknown)}")

    @property
    def history_capacity(self) -> int:
        return max(16, math.ceil(self.rate_hz * self.history_s))

    @staticmethod
    def from_config(d: Mapping) -> LinkConfig:
        return build_table(LinkConfig, d, "link")

    def to_config(self) -> dict:
        return {f.name: (list(v) if isinstance(v := getattr(self, f.name), tuple) else v)
                for f in fields(self)}


@dataclass(frozen=True)
class LinkState:
    status: str  # "connecting", "connected", "silent", "disconnected" or "stopped"
    reason: str
    since_utc: datetime
    since_monotonic: float
    error: LinkError | None = None


@dataclass
class LinkStats:
    sessions: int = 0  # successful connections
    readings: int = 0  # accepted into the history
    rejected: RejectionCounts = field(default_factory=RejectionCounts)  # frames not used, by reason
    parser: ParserStats = field(default_factory=ParserStats)


class EncoderLink:
    """The C-arm's encoder link on a serial port, kept alive by one reader thread."""

    def __init__(self, port: str | Path, config: LinkConfig = LinkConfig(),
                 on_state: Callable[[LinkState], None] | None = None,
                 on_reading: Callable[[EncoderReading], None] | None = None) -> None:
        """``on_state`` and ``on_reading`` are called from the reader thread (keep them short):
        on every state change, and on every reading as it enters the history."""
        self.port = str(port)
        self.config = config
        self._on_state = on_state
        self._on_reading = on_reading
        self._history = ReadingHistory(config.history_capacity)
        self._stats = LinkStats()
        self._parser = FrameParser(stats=self._stats.parser, check=self._take)
        self._stopping = threading.Event()
        self._thread: threading.Thread | None = None
        self._serial: serial.Serial | None = None
        self._write_lock = threading.Lock()
        self._changed = threading.Condition()  # notified on every reading, reply and state change
        self._replies: dict[int, SerialFrame] = {}  # last frame of each non-reading type
        self._seq = 0
        self._identity: DeviceIdentity | None = None
        self._validator: ReadingValidator | None = None  # of the session's device
        self._clock = DeviceClock(config.clock_window)
        self._utc_base = 0.0
        self._last_frame = 0.0
        self._state = self._make_state("stopped", "not started")

    # -- public API -------------------------------------------------------------------------
    def start(self) -> EncoderLink:
        if self._thread is not None:
            raise RuntimeError("the encoder link is already started")
        self._stopping.clear()
        self._set_state("connecting", f"opening {self.port}")
        self._thread = threading.Thread(target=self._run, name=f"encoder-link {self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        """Stop streaming, close the port and end the reader thread (idempotent)."""
        thread = self._thread
        if thread is None:
            return
        self._stopping.set()
        ser = self._serial
        if ser is not None:
            try:
                ser.cancel_read()
            except (OSError, serial.SerialException, TypeError):
                pass  # the reader closed it already
        thread.join(timeout)
        if thread.is_alive():
            raise RuntimeError(f"the encoder link reader thread for {self.port} did not stop")
        self._thread = None
        self._set_state("stopped", "stopped by the host")

    def __enter__(self) -> EncoderLink:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.stop()

    @property
    def state(self) -> LinkState:
        return self._state

    @property
    def history(self) -> ReadingHistory:
        """The bounded history (read it through reading_at/latest for the age rule)."""
        return self._history

    @property
    def stats(self) -> LinkStats:
        return replace(self._stats, parser=replace(self._stats.parser))

    def wait_connected(self, timeout: float) -> DeviceIdentity:
        """Block until the link streams; raise the last LinkError (or TimeoutError)."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while self._state.status not in ("connected", "silent"):
                left = deadline - time.monotonic()
                if left <= 0 or self._state.status == "stopped":
                    if self._state.error is not None:
                        raise self._state.error
                    raise TimeoutError(f"encoder link {self.port} not connected after {timeout} s: "
                                       f"{self._state.reason}")
                self._changed.wait(left)
            assert self._identity is not None  # connected: the device has identified itself
            return self._identity

    def wait_reading(self, timeout: float, after_sequence: int | None = None) -> EncoderReading:
        """Block until the newest reading is one other than ``after_sequence`` (or any one)."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while True:
                last = self._history.last()
                if last is not None and (after_sequence is None or last.sequence != after_sequence):
                    return last
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no encoder reading within {timeout} s ({self._state.status}: "
                                       f"{self._state.reason})")
                self._changed.wait(left)

    def reading_at(self, t_utc: datetime, max_age_s: float | None = None) -> EncoderReading | None:
        """The reading sampled closest to ``t_utc`` (e.g. a frame's AcquisitionDateTime), or
        None when no reading lies within the maximum age of that instant."""
        if t_utc.tzinfo is None:
            raise ValueError("reading_at needs a timezone-aware time; DICOM times without an offset "
                             "are local to the modality and must be converted first")
        return self._history.nearest(t_utc.timestamp(), self._max_age(max_age_s))

    def readings_between(self, t0_utc: datetime, t1_utc: datetime) -> list[EncoderReading]:
        """Every reading sampled between two instants (timezone-aware), oldest first: what
        the C-arm did around a frame whose clock may be off the encoder stream."""
        return [r for _, r in self._history.between(t0_utc.timestamp(), t1_utc.timestamp())]

    def latest(self, max_age_s: float | None = None) -> EncoderReading | None:
        """The newest reading if it is not older than the maximum age, else None."""
        last = self._history.last()
        if last is None or last.age_s() > self._max_age(max_age_s):
            return None
        return last

    def read_once(self, timeout: float = 0.25) -> EncoderReading:
        """Ask the device for a reading now and wait for it (works while streaming too).

        Public API for tools and tests: the service reads the streamed history instead."""
        previous = self._history.last()
        self._send(MessageType.READ_ONCE)
        return self.wait_reading(timeout, None if previous is None else previous.sequence)

    def request_status(self, timeout: float = 0.25) -> DeviceStatus:
        """The device's STATUS (flags, stream rate, dropped frames) on request: public API for
        tools and tests diagnosing a device; the service reads only the stream."""
        with self._changed:
            self._replies.pop(MessageType.STATUS, None)
        self._send(MessageType.STATUS_REQUEST)
        frame = self._wait_reply(MessageType.STATUS, time.monotonic() + timeout, pump=False)
        if frame is None:
            raise NoAnswerError(f"{self.port}: no STATUS answer within {timeout} s")
        return decode_status(frame.payload)

    # -- helpers ----------------------------------------------------------------------------
    def _max_age(self, max_age_s: float | None) -> float:
        if max_age_s is None:
            return self.config.max_age_s
        if not 0 <= max_age_s <= self.config.max_age_s:
            raise ValueError(f"max_age_s {max_age_s} must lie in [0, {self.config.max_age_s}] "
                             "(the configured maximum age is never exceeded)")
        return max_age_s

    def _make_state(self, status: str, reason: str, error: LinkError | None = None) -> LinkState:
        return LinkState(status, reason, datetime.now(UTC), time.monotonic(), error)

    def _set_state(self, status: str, reason: str, error: LinkError | None = None) -> None:
        if (status, reason) == (self._state.status, self._state.reason):
            return  # a retry that failed the same way is not news
        state = self._make_state(status, reason, error)
        with self._changed:
            self._state = state
            self._changed.notify_all()
        log.debug("encoder link %s: %s (%s)", self.port, status, reason)  # the service says when it matters
        if self._on_state is not None:
            try:
                self._on_state(state)
            except Exception:  # a faulty observer must not kill the link
                log.exception("encoder link state callback failed")

    def _send(self, mtype: MessageType, payload: bytes = b"") -> int:
        with self._write_lock:
            ser = self._serial
            if ser is None:
                raise LinkError(f"encoder link {self.port} is {self._state.status}: {self._state.reason}")
            self._seq = (self._seq + 1) & 0xFFFFFFFF
            frame = SerialFrame(mtype, self._seq, int(time.monotonic() * 1e6), payload)
            try:
                ser.write(encode_serial_frame(frame))
            except (serial.SerialException, OSError, TypeError) as exc:
                raise DeviceLostError(f"{self.port}: write failed ({exc})") from None
            return self._seq

    # -- reader thread ----------------------------------------------------------------------
    def _run(self) -> None:
        backoff = self.config.backoff_initial_s
        while not self._stopping.is_set():
            connected = False
            try:
                self._serial = open_port(self.port, self.config.baudrate, READ_POLL_S)
                self._handshake()
                connected = True
                self._stream()
            except LinkError as exc:
                if not self._stopping.is_set():
                    self._set_state("disconnected", f"{exc}; retrying", exc)
            except Exception as exc:  # a bug must not leave the link silently dead
                log.exception("encoder link %s: unexpected error", self.port)
                self._set_state("disconnected", f"internal error {exc!r}; retrying",
                                LinkError(f"encoder link {self.port}: internal error {exc!r}"))
            finally:
                self._close()
            if connected:
                backoff = self.config.backoff_initial_s
            if self._stopping.wait(backoff):
                break
            backoff = min(2 * backoff, self.config.backoff_max_s)

    def _close(self) -> None:
        with self._write_lock:
            ser, self._serial = self._serial, None
        if ser is not None:
            try:
                if ser.is_open and self._identity is not None:
                    ser.write(encode_serial_frame(SerialFrame(MessageType.STREAM_STOP, self._seq + 1, 0)))
            except (serial.SerialException, OSError):
                pass  # the device is gone; nothing to stop
            ser.close()

    def _read_chunk(self) -> bytes:
        """Whatever arrived, waiting at most READ_POLL_S; raise DeviceLostError if gone."""
        ser = self._serial
        if ser is None:  # closed by stop() meanwhile
            return b""
        try:
            data = ser.read(max(1, ser.in_waiting))
            if data and ser.in_waiting:
                data += ser.read(ser.in_waiting)
        except (serial.SerialException, OSError, TypeError) as exc:
            if self._stopping.is_set():
                return b""
            gone = "" if os.path.exists(self.port) else f"; {self.port} no longer exists"
            raise DeviceLostError(f"device on {self.port} vanished: read failed ({exc}){gone}") from None
        return data

    def _pump(self) -> None:
        """Read whatever arrived; readings are taken by :meth:`_take`, replies are posted."""
        data = self._read_chunk()
        if not data:
            return
        for frame in self._parser.feed(data):
            if frame.type != MessageType.READING:
                with self._changed:
                    self._replies[frame.type] = frame
                    self._changed.notify_all()

    def _take(self, frame: SerialFrame) -> bool:
        """The parser's check, called in stream order for every frame with valid CRCs: take a
        reading into the history; False means the frame cannot be genuine."""
        if frame.version != PROTOCOL_VERSION:
            raise ProtocolVersionError(
                f"the device on {self.port} speaks protocol version {frame.version}; this driver "
                f"supports version {PROTOCOL_VERSION}")
        self._last_frame = time.monotonic()
        validator = self._validator
        if frame.type != MessageType.READING or validator is None:
            return True
        return self._accept_reading(frame, validator)

    def _wait_reply(self, mtype: MessageType, deadline: float, pump: bool = True,
                    request_seq: int | None = None) -> SerialFrame | None:
        """The reply of type ``mtype`` (for ``request_seq`` if a RESULT), or None at the deadline.

        The reader thread pumps the port itself; other threads wait to be notified.
        """
        while time.monotonic() < deadline and not self._stopping.is_set():
            with self._changed:
                frame = self._replies.pop(mtype, None)
                if frame is not None and (request_seq is None or _answers(frame, request_seq)):
                    return frame
                if not pump:
                    self._changed.wait(max(0.0, deadline - time.monotonic()))
            if pump:
                self._pump()
        return None

    def _request(self, mtype: MessageType, payload: bytes, reply: MessageType) -> SerialFrame | None:
        """Send a request and wait for its reply, retrying; None only when stopping."""
        cfg = self.config
        frames_before, bytes_before = self._parser.stats.frames, self._parser.stats.bytes_in
        for _ in range(cfg.request_attempts):
            seq = self._send(mtype, payload)
            frame = self._wait_reply(reply, time.monotonic() + cfg.answer_timeout_s,
                                     request_seq=seq if reply == MessageType.RESULT else None)
            if frame is not None or self._stopping.is_set():
                return frame
        frames = self._parser.stats.frames - frames_before
        received = self._parser.stats.bytes_in - bytes_before
        waited = f"{cfg.request_attempts} x {cfg.answer_timeout_s} s"
        if frames == 0 and received > 0:
            raise WrongDeviceError(
                f"the device on {self.port} answered {received} bytes to {mtype.name} but no valid "
                f"frame in {waited}: not a C-arm encoder of this protocol, or a wrong baud rate")
        raise NoAnswerError(f"no answer to {mtype.name} from {self.port} within {waited}")

    def _handshake(self) -> None:
        self._utc_base = time.time() - time.monotonic()
        self._parser.reset()
        with self._changed:
            self._replies.clear()
        self._identity, self._validator = None, None
        self._clock.reset()
        assert self._serial is not None  # a handshake follows the port's opening
        self._serial.reset_input_buffer()
        frame = self._request(MessageType.IDENTIFY_REQUEST, b"", MessageType.IDENTIFY)
        if frame is None:
            return
        try:
            identity = decode_identity(frame.payload)
        except ProtocolError as exc:
            raise WrongDeviceError(f"the device on {self.port} sent an invalid IDENTIFY: {exc}") from None
        self._adopt(identity)
        result = self._request(MessageType.STREAM_START, encode_stream_start(self.config.rate_hz),
                               MessageType.RESULT)
        if result is None:
            return
        code = decode_result(result.payload)[2]
        if code != ResultCode.OK:
            name = ResultCode(code).name if code in ResultCode._value2member_map_ else str(code)
            raise DeviceRejectedError(f"the device on {self.port} refused streaming at "
                                      f"{self.config.rate_hz} Hz: {name}")
        self._stats.sessions += 1
        self._last_frame = time.monotonic()
        self._set_state("connected", f"{identity.model} {identity.serial_number} (firmware "
                                     f"{identity.firmware}) streaming at {self.config.rate_hz} Hz")

    def _adopt(self, identity: DeviceIdentity) -> None:
        """Check the device's axes against what the kinematics needs and keep their scales."""
        for axis in identity.axes:
            expected = AXIS_UNITS.get(axis.name)
            if expected is not None and axis.unit != expected:
                raise WrongDeviceError(f"the device on {self.port} reports axis {axis.name!r} in "
                                       f"{axis.unit}; {expected} expected")
        missing = [a for a in self.config.required_axes if a not in identity.axis_names]
        if missing:
            raise WrongDeviceError(f"the device on {self.port} ({identity.model}) lacks the axes {missing}; "
                                   f"it reports {list(identity.axis_names)}")
        self._validator = ReadingValidator(identity, self.config.rate_margin, self.port,
                                           self._stats.rejected)
        self._identity = identity

    def _stream(self) -> None:
        cfg = self.config
        period = 1.0 / cfg.rate_hz
        silent_after = period + cfg.silence_margin_s
        restart_every = max(4 * silent_after, 0.2)
        last_restart = 0.0
        while not self._stopping.is_set():
            self._pump()
            quiet = time.monotonic() - self._last_frame
            if quiet <= silent_after:
                if self._state.status == "silent":
                    self._set_state("connected", "the device streams again")
                continue
            if quiet > cfg.reopen_after_s:
                raise DeviceLostError(f"the device on {self.port} sent nothing for {quiet:.2f} s; "
                                      "reopening the port")
            if self._state.status != "silent":
                self._set_state("silent", f"no frame from {self.port} for {1000 * quiet:.0f} ms "
                                          f"(expected every {1000 * period:.0f} ms)")
            if time.monotonic() - last_restart > restart_every:
                # A device that restarted has forgotten the stream; asking again is harmless.
                self._send(MessageType.STREAM_START, encode_stream_start(cfg.rate_hz))
                last_restart = time.monotonic()

    def _accept_reading(self, frame: SerialFrame, validator: ReadingValidator) -> bool:
        """Put a READING frame that passes the validator in the history; False for one whose
        content is impossible (:mod:`drivers.reading_validation`)."""
        judgement = validator.judge(frame)
        if judgement.verdict is not Verdict.USE or judgement.joints is None:
            return judgement.verdict is Verdict.SKIP
        if judgement.clock_restarted:
            self._clock.reset()
        now = time.monotonic()
        t_utc = self._clock.update(frame.device_time_us, self._utc_base + now)
        reading = EncoderReading(frame.sequence, frame.device_time_us,
                                 datetime.fromtimestamp(t_utc, UTC),
                                 datetime.fromtimestamp(self._utc_base + now, UTC),
                                 now, judgement.joints, judgement.flags)
        self._history.append(reading, t_utc)
        self._stats.readings += 1
        with self._changed:
            self._changed.notify_all()
        if self._on_reading is not None:
            try:
                self._on_reading(reading)
            except Exception:  # a faulty observer must not kill the link
                log.exception("encoder link reading callback failed")
        return True


def _answers(frame: SerialFrame, request_seq: int) -> bool:
    """Whether a RESULT frame answers the request with sequence number ``request_seq``."""
    try:
        return decode_result(frame.payload)[1] == request_seq
    except ProtocolError:
        return False
