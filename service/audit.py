"""The append-only audit log: one JSON line per received, rejected, processed and sent object.

Rerun recordings are not crash-safe on their own, so every event that matters for the audit
trail is also appended here and fsynced before the caller carries on (for a received
instance: before the C-STORE success goes back). Lines are never rewritten; a line torn by
a crash is skipped when the log is read.
"""

from __future__ import annotations

import json
import os
import threading
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable, Iterator

__all__ = ["AuditLog", "read_audit", "last_event", "EVENTS"]

EVENTS = ("service_started", "service_stopped", "connection_refused", "association_rejected",
          "association_aborted", "context_rejected", "received", "rejected", "duplicate",
          "view_unusable", "case_triggered", "processed", "failed", "sent", "send_failed",
          "send_abandoned",
          # the re-measurement loop (service.workflow, service.clock, service.sender)
          "pin_check", "pin_set_started", "status_sent", "output_failed", "operator_request",
          "clock_mismatch", "send_superseded")


class AuditLog:
    """Thread-safe appender; each :meth:`record` is one ``write`` + ``fsync``."""

    def __init__(self, path: Path, listeners: list[Callable[[dict], None]] | None = None):
        self.path = Path(path)
        self.listeners = list(listeners or [])
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o640)
        self._lock = threading.Lock()

    def record(self, event: str, **fields: Any) -> dict:
        if event not in EVENTS:
            raise ValueError(f"unknown audit event {event!r}")
        entry = {"time": datetime.now(timezone.utc).isoformat(timespec="microseconds"),
                 "event": event, **fields}
        line = (json.dumps(entry, default=str, separators=(",", ":")) + "\n").encode()
        with self._lock:
            os.write(self._fd, line)
            os.fsync(self._fd)
        for listener in self.listeners:
            listener(entry)
        return entry

    def close(self) -> None:
        with self._lock:
            if self._fd >= 0:
                os.close(self._fd)
                self._fd = -1


def read_audit(path: Path) -> Iterator[dict]:
    """The entries of an audit log in order; a torn (partial) line is skipped."""
    path = Path(path)
    if not path.is_file():
        return
    with path.open("rb") as f:
        for raw in f:
            try:
                yield json.loads(raw)
            except json.JSONDecodeError:
                continue


def last_event(path: Path, event: str, tail_bytes: int = 1 << 20) -> dict | None:
    """The newest entry of kind ``event`` within the last ``tail_bytes`` of the log."""
    path = Path(path)
    if not path.is_file():
        return None
    with path.open("rb") as f:
        f.seek(max(0, f.seek(0, os.SEEK_END) - tail_bytes))
        lines = f.read().splitlines()
    for raw in reversed(lines):
        try:
            entry = json.loads(raw)
        except json.JSONDecodeError:
            continue  # torn, or cut by the tail window
        if entry.get("event") == event:
            return entry
    return None
