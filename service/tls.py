"""TLS contexts for the DICOM receiver and the result sender, and certificate fingerprints.

Receiving: mutual TLS, our certificate, client certificates required (which client may call
from where is :mod:`service.admission`'s business). Sending: the destination's certificate
must chain to its configured CAs *and* name the host we dialled (``check_hostname``; the
server name is sent with SNI), so a PACS holding another host's certificate from the same CA
is refused; a destination may also pin the SHA-256 of its certificate, checked during the
handshake, before a byte of DICOM is sent.
"""

from __future__ import annotations

import hashlib
import ssl
from pathlib import Path
from typing import TypeVar

from slamtka.service.config import ConfigError, TlsConfig

__all__ = ["server_ssl_context", "client_ssl_context", "certificate_sha256", "fingerprint",
           "ClientContext", "PinMismatch"]

_Context = TypeVar("_Context", bound=ssl.SSLContext)
_TLS_VERSIONS = {"1.2": ssl.TLSVersion.TLSv1_2, "1.3": ssl.TLSVersion.TLSv1_3}


class PinMismatch(ssl.SSLCertVerificationError):
    """The peer's certificate chains and names the host, but is not the pinned one."""


def fingerprint(der: bytes) -> str:
    """SHA-256 of a DER certificate, lower-case hex (``openssl x509 -fingerprint -sha256``
    prints the same digits in capitals with colons)."""
    return hashlib.sha256(der).hexdigest()


def certificate_sha256(path: Path) -> str:
    """The fingerprint of the first certificate in a PEM file."""
    return fingerprint(ssl.PEM_cert_to_DER_cert(Path(path).read_text()))


class _ClientSocket(ssl.SSLSocket):
    """Checks the context's pin as soon as the handshake completes, and leaves the reason a
    handshake failed on the context (pynetdicom reports only "aborted")."""

    def do_handshake(self, block: bool = False) -> None:
        context = self.context
        assert isinstance(context, ClientContext), "only a ClientContext wraps this socket class"
        try:
            super().do_handshake(block)
            seen = fingerprint(self.getpeercert(binary_form=True) or b"")
            if context.pin_sha256 and seen != context.pin_sha256:
                raise PinMismatch(f"certificate SHA-256 {seen} is not the pinned "
                                  f"{context.pin_sha256}")
        except ssl.SSLError as exc:
            context.handshake_error = getattr(exc, "verify_message", "") or str(exc)
            if isinstance(exc, PinMismatch):
                context.handshake_error = exc.args[0]
                self.close()
            raise


class ClientContext(ssl.SSLContext):
    """An SCU's TLS context: its pin, and why its last handshake failed."""

    sslsocket_class = _ClientSocket
    pin_sha256 = ""
    handshake_error = ""


def _load(ctx: _Context, certificate: Path | None, private_key: Path | None,
          ca_certificates: Path | None, where: str) -> _Context:
    try:
        if certificate is not None:
            ctx.load_cert_chain(certificate, private_key)
        if ca_certificates is not None:
            ctx.load_verify_locations(cafile=ca_certificates)
    except (OSError, ssl.SSLError) as exc:
        raise ConfigError(f"{where}: cannot load certificates ({exc})") from None
    return ctx


def server_ssl_context(tls: TlsConfig) -> ssl.SSLContext:
    """Mutual TLS for the SCP: our certificate, client certificates required."""
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = _TLS_VERSIONS[tls.min_version]
    ctx.verify_mode = ssl.CERT_REQUIRED
    return _load(ctx, tls.certificate, tls.private_key, tls.ca_certificates, "dicom.tls")


def client_ssl_context(ca_certificates: Path, certificate: Path | None = None,
                       private_key: Path | None = None, where: str = "tls", *,
                       check_hostname: bool = True, pin_sha256: str = "") -> ClientContext:
    """TLS for an SCU: the server must chain to ``ca_certificates`` and (``check_hostname``)
    name the host dialled, which the caller passes as ``server_hostname``; with
    ``pin_sha256`` its certificate must also be that one. Ours is presented if given."""
    ctx = ClientContext(ssl.PROTOCOL_TLS_CLIENT)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    ctx.check_hostname = check_hostname
    ctx.verify_mode = ssl.CERT_REQUIRED
    ctx.pin_sha256 = pin_sha256
    return _load(ctx, certificate, private_key, ca_certificates, where)
