"""``slamtka replay RECORDING.rrd [--check RESULT.json] [--resolve]``: the audit, headless.

Reads a run's rerun recording with rerun's chunk reader (no viewer) and prints the case's
stages, views, contours, the solver's iterations and the final result. ``--check`` confirms
that the recording reproduces a result document: the recorded result must match it (UIDs,
calibration, status, angles, poses), and the angles recomputed from the recorded pin poses
and the recorded plan landmarks must equal its angles. ``--resolve`` goes further and re-runs
the joint solver from the recorded inputs (the plan meshes, the contours and the initial
poses as the solver received them) and compares the angles. Exit status 0 when everything
matches, 1 when something does not (each mismatch is named), 2 on unreadable input.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamtka.service.results import MeasurementResult
from slamtka.solver.anatomy import Landmarks
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose
from slamtka.solver.imaging.calibration_file import calibration_from_document
from slamtka.solver.imaging.edges import BoneEdgeSearch
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.measurement import fit_resection_plane
from slamtka.solver.observations import LABELS, ViewObservation, VisibleRegion
from slamtka.solver.pin import PinSpec, build_pin
from slamtka.solver.plan import DEFAULT_SEGMENTATION_SD_MM, Plan, Target
from slamtka.solver.slam import InitialGuess, SolverConfig, solve_joint
from slamtka.solver.surface import Surface, mesh_digest

__all__ = ["Recording", "read_recording", "check_recording", "recorded_edge_searches", "resolve_recording",
           "add_replay_parser"]

ANGLE_TOLERANCE_DEG = 1e-6  # recomputing the plane from the same poses
RESOLVE_TOLERANCE_DEG = 1e-3  # re-running the solver (floating-point summation order)
_ROW_ID = "rerun.controls.RowId"


@dataclass
class Recording:
    """What a run's recording holds, per entity path."""

    path: Path
    recording_id: str
    entities: set[str] = field(default_factory=set)
    texts: dict[str, list[str]] = field(default_factory=dict)  # TextLog lines
    documents: dict[str, dict] = field(default_factory=dict)  # JSON TextDocuments (last)
    scalars: dict[str, list[float]] = field(default_factory=dict)
    meshes: dict[str, Surface] = field(default_factory=dict)
    points: dict[str, int] = field(default_factory=dict)  # Points2D entity -> point count

    @property
    def result(self) -> dict | None:
        return self.documents.get("result/document")

    def views(self) -> list[str]:
        return sorted({e.split("/")[1] for e in self.entities if e.startswith("views/")
                       and e.endswith("/image")})


def read_recording(path: Path) -> Recording:
    from rerun.chunk import RrdReader  # here: keeps every other `slamtka` command quick to start

    from slamtka.service.recording import APPLICATION_ID

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such recording")
    try:
        reader = RrdReader(path)
        stores = reader.recordings()
        if not stores:
            raise ValueError(f"{path}: holds no recording")
        chunks = reader.stream(store=stores[0]).collect().stream()
        rec = Recording(path, stores[0].recording_id)
        if stores[0].application_id != APPLICATION_ID:
            raise ValueError(f"{path}: recorded by {stores[0].application_id!r}, not slamtka")
        # Rows in logging order: a row id (TUID) grows with the time it was logged.
        pieces: dict[tuple[str, str], list] = defaultdict(list)
        for chunk in chunks:
            entity = chunk.entity_path.lstrip("/")
            rec.entities.add(entity)
            batch = chunk.to_record_batch()
            row_ids = batch.column(_ROW_ID).to_pylist()
            for column in batch.schema.names:
                if ":" in column:
                    pieces[entity, column].extend(zip(row_ids, batch.column(column).to_pylist()))
    except (OSError, RuntimeError) as exc:
        raise ValueError(f"{path}: cannot be read as a rerun recording ({exc})") from None
    columns = {key: [v for _, v in sorted(rows, key=lambda kv: kv[0])]
               for key, rows in pieces.items()}
    for (entity, column), rows in columns.items():
        if column == "TextLog:text":
            rec.texts[entity] = [r[0] for r in rows if r]
        elif column == "TextDocument:text" and rows and rows[-1]:
            text = rows[-1][0]
            try:
                rec.documents[entity] = json.loads(text)
            except json.JSONDecodeError:
                rec.documents[entity] = {"text": text}
        elif column == "Scalars:scalars":
            rec.scalars[entity] = [r[0] for r in rows if r]
        elif column == "Points2D:positions" and rows:
            rec.points[entity] = len(rows[-1])
    for entity in rec.entities:
        vertices = columns.get((entity, "Mesh3D:vertex_positions"))
        faces = columns.get((entity, "Mesh3D:triangle_indices"))
        if vertices and faces and entity.startswith("plan/"):
            rec.meshes[entity] = Surface(np.asarray(vertices[-1], float),
                                         np.asarray(faces[-1], np.int64))
    return rec


def _recorded_plan(rec: Recording) -> tuple[Plan, dict]:
    inputs = rec.documents.get("inputs/solver")
    if inputs is None or "plan/tibia" not in rec.meshes:
        raise ValueError("the recording holds no solver inputs (the run stopped before the solve)")
    p = inputs["plan"]
    spec = PinSpec(**p["pin"]) if p["pin"] is not None else None
    pin_mesh = build_pin(spec) if spec is not None else rec.meshes["plan/pin"]
    plan = Plan(rec.meshes["plan/tibia"], rec.meshes.get("plan/fibula"),
                Landmarks.from_json(p["landmarks"]), pin_mesh, spec, Target(**p["target"]),
                p["patient_id"],
                segmentation_sd_mm=p.get("segmentation_sd_mm", DEFAULT_SEGMENTATION_SD_MM))
    return plan, inputs


def check_recording(rec: Recording, expected: MeasurementResult) -> list[str]:
    """Every way in which ``rec`` does not reproduce the result ``expected``."""
    problems = []
    if rec.result is None:
        return ["the recording holds no result document (the run did not finish)"]
    recorded = MeasurementResult.from_document(rec.result)
    for key in ("case_id", "run_id", "status", "verdict", "reason", "calibration", "case",
                "angles", "deviation", "plane", "poses", "target"):
        if getattr(recorded, key) != getattr(expected, key):
            problems.append(f"{key}: recorded {getattr(recorded, key)!r} != result "
                            f"{getattr(expected, key)!r}")
    if ([s.sop_instance_uid for s in recorded.sources]
            != [s.sop_instance_uid for s in expected.sources]):
        problems.append("source SOP Instance UIDs differ")
    if expected.angles is not None and expected.poses is not None:
        plan, _ = _recorded_plan(rec)
        plane = fit_resection_plane(expected.solved_pin_poses(), plan.pin_length(), plan.landmarks)
        for name, value in (("ctr_deg", plane.ctr), ("str_deg", plane.str_)):
            diff = abs(float(np.degrees(value)) - getattr(expected.angles, name))
            if diff > ANGLE_TOLERANCE_DEG:
                problems.append(f"{name} recomputed from the recorded pins differs by {diff:.2e} deg")
    return problems


def resolve_recording(rec: Recording) -> tuple[dict, list[str]]:
    """Re-run the solver from the recorded inputs: (angles or refusal, notes)."""
    plan, inputs = _recorded_plan(rec)
    notes = []
    if mesh_digest(plan.bone_meshes()) != inputs["plan"]["bone_mesh_sha256"]:
        notes.append("the recorded bone mesh does not match the digest of the plan that was used")
    if repr(SolverConfig()) != inputs["solver_config"]:
        notes.append("this software's solver configuration differs from the recorded one")
    camera = Camera.from_json(inputs["camera"])
    searches = recorded_edge_searches(rec)
    views = [ViewObservation(v["view_id"], camera,
                             {label: np.asarray(v[label], float).reshape(-1, 2) for label in LABELS},
                             dict(v.get("notes", {})),
                             VisibleRegion.from_json(v["bone_visible"]) if v.get("bone_visible") else None,
                             searches.get(v["view_id"]), bool(v.get("pins_opaque", False)))
             for v in inputs["views"]]
    solver = (rec.result or {}).get("solver") or {}
    if solver.get("bone_edges") == "sought near the model" and any(
            v.bone_edge_search is None for v in views):
        notes.append("the run sought the bone's edges in its frames near the model's outline; "
                     "this recording does not hold what they were sought in, so the re-run cannot")
    init = inputs["initial"]
    pin1, pin2 = (Pose.from_json(T) for T in init["T_tibia_pin"])
    initial = InitialGuess(tuple(Pose.from_json(T) for T in init["T_cam_tibia"]), (pin1, pin2),
                           None if init["odometry_sigma"] is None else tuple(init["odometry_sigma"]))
    outcome = solve_joint(plan, views, initial, SolverConfig())
    if outcome.status != "measured" or outcome.angles_deg is None:
        return {"status": outcome.status, "reason": outcome.reason}, notes
    ctr_deg, str_deg = outcome.angles_deg
    return {"status": "measured", "ctr_deg": ctr_deg, "str_deg": str_deg}, notes


def recorded_edge_searches(rec: Recording) -> dict[str, BoneEdgeSearch]:
    """Each view's bone edge search as the run recorded it (only runs that sought the
    bone's edges record them), by view id, through the run's calibration (the search maps
    the solver's undistorted outline to the frame's raw pixels)."""
    docs = rec.documents.get("inputs/bone_edge_searches") or {}
    if not docs:
        return {}
    calibration = calibration_from_document(rec.documents.get("calibration") or {},
                                            "the recorded calibration")
    return {view_id: BoneEdgeSearch.from_json(doc, calibration.distort_points, calibration.undistort_points)
            for view_id, doc in docs.items()}


def _summary(rec: Recording) -> str:
    lines = [f"recording {rec.path} ({rec.recording_id})", "stages:"]
    lines += [f"  {i}. {text}" for i, text in enumerate(rec.texts.get("pipeline/stages", []), 1)]
    for view in rec.views():
        counts = ", ".join(f"{label} {rec.points[f'views/{view}/contours/{label}']}"
                           for label in LABELS if f"views/{view}/contours/{label}" in rec.points)
        enc = rec.documents.get(f"views/{view}/encoder") or {}
        lines.append(f"  {view}: initialised from {enc.get('initialisation')}; contours "
                     f"{counts or 'none'}")
    costs = rec.scalars.get("solver/cost", [])
    if costs:
        lines.append(f"solver: {len(costs)} iterations recorded, cost {costs[0]:.4g} -> {costs[-1]:.4g}")
    result = None if rec.result is None else MeasurementResult.from_document(rec.result)
    if result is None:
        lines.append("result: none (the run did not finish)")
    elif result.angles is None:
        lines.append(f"result: {result.case_id} not measured: {result.reason}")
    else:
        a = result.angles
        lines.append(f"result: {result.case_id} CTR {a.ctr_deg:+.2f} +- {a.ctr_sigma_deg:.2f} deg, "
                     f"STR {a.str_deg:+.2f} +- {a.str_sigma_deg:.2f} deg, {result.verdict}")
    return "\n".join(lines)


def cmd_replay(args: argparse.Namespace) -> int:
    rec = read_recording(args.recording)
    print(_summary(rec))
    problems: list[str] = []
    if args.check is not None:
        expected = MeasurementResult.from_document(read_json_object(args.check))
        problems = check_recording(rec, expected)
        if args.resolve:
            again, notes = resolve_recording(rec)
            problems += notes
            if again["status"] != expected.status:
                problems.append(f"re-solved status {again['status']} != {expected.status}")
            elif expected.angles is not None:
                for name in ("ctr_deg", "str_deg"):
                    diff = abs(again[name] - getattr(expected.angles, name))
                    if diff > RESOLVE_TOLERANCE_DEG:
                        problems.append(f"re-solved {name} differs by {diff:.4f} deg")
            print(f"re-solved from the recorded inputs: {again}")
        for problem in problems:
            print(f"MISMATCH {problem}")
        print("check: the recording reproduces the result" if not problems
              else f"check: {len(problems)} mismatch(es)")
    return 1 if problems else 0


def add_replay_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="read a run's recording headless; check it against a result")
    p.add_argument("recording", type=Path, help="RECORDING.rrd")
    p.add_argument("--check", type=Path, metavar="RESULT.json",
                   help="confirm the recording reproduces this result")
    p.add_argument("--resolve", action="store_true",
                   help="with --check: also re-run the solver from the recorded inputs")
    p.set_defaults(func=cmd_replay)
