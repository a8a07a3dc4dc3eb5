"""The append-only audit log: one JSON line per received, rejected, processed and sent object.

Rerun recordings are not crash-safe on their own, so every event that matters for the audit
trail is also appended here and fsynced before the caller carries on (for a received
instance: before the C-STORE success goes back). A line is written whole or not at all: a
short write is continued, a failed one is cut back off, so a full disk never fuses two events.
A tail torn by a power cut is cut off at open and the repair audited (``audit_repaired``).

Tamper evidence: each line carries ``prev``, the SHA-256 of the previous line's bytes, so an
edited, removed or inserted line breaks the chain (``slamtka audit verify`` names the first
broken line); run lines carry the SHA-256 digests of the run's outputs. A log written before
the chain existed is verified from its first chained line on.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = ["AuditLog", "read_audit", "last_event", "verify_chain", "file_digests", "EVENTS"]

EVENTS = ("service_started", "service_stopped", "connection_refused", "association_rejected",
          "association_aborted", "context_rejected", "received", "rejected", "duplicate",
          "view_unusable", "case_triggered", "processed", "failed", "sent", "send_failed",
          "send_abandoned",
          # the re-measurement loop (service.workflow, service.clock, service.sender)
          "pin_check", "pin_set_started", "status_sent", "output_failed", "operator_request",
          "clock_mismatch", "send_superseded",
          # storage robustness: the log's own repair, damaged spool files, UID conflicts
          "audit_repaired", "quarantined", "uid_conflict",
          # retention (service.retention)
          "case_archived", "case_pruned",
          # calibrations followed while running; cases refused for a missing plan or
          # calibration run again when one is added (service.calibrations, service.serve)
          "calibrations_reloaded", "calibrations_unreadable", "rerun_after_change")

CHAIN_FIELD = "prev"  # SHA-256 (hex) of the previous line's bytes, without its newline
_GENESIS = "0" * 64  # ``prev`` of the first line of a new log


def _line_hash(raw: bytes) -> str:
    return hashlib.sha256(raw.rstrip(b"\n")).hexdigest()


def file_digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every file under ``folder`` by relative path: what a run line vouches for."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _repair_tail(fd: int) -> tuple[bytes | None, int]:
    """Cut a torn last line off (a crash mid-write); (the last whole line, bytes cut)."""
    size = os.fstat(fd).st_size
    if size == 0:
        return None, 0
    window = min(size, 1 << 20)
    tail = os.pread(fd, window, size - window)
    end = tail.rfind(b"\n") + 1  # the end of the last complete line within the window
    cut = len(tail) - end
    if cut:
        if end == 0 and window < size:
            raise RuntimeError("audit log: the last line is longer than 1 MiB; refusing to cut it")
        os.ftruncate(fd, size - cut)
        os.fsync(fd)
    whole = tail[:end].rstrip(b"\n")
    return (whole.rsplit(b"\n", 1)[-1] if whole else None), cut


class AuditLog:
    """Thread-safe appender; each :meth:`record` is one whole line, fsynced, chained."""

    def __init__(self, path: Path, listeners: list[Callable[[dict], None]] | None = None):
        self.path = Path(path)
        self.listeners = list(listeners or [])
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o640)
        self._lock = threading.Lock()
        last, cut = _repair_tail(self._fd)
        self._prev = _line_hash(last) if last is not None else _GENESIS
        if cut:
            self.record("audit_repaired", bytes_removed=cut,
                        reason="torn last line (interrupted write) cut off at open")

    def record(self, event: str, **fields: Any) -> dict:
        """Append one event; raises OSError (nothing written) if the line cannot be stored."""
        if event not in EVENTS:
            raise ValueError(f"unknown audit event {event!r}")
        entry = {"time": datetime.now(UTC).isoformat(timespec="microseconds"),
                 "event": event, **fields}
        with self._lock:
            entry[CHAIN_FIELD] = self._prev
            line = json.dumps(entry, default=str, separators=(",", ":")).encode()
            self._append(line + b"\n")
            self._prev = _line_hash(line)
        for listener in self.listeners:
            listener(entry)
        return entry

    def _append(self, data: bytes) -> None:
        """Write ``data`` whole: continue short writes; on an error cut the partial line off."""
        start = os.fstat(self._fd).st_size
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self._fd, view):]
            os.fsync(self._fd)
        except OSError:
            try:  # a shrinking truncate needs no free blocks
                os.ftruncate(self._fd, start)
            except OSError:
                pass  # then the next open cuts the torn tail (audited)
            raise

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


@dataclass(frozen=True)
class ChainReport:
    """What :func:`verify_chain` found; line numbers count from 1."""

    lines: int
    chain_starts: int | None  # the first line carrying ``prev`` (None: no chained line)
    broken: int | None  # the first line that breaks the chain
    reason: str = ""


def verify_chain(path: Path) -> ChainReport:
    """Check every line's ``prev`` against the previous line's hash."""
    prev_hash: str | None = None
    start = None
    number = 0
    with Path(path).open("rb") as f:
        for number, raw in enumerate(f, 1):
            line = raw.rstrip(b"\n")
            try:
                entry = json.loads(line)
                if not isinstance(entry, dict):
                    raise ValueError("not an object")
            except ValueError:
                return ChainReport(number, start, number, "not a JSON object (torn or edited)")
            claimed = entry.get(CHAIN_FIELD)
            if claimed is None:
                if start is not None:
                    return ChainReport(number, start, number, f"no {CHAIN_FIELD!r} hash")
            else:
                # line 1 of a chained log follows the genesis value; an older log's chain
                # starts with the hash of its last line written before the chain existed
                if claimed != (prev_hash or _GENESIS):
                    return ChainReport(number, start or number, number,
                                       "hash of the previous line does not match")
                start = start or number
            prev_hash = _line_hash(line)
    return ChainReport(number, start, None)


def cmd_audit_verify(args: argparse.Namespace) -> int:
    """Exit 0: chain intact; 1: broken (the line named); 2: no log or unreadable."""
    path = args.data / "audit.jsonl"
    if not path.is_file():
        print(f"{path}: no audit log here")
        return 2
    report = verify_chain(path)
    if report.chain_starts is None:
        print(f"{path}: {report.lines} lines, none carries a hash (written before the chain)")
    elif report.chain_starts > 1:
        print(f"{path}: lines 1-{report.chain_starts - 1} predate the chain; "
              f"it starts at line {report.chain_starts}")
    if report.broken is not None:
        print(f"{path}: BROKEN at line {report.broken}: {report.reason}")
        return 1
    print(f"{path}: {report.lines} lines, chain intact")
    return 0


def add_audit_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("audit", help="check the audit log")
    actions = p.add_subparsers(dest="action", required=True)
    verify = actions.add_parser("verify", help="check the hash chain; name the first broken line")
    verify.add_argument("--data", type=Path, default=Path("/var/lib/slamtka"),
                        help="the service's data folder (default: /var/lib/slamtka)")
    verify.set_defaults(func=cmd_audit_verify)
