"""The service's result document: the solver's result plus the DICOM inputs it came from.

:func:`build_result` wraps :func:`solver.result.result_document` with what only the service
knows (case and source UIDs, calibration id and hash, encoder readings and how each view was
initialised, timings, where the outputs are) and validates the whole against the published
JSON Schema ``service/schemas/result.schema.json``; an invalid document is a bug and raises.
A case refused before the solver ran (no plan, no usable view) gets the same document with
the solver-side members ``null`` and the reasons filled in. A refused case also carries its
:class:`~slamtka.service.refusals.Refusal` (``refusal``: code, detail, may_restart).
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from functools import lru_cache
from importlib.resources import files

import jsonschema

from slamtka.service.refusals import Refusal, solver_refusal
from slamtka.solver.anatomy import SIGN_CONVENTION
from slamtka.solver.observations import ViewObservation
from slamtka.solver.plan import Plan
from slamtka.solver.result import RESULT_FORMAT, result_document, software_version
from slamtka.solver.slam import InitialGuess, SolveOutcome

__all__ = ["SCHEMA_VERSION", "result_schema", "validate_result", "build_result"]

SCHEMA_VERSION = "1.0"


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


def _refused_base(case_id: str, plan: Plan | None, reason: str) -> dict:
    """The solver-side members of a document for a case refused before the solve."""
    target = None if plan is None else {"ctr_deg": plan.target.ctr_deg,
                                        "str_deg": plan.target.str_deg,
                                        "tolerance_deg": plan.target.tolerance_deg}
    return {"format": RESULT_FORMAT, "software": {"name": "slamtka", "version": software_version()},
            "case_id": case_id, "status": "not_measured", "reason": reason,
            "sign_convention": SIGN_CONVENTION, "angles": None, "deviation": None,
            "target": target, "plane": None, "poses": None, "solver": None, "inputs": None}


def build_result(*, case_id: str, run_id: str, case: dict, sources: list[dict],
                 outcome: SolveOutcome | None, method: str, plan: Plan | None,
                 views: list[ViewObservation], calibration: dict | None,
                 initial: InitialGuess | None, refusal: Refusal | None, reasons: list[str],
                 timings: dict[str, float],
                 outputs: dict, measurement: dict | None = None) -> dict:
    """The validated result document of one pipeline run.

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
    validate_result(doc)
    return doc
