"""Helpers shared by the service tests: frames, free ports, throwaway TLS certificates."""

from __future__ import annotations

import datetime as dt
import ipaddress
import socket
from pathlib import Path

import numpy as np
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from service.frames import Frame


def free_port() -> int:
    """A port nothing listens on right now (loopback)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def small_frame(**changes) -> Frame:
    """A valid 64 x 64 XA frame with positioner angles (pixels are noise)."""
    fields = dict(pixels=np.random.default_rng(0).integers(0, 4000, (64, 64)).astype(np.uint16),
                  imager_pixel_spacing_mm=(0.3, 0.3), primary_angle_deg=-30.0,
                  secondary_angle_deg=0.0, sid_mm=1000.0, sod_mm=620.0,
                  acquisition_datetime=dt.datetime.now(dt.timezone.utc), patient_id="P-1",
                  patient_name="Doe^Jane", laterality="R", bits_stored=12)
    fields.update(changes)
    return Frame(**fields)


def _name(common: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common)])


def _certificate(subject: str, key, issuer: str, issuer_key, ca: bool) -> x509.Certificate:
    now = dt.datetime.now(dt.timezone.utc)
    builder = (x509.CertificateBuilder().subject_name(_name(subject)).issuer_name(_name(issuer))
               .public_key(key.public_key()).serial_number(x509.random_serial_number())
               .not_valid_before(now - dt.timedelta(minutes=5))
               .not_valid_after(now + dt.timedelta(days=1))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True))
    if not ca:
        builder = builder.add_extension(x509.SubjectAlternativeName(
            [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
            critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def make_pki(folder: Path) -> dict[str, Path]:
    """A CA and, signed by it, a server and a client certificate (plus an untrusted client).

    Returns paths: ca, server_cert, server_key, client_cert, client_key, rogue_cert, rogue_key.
    """
    folder.mkdir(parents=True, exist_ok=True)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = _certificate("slamtka test CA", ca_key, "slamtka test CA", ca_key, True)
    rogue_ca_key = ec.generate_private_key(ec.SECP256R1())
    paths = {"ca": folder / "ca.pem"}
    paths["ca"].write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    for name, issuer, issuer_key in (("server", "slamtka test CA", ca_key),
                                     ("client", "slamtka test CA", ca_key),
                                     ("rogue", "rogue CA", rogue_ca_key)):
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(name, key, issuer, issuer_key, False)
        paths[f"{name}_cert"] = folder / f"{name}.pem"
        paths[f"{name}_key"] = folder / f"{name}.key"
        paths[f"{name}_cert"].write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        paths[f"{name}_key"].write_bytes(key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption()))
    return paths
