"""The durable spool of received instances.

An instance is written to a temporary file under a random name, fsynced, then hard-linked
into ``instances/`` under a name derived from the SHA-256 of its SOP Instance UID (never from
the untrusted value itself), and the directory is fsynced: only then is the C-STORE
acknowledged. Linking refuses to replace an existing file, so a re-sent instance is detected
atomically and the first copy is kept (processing is idempotent by SOP Instance UID).

Beside each instance the case assembler keeps a small JSON sidecar (how the frame was
paired with the C-arm's encoders), written the same crash-safe way, so a restart re-builds
every case exactly as it was. A crash can leave only temporary files (``.tmp-*``) behind,
never a partial instance (:mod:`slamtka.service.atomic_files`).
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path

import pydicom
from pydicom.dataset import Dataset

from slamtka.service.atomic_files import write_atomic, write_json_atomic

__all__ = ["Spool", "SpoolEntry", "entry_id"]

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


class Spool:
    def __init__(self, root: Path):
        self.root = Path(root)
        self.instances = self.root / "instances"
        self.instances.mkdir(parents=True, exist_ok=True)

    def store(self, ds: Dataset) -> tuple[SpoolEntry, bool]:
        """Persist ``ds`` (with its file meta); False in the tuple if it was already spooled."""
        uid = str(ds.SOPInstanceUID)
        buffer = io.BytesIO()
        ds.save_as(buffer, enforce_file_format=True)
        entry = self.entry(uid)
        created = write_atomic(entry.path, buffer.getvalue(), replace=False)
        return entry, created

    def entry(self, sop_instance_uid: str) -> SpoolEntry:
        stem = entry_id(sop_instance_uid)
        return SpoolEntry(stem, self.instances / f"{stem}.dcm", sop_instance_uid)

    def read(self, entry: SpoolEntry, pixels: bool = True) -> Dataset:
        return pydicom.dcmread(entry.path, stop_before_pixels=not pixels)

    def entries(self) -> list[SpoolEntry]:
        """Every spooled instance in the order it was received (file modification time)."""
        files = sorted(self.instances.glob("*.dcm"), key=lambda p: (p.stat().st_mtime_ns, p.name))
        out = []
        for path in files:
            uid = str(pydicom.dcmread(path, stop_before_pixels=True,
                                      specific_tags=["SOPInstanceUID"]).SOPInstanceUID)
            out.append(SpoolEntry(path.stem, path, uid))
        return out

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
