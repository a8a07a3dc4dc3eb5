"""The DICOM receiver (SCP): Verification and X-ray image storage, thin handlers.

Associations are accepted only from the configured calling AE titles (and, if configured,
source addresses, and per :mod:`service.admission`) and only when they call our AE title;
TLS (1.2 or newer, client certificates required) is optional. Images may come uncompressed,
JPEG Lossless, JPEG-LS or RLE (those whose decoder is installed); an image context refused
for its transfer syntax is audited (``context_rejected``) with the syntaxes proposed.
Connections, PDUs and message sizes are policed at the byte level by :mod:`service.wire`
before pynetdicom sees them. The C-STORE handler only
validates, persists and queues: it checks the command (UIDs), the dataset's byte structure
(:mod:`service.dataset_guard`, before pydicom parses it), then the instance (SOP class
against the negotiated context, UIDs, transfer syntax), decodes it (image attributes and
pixel data through :func:`service.frames.decode_frame`: the only time it is decoded,
:mod:`service.decoded`), writes it to the spool with the decoded facts beside it (fsynced)
and appends an audit line before the success status goes back; the decoded frame is then
handed to the worker in memory. A refused instance gets a failure status with the reason in
the Error Comment and an audit line. The pipeline runs elsewhere.

Storage robustness: at most ``dicom.max_frames_in_memory`` instances are decoded and spooled
at once (others wait up to ``dicom.memory_wait_s``, then get 0xA700, audited), so a burst of
large frames cannot grow the process without bound. An instance whose receipt cannot be
audited (a full disk) is taken back out of the spool and refused with 0xA700, so the C-arm's
retry is stored and measured rather than taken for a duplicate. Another image under a SOP
Instance UID already received is refused with 0x0111 and audited ``uid_conflict``.
"""

from __future__ import annotations

import logging
import re
import threading
from collections.abc import Callable

from pydicom.dataset import Dataset
from pydicom.pixels.decoders.base import get_decoder
from pydicom.uid import (
    UID,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    JPEGLossless,
    JPEGLosslessSV1,
    JPEGLSLossless,
    JPEGLSNearLossless,
    RLELossless,
)
from pynetdicom import AE, evt
from pynetdicom.events import EventHandlerType
from pynetdicom.sop_class import Verification  # type: ignore[attr-defined]  # made at import
from pynetdicom.transport import ThreadedAssociationServer

from slamtka.service.audit import AuditLog
from slamtka.service.config import DicomConfig
from slamtka.service.dataset_guard import DatasetError, check_dataset_bytes
from slamtka.service.frames import (
    DX_PRESENTATION_STORAGE,
    DX_PROCESSING_STORAGE,
    ENHANCED_XA_IMAGE_STORAGE,
    RF_IMAGE_STORAGE,
    SECONDARY_CAPTURE_STORAGE,
    XA_IMAGE_STORAGE,
    Frame,
    FrameError,
    decode_frame,
)
from slamtka.service.spool import Spool, SpoolEntry
from slamtka.service.tls import server_ssl_context
from slamtka.service.wire import GuardedServer, WireLimits

__all__ = ["DicomReceiver", "STORAGE_SOP_CLASSES", "TRANSFER_SYNTAXES", "check_instance"]

log = logging.getLogger("slamtka.scp")

STORAGE_SOP_CLASSES = (XA_IMAGE_STORAGE, ENHANCED_XA_IMAGE_STORAGE, RF_IMAGE_STORAGE,
                       DX_PRESENTATION_STORAGE, DX_PROCESSING_STORAGE, SECONDARY_CAPTURE_STORAGE)
UNCOMPRESSED = (ExplicitVRLittleEndian, ImplicitVRLittleEndian)
# The lossless (and JPEG-LS near-lossless) syntaxes C-arms default to; each is offered only
# if pydicom has a decoder for it installed (pylibjpeg and its plugins, pyjpegls).
COMPRESSED = (JPEGLossless, JPEGLosslessSV1, JPEGLSLossless, JPEGLSNearLossless, RLELossless)
TRANSFER_SYNTAXES = UNCOMPRESSED + tuple(uid for uid in COMPRESSED
                                         if get_decoder(uid).is_available)

STATUS_SUCCESS = 0x0000
STATUS_DUPLICATE_SOP = 0x0111  # "Duplicate SOP instance" (PS3.7 C.4.2.1.4)
STATUS_NOT_AUTHORIZED = 0x0124
STATUS_OUT_OF_RESOURCES = 0xA700
STATUS_NOT_SOP_CLASS = 0xA900
STATUS_CANNOT_UNDERSTAND = 0xC000
_TRANSFER_SYNTAX_NOT_SUPPORTED = 0x04  # presentation context result (PS3.8 9.3.3.2)


def check_instance(ds: Dataset, context_sop_class: str, transfer_syntax: str,
                   affected_sop_instance_uid: str) -> tuple[int, str] | None:
    """(failure status, reason) if the instance must be refused before it is decoded, else None."""
    if transfer_syntax not in TRANSFER_SYNTAXES:
        return STATUS_CANNOT_UNDERSTAND, f"transfer syntax {transfer_syntax} is not accepted"
    sop_class = str(ds.get("SOPClassUID", "") or "")
    if sop_class != context_sop_class:
        return STATUS_NOT_SOP_CLASS, (f"SOPClassUID {sop_class or '(missing)'} does not match "
                                      f"the negotiated {context_sop_class}")
    for keyword in ("SOPInstanceUID", "StudyInstanceUID", "SeriesInstanceUID"):
        value = str(ds.get(keyword, "") or "")
        if not value:
            return STATUS_CANNOT_UNDERSTAND, f"{keyword} is missing"
        if not UID(value).is_valid:
            return STATUS_CANNOT_UNDERSTAND, f"{keyword} is not a valid UID"
    if str(ds.SOPInstanceUID) != str(affected_sop_instance_uid):
        return STATUS_CANNOT_UNDERSTAND, "SOPInstanceUID differs from the C-STORE request"
    return None


def check_command(request, context_sop_class: str) -> tuple[int, str] | None:
    """(failure status, reason) if the C-STORE command's UIDs are unusable, else None."""
    for keyword in ("AffectedSOPInstanceUID", "AffectedSOPClassUID"):
        value = str(getattr(request, keyword, "") or "")
        if not value or not UID(value).is_valid:
            return STATUS_CANNOT_UNDERSTAND, f"{keyword} in the command is not a valid UID"
    if str(request.AffectedSOPClassUID) != context_sop_class:
        return STATUS_NOT_SOP_CLASS, "AffectedSOPClassUID differs from the negotiated context"
    return None


_NOT_LO = re.compile(r"[^\x20-\x5b\x5d-\x7e]")  # Error Comment is LO: printable, no backslash


def _status(code: int, comment: str = "") -> Dataset:
    status = Dataset()
    status.Status = code
    if comment:
        status.ErrorComment = _NOT_LO.sub("?", comment)[:64]
    return status


class DicomReceiver:
    """The SCP of the service; ``on_stored`` is called with each newly spooled instance."""

    def __init__(self, config: DicomConfig, spool: Spool, audit: AuditLog,
                 on_stored: Callable[[SpoolEntry], None],
                 space_problem: Callable[[], str | None] = lambda: None):
        """``space_problem`` says why no frame may be stored now (the disk floor): storage
        associations are then refused with that reason, echoes still answered."""
        self.config, self.spool, self.audit, self.on_stored = config, spool, audit, on_stored
        self.space_problem = space_problem
        self._ssl = server_ssl_context(config.tls) if config.tls.enabled else None
        self._server: ThreadedAssociationServer | None = None
        ae = AE(ae_title=config.ae_title)
        ae.require_called_aet = True
        ae.require_calling_aet = [*config.allowed_calling_ae_titles, config.health_ae_title]
        ae.maximum_pdu_size = config.max_pdu_bytes
        # Only a backstop: service.wire counts associations by caller, not sockets.
        ae.maximum_associations = config.max_connections
        ae.network_timeout = config.idle_timeout_s
        ae.acse_timeout = config.request_timeout_s  # also how long a refused request lingers
        ae.dimse_timeout = config.dimse_timeout_s
        ae.add_supported_context(Verification)
        for sop_class in STORAGE_SOP_CLASSES:
            ae.add_supported_context(sop_class, list(TRANSFER_SYNTAXES))
        self.ae = ae
        self._in_memory = threading.BoundedSemaphore(config.max_frames_in_memory)

    def start(self) -> None:
        handlers: list[EventHandlerType] = [(evt.EVT_C_STORE, self._on_store), (evt.EVT_C_ECHO, self._on_echo),
                    (evt.EVT_REJECTED, self._on_rejected), (evt.EVT_ACCEPTED, self._on_accepted)]
        limits = WireLimits(self.config, self.audit.record)
        limits.space_problem = self.space_problem
        server = self.ae.make_server((self.config.bind_address, self.config.port),
                                     evt_handlers=handlers, ssl_context=self._ssl,
                                     server_class=GuardedServer, limits=limits)
        self._server = server
        self.ae._servers.append(server)  # so that AE.shutdown() reaches it too
        threading.Thread(target=server.serve_forever, name="slamtka-scp-accept",
                         daemon=True).start()
        log.info("DICOM SCP %s listening on %s:%d%s", self.config.ae_title,
                 self.config.bind_address, self.port, " (TLS)" if self._ssl else "")

    @property
    def port(self) -> int:
        """The bound port (the configured one, or the free port picked for port 0)."""
        return int(self._server.server_address[1]) if self._server else self.config.port

    def stop(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server = None

    # -- handlers (run on pynetdicom's association threads) --------------------------------
    @staticmethod
    def _peer(event) -> dict:
        requestor = event.assoc.requestor
        return {"calling_ae": str(requestor.ae_title).strip(), "peer": requestor.address}

    def _on_echo(self, event) -> int:
        return STATUS_SUCCESS

    def _on_rejected(self, event) -> None:
        peer = self._peer(event)
        request = event.assoc.requestor.primitive
        called = str(request.called_ae_title if request is not None else "").strip()
        if peer["calling_ae"] not in (*self.config.allowed_calling_ae_titles,
                                      self.config.health_ae_title):
            reason = "calling AE title not allowed"
        elif called and called != self.config.ae_title:
            reason = f"called AE title {called!r} is not ours"
        else:
            reason = "too many connections"  # pynetdicom's backstop; service.wire counts first
        self.audit.record("association_rejected", reason=reason, **peer)

    def _on_accepted(self, event) -> None:
        """Audit the image contexts refused for want of a transfer syntax we decode: the
        C-arm then cannot send, and the operator must see which syntaxes it proposed."""
        proposed = {cx.context_id: cx for cx in event.assoc.requestor.requested_contexts}
        refused = [{"sop_class_uid": str(cx.abstract_syntax),
                    "transfer_syntaxes": [str(ts) for ts in proposed[cx.context_id].transfer_syntax]}
                   for cx in event.assoc.rejected_contexts
                   if cx.result == _TRANSFER_SYNTAX_NOT_SUPPORTED and cx.context_id in proposed]
        if refused:
            peer = self._peer(event)
            log.warning("%s proposed only transfer syntaxes we do not decode: %s",
                        peer["calling_ae"], refused)
            self.audit.record("context_rejected", contexts=refused, **peer)

    def _on_store(self, event) -> Dataset:
        peer = self._peer(event)
        request_uid = str(event.request.AffectedSOPInstanceUID or "")
        if peer["calling_ae"] == self.config.health_ae_title:
            return self._refuse(peer, request_uid, STATUS_NOT_AUTHORIZED,
                                "the health-check AE title may not store")
        if not self._in_memory.acquire(timeout=self.config.memory_wait_s):
            return self._refuse(peer, request_uid, STATUS_OUT_OF_RESOURCES,
                                "busy: too many frames in memory, retry later")
        try:
            return self._store(event, peer, request_uid)
        finally:
            self._in_memory.release()

    def _store(self, event, peer: dict, request_uid: str) -> Dataset:
        """Validate, spool and audit one instance (holding one of the in-memory slots)."""
        context = event.context
        refusal = check_command(event.request, context.abstract_syntax)
        if refusal is not None:
            return self._refuse(peer, request_uid, *refusal)
        frame: Frame | None = None
        try:
            syntax = UID(context.transfer_syntax)
            check_dataset_bytes(event.request.DataSet.getvalue(), not syntax.is_implicit_VR,
                                encapsulated=syntax.is_encapsulated)
            ds = event.dataset
            ds.file_meta = event.file_meta
            # Who sent it, kept with it (PS3.10): a calibration may be chosen by it.
            ds.file_meta.SourceApplicationEntityTitle = peer["calling_ae"]
            refusal = check_instance(ds, context.abstract_syntax, context.transfer_syntax,
                                     request_uid)
            if refusal is None:
                frame = decode_frame(ds)
        except DatasetError as exc:
            refusal = STATUS_CANNOT_UNDERSTAND, f"malformed dataset: {exc}"
        except FrameError as exc:
            refusal = STATUS_CANNOT_UNDERSTAND, str(exc)
        except Exception as exc:  # pydicom raises many types on values it cannot convert
            refusal = STATUS_CANNOT_UNDERSTAND, f"dataset cannot be decoded: {exc}"
        if refusal is not None:
            return self._refuse(peer, request_uid, *refusal)
        assert frame is not None  # decoded whenever nothing was refused
        try:
            entry, outcome = self.spool.store(ds, frame.header())
        except OSError as exc:
            log.error("cannot spool %s: %s", request_uid, exc)
            return self._refuse(peer, request_uid, STATUS_OUT_OF_RESOURCES,
                                f"cannot write the spool: {exc.strerror}")
        fields = {"sop_instance_uid": entry.sop_instance_uid, "sop_class_uid": str(ds.SOPClassUID),
                  "study_uid": str(ds.StudyInstanceUID), "spool_id": entry.id, **peer}
        event_name, code, comment = {
            "new": ("received", STATUS_SUCCESS, ""),
            "duplicate": ("duplicate", STATUS_SUCCESS, ""),
            "conflict": ("uid_conflict", STATUS_DUPLICATE_SOP,
                         "another image was received under this SOP Instance UID")}[outcome]
        try:
            self.audit.record(event_name, status=f"0x{code:04X}", **fields)
        except OSError as exc:  # unaudited, it must not count as received: the retry lands
            log.error("cannot audit %s of %s: %s", event_name, request_uid, exc)
            if outcome == "new":
                self.spool.discard(entry)
            return _status(STATUS_OUT_OF_RESOURCES, f"cannot write the audit log: {exc.strerror}")
        if outcome == "new":
            del ds.PixelData  # decoded into the frame; the header is what the stages repeat
            self.spool.decoded.keep(entry, frame, ds)
            self.on_stored(entry)
        elif outcome == "conflict":
            log.warning("refused instance %s from %s: %s", request_uid, peer["calling_ae"], comment)
        return _status(code, comment)

    def _refuse(self, peer: dict, uid: str, code: int, reason: str) -> Dataset:
        log.warning("refused instance %s from %s: %s", uid, peer["calling_ae"], reason)
        try:
            self.audit.record("rejected", sop_instance_uid=uid, status=f"0x{code:04X}",
                              reason=reason, **peer)
        except OSError as exc:  # the refusal still goes back; the log says why it is missing
            log.error("cannot audit the refusal of %s: %s", uid, exc)
        return _status(code, reason)
