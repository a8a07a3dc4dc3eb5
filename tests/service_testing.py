"""Helpers shared by the service tests: frames, free ports, throwaway TLS certificates."""

from __future__ import annotations

import datetime as dt
import socket
import sys
from collections import Counter

import numpy as np

from slamtka.bench.pki import make_pki
from slamtka.service import frames
from slamtka.service.frames import Frame

__all__ = ["free_port", "small_frame", "make_pki", "count_decoding"]


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
                  acquisition_datetime=dt.datetime.now(dt.UTC), patient_id="P-1",
                  patient_name="Doe^Jane", laterality="R", bits_stored=12)
    fields.update(changes)
    return Frame(**fields)


def count_decoding(monkeypatch) -> Counter:
    """Count calls of ``decode_frame`` and ``decode_pixels`` (the pixel-only read, which
    ``decode_frame`` also calls) wherever a loaded slamtka module holds them."""
    calls: Counter = Counter()
    for name in ("decode_frame", "decode_pixels"):
        original = getattr(frames, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        for module in list(sys.modules.values()):
            if (getattr(module, "__name__", "").startswith("slamtka.")
                    and getattr(module, name, None) is original):
                monkeypatch.setattr(module, name, counted)
    return calls
