"""TLS names and pins on the way out: a PACS with another host's certificate gets nothing."""

from __future__ import annotations

import ssl

import pytest
from test_service_sender import _objects

from slamtka.bench.pki import OTHER_HOST, make_pki
from slamtka.service.audit import AuditLog, read_audit
from slamtka.service.config import ConfigError, Destination, SenderConfig, config_from_dict
from slamtka.service.sender import Sender
from slamtka.service.tls import certificate_sha256
from slamtka.sim.theatre import ResultCollector


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return make_pki(tmp_path_factory.mktemp("pki"))


def _pacs(pki, cert: str) -> ResultCollector:
    ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    ctx.load_cert_chain(pki[f"{cert}_cert"], pki[f"{cert}_key"])
    return ResultCollector(ssl_context=ctx)


def _send(tmp_path, pki, pacs: ResultCollector, **destination) -> tuple[int, list[dict]]:
    """Objects sent to ``pacs`` as destination 127.0.0.1 over TLS; (sent, audit entries)."""
    audit = AuditLog(tmp_path / "audit.jsonl")
    dest = Destination("pacs", "ORDISPLAY", "127.0.0.1", pacs.port, ["sc"], tls=True,
                       ca_certificates=pki["ca"], certificate=pki["client_cert"],
                       private_key=pki["client_key"], **destination)
    sender = Sender("SLAMTKA", [dest], SenderConfig(max_attempts=5, timeout_s=5.0),
                    tmp_path / "queue", audit)
    try:
        sender.enqueue(_objects(tmp_path, 1), "case-1", "run-1")
        return sender.run_once(), list(read_audit(audit.path))
    finally:
        pacs.stop()
        audit.close()


def test_a_pacs_with_another_hosts_certificate_from_the_same_ca_receives_nothing(tmp_path, pki):
    pacs = _pacs(pki, "elsewhere")
    sent, audit = _send(tmp_path, pki, pacs)
    assert sent == 0 and pacs.received == []
    failed = [e for e in audit if e["event"] == "send_failed"]
    assert len(failed) == 1 and "address mismatch" in failed[0]["error"], failed


def test_the_certificate_naming_the_host_is_accepted(tmp_path, pki):
    pacs = _pacs(pki, "server")
    assert _send(tmp_path, pki, pacs)[0] == 1 and len(pacs.received) == 1


def test_a_configured_server_name_is_the_name_checked(tmp_path, pki):
    pacs = _pacs(pki, "elsewhere")
    assert _send(tmp_path, pki, pacs, server_name=OTHER_HOST[0])[0] == 1


def test_a_pinned_destination_accepts_only_its_certificate(tmp_path, pki):
    other = certificate_sha256(pki["elsewhere_cert"])
    pacs = _pacs(pki, "server")
    sent, audit = _send(tmp_path / "wrong", pki, pacs, certificate_sha256=other)
    assert sent == 0 and pacs.received == []
    assert any("pinned" in e.get("error", "") for e in audit), audit
    own = certificate_sha256(pki["server_cert"]).upper()
    pinned = ":".join(own[i:i + 2] for i in range(0, 64, 2))  # as openssl prints it
    pacs = _pacs(pki, "server")
    assert _send(tmp_path / "right", pki, pacs, certificate_sha256=pinned)[0] == 1


def test_a_malformed_pin_is_refused_by_name():
    table = {"dicom": {"allowed_calling_ae_titles": ["CARM1"]}, "carm": {"calibration": "c.json"},
             "destinations": [{"name": "pacs", "ae_title": "PACS", "host": "pacs", "tls": True,
                               "ca_certificates": "ca.pem", "certificate_sha256": "abc"}]}
    with pytest.raises(ConfigError, match=r"destinations\[0\]\.certificate_sha256"):
        config_from_dict(table, environ={})
