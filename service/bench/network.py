"""The network and decoding items of ``slamtka bench hardening``.

- ``tls_names``: the sender against fake PACSes on loopback presenting another host's
  certificate from the same CA, or a certificate other than the pinned one (nothing may be
  delivered), and the right one (delivered); on the way in, a client certificate bound to
  the C-arm's address presented from another address (refused, audited).
- ``ae_squatting``: hosts on other loopback addresses use the C-arm's AE title (refused) and
  another allowed title, holding every slot they can with keep-alive C-ECHOs; the bound
  C-arm must still associate and store, and no refusal may name its address.
- ``compressed``: each compressed syntax the receiver accepts, encoded by DCMTK and sent by
  storescu, must be acknowledged, spooled and decode to its pixels; a syntax still refused
  (JPEG 2000) must be audited with the proposal.
- ``pixel_layouts``: every case of :mod:`service.pixel_layouts` sent over loopback: accepted
  and decoded from the spool to the expected pixels, or refused (and audited) by name.
"""

from __future__ import annotations

import ssl
import tempfile
from pathlib import Path

import numpy as np
from pydicom.uid import JPEG2000Lossless, JPEGLSNearLossless, generate_uid

from slamtka.bench.hardening import ServiceUnderTest, Tally
from slamtka.bench.hostile import Dropped, RawAssociation, noise_frame, wire_bytes
from slamtka.bench.pki import client_context, make_pki
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.compressed import ENCODERS, NEAR_LOSSLESS_DEVIATION, compress, storescu
from slamtka.service.config import Destination, SenderConfig
from slamtka.service.frames import SECONDARY_CAPTURE_STORAGE, decode_frame, encode_frame
from slamtka.service.pixel_layouts import layout_cases
from slamtka.service.sender import OutgoingObject, Sender
from slamtka.service.tls import certificate_sha256
from slamtka.sim.theatre import ResultCollector

__all__ = ["NETWORK_ITEMS", "run_network_item"]

NETWORK_ITEMS = ("tls_names", "ae_squatting", "compressed", "pixel_layouts")
CARM = "127.0.0.1"


def _events(target: ServiceUnderTest, event: str) -> list[dict]:
    return [e for e in read_audit(target.audit.path) if e["event"] == event]


# -- TLS names and pins ------------------------------------------------------------------

def _deliveries(folder: Path, pki: dict, cert: str, **destination) -> tuple[int, str]:
    """(objects the fake PACS presenting ``cert`` received, the sender's error if any)."""
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.load_cert_chain(pki[f"{cert}_cert"], pki[f"{cert}_key"])
    pacs = ResultCollector(ssl_context=ctx)
    audit = AuditLog(folder / "audit.jsonl")
    ds = encode_frame(noise_frame(1, 16))  # as a Secondary Capture result, what PACSes take
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = SECONDARY_CAPTURE_STORAGE
    ds.Modality = "OT"
    path = folder / "object.dcm"
    ds.save_as(path, enforce_file_format=True)
    dest = Destination("pacs", "ORDISPLAY", CARM, pacs.port, ["sc"], tls=True,
                       ca_certificates=pki["ca"], certificate=pki["client_cert"],
                       private_key=pki["client_key"], **destination)
    sender = Sender("SLAMTKA", [dest], SenderConfig(max_attempts=3, timeout_s=5.0),
                    folder / "queue", audit)
    try:
        sender.enqueue([OutgoingObject(path, "sc", SECONDARY_CAPTURE_STORAGE,
                                       str(ds.SOPInstanceUID))],
                       "case", "run")
        sender.run_once()
        pacs.wait(lambda _: True, 0.2)
        errors = [e["error"] for e in read_audit(audit.path) if e["event"] == "send_failed"]
        return len(pacs.received), errors[-1] if errors else ""
    finally:
        pacs.stop()
        audit.close()


def tls_names(folder: Path, count: int) -> Tally:
    tally = Tally()
    pki = make_pki(folder / "pki")
    wrong_pin = certificate_sha256(pki["elsewhere_cert"])
    cases = [("another host's certificate, same CA", "elsewhere", {}, False),
             ("a certificate other than the pinned one", "server",
              {"certificate_sha256": wrong_pin}, False),
             ("the host's own certificate", "server", {}, True),
             ("the host's own certificate, pinned", "server",
              {"certificate_sha256": certificate_sha256(pki["server_cert"])}, True)]
    reasons = {}
    for i in range(max(1, count)):
        for k, (name, cert, destination, deliver) in enumerate(cases):
            case_folder = folder / f"send-{i}-{k}"
            case_folder.mkdir(parents=True)
            received, error = _deliveries(case_folder, pki, cert, **destination)
            tally.count(received != (1 if deliver else 0), f"{name}: {received} delivered")
            if error:
                reasons[name] = error
    target = ServiceUnderTest(folder / "scp", {
        "tls": {"enabled": True, "certificate": str(pki["server_cert"]),
                "private_key": str(pki["server_key"]), "ca_certificates": str(pki["ca"])},
        "callers": [{"ae_title": "CARM1", "addresses": [CARM],
                     "certificate_sha256": certificate_sha256(pki["client_cert"])}]})
    try:
        for _ in range(max(1, count)):
            before = len(_events(target, "association_rejected"))
            for source, cert, admitted in (("127.0.0.2", "client", False),
                                           (CARM, "elsewhere", False), (CARM, "client", True)):
                try:
                    assoc = RawAssociation(target.port, source=source,
                                           tls=client_context(pki, cert)).associate()
                    assoc.release()
                    tally.count(not admitted, f"certificate {cert} from {source} admitted")
                except Dropped:
                    tally.count(admitted, f"certificate {cert} from {source} refused")
            tally.failures += len(_events(target, "association_rejected")) - before != 2
    finally:
        target.stop()
    tally.notes["sender_refusals"] = reasons
    return tally


# -- AE squatting --------------------------------------------------------------------------

def ae_squatting(folder: Path, count: int, squatters: int = 6) -> Tally:
    tally = Tally()
    target = ServiceUnderTest(folder, {"allowed_calling_ae_titles": ["CARM1", "CARM2"],
                             "callers": [{"ae_title": "CARM1", "addresses": [CARM]}]})
    held_most = 0
    try:
        for i in range(max(1, count)):
            held = []
            for n in range(squatters):
                source = f"127.0.4.{1 + n}"
                for title in ("CARM1", "CARM2", "CARM2"):
                    assoc = RawAssociation(target.port, source=source, calling=title)
                    try:
                        assoc.associate()
                    except Dropped:
                        assoc.close()  # as a real client does on A-ASSOCIATE-RJ
                        continue
                    held.append(assoc)
                    tally.count(title == "CARM1", f"CARM1 associated from {source}")
            held_most = max(held_most, len(held))
            for assoc in held:  # keep-alive: the squatters are busy, not idle
                assoc.echo()
            try:
                carm = RawAssociation(target.port, source=CARM).associate()
                frame = noise_frame(i, 32)
                status = carm.store(wire_bytes(encode_frame(frame)), frame.sop_instance_uid)
                carm.release()
                tally.count(status != 0, f"the C-arm's store got 0x{status:04X}")
            except Dropped as exc:
                tally.count(True, f"the C-arm was locked out: {exc}")
            for assoc in held:
                assoc.release()
            target.quiet()
        refused = _events(target, "association_rejected")
        blamed = [e for e in refused if e["peer"] == CARM]
        tally.failures += len(blamed)
        tally.notes.update(squatting_addresses=squatters, most_slots_held_by_squatters=held_most,
                           refusals_audited=len(refused), refusals_naming_the_c_arm=len(blamed))
    finally:
        target.stop()
    return tally


# -- compressed transfer syntaxes ------------------------------------------------------------

def compressed(folder: Path, count: int, size: int = 256) -> Tally:
    tally = Tally()
    target = ServiceUnderTest(folder)
    worst: dict[str, int] = {}
    try:
        for i in range(max(1, count)):
            for k, syntax in enumerate(ENCODERS):
                frame = noise_frame(len(ENCODERS) * i + k, size)
                with tempfile.TemporaryDirectory(dir=folder) as tmp:
                    plain = Path(tmp) / "plain.dcm"
                    encode_frame(frame).save_as(plain, enforce_file_format=True)
                    packed = compress(plain, syntax, Path(tmp) / "packed.dcm")
                    out = storescu(packed, target.port, frame.sop_class_uid, syntax)
                spooled = [e for e in target.stored if e.sop_instance_uid == frame.sop_instance_uid]
                if out.returncode != 0 or len(spooled) != 1:
                    tally.count(True, f"{syntax}: not stored ({out.stderr.strip()[-200:]})")
                    continue
                pixels = decode_frame(target.receiver.spool.read(spooled[0])).pixels
                error = int(np.abs(pixels.astype(int) - frame.pixels).max())
                worst[syntax] = max(worst.get(syntax, 0), error)
                allowed = NEAR_LOSSLESS_DEVIATION if syntax == JPEGLSNearLossless else 0
                tally.count(error > allowed, f"{syntax}: pixels differ by {error}")
            before = len(_events(target, "context_rejected"))
            frame = noise_frame(i, 32)
            with tempfile.TemporaryDirectory(dir=folder) as tmp:
                plain = Path(tmp) / "plain.dcm"
                encode_frame(frame).save_as(plain, enforce_file_format=True)
                storescu(plain, target.port, frame.sop_class_uid, JPEG2000Lossless)
            audited = _events(target, "context_rejected")[before:]
            tally.count(not (len(audited) == 1 and audited[0]["contexts"][0]["transfer_syntaxes"]
                             == [JPEG2000Lossless]), "JPEG 2000 refusal not audited")
        tally.failures += not target.serving()
        tally.notes.update(syntaxes=list(ENCODERS), frame_size=size,
                           max_pixel_error=worst)
    finally:
        target.stop()
    return tally


# -- pixel layouts ---------------------------------------------------------------------------

def pixel_layouts(folder: Path, count: int) -> Tally:
    tally = Tally()
    target = ServiceUnderTest(folder)
    try:
        assoc = RawAssociation(target.port).associate()
        for i in range(max(1, count)):
            for case in layout_cases(encode_frame(noise_frame(i, 64)), seed=i):
                uid = generate_uid()
                case.dataset.SOPInstanceUID = uid
                before = target.refusals()
                status = assoc.store(wire_bytes(case.dataset), uid)
                if case.expected is None:
                    audited = [e for e in _events(target, "rejected")
                               if e["sop_instance_uid"] == uid]
                    tally.count(status == 0 or target.refusals() == before or not audited
                                or case.error not in audited[0]["reason"],
                                f"{case.name}: 0x{status:04X}")
                    continue
                spooled = [e for e in target.stored if e.sop_instance_uid == uid]
                if status != 0 or not spooled:
                    tally.count(True, f"{case.name}: refused with 0x{status:04X}")
                    continue
                pixels = decode_frame(target.receiver.spool.read(spooled[0])).pixels
                tally.count(not np.array_equal(pixels, case.expected), f"{case.name}: pixels differ")
        assoc.release()
        tally.failures += not target.serving()
        tally.notes["layouts"] = len(layout_cases(encode_frame(noise_frame(0, 64))))
    finally:
        target.stop()
    return tally


def run_network_item(name: str, folder: Path, count: int) -> Tally:
    items = {"tls_names": tls_names, "ae_squatting": ae_squatting, "compressed": compressed,
             "pixel_layouts": pixel_layouts}
    return items[name](folder, count)
