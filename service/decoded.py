"""Each received instance decoded once: its facts beside it in the spool, its frame in memory.

The receiver must decode an instance to validate it (pixel data and header checks; JPEG
Lossless decompression when compressed), so that decoding is the only one: the frame's
header facts (:class:`FrameHeader`) go into the instance's sidecar, written crash-safely with
it before the C-STORE is acknowledged, and the decoded frame is handed to the worker in
memory (:meth:`DecodedFrames.keep`). The case assembler reads the facts, the pipeline and
the status objects the frame; none decodes the instance again.

The frames are kept in a small cache by instance digest (the spool entry's id), least
recently used first out, because pixels are large (2 MB for 1024 x 1024, 8 MB for 2048 x
2048) and a burst of receipts must not grow the process without bound: at most
``MAX_FRAMES`` frames and ``MAX_BYTES`` of pixels (the newest frame is always kept). That
holds a run's views (``pipeline.max_views``, 6 by default) and the views just received for
frames up to 1024 x 1024, so on the normal path each instance's pixels are decoded once per
process; of larger frames fewer are kept (the allocator keeps two to three times what is
held resident: ``bench hardening --only burst_memory``). A frame no longer cached
(after a restart, or pushed out) is rebuilt from the sidecar's facts and a pixel-only read
of the spooled file (:func:`decode_pixels`), never by decoding its header again.

A spool written before the facts were kept (a sidecar with the pairing alone, or none) is
decoded once, fully, and its sidecar rewritten with the facts. The sidecar also records the
instance file's size, so a spooled file truncated since its receipt is still refused at
start-up (and quarantined) without decoding its pixels.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pydicom.dataset import Dataset

from slamtka.service.frames import Frame, FrameError, FrameHeader, decode_frame, decode_pixels

if TYPE_CHECKING:
    from slamtka.service.spool import Spool, SpoolEntry

__all__ = ["MAX_FRAMES", "MAX_BYTES", "Decoded", "DecodedFrames", "sidecar_of"]

MAX_FRAMES = 16
MAX_BYTES = 32 << 20
_FRAME, _PAIRING, _BYTES = "frame", "pairing", "instance_bytes"


@dataclass(frozen=True)
class Decoded:
    """One decoded instance: its frame, and its header without pixel data (what chooses the
    calibration and what the SR and SC repeat of it)."""

    frame: Frame
    header: Dataset


def sidecar_of(header: FrameHeader, instance_bytes: int, pairing: dict | None = None) -> dict:
    """The sidecar document of an instance: its facts, its file's size, its pairing."""
    doc = {_FRAME: header.to_json(), _BYTES: instance_bytes}
    return doc if pairing is None else {**doc, _PAIRING: pairing}


def _parts(doc: dict | None) -> tuple[FrameHeader | None, int | None, dict | None]:
    """(facts, file size, pairing) of a sidecar; facts None when it holds none usable."""
    if doc is None:
        return None, None, None
    if _FRAME not in doc and _PAIRING not in doc:
        return None, None, doc  # written before the facts were kept: the pairing alone
    try:
        header = FrameHeader.from_json(doc[_FRAME])
        size = int(doc[_BYTES])
    except (KeyError, TypeError, ValueError):  # another version: decoded again, rewritten
        header, size = None, None
    return header, size, doc.get(_PAIRING)


class DecodedFrames:
    """The decoded instances of one spool (one per process: the service's spool)."""

    def __init__(self, spool: Spool, max_frames: int = MAX_FRAMES, max_bytes: int = MAX_BYTES):
        self.spool, self.max_frames, self.max_bytes = spool, max_frames, max_bytes
        self._frames: OrderedDict[str, Decoded] = OrderedDict()
        self._bytes = 0  # of the pixels kept
        self._lock = threading.Lock()  # receiver threads keep, the worker gets

    def keep(self, entry: SpoolEntry, frame: Frame, header: Dataset) -> None:
        """Hand over the frame the receiver decoded (``header``: the instance without
        PixelData) to the stages after it."""
        self._remember(entry, Decoded(frame, header))

    def facts(self, entry: SpoolEntry) -> tuple[FrameHeader, dict | None]:
        """An instance's header facts and the pairing kept beside it (None: not paired yet).

        :class:`FrameError` when the spooled file is not the size it was received with."""
        header, size, pairing = _parts(self.spool.read_sidecar(entry))
        cached = self._cached(entry)
        if cached is not None:
            return cached.frame.header(), pairing
        if header is None:
            return self._decode_once(entry, pairing).frame.header(), pairing
        found = entry.path.stat().st_size
        if found != size:
            raise FrameError(f"the spooled file has {found} bytes, {size} when received")
        return header, pairing

    def get(self, entry: SpoolEntry) -> Decoded:
        """An instance's frame and header: the one in memory, else its facts and pixels."""
        cached = self._cached(entry)
        if cached is not None:
            return cached
        header, _, pairing = _parts(self.spool.read_sidecar(entry))
        if header is None:
            return self._decode_once(entry, pairing)
        ds = self.spool.read(entry)
        pixels, bits_stored = decode_pixels(ds)
        del ds.PixelData
        return self._remember(entry, Decoded(header.with_pixels(pixels, bits_stored), ds))

    def save_pairing(self, entry: SpoolEntry, header: FrameHeader, pairing: dict) -> None:
        """Keep how the frame was paired with the C-arm beside it (with its facts)."""
        self.spool.write_sidecar(entry, sidecar_of(header, entry.path.stat().st_size, pairing))

    def _decode_once(self, entry: SpoolEntry, pairing: dict | None) -> Decoded:
        """Decode an instance spooled without facts and keep them in its sidecar."""
        ds = self.spool.read(entry)
        frame = decode_frame(ds)
        del ds.PixelData
        self.spool.write_sidecar(entry, sidecar_of(frame.header(), entry.path.stat().st_size,
                                                   pairing))
        return self._remember(entry, Decoded(frame, ds))

    def _cached(self, entry: SpoolEntry) -> Decoded | None:
        with self._lock:
            found = self._frames.get(entry.id)
            if found is not None:
                self._frames.move_to_end(entry.id)
            return found

    def _remember(self, entry: SpoolEntry, decoded: Decoded) -> Decoded:
        with self._lock:
            replaced = self._frames.pop(entry.id, None)
            if replaced is not None:
                self._bytes -= replaced.frame.pixels.nbytes
            self._frames[entry.id] = decoded
            self._bytes += decoded.frame.pixels.nbytes
            while len(self._frames) > 1 and (len(self._frames) > self.max_frames
                                             or self._bytes > self.max_bytes):
                _, dropped = self._frames.popitem(last=False)
                self._bytes -= dropped.frame.pixels.nbytes
        return decoded
