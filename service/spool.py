"""The durable spool of received instances.

An instance is written to a temporary file under a random name, fsynced, then hard-linked
into ``instances/`` under a name derived from the SHA-256 of its SOP Instance UID (never from
the untrusted value itself), and the directory is fsynced: only then is the C-STORE
acknowledged. Linking refuses to replace an existing file, so a re-sent instance is detected
atomically and the first copy is kept (processing is idempotent by SOP Instance UID).

Beside each instance a small JSON sidecar, written the same crash-safe way, keeps the facts
the receiver decoded (:mod:`slamtka.service.decoded`, written with the instance, before the
acknowledgement) and how the case assembler paired the frame with the C-arm's encoders, so
a restart re-builds every case exactly as it was without decoding the instances again. A
crash can leave only temporary files (``.tmp-*``) behind, never a partial instance
(:mod:`slamtka.service.atomic_files`); one between the instance and its sidecar leaves an
instance without facts, which is decoded once more at the next start.

A re-sent SOP Instance UID is compared with the spooled copy: the same image is a duplicate,
another image under the same UID (other patient, other pixels) a conflict the caller refuses.
Files that cannot be read at start-up (a disk error, an edit) are moved to ``quarantine/``
with their sidecar, so one damaged file never keeps the service from starting.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import pydicom
from pydicom.dataset import Dataset

from slamtka.service.atomic_files import _fsync_dir, write_atomic, write_json_atomic
from slamtka.service.decoded import DecodedFrames, sidecar_of
from slamtka.service.frames import FrameHeader

__all__ = ["Spool", "SpoolEntry", "entry_id", "content_digest"]

StoreOutcome = Literal["new", "duplicate", "conflict"]
# What makes two instances "the same image": who, which study and series, and the pixels.
_IDENTITY = ("PatientID", "StudyInstanceUID", "SeriesInstanceUID", "SOPClassUID")

def entry_id(sop_instance_uid: str) -> str:
    """File stem for an instance: a digest, so no received value ever becomes a path."""
    return hashlib.sha256(sop_instance_uid.encode("ascii", "replace")).hexdigest()[:40]


@dataclass(frozen=True)
class SpoolEntry:
    """One spooled instance: its file and the SOP Instance UID it was stored under."""

    id: str
    path: Path
    sop_instance_uid: str

    @property
    def sidecar(self) -> Path:
        return self.path.with_suffix(".json")


def content_digest(ds: Dataset) -> str:
    """SHA-256 over the identifying attributes and the decoded pixels (so the same image
    sent again in another transfer syntax is still the same)."""
    digest = hashlib.sha256()
    for keyword in _IDENTITY:
        digest.update(f"{keyword}={ds.get(keyword, '')}\0".encode("utf-8", "replace"))
    pixels = ds.pixel_array
    digest.update(f"{pixels.dtype.str}{pixels.shape}".encode())
    digest.update(pixels.tobytes())
    return digest.hexdigest()


class Spool:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.instances = self.root / "instances"
        self.instances.mkdir(parents=True, exist_ok=True)
        self.decoded = DecodedFrames(self)

    def store(self, ds: Dataset, facts: FrameHeader | None = None) -> tuple[SpoolEntry, StoreOutcome]:
        """Persist ``ds`` (with its file meta) unless its UID is spooled already, and beside
        a new one its decoded ``facts``; then say whether the spooled copy is the same image
        (``duplicate``) or not (``conflict``). OSError: nothing new is left spooled."""
        uid = str(ds.SOPInstanceUID)
        buffer = io.BytesIO()
        ds.save_as(buffer, enforce_file_format=True)
        data, entry = buffer.getvalue(), self.entry(uid)
        if write_atomic(entry.path, data, replace=False):
            if facts is not None:
                try:
                    self.write_sidecar(entry, sidecar_of(facts, len(data)))
                except OSError:
                    self.discard(entry)
                    raise
            return entry, "new"
        try:
            same = content_digest(self.read(entry)) == content_digest(ds)
        except Exception:  # an unreadable spooled copy cannot vouch for the new one
            same = False
        return entry, "duplicate" if same else "conflict"

    def discard(self, entry: SpoolEntry) -> None:
        """Take back a just-stored instance whose receipt could not be audited (so the
        sender's retry is stored and queued again, not taken for a duplicate)."""
        entry.path.unlink(missing_ok=True)
        entry.sidecar.unlink(missing_ok=True)
        _fsync_dir(self.instances)

    def entry(self, sop_instance_uid: str) -> SpoolEntry:
        stem = entry_id(sop_instance_uid)
        return SpoolEntry(stem, self.instances / f"{stem}.dcm", sop_instance_uid)

    def read(self, entry: SpoolEntry, pixels: bool = True) -> Dataset:
        return pydicom.dcmread(entry.path, stop_before_pixels=not pixels)

    def entries(self) -> list[SpoolEntry]:
        """Every spooled instance in the order it was received (file modification time)."""
        out = []
        for path in self._files():
            uid = str(pydicom.dcmread(path, stop_before_pixels=True,
                                      specific_tags=["SOPInstanceUID"]).SOPInstanceUID)
            out.append(SpoolEntry(path.stem, path, uid))
        return out

    def _files(self) -> list[Path]:
        """The instance files, oldest first (file modification time)."""
        return sorted(self.instances.glob("*.dcm"), key=lambda p: (p.stat().st_mtime_ns, p.name))

    def recover(self) -> tuple[list[SpoolEntry], list[dict]]:
        """:meth:`entries` at start-up: a file whose header cannot be read is quarantined;
        (the readable entries, one ``{"file", "reason", "moved_to"}`` per file moved aside)."""
        entries, moved = [], []
        for path in self._files():
            try:
                if path.stat().st_size == 0:
                    raise ValueError("empty file")
                uid = str(pydicom.dcmread(path, stop_before_pixels=True,
                                          specific_tags=["SOPInstanceUID"]).SOPInstanceUID)
            except Exception as exc:  # pydicom raises many types on a damaged file
                moved.append(self.quarantine(path, f"unreadable: {type(exc).__name__}: {exc}"))
                continue
            entries.append(SpoolEntry(path.stem, path, uid))
        return entries, moved

    def quarantine(self, path: Path, reason: str) -> dict:
        """Move a damaged spool file (an instance takes its sidecar along) out of the way."""
        folder = self.root / "quarantine"
        folder.mkdir(exist_ok=True)
        moved = []
        for item in (path, path.with_suffix(".json")) if path.suffix == ".dcm" else (path,):
            if item.exists():
                target = folder / item.name
                n = 1
                while target.exists():  # a file damaged twice keeps both copies
                    target = folder / f"{item.name}.{n}"
                    n += 1
                os.replace(item, target)
                moved.append(target.name)
        _fsync_dir(self.instances)
        _fsync_dir(folder)
        return {"file": path.name, "reason": reason[:300], "moved_to": moved}

    def write_sidecar(self, entry: SpoolEntry, doc: dict) -> None:
        write_json_atomic(entry.sidecar, doc)

    def read_sidecar(self, entry: SpoolEntry) -> dict | None:
        if not entry.sidecar.is_file():
            return None
        return json.loads(entry.sidecar.read_text())

    def count(self) -> int:
        return sum(1 for _ in self.instances.glob("*.dcm"))

    def bytes_used(self) -> int:
        """Bytes in the spool; a temporary file renamed away while counting is skipped."""
        total = 0
        for path in self.instances.glob("*"):
            try:
                total += path.stat().st_size
            except FileNotFoundError:
                continue
        return total

