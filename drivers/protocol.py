"""Frames and messages of the C-arm encoder protocol (the byte layout is in PROTOCOL.md).

A frame is ``marker | header | header CRC | payload | frame CRC``. The header CRC lets the
parser reject a corrupted length at once instead of waiting for a payload that never comes,
which keeps resynchronisation within one frame. Both checks are CRC-16/CCITT-FALSE
(``binascii.crc_hqx`` with initial value 0xFFFF), stored little-endian.

The parser is incremental and resynchronising: it searches markers with ``bytes.find`` (C
speed), and on any failed check it moves one byte past the rejected marker, so a clean frame
that follows garbage is never lost. Work per byte is constant on average, and between feeds
the buffer holds less than one maximal frame.
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag

import numpy as np

__all__ = [
    "MARKER", "PROTOCOL_VERSION", "MAX_PAYLOAD", "FRAME_OVERHEAD", "ProtocolError", "MessageType",
    "ResultCode", "StatusFlags", "INVALID_FLAGS", "SerialFrame", "crc16", "encode_serial_frame", "FrameParser",
    "ParserStats",
    "AxisInfo", "DeviceIdentity", "encode_identity", "decode_identity", "encode_reading", "encode_readings",
    "decode_reading", "encode_stream_start", "decode_stream_start", "encode_result",
    "decode_result", "DeviceStatus", "encode_status", "decode_status",
]

MARKER = b"\xa5\x5a"
PROTOCOL_VERSION = 1
MAX_PAYLOAD = 512
_HEADER = struct.Struct("<2sBBHIQ")  # marker, version, type, payload length, sequence, time (us)
_CRC = struct.Struct("<H")
HEADER_SIZE = _HEADER.size + _CRC.size  # 20 bytes up to the payload
FRAME_OVERHEAD = HEADER_SIZE + _CRC.size  # 22 bytes around every payload


class ProtocolError(ValueError):
    """A frame or payload that does not follow the protocol."""


class MessageType(IntEnum):
    """Requests (host to device) have the high bit clear; device messages have it set."""

    IDENTIFY_REQUEST = 0x01
    READ_ONCE = 0x02
    STREAM_START = 0x03
    STREAM_STOP = 0x04
    STATUS_REQUEST = 0x05
    RESULT = 0x80
    IDENTIFY = 0x81
    READING = 0x82
    STATUS = 0x85


class ResultCode(IntEnum):
    OK = 0
    MALFORMED = 1
    UNSUPPORTED = 2
    RATE_OUT_OF_RANGE = 3
    VERSION_MISMATCH = 4


class StatusFlags(IntFlag):
    MOVING = 0x01  # at least one axis is in motion
    XRAY_ON = 0x02  # exposure in progress
    AXIS_FAULT = 0x04  # the axes in the fault mask report no valid value
    NOT_REFERENCED = 0x08  # encoders not homed since power-on: values are not absolute
    TX_OVERRUN = 0x10  # the device dropped frames since the previous one


INVALID_FLAGS = StatusFlags.AXIS_FAULT | StatusFlags.NOT_REFERENCED


def crc16(data: bytes | bytearray) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


@dataclass(frozen=True)
class SerialFrame:
    type: int
    sequence: int
    device_time_us: int
    payload: bytes = b""
    version: int = PROTOCOL_VERSION

    @property
    def size(self) -> int:
        return FRAME_OVERHEAD + len(self.payload)


def encode_serial_frame(frame: SerialFrame) -> bytes:
    if len(frame.payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(frame.payload)} bytes exceeds {MAX_PAYLOAD}")
    header = _HEADER.pack(MARKER, frame.version, frame.type, len(frame.payload),
                          frame.sequence & 0xFFFFFFFF, frame.device_time_us & (2**64 - 1))
    body = header[2:] + _CRC.pack(crc16(header[2:])) + frame.payload
    return MARKER + body + _CRC.pack(crc16(body))


@dataclass
class ParserStats:
    bytes_in: int = 0
    frames: int = 0
    header_errors: int = 0  # a marker whose header failed its CRC or length bound
    crc_errors: int = 0  # a frame whose header passed but whose frame CRC failed
    implausible: int = 0  # a frame that passed both CRCs but not the receiver's check
    bytes_discarded: int = 0  # bytes that belonged to no valid frame


@dataclass
class FrameParser:
    """Incremental, resynchronising frame parser; feed it bytes as they arrive.

    ``check``, if given, is asked in stream order about every frame that passed both CRCs.
    A CRC-16 lets about one corrupted frame in 65 536 through; a frame that ``check`` calls
    implausible is treated like a CRC failure (the parser resumes one byte after its
    marker), so that even then the genuine frame that follows is not lost.
    """

    max_payload: int = MAX_PAYLOAD
    stats: ParserStats = field(default_factory=ParserStats)
    check: Callable[[SerialFrame], bool] | None = None
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _carry: int = field(default=0, repr=False)  # leading buffer bytes that ended the last frame

    @property
    def pending(self) -> int:
        """Bytes held back for the next feed: always less than one maximal frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes (after reopening the port)."""
        self.stats.bytes_discarded += len(self._buf) - self._carry
        self._buf.clear()
        self._carry = 0

    def feed(self, data: bytes) -> list[SerialFrame]:
        buf = self._buf
        buf += data
        self.stats.bytes_in += len(data)
        frames: list[SerialFrame] = []
        # ``covered``: bytes before it belong to accepted frames (the buffer may start with the
        # last byte of the previous one, see below). Only bytes beyond it count as discarded.
        carry_in = self._carry
        n, pos, covered, framed = len(buf), 0, carry_in, 0
        while True:
            start = buf.find(MARKER, pos)
            if start < 0:
                # A trailing first marker byte may be completed by the next chunk.
                pos = max(pos, n - 1) if n and buf[-1] == MARKER[0] else n
                break
            if n - start < HEADER_SIZE:
                pos = start
                break
            _, version, mtype, length, seq, t_us = _HEADER.unpack_from(buf, start)
            (header_crc,) = _CRC.unpack_from(buf, start + _HEADER.size)
            if length > self.max_payload or crc16(buf[start + 2:start + _HEADER.size]) != header_crc:
                self.stats.header_errors += 1
                pos = start + 1
                continue
            end = start + HEADER_SIZE + length + _CRC.size
            if n < end:
                pos = start
                break
            (frame_crc,) = _CRC.unpack_from(buf, end - _CRC.size)
            if crc16(buf[start + 2:end - _CRC.size]) != frame_crc:
                self.stats.crc_errors += 1
                pos = start + 1
                continue
            frame = SerialFrame(mtype, seq, t_us, bytes(buf[start + HEADER_SIZE:end - _CRC.size]), version)
            if self.check is not None and not self.check(frame):
                self.stats.implausible += 1
                pos = start + 1
                continue
            frames.append(frame)
            framed += end - max(start, covered)
            covered = end
            # A frame whose last byte was lost still passes when the first byte of the next
            # marker equals that lost byte (1 in 256): then its "last byte" is the next
            # frame's first. So a frame ending in the marker's first byte is searched again
            # from that byte; a genuine frame starting there must also pass both CRCs.
            pos = end - 1 if buf[end - 1] == MARKER[0] else end
        self._carry = max(0, covered - pos)
        self.stats.frames += len(frames)
        self.stats.bytes_discarded += max(pos, covered) - carry_in - framed
        del buf[:pos]
        return frames


# -- payloads ---------------------------------------------------------------------------------

_UNIT_CODES = {"deg": 1, "mm": 2}
_UNITS = {code: unit for unit, code in _UNIT_CODES.items()}
_AXIS = struct.Struct("<BIiiI")  # unit code, resolution (nano-units per count), min, max, max rate
MAX_AXES = 16


@dataclass(frozen=True)
class AxisInfo:
    """One encoder axis as the device declares it; values are ``counts * resolution``."""

    name: str
    unit: str  # "deg" or "mm"
    resolution: float  # units per count
    minimum: float  # units
    maximum: float
    max_rate: float  # units per second

    def __post_init__(self) -> None:
        if not self.name or not self.name.isascii() or len(self.name) > 32:
            raise ProtocolError(f"axis name {self.name!r} must be 1-32 ASCII characters")
        if self.unit not in _UNIT_CODES:
            raise ProtocolError(f"axis {self.name!r}: unit {self.unit!r} is not one of {sorted(_UNIT_CODES)}")
        if not self.resolution > 0 or not self.max_rate > 0:
            raise ProtocolError(f"axis {self.name!r}: resolution and maximum rate must be positive")
        if not self.minimum < self.maximum:
            raise ProtocolError(f"axis {self.name!r}: range [{self.minimum}, {self.maximum}] is empty")

    def counts(self, value: float) -> int:
        return int(round(value / self.resolution))


@dataclass(frozen=True)
class DeviceIdentity:
    model: str
    serial_number: str
    firmware: str
    axes: tuple[AxisInfo, ...]

    def __post_init__(self) -> None:
        if not 1 <= len(self.axes) <= MAX_AXES:
            raise ProtocolError(f"a device declares 1-{MAX_AXES} axes, not {len(self.axes)}")
        names = [a.name for a in self.axes]
        if len(set(names)) != len(names):
            raise ProtocolError(f"duplicate axis names in {names}")

    @property
    def axis_names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    @property
    def reading_size(self) -> int:
        """Bytes of this device's READING payload: flags, fault mask, one count per axis."""
        return 4 + 4 * len(self.axes)


def _pack_text(text: str) -> bytes:
    raw = text.encode()
    if len(raw) > 255:
        raise ProtocolError(f"text field {text[:20]!r}... longer than 255 bytes")
    return bytes([len(raw)]) + raw


class _Reader:
    """Sequential reader over a payload that names the message in its errors."""

    def __init__(self, payload: bytes, what: str) -> None:
        self.payload, self.what, self.pos = payload, what, 0

    def take(self, size: int) -> bytes:
        if self.pos + size > len(self.payload):
            raise ProtocolError(f"{self.what} payload truncated at byte {self.pos} of {len(self.payload)}")
        chunk = self.payload[self.pos:self.pos + size]
        self.pos += size
        return chunk

    def unpack(self, fmt: struct.Struct) -> tuple:
        return fmt.unpack(self.take(fmt.size))

    def text(self) -> str:
        try:
            return self.take(self.take(1)[0]).decode()
        except UnicodeDecodeError:
            raise ProtocolError(f"{self.what}: text field is not UTF-8") from None

    def done(self) -> None:
        if self.pos != len(self.payload):
            raise ProtocolError(f"{self.what} payload has {len(self.payload) - self.pos} extra bytes")


def encode_identity(identity: DeviceIdentity) -> bytes:
    out = [_pack_text(identity.model), _pack_text(identity.serial_number), _pack_text(identity.firmware),
           bytes([len(identity.axes)])]
    for a in identity.axes:
        nano = int(round(a.resolution * 1e9))
        if not 1 <= nano < 2**32:
            raise ProtocolError(f"axis {a.name!r}: resolution {a.resolution} is not encodable")
        out.append(_pack_text(a.name))
        out.append(_AXIS.pack(_UNIT_CODES[a.unit], nano, a.counts(a.minimum), a.counts(a.maximum),
                              a.counts(a.max_rate)))
    return b"".join(out)


def decode_identity(payload: bytes) -> DeviceIdentity:
    r = _Reader(payload, "IDENTIFY")
    model, serial, firmware = r.text(), r.text(), r.text()
    axes = []
    for _ in range(r.take(1)[0]):
        name = r.text()
        unit_code, nano, lo, hi, rate = r.unpack(_AXIS)
        if unit_code not in _UNITS:
            raise ProtocolError(f"IDENTIFY: axis {name!r} has unknown unit code {unit_code}")
        res = nano * 1e-9
        axes.append(AxisInfo(name, _UNITS[unit_code], res, lo * res, hi * res, rate * res))
    r.done()
    return DeviceIdentity(model, serial, firmware, tuple(axes))


_READING_HEAD = struct.Struct("<HH")  # status flags, axis fault mask


def encode_readings(flags: np.ndarray, fault_masks: np.ndarray, counts: np.ndarray) -> list[bytes]:
    """READING payloads of many samples at once: ``counts`` is (samples, axes)."""
    counts = np.asarray(counts)
    layout = [("flags", "<u2"), ("mask", "<u2"), ("counts", "<i4", (counts.shape[1],))]
    rows = np.zeros(len(counts), dtype=layout)
    rows["flags"], rows["mask"], rows["counts"] = flags, fault_masks, counts
    raw, size = rows.tobytes(), rows.dtype.itemsize
    return [raw[k:k + size] for k in range(0, len(raw), size)]


def encode_reading(flags: int, fault_mask: int, counts: np.ndarray) -> bytes:
    return encode_readings(np.array([flags]), np.array([fault_mask]), np.asarray(counts)[None, :])[0]


def decode_reading(payload: bytes, device: DeviceIdentity) -> tuple[int, int, np.ndarray]:
    """(flags, axis fault mask, counts) of a READING payload from ``device``."""
    if len(payload) != device.reading_size:
        raise ProtocolError(f"READING payload of {len(payload)} bytes; {device.reading_size} "
                            f"expected for {len(device.axes)} axes")
    flags, mask = _READING_HEAD.unpack_from(payload)
    return flags, mask, np.frombuffer(payload, dtype="<i4", offset=4).astype(np.int64)


_STREAM = struct.Struct("<H")


def encode_stream_start(rate_hz: int) -> bytes:
    return _STREAM.pack(rate_hz)


def decode_stream_start(payload: bytes) -> int:
    r = _Reader(payload, "STREAM_START")
    (rate,) = r.unpack(_STREAM)
    r.done()
    return rate


_RESULT = struct.Struct("<BIB")  # request type, request sequence, result code


def encode_result(request_type: int, request_seq: int, code: ResultCode) -> bytes:
    return _RESULT.pack(request_type, request_seq & 0xFFFFFFFF, code)


def decode_result(payload: bytes) -> tuple[int, int, int]:
    r = _Reader(payload, "RESULT")
    out = r.unpack(_RESULT)
    r.done()
    return out


@dataclass(frozen=True)
class DeviceStatus:
    flags: int
    fault_mask: int
    stream_rate_hz: int  # 0 when not streaming
    frames_dropped: int  # transmit overruns since power-on


_STATUS = struct.Struct("<HHHI")


def encode_status(status: DeviceStatus) -> bytes:
    return _STATUS.pack(status.flags, status.fault_mask, status.stream_rate_hz,
                        status.frames_dropped & 0xFFFFFFFF)


def decode_status(payload: bytes) -> DeviceStatus:
    r = _Reader(payload, "STATUS")
    status = DeviceStatus(*r.unpack(_STATUS))
    r.done()
    return status
