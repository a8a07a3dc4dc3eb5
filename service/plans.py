"""The plans folder: ``slamtka plan add / list / show`` and the lookup the service does.

A plan is a :class:`solver.plan.Plan` folder (``plan.json``, meshes, ``cache/``) plus
``provenance.json`` (where the meshes came from, whether the landmarks were given or
estimated, when it was imported). Folders are named ``plan-<side>-<digest of the Patient
ID>``: no patient identifier appears in a path (a listing, a backup log, a support ticket
shows none); the Patient ID lives in ``plan.json``, which the lookup reads, so folders named
the earlier way (``<id>-<side>-<digest>``) are still found. ``plan add`` validates the meshes, estimates landmarks from a full-length tibia when
none are given (and says so), and builds the signed distance fields into the plan's cache,
so nothing is computed during surgery. The folder appears atomically (built beside it,
then renamed).

Landmark estimation (full-length tibia, 250-500 mm): the long axis is the principal axis
of the surface; the proximal end is the wider one (the plateau); the knee centre is the
centre of the condyles' outline, 8 mm below the top of the eminence; the ankle centre is the
midpoint of the two malleoli (the most distal points of tibia and fibula) or, without a
fibula, the centre of the distal metaphysis (a few mm medial of the true centre: give the
fibula or landmarks when it matters); the medio-lateral direction is the long axis of the
plateau outline, made lateral by the fibula (or, without one, anterior is where the tibial
tuberosity protrudes).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import re
import shutil
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from slamtka.solver.anatomy import Landmarks
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.plan import BONE_EXTENT_MM, DEFAULT_SEGMENTATION_SD_MM, Plan, Target, check_layout
from slamtka.solver.surface import Surface

if TYPE_CHECKING:
    import trimesh

__all__ = ["PlanFinder", "PlanStore", "PlanSummary", "estimate_landmarks", "add_plan_parser",
           "LATERALITY_TO_SIDE"]

log = logging.getLogger("slamtka.plans")

LATERALITY_TO_SIDE = {"L": "left", "R": "right"}
_FULL_LENGTH_MM = (250.0, 500.0)
_PLATEAU_SLAB_MM = (5.0, 20.0)  # below the most proximal point: the condyles' outline
_EMINENCE_MM = 8.0  # the intercondylar eminence rises about this far above the plateau
_DISTAL_SLAB_MM = (10.0, 25.0)  # above the malleolus tip: the distal metaphysis
_TUBEROSITY_BAND_MM = (30.0, 60.0)


@dataclass(frozen=True)
class PlanSummary:
    folder: Path
    patient_id: str
    side: str
    target: dict
    landmarks: str  # "given" or "estimated"
    imported: str
    # Why the folder cannot be read (file and problem); the other fields are then unknown.
    error: str | None = None


def _read_summary(folder: Path) -> PlanSummary:
    """What ``plan list`` and the lookup need of one plan folder; ValueError naming the file."""
    doc = read_json_object(folder / "plan.json")
    provenance_path = folder / "provenance.json"
    prov = read_json_object(provenance_path) if provenance_path.is_file() else {}
    target = doc.get("target", {})
    if not isinstance(target, dict):
        raise ValueError(f"{folder / 'plan.json'}: target is not a JSON object")
    return PlanSummary(folder, str(doc.get("patient_id")), str(doc.get("side")), target,
                       str(prov.get("landmarks", "given")), str(prov.get("imported", "")))


def _frame_coords(points: np.ndarray, origin: np.ndarray, axes: np.ndarray) -> np.ndarray:
    return (points - origin) @ axes.T


def _bbox_centre(coords: np.ndarray) -> np.ndarray:
    return 0.5 * (coords.min(axis=0) + coords.max(axis=0))


def _surface_in(slab: np.ndarray, where: str) -> np.ndarray:
    """``slab`` (a face mask), refused when it holds too few faces to measure: a mesh that is
    not a tibia (a box, say) has nothing there, and the estimate would divide by zero."""
    if np.count_nonzero(slab) < 3:
        raise ValueError(f"the mesh has no surface {where}: it does not look like a tibia, "
                         "so landmarks cannot be estimated; give --landmarks")
    return slab


def estimate_landmarks(tibia: trimesh.Trimesh, fibula: trimesh.Trimesh | None,
                       side: str) -> Landmarks:
    """Knee centre, ankle centre and anterior direction of a full-length tibia (mm).

    Surface points are face centroids weighted by face area, so the tessellation does not
    bias them.
    """
    points, areas = tibia.triangles_center, tibia.area_faces
    centre = (points * areas[:, None]).sum(axis=0) / areas.sum()
    axis = np.linalg.eigh(np.cov((points - centre).T, aweights=areas))[1][:, -1]
    s = (points - centre) @ axis
    length = float(np.ptp(s))
    if not _FULL_LENGTH_MM[0] <= length <= _FULL_LENGTH_MM[1]:
        raise ValueError(f"the tibia mesh is {length:.0f} mm long: landmarks can only be "
                         f"estimated from a full-length tibia ({_FULL_LENGTH_MM[0]:.0f}-"
                         f"{_FULL_LENGTH_MM[1]:.0f} mm); give --landmarks")

    def across(mask: np.ndarray) -> np.ndarray:
        p = points[mask] - centre
        return p - np.outer(p @ axis, axis)

    if np.ptp(across(s > s.max() - 20.0), axis=0).max() < np.ptp(across(s < s.min() + 20.0),
                                                                    axis=0).max():
        axis, s = -axis, -s  # the wider end (the plateau) is proximal
    top, bottom = float(s.max()), float(s.min())
    plateau = _surface_in((s < top - _PLATEAU_SLAB_MM[0]) & (s > top - _PLATEAU_SLAB_MM[1]),
                          "where the tibial plateau should be")
    ml = np.linalg.eigh(np.cov(across(plateau).T, aweights=areas[plateau]))[1][:, -1]
    ml -= np.dot(ml, axis) * axis
    ml /= np.linalg.norm(ml)
    ap = np.cross(axis, ml)
    axes = np.array([ml, ap])
    knee_xy = _bbox_centre(_frame_coords(points[plateau], centre, axes))
    knee = centre + axis * (top - _EMINENCE_MM) + knee_xy @ axes
    if fibula is not None:
        f_points = fibula.triangles_center
        lateral_tip = f_points[np.argmin((f_points - centre) @ axis)]
        ankle = 0.5 * (points[np.argmin(s)] + lateral_tip)  # midpoint of the malleoli
    else:
        distal = _surface_in((s > bottom + _DISTAL_SLAB_MM[0]) & (s < bottom + _DISTAL_SLAB_MM[1]),
                             "where the distal metaphysis should be")
        ankle_xy = _bbox_centre(_frame_coords(points[distal], centre, axes))
        ankle = centre + axis * (bottom + _DISTAL_SLAB_MM[0]) + ankle_xy @ axes
    z = (knee - ankle) / np.linalg.norm(knee - ankle)
    if fibula is not None:
        lateral = ml * np.sign(np.dot(fibula.triangles_center.mean(axis=0) - knee, ml))
        right = lateral if side == "right" else -lateral  # anatomical +x: the patient's right
        anterior = np.cross(z, right)
    else:
        band = _surface_in((s < top - _TUBEROSITY_BAND_MM[0]) & (s > top - _TUBEROSITY_BAND_MM[1]),
                           "where the tibial tuberosity should be")
        offsets = _frame_coords(points[band], centre, axes)[:, 1] - knee_xy[1]
        anterior = ap if offsets.max() > -offsets.min() else -ap
    return Landmarks(knee, ankle, anterior, side)


def _folder_name(patient_id: str, side: str) -> str:
    return f"plan-{side}-{hashlib.sha256(patient_id.encode()).hexdigest()[:16]}"


class PlanFinder(Protocol):
    """What a run needs of its plans: a :class:`PlanStore`, or ``slamtka measure``'s one plan."""

    def find(self, patient_id: str, laterality: str | None) -> Plan:
        ...


class PlanStore:
    """Plans by Patient ID and side, with an in-memory cache of loaded plans (and their SDFs)."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self._loaded: dict[Path, tuple[float, Plan]] = {}

    def folder(self, patient_id: str, side: str) -> Path:
        return self.root / _folder_name(patient_id, side)

    def summaries(self) -> list[PlanSummary]:
        """Every plan folder, an unreadable one with its ``error`` (and a warning) so that one
        damaged plan never hides the others. Dot folders (``.staging-*`` left by an
        interrupted import) are not plans."""
        out = []
        for doc_path in sorted(self.root.glob("*/plan.json")):
            folder = doc_path.parent
            if folder.name.startswith("."):
                continue
            try:
                out.append(_read_summary(folder))
            except ValueError as exc:
                log.warning("plan folder %s is unreadable and skipped: %s", folder, exc)
                out.append(PlanSummary(folder, "?", "?", {}, "", "", error=str(exc)))
        return out

    def find(self, patient_id: str, laterality: str | None) -> Plan:
        """The plan for this patient and side (L/R); without a laterality, the patient's only
        plan. ValueError says what is missing, ambiguous or unreadable."""
        summaries = self.summaries()
        sides = LATERALITY_TO_SIDE.values() if laterality is None else [LATERALITY_TO_SIDE[laterality]]
        own = {_folder_name(patient_id, side) for side in sides}
        for s in summaries:
            if s.error is not None and s.folder.name in own:
                raise ValueError(f"the plan of patient {patient_id!r} is unreadable: {s.error}")
        mine = [s for s in summaries if s.error is None and s.patient_id == patient_id]
        if laterality is not None:
            side = LATERALITY_TO_SIDE[laterality]
            mine = [s for s in mine if s.side == side]
            if not mine:
                raise ValueError(f"no plan for patient {patient_id!r}, {side} side")
        elif len(mine) != 1:
            raise ValueError(f"no plan for patient {patient_id!r}" if not mine else
                             f"patient {patient_id!r} has plans for both sides and the images "
                             "carry no laterality")
        return self.load(mine[0].folder)

    def load(self, folder: Path) -> Plan:
        """A plan with its models built, reloaded only when its plan.json changed."""
        stamp = (folder / "plan.json").stat().st_mtime
        cached = self._loaded.get(folder)
        if cached is None or cached[0] != stamp:
            plan = Plan.load(folder)
            plan.bone_model()
            plan.pin_model()
            self._loaded[folder] = (stamp, plan)
        return self._loaded[folder][1]

    def add(self, plan: Plan, provenance: dict, replace: bool = False) -> Path:
        """Save ``plan`` with its precomputed models; the folder appears complete or not at all."""
        final = self.folder(plan.patient_id, plan.side)
        if final.exists() and not replace:
            raise ValueError(f"a plan for patient {plan.patient_id!r}, {plan.side} side exists "
                             f"({final}); use --replace")
        self.root.mkdir(parents=True, exist_ok=True)
        staging = self.root / f".staging-{uuid.uuid4().hex}"
        try:
            plan.save(staging)
            saved = Plan.load(staging)  # what the service will load, models cached beside it
            saved.bone_model()
            saved.pin_model()
            (staging / "provenance.json").write_text(json.dumps(provenance, indent=2))
            if final.exists():
                shutil.rmtree(final)
            staging.rename(final)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return final


# -- command line -----------------------------------------------------------------------------

def _store(args: argparse.Namespace) -> PlanStore:
    if args.plans is not None:
        return PlanStore(args.plans)
    from slamtka.service.config import load_config

    return PlanStore(load_config(args.config).plans)


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _segmentation_mm(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 5.0:
        raise argparse.ArgumentTypeError(f"segmentation error {value} mm is outside [0, 5] mm")
    return value


# DICOM's Patient ID (VR LO): up to 64 characters, no control characters, no backslash.
_PATIENT_ID = re.compile(r"^[\x20-\x5b\x5d-\x7e]{1,64}$")


def _patient_id(text: str) -> str:
    """A Patient ID as images will carry it: a plan under any other could never be found."""
    if not _PATIENT_ID.match(text) or not text.strip():
        raise argparse.ArgumentTypeError(
            f"patient ID {text!r} is not a DICOM Patient ID (1-64 printable characters, "
            "not blank, no backslash)")
    return text


def cmd_plan_add(args: argparse.Namespace) -> int:
    from slamtka.solver.meshes import load_mesh  # trimesh (~1 s to import): only `plan add` reads meshes

    tibia_mesh = load_mesh(args.tibia, BONE_EXTENT_MM)
    fibula_mesh = None if args.fibula is None else load_mesh(args.fibula, BONE_EXTENT_MM)
    if args.landmarks is not None:
        landmarks = Landmarks.load(args.landmarks)
        if landmarks.side != args.side:
            raise ValueError(f"--side {args.side} differs from the landmarks' side {landmarks.side}")
        how = "given"
    else:
        try:
            landmarks = estimate_landmarks(tibia_mesh, fibula_mesh, args.side)
        except ValueError as exc:
            raise ValueError(f"{args.tibia}: {exc}") from None
        how = "estimated"
        print("landmarks were not given: estimated from the full-length tibia "
              f"(knee centre {np.round(landmarks.knee_centre, 1).tolist()} mm, ankle centre "
              f"{np.round(landmarks.ankle_centre, 1).tolist()} mm); check them with "
              "`slamtka plan show`")
    tibia = Surface.of(tibia_mesh)
    fibula = None if fibula_mesh is None else Surface.of(fibula_mesh)
    check_layout(tibia, fibula, landmarks, str(args.fibula),
                 str(args.landmarks) if args.landmarks is not None else "estimated landmarks")
    target = Target(args.target_ctr, args.target_str, args.tolerance)
    spec = PinSpec()
    plan = Plan(tibia, fibula, landmarks, build_pin(spec), spec, target, args.patient_id,
                segmentation_sd_mm=args.segmentation_mm)
    provenance = {
        "imported": datetime.now(UTC).isoformat(timespec="seconds"),
        "landmarks": how,
        "sources": {name: {"file": str(Path(p).resolve()), "sha256": _sha256(p)}
                    for name, p in (("tibia", args.tibia), ("fibula", args.fibula),
                                    ("landmarks", args.landmarks)) if p is not None},
    }
    folder = _store(args).add(plan, provenance, replace=args.replace)
    print(f"plan for patient {args.patient_id} ({args.side}) saved to {folder}")
    return 0


def cmd_plan_list(args: argparse.Namespace) -> int:
    summaries = _store(args).summaries()
    if not summaries:
        print("no plans")
    for s in summaries:
        if s.error is not None:
            print(f"{'?':24s} unreadable: {s.error}")
            continue
        print(f"{s.patient_id:24s} {s.side:6s} CTR {s.target.get('ctr_deg', 0):+.1f} "
              f"STR {s.target.get('str_deg', 0):+.1f} +-{s.target.get('tolerance_deg', 0):.1f} deg  "
              f"landmarks {s.landmarks:9s} {s.folder.name}")
    return 0


def cmd_plan_show(args: argparse.Namespace) -> int:
    store = _store(args)
    side = {"left": "L", "right": "R", None: None}[args.side]
    plan = store.find(args.patient_id, side)
    folder = plan.folder
    assert folder is not None, "a stored plan is loaded from its folder"
    provenance_path = folder / "provenance.json"
    prov = json.loads(provenance_path.read_text()) if provenance_path.is_file() else {}
    lm = plan.landmarks
    lines = [
        f"patient {plan.patient_id}, {plan.side} side   ({folder})",
        f"  tibia: {len(plan.tibia.faces)} triangles, extent "
        f"{np.round(plan.tibia.extents, 1).tolist()} mm"
        + ("" if plan.fibula is None else f"; fibula: {len(plan.fibula.faces)} triangles")
        + f"; segmentation error {plan.segmentation_sd_mm:.2f} mm (SD)",
        f"  landmarks ({prov.get('landmarks', 'given')}): knee centre "
        f"{np.round(lm.knee_centre, 1).tolist()}, ankle centre {np.round(lm.ankle_centre, 1).tolist()}, "
        f"mechanical axis {np.linalg.norm(lm.knee_centre - lm.ankle_centre):.0f} mm",
        f"  target: CTR {plan.target.ctr_deg:+.1f} deg, STR {plan.target.str_deg:+.1f} deg, "
        f"tolerance +-{plan.target.tolerance_deg:.1f} deg",
        f"  pin: {'parametric ' + json.dumps(vars(plan.pin_spec)) if plan.pin_spec else 'custom mesh'}"
        f", length {plan.pin_length():.1f} mm",
        f"  imported {prov.get('imported', 'unknown')}; cache: "
        f"{sum(1 for _ in (folder / 'cache').glob('*'))} file(s)",
    ]
    print("\n".join(lines))
    return 0


def add_plan_parser(sub: argparse._SubParsersAction) -> None:
    plan = sub.add_parser("plan", help="pre-operative plans: add, list, show")
    actions = plan.add_subparsers(dest="plan_command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        where = p.add_mutually_exclusive_group(required=True)
        where.add_argument("--plans", type=Path, help="plans folder")
        where.add_argument("--config", type=Path, help="service configuration (its plans folder)")

    p = actions.add_parser("add", help="import a plan (meshes, landmarks, target)")
    common(p)
    p.add_argument("--patient-id", type=_patient_id, required=True)
    p.add_argument("--side", choices=("left", "right"), required=True)
    p.add_argument("--tibia", type=Path, required=True, help="tibia mesh (STL/PLY/OBJ)")
    p.add_argument("--fibula", type=Path, help="fibula mesh")
    p.add_argument("--landmarks", type=Path, help="landmarks JSON (estimated when omitted)")
    p.add_argument("--target-ctr", type=float, default=Target.ctr_deg, help="planned CTR, deg")
    p.add_argument("--target-str", type=float, default=Target.str_deg, help="planned STR, deg")
    p.add_argument("--tolerance", type=float, default=Target.tolerance_deg, help="deg")
    p.add_argument("--segmentation-mm", type=_segmentation_mm, default=DEFAULT_SEGMENTATION_SD_MM,
                   help="SD of the bone surface's segmentation error, mm (its share of each "
                        "result's uncertainty)")
    p.add_argument("--replace", action="store_true", help="replace an existing plan")
    p.set_defaults(func=cmd_plan_add)

    p = actions.add_parser("list", help="list the plans")
    common(p)
    p.set_defaults(func=cmd_plan_list)

    p = actions.add_parser("show", help="describe one plan")
    common(p)
    p.add_argument("--patient-id", required=True)
    p.add_argument("--side", choices=("left", "right"))
    p.set_defaults(func=cmd_plan_show)
