"""The service's result of one run: a typed, frozen object and its published JSON document.

:class:`MeasurementResult` is what every consumer reads: the ``result.json`` writer, the SR
and SC builders, the audit and status board, the re-measurement loop and the command line.
It is made from its JSON document only (:meth:`MeasurementResult.from_document`), which
validates it against the published JSON Schema ``service/schemas/result.schema.json`` there,
once, naming every place it breaks; so an object in hand is valid, and
:meth:`~MeasurementResult.to_document` gives back the same document, key order included.
Reading a stored ``result.json`` goes the same way.

:func:`build_result` composes the document of a pipeline run: :func:`solver.result.result_document`
with what only the service knows (case and source UIDs, calibration id and hash, encoder
readings and how each view was initialised, timings, where the outputs are). A case refused
before the solver ran (no plan, no usable view) gets the same document with the solver-side
members ``null`` and the reasons filled in. A refused case also carries its
:class:`~slamtka.service.refusals.Refusal` (``refusal``: code, detail, may_restart).
Members no consumer reads piece by piece (plane, poses, solver, inputs, calibration, ...)
stay JSON objects, typed read-only.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from functools import lru_cache
from importlib.resources import files
from typing import Any

import jsonschema

from slamtka.service.plans import LATERALITY_TO_SIDE
from slamtka.service.refusals import Refusal, solver_refusal
from slamtka.solver.anatomy import SIGN_CONVENTION
from slamtka.solver.geometry import Pose
from slamtka.solver.observations import ViewObservation
from slamtka.solver.plan import Plan, Target
from slamtka.solver.result import (
    RESULT_FORMAT,
    Angles,
    Deviation,
    result_document,
    software_version,
)
from slamtka.solver.slam import InitialGuess, SolveOutcome

__all__ = ["SCHEMA_VERSION", "result_schema", "validate_result", "build_result",
           "MeasurementResult", "Source", "Outputs", "LoopPlace", "PreviousMeasurement"]

SCHEMA_VERSION = "1.0"
JsonObject = Mapping[str, Any]


@lru_cache(maxsize=1)
def result_schema() -> dict:
    return json.loads(files("slamtka.service").joinpath("schemas/result.schema.json").read_text())


def validate_result(doc: dict) -> None:
    """Raise ValueError naming every place where ``doc`` breaks the published schema."""
    validator = jsonschema.Draft202012Validator(
        result_schema(), format_checker=jsonschema.Draft202012Validator.FORMAT_CHECKER)
    errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
    if errors:
        lines = [f"{'/'.join(map(str, e.absolute_path)) or '(root)'}: {e.message[:200]}"
                 for e in errors]
        raise ValueError("result document breaks the schema:\n  " + "\n  ".join(lines[:20]))


@dataclass(frozen=True)
class Source:
    """One view the run was given (``sources``): its DICOM identity, where its initial pose
    came from, and whether the run used it (``problem`` says why not)."""

    view_id: str
    sop_instance_uid: str
    sop_class_uid: str
    series_instance_uid: str
    acquisition_datetime: str | None
    positioner: JsonObject
    initialisation: str | None
    encoder_reading: JsonObject | None
    angle_check: JsonObject | None
    clock: JsonObject | None  # a clock offset found for the view, and how it was handled
    contours: str | None
    used: bool
    problem: str | None

    @property
    def clock_message(self) -> str | None:
        return None if not self.clock else self.clock["message"]

    @classmethod
    def from_json(cls, doc: JsonObject) -> Source:
        return cls(**{"clock": None, "problem": None, **doc})  # both absent in older documents


@dataclass(frozen=True)
class Outputs:
    """Where the run's results are; ``dicom_error`` why its DICOM results failed, if they did."""

    folder: str
    recording: str
    sr_sop_instance_uid: str
    sc_sop_instance_uids: Mapping[str, str]
    dicom_error: str | None = None

    def to_json(self) -> dict:
        doc = asdict(self)
        if self.dicom_error is None:  # absent, not null, when the DICOM results were made
            del doc["dicom_error"]
        return doc


@dataclass(frozen=True)
class PreviousMeasurement:
    """The case's measurement before this run (any pin set), for the display's comparison."""

    run_id: str
    pin_set: int
    number: int
    ctr_deg: float | None  # None when it was not measured
    str_deg: float | None
    verdict: str


@dataclass(frozen=True)
class LoopPlace:
    """Where the run stands in the re-measurement loop (:mod:`service.pinsets`)."""

    pin_set: int
    number: int
    started_by: str
    previous: PreviousMeasurement | None
    pin_misfit_px: float | None = None  # the set's own pin noise, once measured

    def to_json(self) -> dict:
        doc = asdict(self)
        if self.pin_misfit_px is None:  # absent when the run measured nothing
            del doc["pin_misfit_px"]
        return doc

    @classmethod
    def from_json(cls, doc: JsonObject) -> LoopPlace:
        previous = doc["previous"]
        return cls(doc["pin_set"], doc["number"], doc["started_by"],
                   None if previous is None else PreviousMeasurement(**previous),
                   doc.get("pin_misfit_px"))


@dataclass(frozen=True)
class MeasurementResult:
    """One run's result; made by :meth:`from_document` (or :func:`build_result`), which
    validates it. Members are named as in the document."""

    software_version: str
    created: str
    case_id: str
    run_id: str
    status: str  # measured, not_measured
    reason: str | None  # the first reason when not measured
    reasons: tuple[str, ...]
    refusal: Refusal | None
    verdict: str  # pass, fail, not_measured
    sign_convention: JsonObject
    angles: Angles | None
    deviation: Deviation | None
    target: Target | None
    plane: JsonObject | None
    poses: JsonObject | None  # T_cam_tibia by view id, T_tibia_pin: 4x4 lists
    solver: JsonObject | None
    inputs: JsonObject | None
    case: JsonObject  # patient_id, study_instance_uid, laterality
    sources: tuple[Source, ...]
    calibration: JsonObject | None
    initialisation: JsonObject
    timings: Mapping[str, float]
    outputs: Outputs
    measurement: LoopPlace | None

    @property
    def measured(self) -> bool:
        return self.status == "measured"

    @property
    def side(self) -> str | None:
        """``left`` or ``right``: the plan's side, else the case's laterality (None unknown)."""
        if self.inputs is not None:
            return self.inputs["plan"]["side"]
        return LATERALITY_TO_SIDE.get(self.case["laterality"] or "")

    @property
    def bone_mesh_sha256(self) -> str | None:
        """The digest of the plan's bone meshes (None before the solve)."""
        return None if self.inputs is None else self.inputs["plan"]["bone_mesh_sha256"]

    def solved_view_poses(self) -> dict[str, Pose]:
        """The solved T_cam_tibia of each view used, by its SOP Instance UID."""
        solved = {} if self.poses is None else self.poses["T_cam_tibia"]
        return {s.sop_instance_uid: Pose.from_json(solved[s.view_id])
                for s in self.sources if s.used and s.view_id in solved}

    def solved_pin_poses(self) -> list[Pose]:
        """The solved T_tibia_pin of both pins (none before the solve)."""
        return [] if self.poses is None else [Pose.from_json(T) for T in self.poses["T_tibia_pin"]]

    def completed(self, timings: Mapping[str, float],
                  dicom_error: str | None = None) -> MeasurementResult:
        """This result with the run's final timings and why its DICOM results failed, if they
        did: all that is only known after the SR and SCs were built from it. Not validated
        again: the run's own clock readings and a sentence are all the schema asks of them."""
        return replace(self, timings=dict(timings),
                       outputs=replace(self.outputs, dicom_error=dicom_error))

    def to_document(self) -> dict:
        """The published JSON document (a fresh copy, in the schema's member order)."""
        def opt(member: Any) -> Any:
            return None if member is None else member.to_json()

        doc = {
            "format": RESULT_FORMAT,
            "software": {"name": "slamtka", "version": self.software_version},
            "case_id": self.case_id, "status": self.status, "reason": self.reason,
            "sign_convention": self.sign_convention, "angles": opt(self.angles),
            "deviation": opt(self.deviation),
            "target": None if self.target is None else asdict(self.target),
            "plane": self.plane, "poses": self.poses, "solver": self.solver,
            "inputs": self.inputs, "schema_version": SCHEMA_VERSION, "created": self.created,
            "run_id": self.run_id, "reasons": list(self.reasons), "refusal": opt(self.refusal),
            "verdict": self.verdict, "case": self.case,
            "sources": [asdict(s) for s in self.sources], "calibration": self.calibration,
            "initialisation": self.initialisation, "timings": self.timings,
            "outputs": self.outputs.to_json(), "measurement": opt(self.measurement),
        }
        return copy.deepcopy(doc)

    @classmethod
    def from_document(cls, doc: dict) -> MeasurementResult:
        """The result a document states, once it is validated against the published schema
        (ValueError naming every place it breaks)."""
        validate_result(doc)
        doc = copy.deepcopy(doc)

        def opt(parse: Any, member: str) -> Any:
            value = doc.get(member)  # refusal and measurement: absent in older documents
            return None if value is None else parse(value)

        return cls(
            software_version=doc["software"]["version"], created=doc["created"],
            case_id=doc["case_id"], run_id=doc["run_id"], status=doc["status"],
            reason=doc["reason"], reasons=tuple(doc["reasons"]),
            refusal=opt(Refusal.from_json, "refusal"), verdict=doc["verdict"],
            sign_convention=doc["sign_convention"],
            angles=opt(lambda d: Angles(**d), "angles"),
            deviation=opt(lambda d: Deviation(**d), "deviation"),
            target=opt(lambda d: Target(**d), "target"), plane=doc["plane"],
            poses=doc["poses"], solver=doc["solver"], inputs=doc["inputs"], case=doc["case"],
            sources=tuple(Source.from_json(s) for s in doc["sources"]),
            calibration=doc["calibration"], initialisation=doc["initialisation"],
            timings=doc["timings"], outputs=Outputs(**doc["outputs"]),
            measurement=opt(LoopPlace.from_json, "measurement"))


def _refused_base(case_id: str, plan: Plan | None, reason: str) -> dict:
    """The solver-side members of a document for a case refused before the solve."""
    target = None if plan is None else asdict(plan.target)
    return {"format": RESULT_FORMAT, "software": {"name": "slamtka", "version": software_version()},
            "case_id": case_id, "status": "not_measured", "reason": reason,
            "sign_convention": SIGN_CONVENTION, "angles": None, "deviation": None,
            "target": target, "plane": None, "poses": None, "solver": None, "inputs": None}


def build_result(*, case_id: str, run_id: str, case: dict, sources: list[dict],
                 outcome: SolveOutcome | None, method: str, plan: Plan | None,
                 views: list[ViewObservation], calibration: dict | None,
                 initial: InitialGuess | None, refusal: Refusal | None, reasons: list[str],
                 timings: dict[str, float],
                 outputs: dict, measurement: dict | None = None) -> MeasurementResult:
    """The result of one pipeline run, validated.

    ``refusal`` is the pipeline's own, before the solve (then ``outcome`` is None); the
    solver's is named from its reason. ``reasons`` are the pipeline's other findings (views
    left out): the refusal's detail goes first, the solver's reason last. ``method`` is the one the solver was
    configured with (``SolveOutcome`` does not say). ``measurement``: the run's place in
    the re-measurement loop (pin set, number, previous measurement).
    """
    reasons = list(reasons)
    if outcome is None:
        if refusal is None:
            raise ValueError("a run without a solve must say why")
        reasons.insert(0, refusal.detail)
        doc = _refused_base(case_id, plan, refusal.detail)
    else:
        if plan is None or calibration is None:
            raise ValueError("a solved run needs its plan and calibration")
        doc = result_document(case_id, outcome, plan, views, calibration["id"], method)
        if outcome.status != "measured":
            reasons.append(outcome.reason)
            refusal = solver_refusal(outcome.why, outcome.reason)
    measured = doc["status"] == "measured"
    verdict = ("not_measured" if not measured
               else "pass" if doc["deviation"]["within_tolerance"] else "fail")
    doc.update({
        "schema_version": SCHEMA_VERSION,
        "created": datetime.now(UTC).isoformat(timespec="milliseconds"),
        "run_id": run_id,
        "reason": None if measured else (doc["reason"] or reasons[0]),
        "reasons": reasons,
        "refusal": None if measured or refusal is None else refusal.to_json(),
        "verdict": verdict,
        "case": case,
        "sources": sources,
        "calibration": calibration,
        "initialisation": {
            "views": ({v.view_id: T.to_json() for v, T in zip(views, initial.T_cam_tibia)}
                      if initial is not None else {}),
            "pins": [T.to_json() for T in initial.T_tibia_pin] if initial is not None else [],
        },
        "timings": timings,
        "outputs": outputs,
        "measurement": measurement,
    })
    return MeasurementResult.from_document(doc)
