"""Who may hold one of the receiver's associations, from where, and how many.

An AE title is only a name any host can claim: a host using the C-arm's title held every
association slot with keep-alive echoes and locked the C-arm out. So, counted from the
A-ASSOCIATE-RQ (:mod:`service.wire` asks here before pynetdicom negotiates):

- a calling AE title bound in ``dicom.callers`` associates only from its addresses and, if
  its certificate is pinned, only with that certificate (over TLS); a pinned certificate is
  accepted only from the addresses of its binding;
- storing associations: at most ``max_associations`` in all and
  ``max_associations_per_address`` from one address; when callers are bound, the unbound
  ones together leave one slot free, kept for the bound C-arm(s);
- health checks have :data:`HEALTH_ASSOCIATIONS` slots of their own.

A refusal names who holds the slots, so the audit line points at the squatter, not at the
C-arm it kept out.
"""

from __future__ import annotations

import ipaddress
import threading
from collections import Counter
from dataclasses import dataclass

from slamtka.service.config import DicomConfig, normalise_fingerprint

__all__ = ["Admission", "Ticket", "HEALTH_ASSOCIATIONS"]

HEALTH_ASSOCIATIONS = 2  # concurrent health checks; they never take a C-arm's slot


@dataclass(frozen=True)
class Ticket:
    """One admitted association: give it back with :meth:`Admission.release`."""

    kind: str  # "storer" or "health"
    address: str
    bound: bool


def _networks(addresses: list[str]) -> list:
    return [ipaddress.ip_network(a, strict=False) for a in addresses]


def _within(address: str, networks: list) -> bool:
    try:
        ip = ipaddress.ip_address(address)
    except ValueError:
        return False
    return any(ip in network for network in networks)


class Admission:
    """The bindings and the slot accounting of one receiver (thread-safe)."""

    def __init__(self, config: DicomConfig):
        self.max_associations = config.max_associations
        self.per_address = min(config.max_associations_per_address, config.max_associations)
        self._bound = {c.ae_title: (c.addresses, _networks(c.addresses),
                                    normalise_fingerprint(c.certificate_sha256))
                       for c in config.callers}
        self._certificates = {pin: (title, addresses, networks)
                              for title, (addresses, networks, pin) in self._bound.items() if pin}
        self._held: Counter[Ticket] = Counter()
        self._lock = threading.Lock()

    def binding_problem(self, address: str, calling: str, certificate: str) -> str | None:
        """Why ``calling`` may not associate from ``address`` presenting ``certificate``
        (its SHA-256, "" without TLS), or None."""
        owner = self._certificates.get(certificate)
        if owner is not None and not _within(address, owner[2]):
            return (f"client certificate of {owner[0]} presented from {address}, which is not "
                    f"among its addresses {owner[1]}")
        if calling not in self._bound:
            return None
        addresses, networks, pin = self._bound[calling]
        if not _within(address, networks):
            return f"calling AE title {calling} is bound to {addresses}, not {address}"
        if pin and certificate != pin:
            return f"calling AE title {calling} did not present its pinned client certificate"
        return None

    def _holders(self, kind: str) -> str:
        by_address: Counter[str] = Counter()
        for ticket, count in self._held.items():
            if ticket.kind == kind:
                by_address[ticket.address] += count
        return ", ".join(f"{address} x{n}" for address, n in by_address.most_common())

    def take(self, kind: str, address: str, calling: str) -> Ticket | str:
        """A slot for an association of ``kind`` ("storer" or "health"), or why there is none."""
        ticket = Ticket(kind, address, calling in self._bound)
        with self._lock:
            same_kind = sum(n for t, n in self._held.items() if t.kind == kind)
            if kind == "health":
                if same_kind >= HEALTH_ASSOCIATIONS:
                    return f"too many health-check associations (held by {self._holders(kind)})"
            elif same_kind >= self.max_associations:
                return f"too many associations (held by {self._holders(kind)})"
            elif sum(n for t, n in self._held.items()
                     if t.kind == kind and t.address == address) >= self.per_address:
                return f"too many associations from {address} (at most {self.per_address})"
            elif self._bound and not ticket.bound and sum(
                    n for t, n in self._held.items()
                    if t.kind == kind and not t.bound) >= self.max_associations - 1:
                return ("too many associations from unbound callers: the last slot is kept for "
                        f"{', '.join(self._bound)} (held by {self._holders(kind)})")
            self._held[ticket] += 1
        return ticket

    def release(self, ticket: Ticket) -> None:
        with self._lock:
            self._held[ticket] -= 1
            if self._held[ticket] <= 0:
                del self._held[ticket]
