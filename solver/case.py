"""A self-describing case folder: plan, calibration, contours, initial guess (and truth).

Layout::

    case.json            format, case id, view ids, which file holds what
    plan/                the pre-operative plan (see solver.plan)
    calibration.json     the C-arm camera (intrinsics, image and field size), id and sha256
    contours.json        per view: bone, pin1, pin2 contour pixels (undistorted)
    initial.json         per view T_cam_tibia (encoders) and per pin T_tibia_pin (plan)
    ground_truth.json    simulated cases only; the solver never reads it

The contour document is also the format for contours drawn by hand.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .geometry import Pose
from .imaging import calibration as imaging_calibration
from .observations import LABELS, ViewObservation
from .plan import Plan
from .slam import InitialGuess

__all__ = ["Case", "CASE_FORMAT", "load_case", "write_case"]

CASE_FORMAT = "slamtka-case/1"
CONTOURS_FORMAT = "slamtka-contours/1"


@dataclass
class Case:
    folder: Path
    case_id: str
    plan: Plan
    views: list[ViewObservation]
    initial: InitialGuess
    calibration_id: str


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise ValueError(f"{path}: file missing from the case folder")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None


def _load_calibration(path: Path) -> tuple[Camera, str]:
    """Camera and id of a case's calibration. Contours in a case folder are already
    undistorted, so the distortion model (needed only for raw frames) is not applied here."""
    if not path.is_file():
        raise ValueError(f"{path}: file missing from the case folder")
    calibration = imaging_calibration.load_calibration(path)
    return calibration.camera, calibration.calibration_id


def _odometry_sigma(initial_doc: dict) -> tuple[float, float] | None:
    """The encoders' relative-motion uncertainty from initial.json, if it states one."""
    sigma = initial_doc.get("odometry_sigma")
    if sigma is None:
        return None
    try:
        rot, trans = float(sigma["rot_rad"]), float(sigma["trans_mm"])
    except (KeyError, TypeError, ValueError):
        raise ValueError("initial.json: odometry_sigma needs numbers rot_rad and trans_mm") from None
    if not (rot > 0 and trans > 0):
        raise ValueError("initial.json: odometry_sigma must be positive")
    return rot, trans


def write_case(folder: Path, case_id: str, plan: Plan, views: list[ViewObservation],
               initial: InitialGuess, calibration_id: str, truth: dict | None = None) -> None:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    plan.save(folder / "plan")
    camera = views[0].camera
    if any(v.camera != camera for v in views):
        raise ValueError("all views of a case must come from one calibrated C-arm")
    (folder / "calibration.json").write_text(json.dumps(
        imaging_calibration.calibration_document(camera, calibration_id, "C-arm intrinsics"),
        indent=2))
    contours = {"format": CONTOURS_FORMAT, "units": "px", "views": [
        {"view_id": v.view_id, **{label: np.round(v.contours[label], 3).tolist() for label in LABELS}}
        for v in views]}
    (folder / "contours.json").write_text(json.dumps(contours))
    (folder / "initial.json").write_text(json.dumps({
        "views": {v.view_id: T.to_json() for v, T in zip(views, initial.T_cam_tibia)},
        "pins": [T.to_json() for T in initial.T_tibia_pin],
        "odometry_sigma": (None if initial.odometry_sigma is None else
                           {"rot_rad": initial.odometry_sigma[0], "trans_mm": initial.odometry_sigma[1]}),
    }, indent=2))
    manifest = {"format": CASE_FORMAT, "case_id": case_id, "plan": "plan",
                "calibration": "calibration.json", "contours": "contours.json",
                "initial": "initial.json", "views": [v.view_id for v in views]}
    if truth is not None:
        (folder / "ground_truth.json").write_text(json.dumps(truth, indent=2))
        manifest["ground_truth"] = "ground_truth.json"
    (folder / "case.json").write_text(json.dumps(manifest, indent=2))


def load_case(folder: Path) -> Case:
    folder = Path(folder)
    manifest = _read_json(folder / "case.json")
    if manifest.get("format") != CASE_FORMAT:
        raise ValueError(f"{folder}: case format {manifest.get('format')!r} is not {CASE_FORMAT!r}")
    plan = Plan.load(folder / manifest.get("plan", "plan"))
    camera, calibration_id = _load_calibration(folder / manifest.get("calibration", "calibration.json"))
    contours = _read_json(folder / manifest.get("contours", "contours.json"))
    if contours.get("format") != CONTOURS_FORMAT:
        raise ValueError(f"contours format {contours.get('format')!r} is not {CONTOURS_FORMAT!r}")
    initial_doc = _read_json(folder / manifest.get("initial", "initial.json"))
    views, poses = [], []
    for entry in contours.get("views", []):
        view_id = str(entry.get("view_id", ""))
        if view_id not in initial_doc.get("views", {}):
            raise ValueError(f"view {view_id!r} has contours but no initial pose in initial.json")
        views.append(ViewObservation(view_id, camera,
                                     {label: np.asarray(entry.get(label, []), float) for label in LABELS}))
        poses.append(Pose.from_json(initial_doc["views"][view_id]))
    pins = [Pose.from_json(p) for p in initial_doc.get("pins", [])]
    if len(pins) != 2:
        raise ValueError(f"initial.json must give exactly two pin poses, found {len(pins)}")
    return Case(folder, str(manifest.get("case_id", folder.name)), plan, views,
                InitialGuess(tuple(poses), (pins[0], pins[1]), _odometry_sigma(initial_doc)),
                calibration_id)
