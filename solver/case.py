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

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.imaging import calibration_file
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.observations import LABELS, ViewObservation
from slamtka.solver.plan import Plan
from slamtka.solver.problem import InitialGuess

__all__ = ["CaseFolder", "CASE_FORMAT", "load_case", "write_case"]

CASE_FORMAT = "slamtka-case/1"
CONTOURS_FORMAT = "slamtka-contours/1"


@dataclass
class CaseFolder:
    """A case read from its folder (plan, views, initial poses): what `slamtka solve` measures;
    the service's cases being assembled from DICOM frames are :class:`slamtka.service.cases.Case`."""

    folder: Path
    case_id: str
    plan: Plan
    views: list[ViewObservation]
    initial: InitialGuess
    calibration_id: str


# Contour points may lie this far outside the image (undistortion moves rim points outwards);
# beyond it they would be silently dropped from the distance maps, so the file is refused.
CONTOUR_MARGIN_PX = 64.0


def _part(folder: Path, manifest: dict, key: str, default: str) -> Path:
    """Path of the case part that case.json names under ``key``."""
    name = manifest.get(key, default)
    if not isinstance(name, str) or not name:
        raise ValueError(f"{folder / 'case.json'}: {key!r} must be a file name, got {name!r}")
    return folder / name


def _pose(path: Path, what: str, rows) -> Pose:
    """A pose read from ``path``: a finite 4x4 rigid transform (a NaN would only surface
    deep in the solver as an unrelated numpy error)."""
    try:
        M = np.asarray(rows, dtype=float)
        if M.shape == (4, 4) and not np.all(np.isfinite(M)):
            raise ValueError("has non-finite entries")
        return Pose.from_matrix(M)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {what}: not a valid pose ({exc})") from None


def _flag(path: Path, view_id: str, entry: dict, key: str) -> bool:
    """An optional true/false of a view's contours entry (false when absent)."""
    value = entry.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"{path}: view {view_id!r}: {key!r} must be true or false, not {value!r}")
    return value


def _contour(path: Path, view_id: str, label: str, value, camera: Camera) -> np.ndarray:
    """A contour's pixels as a float array; numbers only, within the image (with a margin)."""
    try:
        pts = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: view {view_id!r}: {label} contour must be a list of "
                         "(u, v) number pairs") from None
    if pts.size and pts.ndim == 2 and pts.shape[1] == 2 and np.all(np.isfinite(pts)):
        low = pts.min(axis=0) < -CONTOUR_MARGIN_PX
        high = pts.max(axis=0) > np.array([camera.width, camera.height]) - 1 + CONTOUR_MARGIN_PX
        if np.any(low) or np.any(high):
            raise ValueError(f"{path}: view {view_id!r}: {label} contour has points outside the "
                             f"{camera.width}x{camera.height} image")
    return pts


def _load_calibration(path: Path) -> tuple[Camera, str]:
    """Camera and id of a case's calibration. Contours in a case folder are already
    undistorted, so the distortion model (needed only for raw frames) is not applied here."""
    if not path.is_file():
        raise ValueError(f"{path}: file missing from the case folder")
    calibration = calibration_file.load_calibration(path)
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
        calibration_file.calibration_document(camera, calibration_id, "C-arm intrinsics"),
        indent=2))
    contours = {"format": CONTOURS_FORMAT, "units": "px", "views": [
        {"view_id": v.view_id, **{label: np.round(v.contours[label], 3).tolist() for label in LABELS},
         **({"pins_opaque": True} if v.pins_opaque else {})}
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


def load_case(folder: Path) -> CaseFolder:
    folder = Path(folder)
    manifest = read_json_object(folder / "case.json")
    if manifest.get("format") != CASE_FORMAT:
        raise ValueError(f"{folder}: case format {manifest.get('format')!r} is not {CASE_FORMAT!r}")
    plan = Plan.load(_part(folder, manifest, "plan", "plan"))
    camera, calibration_id = _load_calibration(_part(folder, manifest, "calibration", "calibration.json"))
    contours_path = _part(folder, manifest, "contours", "contours.json")
    contours = read_json_object(contours_path)
    if contours.get("format") != CONTOURS_FORMAT:
        raise ValueError(f"{contours_path}: contours format {contours.get('format')!r} "
                         f"is not {CONTOURS_FORMAT!r}")
    initial_path = _part(folder, manifest, "initial", "initial.json")
    initial_doc = read_json_object(initial_path)
    entries, initial_views = contours.get("views", []), initial_doc.get("views", {})
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ValueError(f"{contours_path}: 'views' must be a list of objects, one per view")
    if not isinstance(initial_views, dict):
        raise ValueError(f"{initial_path}: 'views' must be an object mapping view id to pose")
    views: list[ViewObservation] = []
    poses: list[Pose] = []
    for entry in entries:
        view_id = str(entry.get("view_id", ""))
        if view_id not in initial_views:
            raise ValueError(f"view {view_id!r} has contours but no initial pose in initial.json")
        if any(v.view_id == view_id for v in views):
            raise ValueError(f"{contours_path}: view {view_id!r} is given twice")
        unknown = sorted(set(entry) - {"view_id", "pins_opaque", *LABELS})
        if unknown:
            raise ValueError(f"{contours_path}: view {view_id!r}: unknown contour labels {unknown} "
                             f"(the labels are {', '.join(LABELS)})")
        pixels = {label: _contour(contours_path, view_id, label, entry.get(label, []), camera)
                  for label in LABELS}
        try:
            views.append(ViewObservation(view_id, camera, pixels,
                                         pins_opaque=_flag(contours_path, view_id, entry, "pins_opaque")))
        except ValueError as exc:
            raise ValueError(f"{contours_path}: {exc}") from None
        poses.append(_pose(initial_path, f"view {view_id!r}", initial_views[view_id]))
    pin_docs = initial_doc.get("pins", [])
    if not isinstance(pin_docs, list):
        raise ValueError(f"{initial_path}: 'pins' must be a list of two poses")
    pins = [_pose(initial_path, f"pin {k + 1}", p) for k, p in enumerate(pin_docs)]
    if len(pins) != 2:
        raise ValueError(f"{initial_path}: must give exactly two pin poses, found {len(pins)}")
    return CaseFolder(folder, str(manifest.get("case_id", folder.name)), plan, views,
                InitialGuess(tuple(poses), (pins[0], pins[1]), _odometry_sigma(initial_doc)),
                calibration_id)
