"""Throwaway TLS certificates for the TLS tests and the hardening bench (never for production).

A private CA, a server and a client certificate it signs, a client certificate signed by an
unrelated CA, an expired one, and one the CA issued to another host (``pacs-b.invalid``,
127.0.0.9): the mutual TLS matrix and the host-name checks of ``slamtka bench hardening``.
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import ssl
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

__all__ = ["make_pki", "client_context", "OTHER_HOST"]


def _name(common: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common)])


OTHER_HOST = ("pacs-b.invalid", "127.0.0.9")  # whom the "elsewhere" certificate names


def _certificate(subject: str, key, issuer: str, issuer_key, ca: bool,
                 expired: bool = False, host: tuple[str, str] = ("localhost", "127.0.0.1")
                 ) -> x509.Certificate:
    now = dt.datetime.now(dt.UTC) - dt.timedelta(days=2 if expired else 0)
    builder = (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(_name(issuer))
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - dt.timedelta(minutes=5))
               .not_valid_after(now + dt.timedelta(days=1))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if not ca:
        builder = builder.add_extension(x509.SubjectAlternativeName(
            [x509.DNSName(host[0]), x509.IPAddress(ipaddress.ip_address(host[1]))]),
            critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def make_pki(folder: Path) -> dict[str, Path]:
    """A CA and, signed by it, a server and a client certificate (plus an untrusted client,
    an expired one and another host's).

    Returns paths: ca, and cert/key pairs server_*, client_*, rogue_* (signed by another CA),
    expired_* (signed by the CA, expired yesterday), elsewhere_* (signed by the CA for
    :data:`OTHER_HOST`, not for localhost).
    """
    folder.mkdir(parents=True, exist_ok=True)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = _certificate("slamtka test CA", ca_key, "slamtka test CA", ca_key, True)
    rogue_ca_key = ec.generate_private_key(ec.SECP256R1())
    paths = {"ca": folder / "ca.pem"}
    paths["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    for name, issuer, issuer_key in (("server", "slamtka test CA", ca_key),
                                     ("client", "slamtka test CA", ca_key),
                                     ("rogue", "rogue CA", rogue_ca_key),
                                     ("expired", "slamtka test CA", ca_key),
                                     ("elsewhere", "slamtka test CA", ca_key)):
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(name, key, issuer, issuer_key, False, expired=name == "expired",
                            **({"host": OTHER_HOST} if name == "elsewhere" else {}))
        paths[f"{name}_cert"] = folder / f"{name}.pem"
        paths[f"{name}_key"] = folder / f"{name}.key"
        paths[f"{name}_cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        paths[f"{name}_key"].write_bytes(key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
    return paths


def client_context(pki: dict[str, Path], cert: str | None = "client",
                   maximum: ssl.TLSVersion | None = None) -> ssl.SSLContext:
    """A TLS client trusting the test CA, presenting ``cert`` (a make_pki name) if given;
    ``maximum`` caps the protocol version (with every cipher allowed, to try old TLS)."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.check_hostname = False
    ctx.load_verify_locations(pki["ca"])
    if maximum is not None:
        ctx.minimum_version = ssl.TLSVersion.MINIMUM_SUPPORTED
        ctx.maximum_version = maximum
        ctx.set_ciphers("ALL:@SECLEVEL=0")
    if cert is not None:
        ctx.load_cert_chain(pki[f"{cert}_cert"], pki[f"{cert}_key"])
    return ctx
