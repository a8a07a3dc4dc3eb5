"""Helpers shared by the service tests: frames, free ports, throwaway TLS certificates, result
documents."""

from __future__ import annotations

import datetime as dt
import json
import socket
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from slamtka.bench.pki import make_pki
from slamtka.service import frames
from slamtka.service.frames import Frame

__all__ = ["free_port", "small_frame", "make_pki", "count_decoding", "result_document",
           "run_result"]

_EYE = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def free_port() -> int:
    """A port nothing listens on right now (loopback)."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def run_result(folder: Path, timeout_s: float = 30.0) -> dict:
    """The ``result.json`` of a run folder, once written: the SR reaches the display before
    the run's SCs are built, and the result document is the run's last file."""
    deadline = time.monotonic() + timeout_s
    while not (folder / "result.json").is_file():
        assert time.monotonic() < deadline, f"no result.json in {folder}"
        time.sleep(0.05)
    return json.loads((folder / "result.json").read_text())


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


def _source(k: int) -> dict:
    return {"view_id": f"view{k}", "sop_instance_uid": f"1.2.3.{k}",
            "sop_class_uid": "1.2.840.10008.5.1.4.1.1.12.1", "series_instance_uid": "1.2.3",
            "acquisition_datetime": "2025-03-14T09:26:53.589793+00:00",
            "positioner": {"primary_angle_deg": -30.0, "secondary_angle_deg": 0.0,
                           "sid_mm": 1000.0, "sod_mm": 620.0},
            "initialisation": "dicom_positioner", "encoder_reading": None, "angle_check": None,
            "clock": None, "contours": "extracted", "used": True, "problem": None}


def result_document(measured: bool = True, **members) -> dict:
    """A complete result document valid under the published schema (no solve needed): a
    measured one within tolerance, or one refused by the solver; ``members`` replaced."""
    doc = {
        "format": "slamtka-result/1", "software": {"name": "slamtka", "version": "0.0.test"},
        "case_id": "case-x", "status": "measured", "reason": None,
        "sign_convention": {"CTR": "positive = varus", "STR": "positive = posterior slope",
                            "units": "degrees"},
        "angles": {"ctr_deg": 0.4, "str_deg": 5.1, "ctr_sigma_deg": 0.1, "str_sigma_deg": 0.2},
        "deviation": {"ctr_deg": 0.4, "str_deg": 2.1, "within_tolerance": True},
        "target": {"ctr_deg": 0.0, "str_deg": 3.0, "tolerance_deg": 3.0},
        "plane": {"point_tibia_mm": [0.0, 0.0, -10.0], "normal_tibia": [0.0, 0.0, 1.0],
                  "normal_anatomical": [0.0, 0.0, 1.0]},
        "poses": {"T_cam_tibia": {"view1": _EYE, "view2": _EYE}, "T_tibia_pin": [_EYE, _EYE]},
        "solver": {"method": "slam", "converged": True, "convergence_reason": "converged",
                   "start": "encoders", "iterations": 12, "seconds": 0.4,
                   "residual_rms_sigma": {"E_rp": 1.0}, "term_costs": {"E_rp": 10.0},
                   "contour_points": {"view1/bone": 300}, "edge_points": {}},
        "inputs": {"views": ["view1", "view2"], "calibration_id": "carm-1",
                   "plan": {"patient_id": "P-1", "side": "right", "bone_mesh_sha256": "cd" * 32,
                            "pin_mesh_sha256": "ef" * 32}},
        "schema_version": "1.0", "created": "2026-03-04T10:11:12.345+00:00",
        "run_id": "0123456789abcdef", "reasons": [], "refusal": None, "verdict": "pass",
        "case": {"patient_id": "P-1", "study_instance_uid": "1.2.3", "laterality": "R"},
        "sources": [_source(1), _source(2)],
        "calibration": {"id": "carm-1", "sha256": "ab" * 32},
        "initialisation": {"views": {"view1": _EYE, "view2": _EYE}, "pins": [_EYE, _EYE]},
        "timings": {"solve_s": 0.4, "total_s": 0.9},
        "outputs": {"folder": "/out", "recording": "/out/recording.rrd",
                    "sr_sop_instance_uid": "1.2.3.9",
                    "sc_sop_instance_uids": {"view1": "1.2.3.10", "view2": "1.2.3.11"}},
        "measurement": None,
    }
    if not measured:
        reason = "the two pins cannot be told apart in view view2"
        doc.update(status="not_measured", reason=reason, reasons=[reason], verdict="not_measured",
                   angles=None, deviation=None, plane=None,
                   refusal={"code": "pins_indistinct", "detail": reason, "may_restart": False})
    doc.update(members)
    return doc
