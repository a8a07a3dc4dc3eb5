"""The measurement pipeline of one case run, recorded stage by stage.

frames -> calibration -> initial poses -> contours -> joint solve -> plane and angles ->
results. The initial poses come before contour extraction because the projected planned
pins label pin 1 and pin 2 consistently in every view. Every stage is logged to the run's
rerun recording (:mod:`service.recording`); the results are a JSON document validated
against the published schema, a Comprehensive 3D SR and one Secondary Capture per view.

A run writes ``output/<case>/<run>/`` (every file crash-safely) and ``result.json`` last: a
run whose ``result.json`` exists is complete and never repeated (idempotent by the SOP
Instance UIDs it uses); one cut short by a crash is run again after the restart. The UIDs of
its DICOM results derive from the case and run, so a run repeated after a crash re-sends the
same objects (which a destination recognises) rather than a second report of the same views.
"""

from __future__ import annotations

import io
import logging
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import TypeVar

import numpy as np
from pydicom.dataset import Dataset
from pydicom.uid import generate_uid

from slamtka.service.atomic_files import remove_partial, write_atomic, write_json_atomic
from slamtka.service.calibrations import CalibrationSet, choose_for_run
from slamtka.service.cases import Case, View, run_id_of
from slamtka.service.dicom_sc import ScOverlay, build_sc, patient_orientation, render_overlay
from slamtka.service.dicom_sr import (
    SrGeometry,
    SrMeasurement,
    build_sr,
    tibia_frame_of_reference_uid,
)
from slamtka.service.display import advice, change_line
from slamtka.service.frames import Frame, encode_frame
from slamtka.service.headers import sanitised_header
from slamtka.service.pinsets import NO_CONTOURS, pin_disagreement_px
from slamtka.service.plans import PlanFinder
from slamtka.service.poses import InitialViews, ViewGeometry, planned_pins
from slamtka.service.recording import CaseRecorder
from slamtka.service.refusals import Refusal, RefusalCode
from slamtka.service.results import MeasurementResult, build_result
from slamtka.service.sender import OutgoingObject
from slamtka.service.spool import Spool
from slamtka.solver.gates import Why
from slamtka.solver.geometry import Pose
from slamtka.solver.imaging.calibration_file import Calibration
from slamtka.solver.imaging.contours import (
    ContourConfig,
    ContourError,
    ExtractedContours,
    agreed_polarity,
    extract_contours,
    load_manual_contours,
)
from slamtka.solver.measurement import pin_axis_points
from slamtka.solver.observations import LABELS, ViewObservation
from slamtka.solver.plan import Plan
from slamtka.solver.slam import InitialGuess, SolveOutcome, SolverConfig, solve_joint

__all__ = ["Pipeline", "RunOutcome", "plane_polygon", "result_uid", "PLANE_PATCH_HALF_MM"]

log = logging.getLogger("slamtka.pipeline")
_T = TypeVar("_T")
PLANE_PATCH_HALF_MM = 30.0
_PREPARED_VIEWS = 64  # extracted contours kept for views waiting for their run
_NO_CALIBRATION = "the frame does not match the C-arm calibration"
_SR_CLASS = "1.2.840.10008.5.1.4.1.1.88.34"  # Comprehensive 3D SR Storage
_SC_CLASS = "1.2.840.10008.5.1.4.1.1.7"  # Secondary Capture Image Storage
_RESULT_UID_NAMESPACE = uuid.UUID("5f0c3a52-7b1e-4c55-9d0e-51a3c0a7e2b4")  # slamtka results
# The defaults, as `slamtka replay --resolve` assumes when it solves a recording again.
_SOLVER_CONFIG = SolverConfig()


@dataclass
class RunOutcome:
    result: MeasurementResult
    folder: Path
    objects: list[OutgoingObject]


@dataclass
class _ViewInput:
    view: View
    view_id: str
    frame: Frame
    header: Dataset  # the instance without pixel data (SR evidence, SC reference)
    contours: ExtractedContours | None = None  # raw pixels, as extracted or drawn
    contour_source: str | None = None
    left_out: str | None = None  # why the run could not use the view (its source says so)

    @property
    def used(self) -> bool:
        return self.left_out is None


@dataclass
class _Run:
    """One run's context: what it was given, and what each stage adds for the next."""

    case: Case
    views: list[View]
    run_id: str
    folder: Path
    recorder: CaseRecorder
    on_output: Callable[[OutgoingObject], object]
    measurement: dict | None  # its place in the re-measurement loop
    when: datetime  # dates the DICOM content
    min_separation_deg: float
    started: float
    reasons: list[str] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    items: list[_ViewInput] = field(default_factory=list)
    plan: Plan | None = None
    refusal: Refusal | None = None  # the pipeline's own, before a solve
    start: InitialViews | None = None
    observations: list[ViewObservation] = field(default_factory=list)
    initial: InitialGuess | None = None
    outcome: SolveOutcome | None = None
    result: MeasurementResult | None = None
    objects: list[OutgoingObject] = field(default_factory=list)
    dicom_error: str | None = None

    @property
    def usable(self) -> list[_ViewInput]:
        return [i for i in self.items if i.used]


def _made(value: _T | None) -> _T:
    """A member of the run context that an earlier stage has made (a stage runs only after
    those before it, unless the run was refused)."""
    if value is None:
        raise RuntimeError("a pipeline stage ran before the stage that makes its input")
    return value


@dataclass(frozen=True)
class _Stage:
    """One unit of a run over its context; the runner records, times and orders them."""

    name: str  # as the recording names it (service.recording.STAGES)
    run: Callable[[Pipeline, _Run], None]
    after_refusal: bool = False  # whether it runs for a run already refused
    describe: Callable[[_Run], str] = lambda run: ""


def result_uid(case_id: str, run_id: str, what: str) -> str:
    """The UID of one result object (or series) of a run: the same every time it runs.

    A name-based UUID under the 2.25 root (PS3.5 B.2); pydicom's ``generate_uid`` ignores
    its entropy sources for that root and would return a random one.
    """
    return f"2.25.{uuid.uuid5(_RESULT_UID_NAMESPACE, f'{case_id}/{run_id}/{what}').int}"


def plane_polygon(point: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """A closed square (5, 3) in the plane, centred on ``point`` (tibia frame, mm)."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1], [1, 1]], float) * PLANE_PATCH_HALF_MM
    return point + corners[:, :1] * u + corners[:, 1:] * v


class Pipeline:
    """Runs cases; everything it needs is built once at service start."""

    def __init__(self, spool: Spool, plans: PlanFinder, calibrations, geometry: ViewGeometry,
                 output_root: Path, *, manual_contours_dir: Path | None = None,
                 institution: str = ""):
        """``calibrations``: a :class:`CalibrationSet` (per C-arm), or one calibration for all."""
        self.spool, self.plans, self.geometry = spool, plans, geometry
        self.calibrations = (calibrations if isinstance(calibrations, CalibrationSet)
                             else CalibrationSet([], calibrations))
        self.calibration: Calibration | None = None  # of the run (or arriving view) being worked on
        self.output_root = Path(output_root)
        self.manual_contours_dir, self.institution = manual_contours_dir, institution
        # Extracted contours by (SOP instance UID, polarity asked for).
        self._extracted: OrderedDict[tuple[str, str], tuple[ExtractedContours | None, str]] = OrderedDict()
        self._pins: tuple[Plan, tuple[Pose, Pose]] | None = None

    def warm_up(self) -> None:
        """Build a throwaway report and image once, so that the first case does not pay for
        loading and initialising the DICOM builders (about half a second)."""
        source = encode_frame(Frame(np.zeros((8, 8), np.uint16), (0.2, 0.2), patient_id="WARMUP",
                                    acquisition_datetime=datetime.now(UTC)))
        now = datetime.now(UTC)
        build_sr([source], None, side=None, version="warm-up", series_uid=generate_uid(prefix=None),
                 sop_instance_uid=generate_uid(prefix=None), content_datetime=now,
                 uid_for=lambda what: generate_uid(prefix=None))
        build_sc(source, np.zeros((8, 8, 3), np.uint8), series_uid=generate_uid(prefix=None),
                 sop_instance_uid=generate_uid(prefix=None), instance_number=1, orientation=None,
                 content_datetime=now)

    def run_folder(self, case: Case, views: list[View], run_id: str | None = None) -> Path:
        return self.output_root / case.case_id / (run_id or run_id_of(
            [v.sop_instance_uid for v in views]))

    def already_done(self, case: Case, views: list[View], run_id: str | None = None) -> bool:
        return (self.run_folder(case, views, run_id) / "result.json").is_file()

    def _calibrated(self) -> Calibration:
        """The calibration of the run (or arriving view) being worked on: a run reaches the
        stages that need it only with one chosen (without, every view is left out)."""
        if self.calibration is None:
            raise RuntimeError("no C-arm calibration has been chosen for these views")
        return self.calibration

    # -- stages ---------------------------------------------------------------------------
    def _manual_contours(self) -> dict[str, tuple[str, ExtractedContours]]:
        """Hand-drawn contours by SOP Instance UID (the documents' view_id), with their
        coordinates ("raw" or "undistorted")."""
        found: dict[str, tuple[str, ExtractedContours]] = {}
        if self.manual_contours_dir is None or not self.manual_contours_dir.is_dir():
            return found
        for path in sorted(self.manual_contours_dir.glob("*.json")):
            try:
                coordinates, views = load_manual_contours(path)
            except ContourError as exc:
                log.error("ignoring manual contours: %s", exc)
                continue
            for uid, contours in views.items():
                found[uid] = (coordinates, contours)
        return found

    def _raw_pixels(self, drawn: tuple[str, ExtractedContours]) -> ExtractedContours:
        """Hand-drawn contours in raw pixels: undistorted ones are distorted with the current
        calibration (the run's, or the arriving view's)."""
        coordinates, contours = drawn
        if coordinates != "undistorted":
            return contours
        distort = self._calibrated().distort_points
        return ExtractedContours(distort(contours.bone), distort(contours.pin1), distort(contours.pin2))

    def _fit_calibration(self, view: View) -> Frame | None:
        """Make the calibration that fits the view's frame the current one; the frame, or
        None when no calibration fits it."""
        decoded = self.spool.decoded.get(view.entry)
        calibration, _ = self.calibrations.select(decoded.header, decoded.frame)
        if calibration is None or calibration.check_frame(decoded.frame) is not None:
            return None
        self.calibration = calibration
        return decoded.frame

    def _extract(self, plan: Plan, view: View, frame: Frame, T_cam_tibia: Pose,
                 pins: tuple[Pose, Pose], polarity: str = "auto") -> tuple[ExtractedContours | None, str]:
        """Extracted contours of one view (raw pixels), or None and the reason; cached."""
        key = (view.sop_instance_uid, polarity)
        if key not in self._extracted:
            try:
                calibration = self._calibrated()
                shadows = plan.pin_shadows(calibration.camera, T_cam_tibia, pins)
                found = extract_contours(frame.pixels, ContourConfig(polarity=polarity),
                                         expected_pins=calibration.distort_points(shadows.centres),
                                         expected_pin_width_px=shadows.width_px,
                                         expected_pin_length_px=shadows.length_px)
                self._extracted[key] = (found, "extracted")
            except ContourError as exc:
                self._extracted[key] = (None, f"{NO_CONTOURS} ({exc})")
            while len(self._extracted) > _PREPARED_VIEWS:
                self._extracted.popitem(last=False)
        return self._extracted[key]

    def prepare(self, case: Case, view: View) -> None:
        """Extract a view's contours as soon as it arrives, so that a run triggered by a later
        view only waits for that view's. Quietly does nothing when there is no plan yet."""
        if not view.usable or (view.sop_instance_uid, "auto") in self._extracted:
            return
        try:
            plan = self.plans.find(case.patient_id, case.laterality)
        except ValueError:
            return
        T = self.geometry.initial_views(plan, [view.pairing], [view.positioner]).T_cam_tibia[0]
        frame = self._fit_calibration(view)
        if frame is not None:
            self._extract(plan, view, frame, T, self._planned_pins(plan))

    def view_contours(self, case: Case, view: View) -> tuple[dict[str, np.ndarray] | None, str]:
        """A view's contours as a run would use them (undistorted pixels) and their source,
        or None and why ("no plan" when the patient has none: nothing can be extracted)."""
        drawn = self._manual_contours().get(view.sop_instance_uid)
        raw: ExtractedContours | None
        if drawn is not None:
            # Undistorted with this view's calibration, not whichever was current (none yet
            # after a start).
            if self._fit_calibration(view) is None:
                return None, _NO_CALIBRATION
            raw, source = self._raw_pixels(drawn), "manual"
        else:
            try:
                self.plans.find(case.patient_id, case.laterality)
            except ValueError:
                return None, "no plan"
            self.prepare(case, view)
            raw, source = self._extracted.get((view.sop_instance_uid, "auto"), (None, _NO_CALIBRATION))
        if raw is None:
            return None, source
        missing = [label for label, points in (("pin1", raw.pin1), ("pin2", raw.pin2))
                   if len(points) == 0]
        if missing:
            why = raw.diagnostics.get("missing", {})
            return None, f"{NO_CONTOURS} (fewer than two pins: " + "; ".join(
                f"{label} {why.get(label, 'not found')}" for label in missing) + ")"
        calibration = self._calibrated()
        return {label: calibration.undistort_points(points)
                for label, points in raw.as_dict().items()}, source

    def _planned_pins(self, plan: Plan) -> tuple[Pose, Pose]:
        """The planned pins of ``plan``, kept for the plan last asked about (the object itself:
        an id could be reused by a plan loaded after this one was dropped)."""
        if self._pins is None or self._pins[0] is not plan:
            self._pins = (plan, planned_pins(plan))
        return self._pins[1]

    # -- the run --------------------------------------------------------------------------
    def run(self, case: Case, views: list[View],
            on_output: Callable[[OutgoingObject], object] = lambda obj: None, *,
            run_id: str | None = None, measurement: dict | None = None,
            triggered: datetime | None = None, min_separation_deg: float = 15.0) -> RunOutcome:
        """Measure ``views`` of ``case``; ``on_output`` gets each DICOM result once it is on
        disk: the report as soon as it is, then the SCs once all of them are.

        ``run_id`` (default: the digest of the views' UIDs) names the run and its UIDs;
        ``measurement`` its place in the re-measurement loop (:mod:`service.pinsets`);
        ``triggered`` dates its DICOM content (default: the latest acquisition time of its
        views), so the same run built again is the same objects."""
        started = time.perf_counter()
        run_id = run_id or run_id_of([v.sop_instance_uid for v in views])
        folder = self.run_folder(case, views, run_id)
        folder.mkdir(parents=True, exist_ok=True)
        remove_partial(folder)  # of an attempt cut short by a crash
        recorder = CaseRecorder(folder / "recording.rrd", case.case_id, run_id)
        when = triggered or max((v.acquisition_datetime for v in views
                                 if v.acquisition_datetime is not None),
                                default=datetime(1970, 1, 1, tzinfo=UTC))
        try:
            return self._run(case, views, run_id, folder, recorder, started, on_output,
                             measurement, when, min_separation_deg)
        finally:
            recorder.close()

    def _run(self, case: Case, views: list[View], run_id: str, folder: Path,
             recorder: CaseRecorder, started: float,
             on_output: Callable[[OutgoingObject], object], measurement: dict | None,
             when: datetime, min_separation_deg: float) -> RunOutcome:
        run = _Run(case, views, run_id, folder, recorder, on_output, measurement, when,
                   min_separation_deg, started)
        for stage in _STAGES:
            if run.refusal is not None and not stage.after_refusal:
                continue
            recorder.stage(stage.name, stage.describe(run))
            begun = time.perf_counter()
            stage.run(self, run)
            run.timings[f"{stage.name}_s"] = time.perf_counter() - begun
        run.timings["total_s"] = time.perf_counter() - started
        result = _made(run.result).completed(run.timings, run.dicom_error)
        doc = result.to_document()
        recorder.result(doc)
        if result.angles is not None:
            recorder.angles(result.angles.ctr_deg, result.angles.str_deg)
        write_json_atomic(folder / "result.json", doc)  # last: marks the run complete
        return RunOutcome(result, folder, run.objects)

    def _frames(self, run: _Run) -> None:
        for k, view in enumerate(run.views, start=1):
            decoded = self.spool.decoded.get(view.entry)
            item = _ViewInput(view, f"view{k}", decoded.frame, sanitised_header(decoded.header))
            run.recorder.frame(item.view_id, item.frame, view.positioner)
            run.recorder.encoder(item.view_id, view.pairing.initialisation,
                                 view.pairing.encoder_reading)
            if view.pairing.angle_check and view.pairing.angle_check.get("status") == "disagrees":
                run.reasons.append(f"{item.view_id}: {view.pairing.angle_check['message']}")
            if view.pairing.clock is not None:
                run.reasons.append(f"{item.view_id}: {view.pairing.clock['message']}")
            run.items.append(item)

    def _calibration(self, run: _Run) -> None:
        """Pick the run's calibration (per C-arm and detector field); views it does not fit
        are left out, saying why."""
        selected = []
        for item in run.items:
            calibration, problem = self.calibrations.select(item.header, item.frame)
            if calibration is not None and problem is None:
                problem = calibration.check_frame(item.frame)
            selected.append((calibration, problem))
        chosen = self.calibration = choose_for_run(selected)
        if chosen is not None:
            run.recorder.calibration(chosen.document())
        for item, (calibration, problem) in zip(run.items, selected):
            if (problem is None and calibration is not None and chosen is not None
                    and calibration is not chosen):
                problem = (f"needs calibration {calibration.calibration_id}, the run uses "
                           f"{chosen.calibration_id} (views from two C-arms or fields)")
            if problem:
                item.left_out = problem
                run.reasons.append(f"{item.view_id}: {problem}")

    def _plan(self, run: _Run) -> None:
        """The patient's plan; a run without one, or with fewer than two usable views, is
        refused here."""
        try:
            run.plan = self.plans.find(run.case.patient_id, run.case.laterality)
        except ValueError as exc:
            run.refusal = Refusal.of(RefusalCode.NO_PLAN, str(exc))
            return
        run.recorder.plan(run.plan)
        if len(run.usable) < 2:
            run.refusal = Refusal.of(
                Why.TOO_FEW_VIEWS if self.calibration is not None else RefusalCode.NO_CALIBRATION,
                f"only {len(run.usable)} usable view(s); at least two are needed")

    def _initial_poses(self, run: _Run) -> None:
        usable, plan = run.usable, _made(run.plan)
        run.start = self.geometry.initial_views(plan, [i.view.pairing for i in usable],
                                                [i.view.positioner for i in usable])
        run.recorder.initial([i.view_id for i in usable], run.start.T_cam_tibia,
                             list(self._planned_pins(plan)), [self._calibrated().camera] * len(usable))

    def _contours(self, run: _Run) -> None:
        """Each usable view's contours (drawn by hand, or extracted at its initial pose) and
        the solver's views of them; fewer than two views with contours are refused."""
        plan, start = _made(run.plan), _made(run.start)
        pins = self._planned_pins(plan)
        manual = self._manual_contours()
        usable = run.usable
        for item, T in zip(usable, start.T_cam_tibia):
            uid = item.view.sop_instance_uid
            if uid in manual:
                item.contours, item.contour_source = self._raw_pixels(manual[uid]), "manual"
            else:
                item.contours, item.contour_source = self._extract(plan, item.view,
                                                                   item.frame, T, pins)
        polarity = agreed_polarity([i.contours for i in usable if i.contour_source != "manual"])
        for item, T in zip(usable, start.T_cam_tibia):
            contours = item.contours
            if (polarity is not None and item.contour_source != "manual"
                    and (contours is None or contours.diagnostics["polarity"] != polarity)):
                # One C-arm stores a case's frames alike: read (or try again) as the clear
                # ones read.
                item.contours, item.contour_source = self._extract(plan, item.view, item.frame, T,
                                                                   pins, polarity)
            if item.contours is None:
                item.left_out = item.contour_source
                run.reasons.append(f"{item.view_id}: {item.contour_source}")
                item.contour_source = None
            else:
                run.recorder.contours(item.view_id, item.contours.as_dict(), _made(item.contour_source))
        kept = [(i, T) for i, T in zip(usable, start.T_cam_tibia) if i.used]
        cal = self._calibrated()
        run.observations = [i.contours.observation(i.view_id, cal.camera, cal.undistort_points,
                                                   cal.distort_points)
                            for i, _ in kept if i.contours is not None]
        run.initial = InitialGuess(tuple(T for _, T in kept), pins, start.odometry_sigma)
        run.recorder.solver_inputs(self._solver_inputs(plan, run.observations, run.initial))
        if len(run.observations) < 2:
            run.refusal = Refusal.of(RefusalCode.TOO_FEW_CONTOURS,
                                     f"only {len(run.observations)} view(s) with contours; at "
                                     "least two are needed")

    def _solve(self, run: _Run) -> None:
        run.outcome = solve_joint(_made(run.plan), run.observations, _made(run.initial),
                                  _SOLVER_CONFIG, callback=run.recorder.iteration)

    def _plane_and_angles(self, run: _Run) -> None:
        """The solved poses, pins and plane into the recording (the solver measured them),
        and, where the solve sought the bone's edges, what it sought them in."""
        outcome = _made(run.outcome)
        polygon = (None if outcome.plane is None
                   else plane_polygon(outcome.plane.point, outcome.plane.normal))
        run.recorder.final([o.view_id for o in run.observations], outcome.T_cam_tibia,
                           outcome.T_tibia_pin, _made(run.plan).pin_mesh, polygon, outcome.residual_rms)
        if outcome.bone_edges_sought:  # what they were sought in, for `replay --resolve` (~1.8 MB a view)
            run.recorder.bone_edge_searches({o.view_id: o.bone_edge_search.to_json()
                                             for o in run.observations if o.bone_edge_search is not None})

    def _results(self, run: _Run) -> None:
        """The validated result, then the SR, sent once on disk, then the SCs, sent once all
        are on disk (the SR does not wait for the overlays: ~0.1 s)."""
        case, items, plan, outcome = run.case, run.items, run.plan, run.outcome
        refused = self._refused_sources(case, len(items), run.reasons)
        used = {i.view_id for i in items if i.used and i.contours is not None}
        uids = {key: result_uid(case.case_id, run.run_id, key)
                for key in ("sr", "sr-series", "sc-series", *(i.view_id for i in items))}
        run.timings["total_s"] = time.perf_counter() - run.started
        measurement = run.measurement
        if measurement is not None and outcome is not None and outcome.status == "measured":
            measurement = {**measurement, "pin_misfit_px": self._pin_misfit(
                _made(run.plan), outcome, run.observations)}
        run.result = build_result(
            case_id=case.case_id, run_id=run.run_id,
            case={"patient_id": case.patient_id, "study_instance_uid": case.study_uid,
                  "laterality": case.laterality},
            sources=[self._source(i.view, i.view_id, i.contour_source, i.view_id in used, i.left_out)
                     for i in items] + refused,
            outcome=outcome, method=_SOLVER_CONFIG.method, plan=plan, views=run.observations,
            calibration=None if self.calibration is None else {
                "id": self.calibration.calibration_id, "sha256": self.calibration.sha256},
            initial=run.initial, refusal=run.refusal,
            reasons=run.reasons, timings=run.timings,
            outputs={"folder": str(run.folder), "recording": str(run.folder / "recording.rrd"),
                     "sr_sop_instance_uid": uids["sr"],
                     "sc_sop_instance_uids": {i.view_id: uids[i.view_id] for i in items}},
            measurement=measurement)
        run.objects = []
        try:
            sr = self._build_sr(run.result, items, plan, outcome, uids, run.when,
                                run.min_separation_deg)
            run.objects.append(self._save(sr, run.folder / "sr.dcm", "sr", _SR_CLASS))
            run.on_output(run.objects[0])  # the measurement reaches the display first
            scs = [self._save(ds, run.folder / name, "sc", _SC_CLASS) for ds, name in
                   self._build_scs(run.result, items, plan, outcome, run.observations, uids,
                                   run.when, run.min_separation_deg)]
        except Exception as exc:  # values that passed receipt must not cost the result
            log.exception("case %s run %s: building the DICOM results failed", case.case_id,
                          run.run_id)
            run.dicom_error = f"{type(exc).__name__}: {exc}"[:500]
            return
        run.objects += scs
        for obj in scs:  # the overlays once every one is on disk
            run.on_output(obj)

    def _solver_inputs(self, plan: Plan, observations: list[ViewObservation],
                       initial: InitialGuess) -> dict:
        """Exactly what the solver was given (float64 JSON), for ``slamtka replay --resolve``."""
        from slamtka.solver.surface import mesh_digest

        return {"camera": self._calibrated().camera.to_json(),
                "views": [{"view_id": o.view_id, **{label: o.contours[label].tolist()
                                                    for label in LABELS}, "notes": o.notes,
                           "bone_visible": None if o.bone_visible is None else o.bone_visible.to_json(),
                           "pins_opaque": o.pins_opaque}
                          for o in observations],
                "initial": {"T_cam_tibia": [T.to_json() for T in initial.T_cam_tibia],
                            "T_tibia_pin": [T.to_json() for T in initial.T_tibia_pin],
                            "odometry_sigma": initial.odometry_sigma},
                "plan": {"patient_id": plan.patient_id, "landmarks": plan.landmarks.to_json(),
                         "target": vars(plan.target),
                         "segmentation_sd_mm": plan.segmentation_sd_mm,
                         "pin": vars(plan.pin_spec) if plan.pin_spec is not None else None,
                         "bone_mesh_sha256": mesh_digest(plan.bone_meshes()),
                         "pin_mesh_sha256": mesh_digest([plan.pin_mesh])},
                "solver_config": repr(_SOLVER_CONFIG)}

    @staticmethod
    def _source(view: View, view_id: str, contours: str | None, used: bool,
                left_out: str | None = None) -> dict:
        """A view's entry in ``sources``; ``problem`` says why it was not used, if it was not."""
        when = view.acquisition_datetime
        return {"view_id": view_id, "sop_instance_uid": view.sop_instance_uid,
                "sop_class_uid": view.sop_class_uid, "series_instance_uid": view.series_uid,
                "acquisition_datetime": None if when is None else when.isoformat(),
                "positioner": view.positioner, "initialisation": view.pairing.initialisation,
                "encoder_reading": view.pairing.encoder_reading,
                "angle_check": view.pairing.angle_check, "clock": view.pairing.clock,
                "contours": contours, "used": used,
                "problem": left_out or view.pairing.problem}

    def _refused_sources(self, case: Case, first: int, reasons: list[str]) -> list[dict]:
        """The case's views whose geometry is unknown (no encoder reading at their time, no
        positioner angles): listed as refused, with the reason, so no view goes unmentioned."""
        out = []
        for k, v in enumerate((v for v in case.ordered() if not v.usable), start=first + 1):
            reasons.append(f"view{k}: not initialised, left out ({v.pairing.problem})")
            out.append(self._source(v, f"view{k}", None, False))
        return out

    # -- DICOM results --------------------------------------------------------------------
    def _build_sr(self, result: MeasurementResult, items: list[_ViewInput], plan: Plan | None,
                  outcome: SolveOutcome | None, uids: dict, when: datetime,
                  min_separation_deg: float) -> Dataset:
        """The run's SR, built in memory."""
        return build_sr([i.header for i in items], self._sr_measurement(result, plan, outcome),
                        side=result.side, version=result.software_version,
                        series_uid=uids["sr-series"], sop_instance_uid=uids["sr"],
                        institution=self.institution,
                        uid_for=lambda what: result_uid(result.case_id, result.run_id, what),
                        content_datetime=when, notes=self._notes(result, min_separation_deg))

    def _build_scs(self, result: MeasurementResult, items: list[_ViewInput], plan: Plan | None,
                   outcome: SolveOutcome | None, observations: list[ViewObservation],
                   uids: dict, when: datetime, min_separation_deg: float
                   ) -> list[tuple[Dataset, str]]:
        """The run's SCs (each view with its overlay), built in memory, with file names."""
        posed = {o.view_id: T for o, T in zip(observations, outcome.T_cam_tibia)} if outcome else {}
        measured = self._sr_measurement(result, plan, outcome)
        built = []
        text = self._summary_lines(result, min_separation_deg)
        within = None if result.deviation is None else result.deviation.within_tolerance
        for n, item in enumerate(items, start=1):
            overlay = ScOverlay(item.contours.as_dict() if item.contours else {}, text=text,
                                within_tolerance=within)
            T = posed.get(item.view_id)
            orientation = None
            if T is not None and plan is not None and outcome is not None:
                if measured is not None and outcome.plane is not None:
                    overlay.plane_px = self._project(T, plane_polygon(outcome.plane.point,
                                                                      outcome.plane.normal))
                overlay.pin_axes_px = [self._project(T, pin_axis_points(P, plan.pin_length())[[0, -1]])
                                       for P in outcome.T_tibia_pin]
                R_anat_cam = plan.landmarks.T_tibia_anat().inverse().R @ T.inverse().R
                orientation = patient_orientation(R_anat_cam)
            rgb = render_overlay(item.frame.pixels, overlay)
            sc = build_sc(item.header, rgb, series_uid=uids["sc-series"],
                          sop_instance_uid=uids[item.view_id], instance_number=n,
                          orientation=orientation, institution=self.institution,
                          content_datetime=when)
            built.append((sc, f"sc-{item.view_id}.dcm"))
        return built

    @staticmethod
    def _sr_measurement(result: MeasurementResult, plan: Plan | None,
                        outcome: SolveOutcome | None) -> SrMeasurement | None:
        """The SR's measurement of a measured run: angles, plane and pins (else None)."""
        if (not result.measured or plan is None or outcome is None or outcome.plane is None
                or result.angles is None or result.deviation is None
                or result.bone_mesh_sha256 is None):
            return None
        pins_axes = [pin_axis_points(T, plan.pin_length())[[0, -1]] for T in outcome.T_tibia_pin]
        axis = plan.landmarks.T_tibia_anat().R[:, 2]
        angles = [float(np.degrees(np.arccos(abs(np.dot(T.R[:, 2], axis)))))
                  for T in outcome.T_tibia_pin]
        return SrMeasurement(result.angles, result.deviation, SrGeometry(
            tibia_frame_of_reference_uid(result.bone_mesh_sha256),
            plane_polygon(outcome.plane.point, outcome.plane.normal), pins_axes, angles,
            plan.side))

    def _pin_misfit(self, plan: Plan, outcome: SolveOutcome,
                    observations: list[ViewObservation]) -> float:
        """The set's own noise for the pin test of later views (:mod:`service.pinsets`): the
        worst offset of a view's pin contours from the solved pins, over the views measured."""
        axes = [pin_axis_points(T, plan.pin_length())[[0, -1]] for T in outcome.T_tibia_pin]
        return round(max(pin_disagreement_px(o.camera, T, axes, [o.contours["pin1"],
                                                                  o.contours["pin2"]])
                         for o, T in zip(observations, outcome.T_cam_tibia)), 3)

    @staticmethod
    def _notes(result: MeasurementResult, min_separation_deg: float) -> list[tuple[str, str]]:
        """The SR's notes in words: why not measured and what to do; the measurement history."""
        notes = []
        if not result.measured:
            notes += [("reason", result.reason or ""),
                      ("action", advice(_refusal_code(result), min_separation_deg))]
        m = result.measurement
        if m is not None:
            text = f"pin set {m.pin_set}, measurement {m.number} ({m.started_by})"
            previous = m.previous
            if previous is not None:
                angles = ("not measured" if previous.ctr_deg is None or previous.str_deg is None
                          else f"CTR {previous.ctr_deg:+.1f}, STR {previous.str_deg:+.1f} deg")
                text += (f"; previous: pin set {previous.pin_set}, measurement "
                         f"{previous.number}: {angles}, {previous.verdict.replace('_', ' ')}")
            change = change_line(previous, result)
            notes.append(("history", text + (f"; {change}" if change else "")))
        return notes

    def _project(self, T_cam_tibia: Pose, points_tibia: np.ndarray) -> np.ndarray:
        calibration = self._calibrated()
        ideal = calibration.camera.project(T_cam_tibia.apply(points_tibia))
        return calibration.distort_points(ideal)

    @staticmethod
    def _summary_lines(result: MeasurementResult, min_separation_deg: float) -> list[str]:
        m = result.measurement
        head = [] if m is None else [f"Pin set {m.pin_set}, measurement {m.number}"]
        a, t, d = result.angles, result.target, result.deviation
        if not result.measured or a is None or t is None or d is None:
            return ["NOT MEASURED", *head, result.reason or "",
                    "Next: " + advice(_refusal_code(result), min_separation_deg)]
        change = change_line(m.previous, result) if m is not None else None
        clock = [f"Note: {s.view_id}: {s.clock_message}" for s in result.sources
                 if s.clock_message]
        return [f"CTR {a.ctr_deg:+.1f} deg (+-{a.ctr_sigma_deg:.1f})  plan {t.ctr_deg:+.1f}",
                f"STR {a.str_deg:+.1f} deg (+-{a.str_sigma_deg:.1f})  plan {t.str_deg:+.1f}",
                f"{'WITHIN' if d.within_tolerance else 'OUTSIDE'} +-{t.tolerance_deg:.0f} deg",
                *head, *([change] if change else []), *clock]

    @staticmethod
    def _save(ds: Dataset, path: Path, kind: str, sop_class: str) -> OutgoingObject:
        buffer = io.BytesIO()
        ds.save_as(buffer, enforce_file_format=True)
        write_atomic(path, buffer.getvalue())
        return OutgoingObject(path, kind, sop_class, str(ds.SOPInstanceUID))


def _refusal_code(result: MeasurementResult) -> str:
    """The refusal code of a not-measured result (``other`` for one without a refusal)."""
    return RefusalCode.OTHER if result.refusal is None else result.refusal.code


_STAGES = (
    _Stage("frames", Pipeline._frames, describe=lambda run: f"{len(run.views)} views"),
    _Stage("calibration", Pipeline._calibration),
    _Stage("plan", Pipeline._plan),
    _Stage("initial_poses", Pipeline._initial_poses),
    _Stage("contours", Pipeline._contours),
    _Stage("solve", Pipeline._solve),
    _Stage("plane_and_angles", Pipeline._plane_and_angles, describe=lambda run: _made(run.outcome).status),
    _Stage("results", Pipeline._results, after_refusal=True),
)
