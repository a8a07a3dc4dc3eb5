"""The rerun recording of one pipeline run: every stage in its own entity path.

One ``.rrd`` file per run, written through rerun's file sink (never a viewer process).
Entity paths (the 3D scene is the tibia frame, ``world``):

- ``pipeline/stages`` — a text log line per stage, on the ``stage`` timeline
- ``calibration`` — the calibration document (JSON)
- ``views/<view>/image`` — each received frame, on the ``acquisition_time`` timeline
- ``views/<view>/positioner``, ``views/<view>/encoder`` — DICOM geometry and the paired
  encoder reading
- ``views/<view>/contours/<label>`` — extracted (or manual) contours over the image
- ``plan/<mesh>``, ``plan/landmarks`` — the plan's meshes and landmarks
- ``world/initial/<view>``, ``world/initial/<pin>`` — initial poses (as T_tibia_x)
- ``solver/cost``, ``solver/terms/<term>``, ``solver/lambda``, ``world/solver/<pose>`` —
  every solver iteration, on the ``solver_iteration`` timeline (``solver/stage`` names it)
- ``world/final/<pose>``, ``world/final/<pin>/mesh``, ``world/final/plane`` — the result
- ``result/ctr_deg``, ``result/str_deg`` and ``result/document`` — angles and the JSON result
- ``inputs/solver`` — the exact solver inputs (JSON, float64) from which ``slamtka replay
  --resolve`` re-runs the solve
- ``inputs/bone_edge_searches`` — where the solve sought the bone's edges near the model,
  each view's search (its frame's smoothed attenuation, compressed), for the same re-run

Everything a viewer shows comes with an exact JSON twin where reproduction needs it, because
rerun stores geometry as float32.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any
from weakref import WeakKeyDictionary

import numpy as np
import rerun as rr
import rerun_bindings

from slamtka.service.frames import Frame
from slamtka.solver.geometry import Pose
from slamtka.solver.optimizer import IterationInfo
from slamtka.solver.plan import Plan
from slamtka.solver.surface import Surface

__all__ = ["CaseRecorder", "APPLICATION_ID", "STAGES"]

APPLICATION_ID = "slamtka"
STAGES = ("frames", "calibration", "plan", "initial_poses", "contours", "solve",
          "plane_and_angles", "results")  # in the pipeline's order
_JSON_MEDIA = "application/json"
_LABEL_COLOURS = {"bone": (255, 220, 0), "pin1": (0, 230, 255), "pin2": (255, 60, 255)}


def _transform(T: Pose) -> rr.Transform3D:
    return rr.Transform3D(translation=T.t.astype(np.float32), mat3x3=T.R.astype(np.float32))


# Each mesh's arrays as recorded, kept while the plan is: every run records the plan's
# meshes, and trimesh's vertex normals took ~30 ms a mesh to build again.
_MESH_ARRAYS: WeakKeyDictionary[Surface, tuple[np.ndarray, np.ndarray, np.ndarray]] = \
    WeakKeyDictionary()


def _mesh(mesh: Surface, colour: tuple[int, int, int]) -> rr.Mesh3D:
    arrays = _MESH_ARRAYS.get(mesh)
    if arrays is None:
        arrays = _MESH_ARRAYS[mesh] = (np.asarray(mesh.vertices, np.float32),
                                       np.asarray(mesh.faces, np.uint32),
                                       np.asarray(mesh.to_trimesh().vertex_normals, np.float32))
    vertices, faces, normals = arrays
    return rr.Mesh3D(vertex_positions=vertices, triangle_indices=faces, vertex_normals=normals,
                     albedo_factor=colour)


class _SolverSteps:
    """The solver's iterations not yet written, by entity: (iteration, value) rows.

    They go to the file as one column per entity (``send_columns``) once the solve is over:
    logged row by row, the ~10 rerun calls of each iteration cost ~2-3 ms of the solve's
    time (80 iterations: ~0.2 s CPU)."""

    def __init__(self) -> None:
        self.texts: dict[str, list[tuple[int, str]]] = {}
        self.scalars: dict[str, list[tuple[int, float]]] = {}
        self.poses: dict[str, list[tuple[int, Pose]]] = {}

    @staticmethod
    def add(rows: dict[str, list[tuple[int, Any]]], entity: str, iteration: int, value: Any) -> None:
        rows.setdefault(entity, []).append((iteration, value))

    def send(self, rec: rr.RecordingStream, stage: int) -> None:
        """Write the kept rows, on the ``stage`` and ``solver_iteration`` timelines."""
        def indexes(rows: list) -> list[rr.TimeColumn]:
            return [rr.TimeColumn("stage", sequence=[stage] * len(rows)),
                    rr.TimeColumn("solver_iteration", sequence=[n for n, _ in rows])]

        for entity, texts in self.texts.items():
            rec.send_columns(entity, indexes(texts), rr.TextLog.columns(text=[t for _, t in texts]))
        for entity, values in self.scalars.items():
            rec.send_columns(entity, indexes(values),
                             rr.Scalars.columns(scalars=np.array([v for _, v in values], float)))
        for entity, poses in self.poses.items():
            rec.send_columns(entity, indexes(poses), rr.Transform3D.columns(
                translation=np.array([T.t for _, T in poses], np.float32),
                mat3x3=np.array([T.R for _, T in poses], np.float32)))
        self.texts, self.scalars, self.poses = {}, {}, {}


class CaseRecorder:
    """Writes one run's recording; call the stage methods in pipeline order, then close."""

    def __init__(self, path: Path, case_id: str, run_id: str):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{case_id}-{run_id}")
        self.rec.save(self.path)
        self.rec.send_recording_name(f"{case_id} run {run_id}")
        self._stage = -1
        self._iteration = 0
        self._view_ids: list[str] = []
        self._steps = _SolverSteps()

    # -- timelines ------------------------------------------------------------------------
    def stage(self, name: str, detail: str = "") -> None:
        if name not in STAGES:
            raise ValueError(f"unknown pipeline stage {name!r}")
        self._steps.send(self.rec, self._stage)
        self._stage += 1
        self.rec.reset_time()
        self.rec.set_time("stage", sequence=self._stage)
        self.rec.log("pipeline/stages", rr.TextLog(f"{name}: {detail}" if detail else name,
                                                   level=rr.TextLogLevel.INFO))

    def _json(self, path: str, doc: dict) -> None:
        self.rec.log(path, rr.TextDocument(json.dumps(doc, default=str),
                                           media_type=_JSON_MEDIA), static=True)

    # -- inputs ---------------------------------------------------------------------------
    def frame(self, view_id: str, frame: Frame, positioner: dict) -> None:
        self._view_ids.append(view_id)
        if frame.acquisition_datetime is not None:
            self.rec.set_time("acquisition_time", timestamp=frame.acquisition_datetime)
        self.rec.log(f"views/{view_id}/image", rr.Image(frame.pixels))
        values: dict[str, Any] = {k: (np.nan if v is None else v) for k, v in positioner.items()}
        self.rec.log(f"views/{view_id}/positioner",
                     rr.AnyValues(**values, sop_instance_uid=frame.sop_instance_uid))

    def encoder(self, view_id: str, source: str | None, reading: dict | None) -> None:
        self.rec.log(f"views/{view_id}/encoder",
                     rr.TextDocument(json.dumps({"initialisation": source, "reading": reading}),
                                     media_type=_JSON_MEDIA))

    def calibration(self, doc: dict) -> None:
        self._json("calibration", doc)

    def contours(self, view_id: str, contours_px: dict[str, np.ndarray], source: str) -> None:
        for label, points in contours_px.items():
            self.rec.log(f"views/{view_id}/contours/{label}",
                         rr.Points2D(np.asarray(points, np.float32).reshape(-1, 2), radii=1.0,
                                     colors=_LABEL_COLOURS.get(label, (255, 255, 255))))
        self.rec.log(f"views/{view_id}/contours", rr.TextLog(f"{source} contours: " + ", ".join(
            f"{label} {len(p)} px" for label, p in contours_px.items())))

    def plan(self, plan: Plan) -> None:
        for name, mesh, colour in (("tibia", plan.tibia, (230, 220, 200)),
                                   ("fibula", plan.fibula, (200, 190, 170)),
                                   ("pin", plan.pin_mesh, (180, 180, 200))):
            if mesh is not None:
                self.rec.log(f"plan/{name}", _mesh(mesh, colour), static=True)
        lm = plan.landmarks
        self.rec.log("plan/landmarks", rr.Points3D(
            np.array([lm.knee_centre, lm.ankle_centre]), labels=["knee centre", "ankle centre"],
            radii=3.0), static=True)
        self._json("plan/document", {"patient_id": plan.patient_id, "side": plan.side,
                                     "landmarks": lm.to_json(), "target": vars(plan.target)})

    def initial(self, view_ids: list[str], T_cam_tibia: list[Pose], T_tibia_pin: list[Pose],
                cameras: list) -> None:
        for view_id, T, camera in zip(view_ids, T_cam_tibia, cameras):
            self.rec.log(f"world/initial/{view_id}", _transform(T.inverse()))
            self.rec.log(f"world/initial/{view_id}", rr.Pinhole(
                focal_length=[camera.fx, camera.fy], principal_point=[camera.cx, camera.cy],
                resolution=[camera.width, camera.height], image_plane_distance=100.0))
        for k, T in enumerate(T_tibia_pin, start=1):
            self.rec.log(f"world/initial/pin{k}", _transform(T))

    def solver_inputs(self, doc: dict) -> None:
        self._json("inputs/solver", doc)

    def bone_edge_searches(self, doc: dict) -> None:
        """Each view's bone edge search (view id -> its JSON), when the solve sought the
        bone's edges near the model: the frames' evidence a re-run needs."""
        self._json("inputs/bone_edge_searches", doc)

    # -- the solve ------------------------------------------------------------------------
    def iteration(self, stage: str, info: IterationInfo) -> None:
        """The solver callback: costs and every pose after each step (kept, and written
        when the next pipeline stage begins)."""
        self._iteration += 1
        steps, n = self._steps, self._iteration
        steps.add(steps.texts, "solver/stage", n, f"{stage}: iteration {info.iteration}")
        steps.add(steps.scalars, "solver/cost", n, info.cost)
        steps.add(steps.scalars, "solver/lambda", n, info.lambda_)
        for term, cost in info.term_costs.items():
            steps.add(steps.scalars, f"solver/terms/{term}", n, cost)
        poses, keys = info.state.poses, info.state.ordering.keys
        views = [key for key in keys if key.kind == "view"]
        for view_id, key in zip(self._view_ids, views):
            steps.add(steps.poses, f"world/solver/{view_id}", n, poses[key].inverse())
        for key in keys:
            if key.kind == "pin":
                steps.add(steps.poses, f"world/solver/{key.label}", n, poses[key])

    # -- the result -----------------------------------------------------------------------
    def final(self, view_ids: list[str], T_cam_tibia: list[Pose], T_tibia_pin: list[Pose],
              pin_mesh: Surface, plane_polygon: np.ndarray | None,
              residual_rms: dict[str, float]) -> None:
        for view_id, T in zip(view_ids, T_cam_tibia):
            self.rec.log(f"world/final/{view_id}", _transform(T.inverse()))
        for k, T in enumerate(T_tibia_pin, start=1):
            self.rec.log(f"world/final/pin{k}", _transform(T))
            self.rec.log(f"world/final/pin{k}/mesh", _mesh(pin_mesh, _LABEL_COLOURS[f"pin{k}"]))
        if plane_polygon is not None:
            quad = np.asarray(plane_polygon[:4], np.float32)
            self.rec.log("world/final/plane", rr.Mesh3D(
                vertex_positions=quad, triangle_indices=np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
                albedo_factor=(60, 230, 60, 120)))
        for term, rms in residual_rms.items():
            self.rec.log(f"result/residual_rms/{term}", rr.Scalars(rms))

    def angles(self, ctr_deg: float, str_deg: float) -> None:
        self.rec.log("result/ctr_deg", rr.Scalars(ctr_deg))
        self.rec.log("result/str_deg", rr.Scalars(str_deg))

    def result(self, doc: dict) -> None:
        self._json("result/document", doc)

    def close(self) -> None:
        """Finish the file and free the stream: rerun keeps a dropped stream's two threads
        (and their buffers) until orphaned streams are cleaned up, which only ``rr.init``
        does otherwise, so a service writing one recording per run would grow without end."""
        self._steps.send(self.rec, self._stage)
        self.rec.flush()
        self.rec.disconnect()
        del self.rec
        rerun_bindings.flush_and_cleanup_orphaned_recordings()
