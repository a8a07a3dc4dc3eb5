"""Compressed copies of DICOM files made with DCMTK's encoders (tests and the hardening bench).

C-arms send JPEG Lossless, JPEG-LS and RLE; the receiver must accept and decode what a real
encoder writes, not what our own code would, so the copies come from DCMTK's ``dcmcjpeg``,
``dcmcjpls`` and ``dcmcrle``, and :func:`storescu` sends them as a C-arm would, proposing
exactly the file's syntax (storescu's own options cannot propose JPEG Lossless process 14).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from pydicom.uid import UID, JPEGLossless, JPEGLosslessSV1, JPEGLSLossless, JPEGLSNearLossless, RLELossless

__all__ = ["ENCODERS", "NEAR_LOSSLESS_DEVIATION", "compress", "encoders_available", "storescu"]

NEAR_LOSSLESS_DEVIATION = 2  # JPEG-LS NEAR: the largest error per pixel
ENCODERS: dict[UID, list[str]] = {
    JPEGLossless: ["dcmcjpeg", "+el"],  # process 14, any predictor
    JPEGLosslessSV1: ["dcmcjpeg", "+e1"],  # process 14, first-order prediction
    JPEGLSLossless: ["dcmcjpls", "+el"],
    JPEGLSNearLossless: ["dcmcjpls", "+en", "+md", str(NEAR_LOSSLESS_DEVIATION), "+un"],
    RLELossless: ["dcmcrle"],
}


def encoders_available() -> bool:
    return all(shutil.which(command[0]) for command in [*ENCODERS.values(), ["storescu"]])


def compress(source: Path, syntax: str, target: Path) -> Path:
    """``source`` (an uncompressed DICOM file) re-encoded in ``syntax`` at ``target``."""
    command = [*ENCODERS[UID(syntax)], str(source), str(target)]
    out = subprocess.run(command, capture_output=True, text=True, timeout=60)
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed: {out.stderr.strip()}")
    return target


def storescu(path: Path, port: int, sop_class: str, syntax: str, calling_ae: str = "CARM1",
             called_ae: str = "SLAMTKA", host: str = "127.0.0.1") -> subprocess.CompletedProcess:
    """Send ``path`` with DCMTK's storescu, proposing only ``sop_class`` in ``syntax``."""
    config = Path(path).with_suffix(".storescu.cfg")
    config.write_text("[[TransferSyntaxes]]\n[Proposed]\n"
                      f"TransferSyntax1 = {syntax}\n\n"
                      "[[PresentationContexts]]\n[Images]\n"
                      f"PresentationContext1 = {sop_class}\\Proposed\n\n"
                      "[[Profiles]]\n[Default]\nPresentationContexts = Images\n")
    return subprocess.run(["storescu", "-aet", calling_ae, "-aec", called_ae, "--config-file",
                           str(config), "Default", host, str(port), str(path)],
                          capture_output=True, text=True, timeout=60)
