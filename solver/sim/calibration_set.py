"""A simulated phantom set as a C-arm sends it (``slamtka simulate --calibration-images N``).

Writes into a folder what a technician would collect to calibrate the simulated C-arm (the
same camera and intensifier as ``slamtka simulate --images`` renders cases with, and the
same Device Serial Number): XA DICOM frames of a ball plate whose balls sit off the perfect
grid, with dark specks (one where the grid would continue) and a ball missing, one frame
without the phantom and one byte copy of a frame; plus ``truth.json`` (the true camera,
distortion and plate) to compare a calibration against.
"""

from __future__ import annotations

import json
import shutil
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from pydicom.uid import generate_uid

from slamtka.service.frames import Frame, encode_frame
from slamtka.sim.plate_images import plate_offsets, simulate_phantom_set
from slamtka.sim.simulate import DETECTOR_FIELD_MM, SOURCE_TO_DETECTOR_MM, default_camera
from slamtka.sim.xray import default_distortion
from slamtka.solver.imaging.plate import PhantomSpec

__all__ = ["write_calibration_set", "PLATE_ERROR_MM"]

PLATE_ERROR_MM = 0.15  # RMS offset of the simulated plate's balls from the perfect grid
_MISSING_BALL = 6  # a ball lost from the plate (row 1, column 1)


def write_calibration_set(folder: Path, count: int, seed: int) -> list[Path]:
    """``count`` phantom frames plus an empty frame and a duplicate; returns the paths."""
    if count < 1:
        raise ValueError(f"--calibration-images must be at least 1, got {count}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    camera = default_camera()
    distortion = default_distortion(camera)
    spec = PhantomSpec()
    rng = np.random.default_rng(seed)
    phantom = simulate_phantom_set(camera, distortion, spec, count, rng,
                                   plate_offsets(spec, PLATE_ERROR_MM, rng), missing_balls=(_MISSING_BALL,),
                                   specks=2, empty_frames=1)
    spacing = DETECTOR_FIELD_MM / camera.width
    study, series = generate_uid(), generate_uid()
    start = datetime.now(UTC)
    paths = []
    for k, (name, image) in enumerate(zip(phantom.names, phantom.images)):
        frame = Frame(image, (spacing, spacing), sid_mm=SOURCE_TO_DETECTOR_MM,
                      acquisition_datetime=start + timedelta(seconds=5 * k), patient_id="PHANTOM",
                      patient_name="CALIBRATION^PHANTOM", study_uid=study, series_uid=series,
                      bits_stored=12, instance_number=k + 1)
        path = folder / f"{name}.dcm"
        encode_frame(frame, intensifier_size_mm=DETECTOR_FIELD_MM).save_as(path, enforce_file_format=True)
        paths.append(path)
    copy = folder / "resent-img00.dcm"
    shutil.copyfile(paths[0], copy)  # sent twice, as happens
    paths.append(copy)
    (folder / "truth.json").write_text(json.dumps({
        "camera": camera.to_json(), "distortion": distortion.to_json(), "phantom": spec.to_json(),
        "plate_error_rms_mm": PLATE_ERROR_MM, "missing_ball": [_MISSING_BALL % spec.cols, _MISSING_BALL // spec.cols],
        "plate_mm": [[None if np.isnan(v) else round(float(v), 4) for v in p] for p in phantom.plate_mm],
        "notes": {**phantom.notes, copy.stem: "byte copy of img00"}}, indent=2))
    return paths
