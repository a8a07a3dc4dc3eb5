"""The encoder protocol: frame layout, message codecs and the resynchronising parser."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest

from slamtka.drivers.carm_sim import DEFAULT_IDENTITY, FaultInjector, FaultSpec
from slamtka.drivers.protocol import (
    FRAME_OVERHEAD,
    MARKER,
    MAX_PAYLOAD,
    AxisInfo,
    DeviceIdentity,
    DeviceStatus,
    FrameParser,
    MessageType,
    ProtocolError,
    ResultCode,
    SerialFrame,
    crc16,
    decode_identity,
    decode_reading,
    decode_result,
    decode_status,
    decode_stream_start,
    encode_identity,
    encode_reading,
    encode_result,
    encode_serial_frame,
    encode_status,
    encode_stream_start,
)


def reading_frame(seq: int, n_axes: int = 6) -> SerialFrame:
    counts = (np.arange(n_axes) + 1) * (seq * 7919 % 100_000) - 50_000
    return SerialFrame(MessageType.READING, seq, 1_000_000 + 250 * seq, encode_reading(seq % 4, 0, counts))


def test_crc16_is_ccitt_false():
    assert crc16(b"123456789") == 0x29B1  # the catalogue check value of CRC-16/CCITT-FALSE
    assert crc16(b"") == 0xFFFF


def test_frame_layout_matches_the_protocol_page():
    payload = b"\x01\x02\x03"
    raw = encode_serial_frame(SerialFrame(MessageType.STATUS, 0x01020304, 0x1122334455667788, payload))
    assert raw[:2] == MARKER == b"\xa5\x5a"
    version, mtype, length, seq, t_us = struct.unpack_from("<BBHIQ", raw, 2)
    assert (version, mtype, length, seq, t_us) == (1, 0x85, 3, 0x01020304, 0x1122334455667788)
    assert struct.unpack_from("<H", raw, 18)[0] == crc16(raw[2:18])
    assert raw[20:23] == payload
    assert struct.unpack_from("<H", raw, 23)[0] == crc16(raw[2:23])
    assert len(raw) == FRAME_OVERHEAD + len(payload) == 25


def test_messages_round_trip():
    assert decode_identity(encode_identity(DEFAULT_IDENTITY)) == DEFAULT_IDENTITY
    values = [-7, 0, 2**31 - 1, -2**31, 1, 2]
    flags, mask, counts = decode_reading(encode_reading(5, 3, np.array(values)), DEFAULT_IDENTITY)
    assert (flags, mask, counts.tolist()) == (5, 3, values)
    assert decode_stream_start(encode_stream_start(250)) == 250
    result = encode_result(MessageType.STREAM_START, 99, ResultCode.RATE_OUT_OF_RANGE)
    assert decode_result(result) == (3, 99, 3)
    status = DeviceStatus(0x11, 0x4, 100, 12345)
    assert decode_status(encode_status(status)) == status


def test_payload_errors_name_the_problem():
    raw = encode_identity(DEFAULT_IDENTITY)
    with pytest.raises(ProtocolError, match="IDENTIFY payload truncated"):
        decode_identity(raw[:-3])
    with pytest.raises(ProtocolError, match="extra bytes"):
        decode_identity(raw + b"\x00")
    with pytest.raises(ProtocolError, match="28 expected for 6 axes"):
        decode_reading(b"\x00" * 24, DEFAULT_IDENTITY)
    with pytest.raises(ProtocolError, match="exceeds 512"):
        encode_serial_frame(SerialFrame(MessageType.STATUS, 1, 1, b"\x00" * (MAX_PAYLOAD + 1)))
    with pytest.raises(ProtocolError, match="unit 'rad'"):
        AxisInfo("orbital", "rad", 0.001, -1.0, 1.0, 1.0)
    with pytest.raises(ProtocolError, match="empty"):
        AxisInfo("lift", "mm", 0.001, 5.0, 5.0, 1.0)
    with pytest.raises(ProtocolError, match="duplicate axis"):
        DeviceIdentity("m", "s", "f", (DEFAULT_IDENTITY.axes[0],) * 2)
    bad_unit = bytearray(raw)
    bad_unit[raw.index(b"orbital") + len("orbital")] = 9  # the unit code after the first axis name
    with pytest.raises(ProtocolError, match="unknown unit code 9"):
        decode_identity(bytes(bad_unit))


def test_parser_gives_the_same_frames_for_any_chunking():
    frames = [reading_frame(k) for k in range(200)]
    stream = b"".join(encode_serial_frame(f) for f in frames)
    rng = np.random.default_rng(3)
    cuts = np.sort(rng.choice(np.arange(1, len(stream)), 600, replace=False))
    parser = FrameParser()
    got = []
    for chunk in np.split(np.frombuffer(stream, np.uint8), cuts):
        got += parser.feed(chunk.tobytes())
    assert got == frames
    one_by_one = FrameParser()
    assert [f for k in range(len(stream)) for f in one_by_one.feed(stream[k:k + 1])] == frames
    assert parser.stats.bytes_discarded == 0 and one_by_one.stats.bytes_discarded == 0
    assert parser.pending <= 1  # a frame's last byte is kept when it may start a marker


def test_parser_resynchronises_within_one_frame():
    good = [encode_serial_frame(reading_frame(k)) for k in range(6)]
    flipped = bytearray(good[1])
    flipped[30] ^= 0x10  # a payload bit: the frame CRC fails
    long_length = bytearray(good[3])
    long_length[4] = 0xFF  # a length of 255: the header CRC fails at once
    truncated = good[5][:-7]
    stream = (b"\xa5\xa5\x5a garbage \x5a" + good[0] + bytes(flipped) + good[2] + bytes(long_length)
              + truncated + good[4])
    parser = FrameParser()
    got = parser.feed(stream)
    assert [f.sequence for f in got] == [0, 2, 4]
    assert parser.stats.crc_errors >= 1 and parser.stats.header_errors >= 1


def test_a_corrupted_length_does_not_hold_back_the_next_frame():
    first, second = encode_serial_frame(reading_frame(1)), encode_serial_frame(reading_frame(2))
    corrupted = bytearray(first)
    corrupted[4], corrupted[5] = 0xF4, 0x01  # claims a 500-byte payload
    parser = FrameParser()
    # Exactly the bytes of both frames: the second is delivered without waiting for 500 bytes.
    assert [f.sequence for f in parser.feed(bytes(corrupted) + second)] == [2]


def test_parser_never_yields_a_corrupted_frame_and_never_loses_a_clean_one():
    frames = [reading_frame(k) for k in range(6000)]
    injector = FaultInjector(FaultSpec(ber=3e-4, drop=5e-3, dup=5e-3, noise=0.2),
                             np.random.default_rng(11))
    parser = FrameParser()
    received, corrupted = [], np.zeros(len(frames), bool)
    for k in range(0, len(frames), 8):
        data, hit = injector.apply([encode_serial_frame(f) for f in frames[k:k + 8]])
        corrupted[k:k + 8] = hit
        received += parser.feed(data)
        assert parser.pending < FRAME_OVERHEAD + MAX_PAYLOAD
    assert corrupted.sum() > 2000  # the run is meaningful
    for frame in received:
        assert frame == frames[frame.sequence]
    seen = np.zeros(len(frames), bool)
    seen[[f.sequence for f in received]] = True
    assert not np.any(~corrupted & ~seen), "a clean frame after a corrupted one was lost"


def test_a_frame_failing_the_check_does_not_swallow_the_next_one():
    """A corrupted frame can pass a CRC-16 by chance (1 in 65 536) while its tail overlaps the
    next frame's marker, as a dropped byte makes it. The receiver's check rejects its content;
    the parser must then still find the next frame inside those bytes."""
    following = encode_serial_frame(reading_frame(2))
    # Search a bogus frame whose frame CRC bytes are exactly the next frame's marker.
    for k in range(1 << 16):
        bogus = encode_serial_frame(SerialFrame(MessageType.READING, 1, 10, k.to_bytes(2, "little") + b"\xff" * 26))
        if bogus[-2:] == MARKER:
            break
    stream = bogus[:-2] + following  # the bogus frame ends inside the genuine one
    assert [f.sequence for f in FrameParser().feed(stream)] == [1]  # CRCs alone lose frame 2
    checked = FrameParser(check=lambda f: f.payload[2:4] != b"\xff\xff")
    assert [f.sequence for f in checked.feed(stream)] == [2]
    assert checked.stats.implausible == 1


def test_a_frame_that_lost_its_last_byte_does_not_swallow_the_next_one():
    """Drop the last byte of a frame whose CRC ends in 0xA5 (the marker's first byte): the
    frame still passes, completed by the next frame's first byte, and is genuine. The next
    frame must be found starting inside it, also across feeds."""
    for k in range(1 << 16):
        frame = SerialFrame(MessageType.READING, 1, 10, encode_reading(0, 0, np.array([k, 0, 0])))
        raw = encode_serial_frame(frame)
        if raw[-1] == MARKER[0]:
            break
    following = encode_serial_frame(reading_frame(2))
    stream = raw[:-1] + following
    parser = FrameParser()
    assert [f.sequence for f in parser.feed(stream)] == [1, 2]
    split = FrameParser()
    cut = len(raw)  # the first feed ends with the byte both frames share
    assert [f.sequence for f in split.feed(stream[:cut]) + split.feed(stream[cut:])] == [1, 2]
    assert parser.stats.bytes_discarded == split.stats.bytes_discarded == 0


def test_parser_stays_bounded_on_endless_garbage():
    rng = np.random.default_rng(5)
    parser = FrameParser()
    for _ in range(50):
        noise = rng.integers(0, 256, 4096, dtype=np.uint8)
        noise[rng.integers(0, 4094, 40)] = 0xA5  # many false markers
        assert parser.feed(noise.tobytes()) == []
        assert parser.pending < FRAME_OVERHEAD + MAX_PAYLOAD
    assert parser.stats.bytes_discarded + parser.pending == parser.stats.bytes_in


def test_protocol_page_examples_decode():
    """The hex examples of PROTOCOL.md are real frames (the page cannot drift from the code)."""
    page = (Path(__file__).resolve().parents[1] / "drivers" / "PROTOCOL.md").read_text()
    blocks = re.findall(r"```\n((?:[0-9a-f]{2}[ \n])+)```", page)
    frames = [f for block in blocks for f in FrameParser().feed(bytes.fromhex(block.replace("\n", " ")))]
    assert [f.type for f in frames] == [MessageType.IDENTIFY_REQUEST, MessageType.STREAM_START,
                                        MessageType.RESULT, MessageType.READING, MessageType.STATUS]
    assert decode_stream_start(frames[1].payload) == 100
    assert decode_result(frames[2].payload) == (MessageType.STREAM_START, 2, ResultCode.OK)
    flags, _, counts = decode_reading(frames[3].payload, DEFAULT_IDENTITY)
    assert flags == 1 and counts.tolist() == [-30000, 0, 0, 200000, 100000, 1000000]
    assert frames[3].sequence == 42 and frames[3].device_time_us == 7_000_020_000
    assert decode_status(frames[4].payload) == DeviceStatus(0, 0, 100, 0)
