"""The DICOM receiver over loopback: DCMTK and pynetdicom clients, AE titles, validation, TLS."""

from __future__ import annotations

import shutil
import ssl
import subprocess
import time

import pytest
from pynetdicom import AE
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage
from service_testing import make_pki, small_frame

from slamtka.bench.pki import client_context
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import config_from_dict
from slamtka.service.frames import encode_frame
from slamtka.service.scp import DicomReceiver, check_instance
from slamtka.service.spool import Spool, entry_id

needs_dcmtk = pytest.mark.skipif(shutil.which("storescu") is None, reason="DCMTK not installed")


def _receiver(tmp_path, **dicom):
    table = {"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1"], "max_pdu_bytes": 65536,
                       **dicom}, "carm": {"calibration": "unused.json"}}
    config = config_from_dict(table, environ={})
    stored = []
    audit = AuditLog(tmp_path / "audit.jsonl")
    receiver = DicomReceiver(config.dicom, Spool(tmp_path / "spool"), audit, stored.append)
    receiver.start()
    return receiver, stored, audit


@pytest.fixture
def scp(tmp_path):
    receiver, stored, audit = _receiver(tmp_path)
    yield receiver, stored, tmp_path
    receiver.stop()
    audit.close()


def _events(tmp_path, name):
    return [e for e in read_audit(tmp_path / "audit.jsonl") if e["event"] == name]


def _events_once(tmp_path, name, count, timeout_s=10.0):
    """The events ``name`` once ``count`` are recorded: the SCP audits a rejection on its
    association's thread, which may run on after the peer has read the rejection."""
    deadline = time.monotonic() + timeout_s
    while len(events := _events(tmp_path, name)) < count and time.monotonic() < deadline:
        time.sleep(0.02)
    return events


def _client(title="CARM1"):
    ae = AE(ae_title=title)
    ae.add_requested_context(Verification)
    ae.add_requested_context(XRayAngiographicImageStorage)
    return ae


@needs_dcmtk
def test_dcmtk_echo_and_store_from_an_allowed_ae_are_spooled_and_audited(scp):
    receiver, stored, tmp_path = scp
    port = str(receiver.port)
    assert subprocess.run(["echoscu", "-aet", "CARM1", "-aec", "SLAMTKA", "127.0.0.1", port],
                          capture_output=True, timeout=30).returncode == 0
    frame = small_frame()
    path = tmp_path / "frame.dcm"
    encode_frame(frame).save_as(path, enforce_file_format=True)
    for _ in range(2):  # the second time is a duplicate: success, spooled once
        out = subprocess.run(["storescu", "-aet", "CARM1", "-aec", "SLAMTKA", "127.0.0.1", port,
                              str(path)], capture_output=True, text=True, timeout=30)
        assert out.returncode == 0, out.stderr
    assert [e.sop_instance_uid for e in stored] == [frame.sop_instance_uid]
    spooled = receiver.spool.entries()
    assert [e.path.name for e in spooled] == [f"{entry_id(frame.sop_instance_uid)}.dcm"]
    back = receiver.spool.read(spooled[0])
    assert back.SOPInstanceUID == frame.sop_instance_uid and back.PixelData == frame.pixels.tobytes()
    received = _events(tmp_path, "received")
    assert len(received) == 1 and received[0]["calling_ae"] == "CARM1"
    assert len(_events(tmp_path, "duplicate")) == 1


@needs_dcmtk
def test_refused_calling_and_called_ae_titles(scp):
    receiver, stored, tmp_path = scp
    port = str(receiver.port)
    wrong_caller = subprocess.run(["echoscu", "-aet", "INTRUDER", "-aec", "SLAMTKA", "127.0.0.1",
                                   port], capture_output=True, text=True, timeout=30)
    wrong_called = subprocess.run(["echoscu", "-aet", "CARM1", "-aec", "OTHER", "127.0.0.1", port],
                                  capture_output=True, text=True, timeout=30)
    assert wrong_caller.returncode != 0 and "Calling AE Title Not Recognized" in wrong_caller.stderr
    assert wrong_called.returncode != 0 and "Called AE Title Not Recognized" in wrong_called.stderr
    reasons = [(e["calling_ae"], e["reason"]) for e in _events_once(tmp_path, "association_rejected", 2)]
    assert reasons == [("INTRUDER", "calling AE title not allowed"),
                       ("CARM1", "called AE title 'OTHER' is not ours")]


@pytest.mark.filterwarnings("ignore:Invalid value for VR UI")
def test_invalid_instances_get_a_failure_status_with_the_reason(scp):
    receiver, stored, tmp_path = scp
    assoc = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
    assert assoc.is_established
    assert assoc.acceptor.maximum_length == 65536  # our PDU limit is negotiated
    no_patient = encode_frame(small_frame())
    del no_patient.PatientID
    truncated = encode_frame(small_frame())
    truncated.PixelData = truncated.PixelData[:-100]
    bad_uid = encode_frame(small_frame(sop_instance_uid="1.2.3.abc"))
    statuses = [assoc.send_c_store(ds) for ds in (no_patient, truncated, bad_uid)]
    assert [s.Status for s in statuses[:2]] == [0xC000, 0xC000]
    assert statuses[0].ErrorComment == "PatientID is missing"
    assert "PixelData holds" in statuses[1].ErrorComment
    # A command whose UID pynetdicom cannot decode: the association is aborted, and audited.
    # Both land asynchronously (the requestor's thread, the receiver's audit), so wait.
    assert "Status" not in statuses[2]
    assoc.join(timeout=10.0)
    deadline = time.monotonic() + 10.0
    while not _events(tmp_path, "association_aborted") and time.monotonic() < deadline:
        time.sleep(0.05)
    assert assoc.is_aborted
    assert stored == [] and receiver.spool.count() == 0
    rejected = _events(tmp_path, "rejected")
    aborted = _events(tmp_path, "association_aborted")
    assert [e["reason"] for e in aborted] == [
        "Affected SOP Instance UID in the command is not a valid UID"]
    assert [e["reason"] for e in rejected][0] == "PatientID is missing" and len(rejected) == 2


def test_sop_class_must_match_the_negotiated_context():
    ds = encode_frame(small_frame())
    status, reason = check_instance(ds, "1.2.840.10008.5.1.4.1.1.12.2", ds.file_meta.TransferSyntaxUID,
                                    ds.SOPInstanceUID)
    assert status == 0xA900 and "does not match the negotiated" in reason
    status, reason = check_instance(ds, ds.SOPClassUID, "1.2.840.10008.1.2.4.50", ds.SOPInstanceUID)
    assert status == 0xC000 and "transfer syntax" in reason


def test_the_health_check_ae_may_echo_but_not_store(scp):
    receiver, stored, tmp_path = scp
    assoc = _client("SLAMTKA_HEALTH").associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
    assert assoc.send_c_echo().Status == 0
    status = assoc.send_c_store(encode_frame(small_frame()))
    assoc.release()
    assert status.Status == 0x0124 and stored == []


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return make_pki(tmp_path_factory.mktemp("pki"))


def _tls_client(pki, cert="client", maximum=None) -> tuple:
    return client_context(pki, cert, maximum), None


@pytest.mark.filterwarnings("ignore:ssl.TLSVersion.TLSv1_1 is deprecated")
def test_mutual_tls(tmp_path, pki):
    receiver, stored, audit = _receiver(tmp_path, tls={
        "enabled": True, "certificate": str(pki["server_cert"]),
        "private_key": str(pki["server_key"]), "ca_certificates": str(pki["ca"])})
    try:
        assoc = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA",
                                    tls_args=_tls_client(pki))
        assert assoc.is_established
        assert assoc.send_c_store(encode_frame(small_frame())).Status == 0
        assoc.release()
        assert len(stored) == 1
        for client in (_tls_client(pki, cert=None), _tls_client(pki, cert="rogue"),
                       _tls_client(pki, maximum=ssl.TLSVersion.TLSv1_1)):
            try:
                refused = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA",
                                              tls_args=client)
                established = refused.is_established
            except (ssl.SSLError, OSError):
                established = False
            assert not established
        plain = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert not plain.is_established
        if shutil.which("echoscu"):
            out = subprocess.run(["echoscu", "-aet", "CARM1", "-aec", "SLAMTKA", "+tls",
                                  str(pki["client_key"]), str(pki["client_cert"]), "+cf",
                                  str(pki["ca"]), "127.0.0.1", str(receiver.port)],
                                 capture_output=True, text=True, timeout=30)
            assert out.returncode == 0, out.stderr
    finally:
        receiver.stop()
        audit.close()


def test_associations_beyond_the_limit_are_refused_and_audited(tmp_path):
    receiver, stored, audit = _receiver(tmp_path, max_associations=1)
    try:
        first = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        second = _client().associate("127.0.0.1", receiver.port, ae_title="SLAMTKA")
        assert first.is_established and second.is_rejected
        first.release()
        refused = _events_once(tmp_path, "association_rejected", 1)
        assert len(refused) == 1 and refused[0]["peer"] == "127.0.0.1"
        assert refused[0]["reason"] == "too many associations (held by 127.0.0.1 x1)"
    finally:
        receiver.stop()
        audit.close()
