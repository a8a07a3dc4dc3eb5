"""The SCP's network guard: who may connect, and how much a peer may send.

pynetdicom is a protocol library, not a hardened server. Left alone it does the TLS
handshake in its accept loop (one silent client stalls every other), counts sockets that
never sent a byte as associations (a few idle sockets lock the C-arm out), reads whatever
length a PDU header declares into memory, and assembles a message of any size. This module
wraps its server at the byte level, before any of that:

- admission (accept thread): the source-address allow-list, a total and a per-peer cap on
  open connections; at the total cap the oldest connection still silent (no A-ASSOCIATE-RQ
  yet) is dropped to make room, so idle sockets cannot lock the C-arm out;
- the connection's own thread: the TLS handshake, then the first PDU, each within
  ``request_timeout_s``; a socket read then stalls at most ``idle_timeout_s``;
- every PDU header is checked before its body is read: known type, a length within the
  limit for its type (``max_pdu_bytes`` for P-DATA, which we negotiate);
- every P-DATA body is parsed: its PDV items must tile it exactly and name an accepted
  presentation context; a message (command or dataset) is dropped as soon as its fragments
  exceed its limit (``max_message_bytes`` for a dataset), never assembled;
- a command set must be well formed, its UIDs conformant and a C-STORE must name its
  instance (pynetdicom would abort unaudited, or answer an empty UID with success);
- the A-ASSOCIATE-RQ is admitted by :mod:`service.admission` (callers bound to addresses and
  certificates, association slots per address and in all, one kept for the bound C-arm)
  before pynetdicom negotiates; callers refused by AE title never take a slot.

A violation sends an A-ABORT (or A-ASSOCIATE-RJ when admission refuses), closes the
connection and is audited; the server keeps serving.
"""

from __future__ import annotations

import ipaddress
import logging
import select
import socket
import ssl
import struct
import threading
from collections import Counter
from collections.abc import Callable

from pydicom.uid import UID
from pynetdicom.transport import AssociationSocket, RequestHandler, ThreadedAssociationServer

from slamtka.service.admission import Admission, Ticket
from slamtka.service.tls import fingerprint

__all__ = ["GuardedServer", "WireLimits", "ASSOCIATE_RQ_MAX_BYTES"]

log = logging.getLogger("slamtka.wire")

ASSOCIATE_RQ_MAX_BYTES = 65536  # room for ~500 presentation contexts
COMMAND_MAX_BYTES = 65536  # a DIMSE command set is a few hundred bytes
_SMALL_PDU_BYTES = {0x03: 64, 0x05: 64, 0x06: 64, 0x07: 64}  # reject, release, abort
_A_ABORT = bytes([0x07, 0, 0, 0, 0, 4, 0, 0, 2, 0])  # source: service provider
_A_ASSOCIATE_RJ_LIMIT = bytes([0x03, 0, 0, 0, 0, 4, 0, 2, 3, 2])  # transient, local limit
_A_ASSOCIATE_RJ_CALLER = bytes([0x03, 0, 0, 0, 0, 4, 0, 1, 1, 3])  # calling AE not recognised
_COMMAND_UIDS = {0x0002: "Affected SOP Class UID", 0x0003: "Requested SOP Class UID",
                 0x1000: "Affected SOP Instance UID", 0x1001: "Requested SOP Instance UID"}
C_STORE_RQ = 0x0001


def command_problem(command: bytes) -> str | None:
    """Why a command set (implicit VR LE, group 0000) is unusable, or None."""
    pos, values = 0, {}
    while pos < len(command):
        if len(command) - pos < 8:
            return "command set ends inside an element header"
        group, element, length = struct.unpack_from("<HHL", command, pos)
        if group != 0 or pos + 8 + length > len(command):
            return f"command element ({group:04X},{element:04X}) is malformed"
        values[element] = command[pos + 8:pos + 8 + length]
        pos += 8 + length
    for element, name in _COMMAND_UIDS.items():
        if element in values:
            text = values[element].rstrip(b"\0 ").decode("ascii", "replace")
            if not UID(text).is_valid:
                return f"{name} in the command is not a valid UID"
    field = values.get(0x0100, b"")
    if len(field) == 2 and struct.unpack("<H", field)[0] == C_STORE_RQ and not (
            values.get(0x1000, b"").strip(b"\0 ") and values.get(0x0002, b"").strip(b"\0 ")):
        return "C-STORE command without Affected SOP Class/Instance UID"
    return None


class WireLimits:
    """The limits and identities the guard enforces (from :class:`~service.config.DicomConfig`)."""

    def __init__(self, config, audit: Callable[..., object]):
        self.ae_title = config.ae_title
        self.storers = set(config.allowed_calling_ae_titles)
        self.health = config.health_ae_title
        self.networks = [ipaddress.ip_network(a, strict=False)
                         for a in config.allowed_source_addresses]
        self.max_connections = config.max_connections
        self.max_per_peer = config.max_connections_per_peer
        self.admission = Admission(config)
        self.max_pdu = config.max_pdu_bytes
        self.max_message = config.max_message_bytes
        self.request_timeout_s = config.request_timeout_s
        self.idle_timeout_s = config.idle_timeout_s
        self.audit = audit
        self.space_problem: Callable[[], str | None] = lambda: None  # the disk floor (retention)

    def address_allowed(self, host: str) -> bool:
        if not self.networks:
            return True
        try:
            address = ipaddress.ip_address(host)
        except ValueError:
            return False
        return any(address in network for network in self.networks)


class _Violation(OSError):
    """Raised from a socket read: pynetdicom's DUL then closes the connection (Evt17)."""


class GuardedSocket(AssociationSocket):
    """pynetdicom's socket with every PDU checked before (header) and after (body) it is read."""

    guard: GuardedServer
    peer: dict
    _body_type: int | None
    _message_bytes: dict
    _association: Ticket | None
    _requested: bool  # an A-ASSOCIATE-RQ came (one per connection)
    _command: bytearray
    certificate: str  # SHA-256 of the client certificate ("" without TLS)

    @classmethod
    def adopt(cls, plain: AssociationSocket, server: GuardedServer, peer: dict) -> GuardedSocket:
        """Take over the socket pynetdicom built (its state, its queued connection event)."""
        sock = cls.__new__(cls)
        sock.__dict__.update(plain.__dict__)
        sock.guard, sock.peer, sock._requested = server, peer, False
        sock._body_type, sock._message_bytes, sock._association = None, Counter(), None
        sock._command = bytearray()
        der = plain.socket.getpeercert(True) if isinstance(plain.socket, ssl.SSLSocket) else None
        sock.certificate = fingerprint(der) if der else ""
        return sock

    def recv(self, nr_bytes: int) -> bytearray:
        if self._body_type is None:
            header = super().recv(nr_bytes)
            if len(header) == 6:
                self._check_header(header[0], struct.unpack_from(">L", header, 2)[0])
            return header
        pdu_type, self._body_type = self._body_type, None
        body = super().recv(nr_bytes)
        if len(body) == nr_bytes:
            if pdu_type == 0x01:
                self._check_associate(body)
            elif pdu_type == 0x04:
                self._check_pdata(body)
        return body

    def _violation(self, reason: str, reply: bytes = _A_ABORT) -> _Violation:
        # Audited before the peer is answered: a peer that has read its refusal finds it
        # on record. Answered and released even if the audit cannot be written.
        event = "association_rejected" if reply[0] == 0x03 else "association_aborted"
        log.warning("%s from %s: %s", event, self.peer["peer"], reason)
        try:
            self.guard.limits.audit(event, reason=reason, **self.peer)
        finally:
            try:
                if self.socket is not None:  # None once pynetdicom has closed the connection
                    self.socket.sendall(reply)
            except OSError:
                pass
            self.release()  # this association is over: its slot is free for the next one now
        return _Violation(reason)

    def _check_header(self, pdu_type: int, length: int) -> None:
        limit = {0x01: ASSOCIATE_RQ_MAX_BYTES, 0x02: ASSOCIATE_RQ_MAX_BYTES,
                 0x04: self.guard.limits.max_pdu, **_SMALL_PDU_BYTES}.get(pdu_type)
        if limit is None:
            raise self._violation(f"unknown PDU type 0x{pdu_type:02X}")
        if length > limit:
            raise self._violation(f"PDU type 0x{pdu_type:02X} declares {length} bytes, more than "
                                  f"the {limit} allowed")
        if pdu_type in (0x05, 0x07):  # the peer releases or aborts: free its slot at once, so
            self.release()            # its next association is not refused by a lingering one
        self._body_type = pdu_type

    def _check_associate(self, body: bytes | bytearray) -> None:
        """Admit the association (before pynetdicom negotiates): binding, then a slot."""
        if len(body) < 36 or self._requested:
            raise self._violation("malformed or repeated A-ASSOCIATE-RQ")
        self._requested = True
        called = body[4:20].decode("ascii", "replace").strip()
        calling = body[20:36].decode("ascii", "replace").strip()
        self.peer["calling_ae"] = calling
        if called != self.guard.limits.ae_title:
            return  # pynetdicom refuses it (and we audit that) without taking a slot
        kind = ("storer" if calling in self.guard.limits.storers
                else "health" if calling == self.guard.limits.health else None)
        if kind is None:
            return
        admission, address = self.guard.limits.admission, self.peer["peer"]
        problem = admission.binding_problem(address, calling, self.certificate)
        if problem:
            raise self._violation(problem, _A_ASSOCIATE_RJ_CALLER)
        problem = self.guard.limits.space_problem() if kind == "storer" else None
        if problem:  # transient: the C-arm may try again once space is freed
            raise self._violation(problem, _A_ASSOCIATE_RJ_LIMIT)
        ticket = admission.take(kind, address, calling)
        if isinstance(ticket, str):
            raise self._violation(ticket, _A_ASSOCIATE_RJ_LIMIT)
        self._association = ticket

    def _check_pdata(self, body: bytes | bytearray) -> None:
        accepted = {cx.context_id for cx in self._assoc.accepted_contexts}
        pos = 0
        while pos < len(body):
            if len(body) - pos < 6:
                raise self._violation("P-DATA-TF ends inside a PDV item header")
            length, context_id, control = struct.unpack_from(">LBB", body, pos)
            if length < 2 or pos + 4 + length > len(body):
                raise self._violation(f"PDV item length {length} does not fit the P-DATA-TF")
            if control & 0xFC:
                raise self._violation(f"PDV message control header 0x{control:02X} is invalid")
            if context_id not in accepted:
                raise self._violation(f"PDV for presentation context {context_id}, which was "
                                      "not accepted")
            kind = "command" if control & 1 else "dataset"
            self._message_bytes[kind] += length - 2
            limit = COMMAND_MAX_BYTES if kind == "command" else self.guard.limits.max_message
            if self._message_bytes[kind] > limit:
                raise self._violation(f"{kind} exceeds {limit} bytes; dropped unread")
            if kind == "command":
                self._command += body[pos + 6:pos + 4 + length]
            if control & 2:
                self._message_bytes[kind] = 0
                if kind == "command":
                    problem = command_problem(bytes(self._command))
                    self._command.clear()
                    if problem:
                        raise self._violation(problem)
            pos += 4 + length

    def release(self) -> None:
        if self._association is not None:
            self.guard.limits.admission.release(self._association)
            self._association = None


class _GuardedHandler(RequestHandler):
    """Runs the association in this connection's thread, on a :class:`GuardedSocket`."""

    def _create_association(self):
        assoc = super()._create_association()
        self.guarded = GuardedSocket.adopt(assoc.dul.socket, self.server,
                                           {"peer": self.client_address[0], "calling_ae": ""})
        assoc.dul.socket = self.guarded
        self.association = assoc
        return assoc

    def handle(self) -> None:
        super().handle()
        try:
            self.association.join()
        finally:
            self.guarded.release()


class GuardedServer(ThreadedAssociationServer):
    """pynetdicom's threaded server with admission, TLS off the accept loop and wire limits."""

    daemon_threads = True
    block_on_close = False
    request_queue_size = 256  # listen backlog: socketserver's 5 drops SYNs under a flood

    def __init__(self, ae, address, ae_title, contexts, ssl_context, evt_handlers,
                 limits: WireLimits):
        self.limits = limits
        self._lock = threading.Lock()
        self._peers: Counter[str] = Counter()
        self._silent: dict[socket.socket, str] = {}  # admitted, no PDU yet; oldest first
        super().__init__(ae, address, ae_title, contexts, ssl_context, evt_handlers,
                         request_handler=_GuardedHandler)

    @property
    def open_connections(self) -> int:
        with self._lock:
            return sum(self._peers.values())

    # -- socketserver hooks --------------------------------------------------------------
    def get_request(self) -> tuple[socket.socket, tuple]:
        assert self.socket is not None, "socketserver opens its socket before serving"
        return self.socket.accept()  # no TLS here: the handshake runs in the connection's thread

    def verify_request(self, request, client_address) -> bool:
        host = client_address[0]
        reason = None
        if not self.limits.address_allowed(host):
            reason = "source address not allowed"
        evicted = None
        with self._lock:
            if reason is None and self._peers[host] >= self.limits.max_per_peer:
                reason = "too many connections from this address"
            elif reason is None and sum(self._peers.values()) >= self.limits.max_connections:
                if self._silent:
                    evicted = next(iter(self._silent.items()))
                    del self._silent[evicted[0]]
                else:
                    reason = "too many connections"
            if reason is None:
                self._peers[host] += 1
                self._silent[request] = host
        if evicted is not None:
            self.limits.audit("connection_refused", peer=evicted[1],
                              reason="silent connection dropped to make room")
            try:
                evicted[0].shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        if reason is None:
            return True
        self.limits.audit("connection_refused", reason=reason, peer=host)
        return False

    def process_request_thread(self, request, client_address) -> None:
        host, raw = client_address[0], request
        try:
            request = self._open(request, host, raw)
            if request is not None:
                request.settimeout(self.limits.idle_timeout_s)
                self.finish_request(request, client_address)
        except Exception:
            log.exception("connection from %s failed", host)
        finally:
            with self._lock:
                self._silent.pop(raw, None)
                self._peers[host] -= 1
                if self._peers[host] <= 0:
                    del self._peers[host]
            if request is not None:
                self.shutdown_request(request)

    def _open(self, request: socket.socket, host: str,
              raw: socket.socket) -> socket.socket | None:
        """The TLS handshake and the first bytes, each within ``request_timeout_s``."""
        request.settimeout(self.limits.request_timeout_s)
        if self.ssl_context is not None:
            try:
                request = self.ssl_context.wrap_socket(request, server_side=True)
            except (ssl.SSLError, OSError) as exc:
                detail = getattr(exc, "verify_message", None) or getattr(exc, "reason", None) or exc
                self.limits.audit("connection_refused", reason=f"TLS handshake failed: {detail}",
                                  peer=host)
                request.close()
                return None
        pending = isinstance(request, ssl.SSLSocket) and request.pending()
        if not pending and not select.select([request], [], [], self.limits.request_timeout_s)[0]:
            self.limits.audit("connection_refused", peer=host, reason=(
                f"no association request within {self.limits.request_timeout_s:g} s"))
            request.close()
            return None
        with self._lock:
            if self._silent.pop(raw, None) is None:  # evicted while silent
                request.close()
                return None
        return request
