"""Legal but unusual pixel layouts of one X-ray frame, with what each must decode to.

Tooling for the tests and ``slamtka bench hardening``: the same 12-bit image stored with its
bits high in the word, with overlay bits above them, as signed values, in 8 or 16 bits, and
with each way DICOM says "inverted" (MONOCHROME1, Presentation LUT Shape INVERSE, Pixel
Intensity Relationship Sign -1); and layouts the decoder must refuse by name. A decoder
that ignores BitsStored/HighBit or an inversion attribute returns noise or a negative.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydicom.dataset import Dataset

__all__ = ["LayoutCase", "layout_cases"]


@dataclass
class LayoutCase:
    name: str
    dataset: Dataset
    expected: np.ndarray | None  # the decoded pixels, or None: refused
    error: str = ""  # for a refusal, a word the error must contain


def _variant(ds: Dataset, words: np.ndarray, **attributes) -> Dataset:
    out = copy.deepcopy(ds)
    for keyword, value in attributes.items():
        setattr(out, keyword, value)
    dtype = "<u1" if int(out.BitsAllocated) == 8 else "<u2"
    out.PixelData = np.ascontiguousarray(words, dtype=dtype).tobytes()
    return out


def layout_cases(ds: Dataset, seed: int = 0) -> list[LayoutCase]:
    """Cases made from ``ds``: an uncompressed MONOCHROME2 frame with 12 bits stored."""
    if int(ds.BitsStored) != 12 or int(ds.BitsAllocated) != 16:
        raise ValueError("layout cases are made from a 12-bit frame in 16-bit words")
    v = np.frombuffer(ds.PixelData, "<u2").reshape(int(ds.Rows), int(ds.Columns)).astype(np.int64)
    garbage = np.random.default_rng(seed).integers(0, 1 << 16, v.shape)
    signed = v - 2048  # the same image as two's complement values, offset binary on decode
    high = dict(HighBit=15)
    # (name, stored words, attributes changed, the pixels decoded or the refusal's keyword)
    cases: list[tuple[str, np.ndarray, dict[str, Any], np.ndarray | str]] = [
        ("12 bits stored, overlay bits above HighBit 11", v | (garbage & 0xF000), {}, v),
        ("12 bits stored in the high bits (HighBit 15)", v << 4 | garbage & 0xF, high, v),
        ("12 bits stored at HighBit 13, garbage either side",
         v << 2 | garbage & 0xC003, dict(HighBit=13), v),
        ("signed 12 bits, sign-extended", signed & 0xFFFF, dict(PixelRepresentation=1), v),
        ("signed 12 bits at HighBit 15", (signed & 0xFFF) << 4,
         dict(PixelRepresentation=1, **high), v),
        ("8 bits allocated and stored", v >> 4,
         dict(BitsAllocated=8, BitsStored=8, HighBit=7), v >> 4),
        ("16 bits stored", v << 4, dict(BitsStored=16, HighBit=15), v << 4),
        ("MONOCHROME1", 4095 - v, dict(PhotometricInterpretation="MONOCHROME1"), v),
        ("MONOCHROME2 with Presentation LUT Shape INVERSE", 4095 - v,
         dict(PresentationLUTShape="INVERSE"), v),
        ("MONOCHROME1 with Presentation LUT Shape INVERSE (as DX pairs them)", 4095 - v,
         dict(PhotometricInterpretation="MONOCHROME1", PresentationLUTShape="INVERSE"), v),
        ("Pixel Intensity Relationship Sign -1", 4095 - v,
         dict(PixelIntensityRelationshipSign=-1), v),
        ("MONOCHROME1 with Pixel Intensity Relationship Sign +1", v,
         dict(PhotometricInterpretation="MONOCHROME1", PixelIntensityRelationshipSign=1), v),
        ("HighBit 10 below BitsStored 12", v, dict(HighBit=10), "HighBit"),
        ("HighBit 16 outside the 16-bit word", v, dict(HighBit=16), "HighBit"),
        ("Pixel Intensity Relationship Sign 0", v, dict(PixelIntensityRelationshipSign=0),
         "PixelIntensityRelationshipSign"),
        ("Presentation LUT Shape LIN OD", v, dict(PresentationLUTShape="LIN OD"),
         "PresentationLUTShape"),
    ]
    return [LayoutCase(name, _variant(ds, words, **attributes),
                       None if isinstance(outcome, str) else outcome.astype(np.uint16),
                       outcome if isinstance(outcome, str) else "")
            for name, words, attributes, outcome in cases]
