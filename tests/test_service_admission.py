"""AE squatting: another host using the C-arm's AE title cannot lock the real C-arm out.

The squatters hold their associations open with keep-alive C-ECHOs from other loopback
addresses (Linux routes all of 127/8 to lo), as other hosts on the network would.
"""

from __future__ import annotations

import pytest
from pynetdicom import AE
from pynetdicom.sop_class import Verification, XRayAngiographicImageStorage
from service_testing import make_pki, small_frame

from slamtka.bench.pki import client_context
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import ConfigError, config_from_dict
from slamtka.service.frames import encode_frame
from slamtka.service.scp import DicomReceiver
from slamtka.service.spool import Spool
from slamtka.service.tls import certificate_sha256


@pytest.fixture
def receiver(tmp_path):
    made = []

    def make(**dicom) -> DicomReceiver:
        table = {"dicom": {"port": 0, "allowed_calling_ae_titles": ["CARM1", "CARM2"], **dicom},
                 "carm": {"calibration": "unused.json"}}
        audit = AuditLog(tmp_path / "audit.jsonl")
        scp = DicomReceiver(config_from_dict(table, environ={}).dicom, Spool(tmp_path / "spool"),
                            audit, lambda entry: None)
        scp.start()
        made.append((scp, audit))
        return scp
    yield make
    for scp, audit in made:
        scp.stop()
        audit.close()


def _associate(port: int, source: str, title: str = "CARM1", tls=None):
    ae = AE(ae_title=title)
    ae.add_requested_context(Verification)
    ae.add_requested_context(XRayAngiographicImageStorage)
    return ae.associate("127.0.0.1", port, ae_title="SLAMTKA", bind_address=(source, 0),
                        tls_args=tls)


def _squat(port: int, sources: list[str], title: str) -> list:
    """Associations held from ``sources`` (each tries twice), kept alive with a C-ECHO."""
    held = []
    for source in sources:
        for _ in range(2):
            assoc = _associate(port, source, title)
            if assoc.is_established:
                assert assoc.send_c_echo().Status == 0
                held.append(assoc)
    return held


def _rejections(tmp_path) -> list[dict]:
    return [e for e in read_audit(tmp_path / "audit.jsonl") if e["event"] == "association_rejected"]


def test_one_address_holds_at_most_its_share_of_the_slots(tmp_path, receiver):
    scp = receiver()  # nothing bound: only the per-address cap protects the C-arm
    held = _squat(scp.port, ["127.0.0.2"] * 2, "CARM1")
    try:
        assert len(held) == 2
        carm = _associate(scp.port, "127.0.0.1")
        assert carm.is_established and carm.send_c_store(encode_frame(small_frame())).Status == 0
        carm.release()
        refused = _rejections(tmp_path)
        assert refused and {e["peer"] for e in refused} == {"127.0.0.2"}
        assert all("127.0.0.2" in e["reason"] for e in refused)
    finally:
        for assoc in held:
            assoc.release()


def test_the_bound_c_arm_keeps_a_slot_and_its_title_is_refused_elsewhere(tmp_path, receiver):
    scp = receiver(callers=[{"ae_title": "CARM1", "addresses": ["127.0.0.1"]}])
    squatters = [f"127.0.0.{k}" for k in range(2, 6)]
    with_title = _squat(scp.port, squatters, "CARM1")
    other_title = _squat(scp.port, squatters, "CARM2")
    try:
        assert with_title == [] and len(other_title) == 3  # max_associations 4, one kept
        carm = _associate(scp.port, "127.0.0.1")
        assert carm.is_established and carm.send_c_store(encode_frame(small_frame())).Status == 0
        carm.release()
        refused = _rejections(tmp_path)
        bound = [e for e in refused if "is bound to" in e["reason"]]
        assert sorted(e["peer"] for e in bound) == sorted(squatters * 2)
        assert all("127.0.0.1" not in e["peer"] for e in refused)
        assert any("kept for CARM1" in e["reason"] for e in refused)
    finally:
        for assoc in other_title:
            assoc.release()


def test_a_pinned_client_certificate_is_accepted_only_from_its_address(tmp_path, receiver):
    pki = make_pki(tmp_path / "pki")
    scp = receiver(tls={"enabled": True, "certificate": str(pki["server_cert"]),
                        "private_key": str(pki["server_key"]), "ca_certificates": str(pki["ca"])},
                   callers=[{"ae_title": "CARM1", "addresses": ["127.0.0.1"],
                             "certificate_sha256": certificate_sha256(pki["client_cert"])}])
    good = (client_context(pki, "client"), None)
    other = (client_context(pki, "elsewhere"), None)
    assoc = _associate(scp.port, "127.0.0.1", tls=good)
    assert assoc.is_established
    assoc.release()
    assert not _associate(scp.port, "127.0.0.1", tls=other).is_established  # not its certificate
    assert not _associate(scp.port, "127.0.0.2", "CARM2", tls=good).is_established  # elsewhere
    reasons = [e["reason"] for e in _rejections(tmp_path)]
    assert any("pinned client certificate" in r for r in reasons)
    assert any("client certificate of CARM1 presented from 127.0.0.2" in r for r in reasons)


def test_bindings_are_checked_at_start():
    table = {"dicom": {"allowed_calling_ae_titles": ["CARM1"],
                       "callers": [{"ae_title": "CARM9", "addresses": ["10.0.0.7"]}]},
             "carm": {"calibration": "c.json"}}
    with pytest.raises(ConfigError, match=r"dicom\.callers\[0\]\.ae_title"):
        config_from_dict(table, environ={})
    table["dicom"]["callers"] = [{"ae_title": "CARM1", "addresses": ["10.0.0.x"]}]
    with pytest.raises(ConfigError, match=r"dicom\.callers\[0\]\.addresses\[0\]"):
        config_from_dict(table, environ={})
