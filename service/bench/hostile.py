"""Hostile DICOM at the byte level: a raw upper-layer client and the inputs it sends.

pynetdicom's client refuses to send most of what an attacker or a broken C-arm would, so
the hardening tests and ``slamtka bench hardening`` build PDUs, command sets and datasets
here, byte by byte, and push them over a plain (or TLS) socket. Every input generator is
deterministic for a given seed.
"""

from __future__ import annotations

import datetime as dt
import socket
import ssl
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from pydicom.dataset import Dataset
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset
from pydicom.uid import ExplicitVRLittleEndian, ImplicitVRLittleEndian, generate_uid

from slamtka.service.frames import XA_IMAGE_STORAGE, Frame, encode_frame

__all__ = ["RawAssociation", "Dropped", "frame_dataset_bytes", "dataset_bytes", "wire_bytes",
           "noise_frame", "uid_cases",
           "truncations", "pixel_length_cases", "element_length_cases", "nested_sequence",
           "deflate_bomb", "mutations", "malformed_pdus", "associate_rq", "pdata", "DEFLATED"]

DEFLATED = "1.2.840.10008.1.2.1.99"
_APPLICATION_CONTEXT = b"1.2.840.10008.3.1.1.1"
_IMPLEMENTATION_UID = b"1.2.826.0.1.3680043.9.7433.1.1"
VERIFICATION = "1.2.840.10008.1.1"


class Dropped(Exception):
    """The peer closed the connection or sent an A-ABORT / A-ASSOCIATE-RJ."""

    @property
    def aborted(self) -> bool:
        """The server said so (A-ABORT), rather than going silent or resetting."""
        return "A-ABORT" in str(self)


def _item(item_type: int, payload: bytes) -> bytes:
    return struct.pack(">BBH", item_type, 0, len(payload)) + payload


def associate_rq(calling: str, called: str, contexts: list[tuple[int, str, list[str]]],
                 max_pdu: int = 16384) -> bytes:
    """An A-ASSOCIATE-RQ PDU; ``contexts`` are (id, abstract syntax, transfer syntaxes)."""
    body = struct.pack(">HH", 1, 0) + called.encode().ljust(16) + calling.encode().ljust(16)
    body += bytes(32) + _item(0x10, _APPLICATION_CONTEXT)
    for context_id, abstract, syntaxes in contexts:
        sub = _item(0x30, abstract.encode()) + b"".join(_item(0x40, s.encode()) for s in syntaxes)
        body += _item(0x20, bytes([context_id, 0, 0, 0]) + sub)
    body += _item(0x50, _item(0x51, struct.pack(">L", max_pdu)) + _item(0x52, _IMPLEMENTATION_UID))
    return struct.pack(">BBL", 0x01, 0, len(body)) + body


def pdata(context_id: int, fragment: bytes, command: bool, last: bool) -> bytes:
    """One P-DATA-TF PDU with one PDV item."""
    pdv = struct.pack(">LBB", len(fragment) + 2, context_id, int(command) | int(last) << 1)
    return struct.pack(">BBL", 0x04, 0, len(pdv) + len(fragment)) + pdv + fragment


def _element(group: int, element: int, value: bytes) -> bytes:
    if len(value) % 2:
        value += b"\0"
    return struct.pack("<HHL", group, element, len(value)) + value


def store_command(sop_class: str, sop_instance: str, message_id: int = 1) -> bytes:
    """A C-STORE-RQ command set (implicit VR LE) carrying the UIDs exactly as given."""
    body = (_element(0, 0x0002, sop_class.encode("latin-1"))
            + _element(0, 0x0100, struct.pack("<H", 0x0001))
            + _element(0, 0x0110, struct.pack("<H", message_id & 0xFFFF))
            + _element(0, 0x0700, struct.pack("<H", 0))
            + _element(0, 0x0800, struct.pack("<H", 0x0000))
            + _element(0, 0x1000, sop_instance.encode("latin-1")))
    return _element(0, 0x0000, struct.pack("<L", len(body))) + body


def echo_command(message_id: int = 1) -> bytes:
    body = (_element(0, 0x0002, VERIFICATION.encode()) + _element(0, 0x0100, struct.pack("<H", 0x0030))
            + _element(0, 0x0110, struct.pack("<H", message_id)) + _element(0, 0x0800, struct.pack("<H", 0x0101)))
    return _element(0, 0x0000, struct.pack("<L", len(body))) + body


def _status_of(command: bytes) -> int:
    pos = 0
    while pos + 8 <= len(command):
        group, element, length = struct.unpack_from("<HHL", command, pos)
        if (group, element) == (0, 0x0900):
            return struct.unpack_from("<H", command, pos + 8)[0]
        pos += 8 + length
    raise Dropped("response without a Status")


@dataclass
class RawAssociation:
    """A hand-driven association: connect, associate, push bytes, read the response status."""

    port: int
    host: str = "127.0.0.1"
    calling: str = "CARM1"
    called: str = "SLAMTKA"
    contexts: list = field(default_factory=lambda: [
        (1, XA_IMAGE_STORAGE, [ExplicitVRLittleEndian]), (3, XA_IMAGE_STORAGE, [ImplicitVRLittleEndian]),
        (5, VERIFICATION, [ImplicitVRLittleEndian])])
    source: str | None = None
    tls: ssl.SSLContext | None = None
    timeout_s: float = 20.0
    accepted: dict = field(default_factory=dict)
    max_pdu: int = 16384

    def connect(self) -> RawAssociation:
        sock = socket.create_connection((self.host, self.port), self.timeout_s,
                                        source_address=(self.source, 0) if self.source else None)
        # A message goes out as two writes (command, dataset): without this, Nagle's algorithm
        # waits for the peer's delayed ACK and every store costs 40 ms of idle time.
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock = self.tls.wrap_socket(sock) if self.tls else sock
        return self

    def associate(self) -> RawAssociation:
        self.connect()
        self.send(associate_rq(self.calling, self.called, self.contexts))
        pdu_type, body = self.read_pdu()
        if pdu_type != 0x02:
            raise Dropped(f"association not accepted (PDU type 0x{pdu_type:02X})")
        pos = 68
        while pos + 4 <= len(body):
            item_type, _, length = struct.unpack_from(">BBH", body, pos)
            if item_type == 0x21 and body[pos + 6] == 0:
                ts_len = struct.unpack_from(">H", body, pos + 10)[0]
                self.accepted[body[pos + 4]] = body[pos + 12:pos + 12 + ts_len].decode().rstrip("\0")
            if item_type == 0x50 and length >= 8 and body[pos + 4] == 0x51:
                self.max_pdu = struct.unpack_from(">L", body, pos + 8)[0] or self.max_pdu
            pos += 4 + length
        return self

    def send(self, data: bytes) -> None:
        try:
            self.sock.sendall(data)
        except OSError as exc:
            raise Dropped(f"send failed: {exc}") from None

    def _read(self, n: int) -> bytes:
        out = bytearray()
        while len(out) < n:
            try:
                chunk = self.sock.recv(min(n - len(out), 1 << 16))
            except (OSError, ssl.SSLError) as exc:
                raise Dropped(f"receive failed: {exc}") from None
            if not chunk:
                raise Dropped("connection closed")
            out += chunk
        return bytes(out)

    def read_pdu(self) -> tuple[int, bytes]:
        header = self._read(6)
        pdu_type, _, length = struct.unpack(">BBL", header)
        body = self._read(length)
        if pdu_type in (0x03, 0x07):
            raise Dropped(f"peer sent {'A-ASSOCIATE-RJ' if pdu_type == 3 else 'A-ABORT'}")
        return pdu_type, body

    def message(self, context_id: int, command: bytes, dataset: bytes | None) -> int:
        """Send one DIMSE message; the response's Status."""
        room = self.max_pdu - 6
        self.send(pdata(context_id, command, True, True))
        if dataset is not None:
            chunks = [dataset[i:i + room] for i in range(0, len(dataset), room)] or [b""]
            self.send(b"".join(pdata(context_id, c, False, i == len(chunks) - 1)
                               for i, c in enumerate(chunks)))
        response = b""
        while True:
            pdu_type, body = self.read_pdu()
            if pdu_type != 0x04:
                raise Dropped(f"unexpected PDU type 0x{pdu_type:02X}")
            response += body[6:]
            if body[5] & 2:
                return _status_of(response)

    def store(self, dataset: bytes, sop_instance: str, context_id: int = 1,
              sop_class: str = XA_IMAGE_STORAGE, command_uid: str | None = None) -> int:
        return self.message(context_id, store_command(
            sop_class, sop_instance if command_uid is None else command_uid),
                            dataset)

    def echo(self) -> int:
        return self.message(5, echo_command(), None)

    def release(self) -> None:
        try:
            self.send(bytes([0x05, 0, 0, 0, 0, 4, 0, 0, 0, 0]))
            self.read_pdu()
        except Dropped:
            pass
        self.close()

    def close(self) -> None:
        try:
            self.sock.close()
        except OSError:
            pass


# -- datasets ----------------------------------------------------------------------------

def noise_frame(seed: int = 0, size: int = 32, sop_instance_uid: str | None = None) -> Frame:
    """A valid 12-bit XA frame of noise with its geometry."""
    rng = np.random.default_rng(seed)
    return Frame(pixels=rng.integers(0, 4000, (size, size)).astype(np.uint16),
                 imager_pixel_spacing_mm=(0.3, 0.3), primary_angle_deg=-30.0,
                 secondary_angle_deg=0.0, sid_mm=1000.0, sod_mm=620.0,
                 acquisition_datetime=dt.datetime.now(dt.UTC), patient_id="P-1",
                 laterality="R", bits_stored=12,
                 sop_instance_uid=sop_instance_uid or generate_uid())


def frame_dataset_bytes(seed: int = 0, size: int = 32, explicit: bool = True,
                        sop_instance_uid: str | None = None) -> tuple[bytes, str]:
    """A valid XA frame's dataset (no file meta) as sent on the wire, and its SOP Instance UID."""
    frame = noise_frame(seed, size, sop_instance_uid)
    return dataset_bytes(frame, explicit), frame.sop_instance_uid


def dataset_bytes(frame: Frame, explicit: bool = True) -> bytes:
    """``frame`` encoded as a C-STORE carries it: the dataset without file meta."""
    return wire_bytes(encode_frame(frame), explicit)


def wire_bytes(ds: Dataset, explicit: bool = True) -> bytes:
    """``ds`` as a C-STORE carries it (little endian, without its file meta)."""
    buffer = DicomBytesIO()
    buffer.is_little_endian, buffer.is_implicit_VR = True, not explicit
    write_dataset(buffer, ds)  # the file meta (group 0002) is not a dataset element
    return buffer.getvalue()


def _pixel_header_offset(data: bytes, explicit: bool) -> int:
    """Where the PixelData element (the last one) starts."""
    offset = data.find(b"\xe0\x7f\x10\x00" + (b"OW" if explicit else b""))
    if offset < 0:
        raise ValueError("no PixelData element")
    return offset


def uid_cases() -> list[tuple[str, str, str]]:
    """(name, UID in the command, UID in the dataset): path tricks, over-long, non-conformant."""
    good = generate_uid()
    hostile = {"parent path": "../../../../tmp/slamtka-escape", "absolute path": "/etc/passwd",
               "backslash path": "..\\..\\windows\\system32", "over-long": "1.2." + "3" * 70,
               "leading zero": "1.2.03.4", "letters": "1.2.3.abc", "trailing dot": "1.2.3.",
               "empty": "", "embedded NUL": "1.2.3\0/../x", "spaces": "1.2 .3",
               "control characters": "1.2.3\n4", "non-ascii": "1.2.3.\u00e9"}
    cases = []
    for name, value in hostile.items():
        cases += [(f"{name} in the command", value, good), (f"{name} in the dataset", good, value),
                  (f"{name} in both", value, value)]
    cases.append(("command and dataset differ", good, generate_uid()))
    return cases


def with_uid(data: bytes, new: str, explicit: bool) -> bytes:
    """``data`` with the SOP Instance UID element's value replaced (length fixed up)."""
    tag = struct.pack("<HH", 0x0008, 0x0018)
    pos = data.index(tag + (b"UI" if explicit else b""))
    value = new.encode("latin-1")
    value += b"\0" * (len(value) % 2)
    header = 8
    length = struct.unpack_from("<H" if explicit else "<L", data, pos + (6 if explicit else 4))[0]
    head = tag + (b"UI" + struct.pack("<H", len(value)) if explicit else struct.pack("<L", len(value)))
    return data[:pos] + head + value + data[pos + header + length:]


def truncations(data: bytes, count: int) -> list[int]:
    """``count`` distinct offsets to cut ``data`` at, spread over the whole of it."""
    return sorted(set(np.linspace(1, len(data) - 1, count).astype(int).tolist()))


def pixel_length_cases(data: bytes, explicit: bool) -> list[tuple[str, bytes]]:
    """The frame with pixel data shorter or longer than Rows x Columns x BitsAllocated."""
    start = _pixel_header_offset(data, explicit)
    header = 12 if explicit else 8
    pixels = data[start + header:]
    out = []
    for delta in (-2, -128, -len(pixels) // 2, -len(pixels) + 2, 2, 128, len(pixels)):
        value = pixels[:len(pixels) + delta] if delta < 0 else pixels + bytes(delta)
        out.append((f"PixelData {delta:+d} bytes", data[:start + header - 4]
                    + struct.pack("<L", len(value)) + value))
    return out


def element_length_cases(data: bytes, explicit: bool) -> list[tuple[str, bytes]]:
    """Element lengths of 1 GiB, 4 GiB - 2 and undefined, on PixelData and on an inserted UT."""
    start = _pixel_header_offset(data, explicit)
    header = 12 if explicit else 8
    out = []
    for name, length in (("1 GiB", 1 << 30), ("4 GiB", 0xFFFFFFFE), ("undefined", 0xFFFFFFFF)):
        out.append((f"PixelData declares {name}",
                    data[:start + header - 4] + struct.pack("<L", length) + data[start + header:]))
        # an unknown (0028,9999) UT element just before the pixel data
        ut = struct.pack("<HH", 0x0028, 0x9999) + (b"UT\0\0" if explicit else b"")
        out.append((f"an element declares {name}", data[:start] + ut + struct.pack("<L", length)
                    + b"x" * 64 + data[start:]))
    return out


def nested_sequence(data: bytes, depth: int, explicit: bool) -> bytes:
    """The frame with a (0040,A730) Content Sequence nested ``depth`` deep (undefined lengths)."""
    start = _pixel_header_offset(data, explicit)
    sq = struct.pack("<HH", 0x0040, 0xA730) + (b"SQ\0\0" if explicit else b"") + b"\xff" * 4
    item = struct.pack("<HHL", 0xFFFE, 0xE000, 0xFFFFFFFF)
    close = struct.pack("<HHL", 0xFFFE, 0xE00D, 0) + struct.pack("<HHL", 0xFFFE, 0xE0DD, 0)
    return data[:start] + (sq + item) * depth + close * depth + data[start:]


def deflate_bomb(inflated_bytes: int = 1 << 30) -> bytes:
    """A raw deflate stream (as Deflated Explicit VR LE carries) of ``inflated_bytes`` zeros.

    Built from one compressed MiB repeated (full flushes reset the window), in milliseconds.
    """
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    block = c.compress(bytes(1 << 20)) + c.flush(zlib.Z_FULL_FLUSH)
    return block * (inflated_bytes >> 20) + c.flush()


def mutations(data: bytes, count: int, seed: int) -> Iterator[tuple[str, bytes]]:
    """Random byte flips, truncations, insertions, deletions and length-field smashes."""
    rng = np.random.default_rng(seed)
    buf = np.frombuffer(data, np.uint8)
    for _ in range(count):
        kind = int(rng.integers(0, 5))
        if kind == 0:
            mutant = buf.copy()
            where = rng.integers(0, len(buf), int(rng.integers(1, 9)))
            mutant[where] ^= rng.integers(1, 256, where.size).astype(np.uint8)
            yield "flip", mutant.tobytes()
        elif kind == 1:
            yield "truncate", data[:int(rng.integers(0, len(data)))]
        elif kind == 2:
            at = int(rng.integers(0, len(data)))
            yield "insert", data[:at] + rng.bytes(int(rng.integers(1, 33))) + data[at:]
        elif kind == 3:
            at = int(rng.integers(0, len(data)))
            yield "delete", data[:at] + data[at + int(rng.integers(1, 33)):]
        else:
            at = int(rng.integers(0, len(data) - 4))
            value = rng.choice([0, 1, 0xFFFF, 0x7FFFFFFF, 0xFFFFFFFF, int(rng.integers(0, 1 << 32))])
            yield "length", data[:at] + struct.pack("<L", int(value)) + data[at + 4:]


def malformed_pdus(count: int, seed: int, calling: str = "CARM1",
                   called: str = "SLAMTKA") -> Iterator[tuple[str, bytes, bool]]:
    """(kind, bytes, after_association): broken PDUs, sent on a fresh connection each.

    ``after_association`` says the bytes follow a valid A-ASSOCIATE-RQ/AC exchange.
    """
    rng = np.random.default_rng(seed)
    rq = associate_rq(calling, called, [(1, XA_IMAGE_STORAGE, [ExplicitVRLittleEndian])])
    for _ in range(count):
        kind = int(rng.integers(0, 6))
        if kind == 0:  # a mutated association request
            mutant = bytearray(rq)
            for at in rng.integers(0, len(rq), int(rng.integers(1, 6))):
                mutant[int(at)] = int(rng.integers(0, 256))
            yield "mutated A-ASSOCIATE-RQ", bytes(mutant), False
        elif kind == 1:  # random bytes
            yield "random bytes", rng.bytes(int(rng.integers(1, 512))), bool(rng.integers(0, 2))
        elif kind == 2:  # a header with any type and a huge length
            header = struct.pack(">BBL", int(rng.integers(0, 256)), 0, int(rng.integers(0, 1 << 32)))
            yield "header", header + rng.bytes(int(rng.integers(0, 64))), bool(rng.integers(0, 2))
        elif kind == 3:  # P-DATA whose PDV items do not tile the PDU
            pdv = struct.pack(">LBB", int(rng.integers(0, 1 << 32)), 1, int(rng.integers(0, 256)))
            body = pdv + rng.bytes(int(rng.integers(0, 64)))
            yield "P-DATA items", struct.pack(">BBL", 4, 0, len(body)) + body, True
        elif kind == 4:  # a command with garbage in it
            command = rng.bytes(int(rng.integers(0, 256)))
            yield "garbage command", pdata(1, command, True, True), True
        else:  # a valid command, a PDV on an unknown context, or a release out of order
            context = int(rng.integers(0, 256)) | 1
            yield "unknown context", pdata(context if context != 1 else 3, b"\0" * 8, True, True), True

