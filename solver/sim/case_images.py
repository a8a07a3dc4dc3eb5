"""Rendered X-ray frames for a simulated case folder (``slamtka simulate --images``).

Adds to the folder written by ``solver.case.write_case``:

    frames/VIEW.dcm            each view as an XA DICOM frame from the simulated C-arm
    truth_silhouettes.json     the true outlines per view and label, raw (distorted) pixels
                               (with an operating-room scene: the nuisances, and per view
                               the indices of the outline points they hide)
    calibration.json           rewritten with the intensifier's distortion and pixel spacing

and names them in ``case.json`` (``frames``, ``truth_silhouettes``). The case's
``contours.json`` is unchanged: the frames are what a C-arm would send for the same poses.
"""

from __future__ import annotations

import json
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
from pydicom.uid import generate_uid

from slamtka.service.frames import Frame, encode_frame
from slamtka.sim.operating_room import OperatingRoom, render_room, room_bodies, room_scene
from slamtka.sim.simulate import (
    DETECTOR_FIELD_MM,
    SOURCE_TO_DETECTOR_MM,
    SOURCE_TO_ISOCENTRE_MM,
    SimulatedCase,
)
from slamtka.sim.xray import XRayParams, XRayScene, default_distortion
from slamtka.solver.imaging.calibration_file import write_calibration
from slamtka.solver.plan import Plan

__all__ = ["write_case_images"]


def write_case_images(folder: Path, plan: Plan, case: SimulatedCase, calibration_id: str,
                      seed: int, params: XRayParams = XRayParams(),
                      room: OperatingRoom | None = None, patient_name: str | None = None) -> list[Path]:
    """Render every view of ``case``, write the frames and their truth; returns the frame paths.

    ``room``: the operating-room nuisances to render (drawn from ``seed``; none: the
    idealised frames); the truth then also says which outline points they hide."""
    folder = Path(folder)
    draw = (room or OperatingRoom()).draw(seed)
    camera = draw.camera(case.views[0].camera)
    distortion = draw.distortion(camera, params.distortion or default_distortion(camera))
    params = replace(params, distortion=distortion)
    scene = room_scene(XRayScene.from_plan(plan, params), draw)
    bodies = room_bodies(plan, draw)
    rng = np.random.default_rng(seed)
    spacing = DETECTOR_FIELD_MM / camera.width
    study, series = generate_uid(), generate_uid()
    start = datetime.now(UTC)
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    paths, truth = [], {}
    for k, (view, T, angle) in enumerate(zip(case.views, case.truth_T_cam_tibia,
                                             case.config.view_angles_deg)):
        rendered = render_room(plan, T, case.truth_T_tibia_pin, camera, params, draw, rng, scene, bodies)
        radiograph = rendered.radiograph
        frame = Frame(radiograph.image, (spacing, spacing), primary_angle_deg=float(angle),
                      secondary_angle_deg=0.0, sid_mm=SOURCE_TO_DETECTOR_MM,
                      sod_mm=SOURCE_TO_ISOCENTRE_MM, acquisition_datetime=start + timedelta(seconds=20 * k),
                      patient_id=plan.patient_id, patient_name=patient_name or plan.patient_id,
                      study_uid=study, series_uid=series,
                      laterality="R" if plan.side == "right" else "L",
                      bits_stored=radiograph.bits_stored if draw.processing is None
                      else draw.processing["bits"], instance_number=k + 1)
        path = folder / "frames" / f"{view.view_id}.dcm"
        encode_frame(frame).save_as(path, enforce_file_format=True)
        paths.append(path)
        truth[view.view_id] = {label: np.round(points, 3).tolist()
                               for label, points in radiograph.silhouettes.items()}
        if room is not None and room.names:
            truth[view.view_id]["hidden"] = {label: np.flatnonzero(h).tolist()
                                             for label, h in rendered.hidden.items()}
    (folder / "truth_silhouettes.json").write_text(json.dumps(
        {"format": "slamtka-contours/1", "units": "px", "coordinates": "raw",
         "nuisances": room.names if room is not None else [],
         "views": [{"view_id": v, **labels} for v, labels in truth.items()]}))
    detector = "flat-panel detector" if draw.room.flat_panel else "image-intensifier distortion"
    write_calibration(folder / "calibration.json", camera, distortion, f"simulated C-arm with {detector}",
                      calibration_id, (spacing, spacing))
    manifest_path = folder / "case.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["frames"] = {v.view_id: f"frames/{v.view_id}.dcm" for v in case.views}
    manifest["truth_silhouettes"] = "truth_silhouettes.json"
    manifest_path.write_text(json.dumps(manifest, indent=2))
    return paths
