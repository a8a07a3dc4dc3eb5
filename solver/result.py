"""The versioned result document of one measurement (JSON).

It states the angles with their sign convention and uncertainty, the deviation from the
plan, every pose the solver estimated, how the solve went, and the inputs it came from, so
that a measurement can be reproduced and audited. A refused measurement carries no angles,
only the reason.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from importlib.metadata import PackageNotFoundError, version

import numpy as np

from slamtka.solver.anatomy import SIGN_CONVENTION
from slamtka.solver.observations import ViewObservation
from slamtka.solver.plan import Plan
from slamtka.solver.slam import SolveOutcome
from slamtka.solver.surface import mesh_digest

__all__ = ["RESULT_FORMAT", "Angles", "Deviation", "measured_angles", "result_document",
           "software_version"]

RESULT_FORMAT = "slamtka-result/1"


def software_version() -> str:
    try:
        return version("slamtka")
    except PackageNotFoundError:
        return "unknown"


@dataclass(frozen=True)
class Angles:
    """The measured resection angles and their 1-sigma, in degrees (CTR + varus, STR +
    posterior slope)."""

    ctr_deg: float
    str_deg: float
    ctr_sigma_deg: float
    str_sigma_deg: float

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Deviation:
    """Measured minus planned angles (degrees), and whether both are within the tolerance."""

    ctr_deg: float
    str_deg: float
    within_tolerance: bool

    def to_json(self) -> dict:
        return asdict(self)


def measured_angles(outcome: SolveOutcome, plan: Plan) -> tuple[Angles, Deviation] | None:
    """The angles of a measured outcome and their deviation from the plan (None if refused)."""
    if outcome.status != "measured" or outcome.plane is None or outcome.angle_cov is None:
        return None
    ctr, str_ = float(np.degrees(outcome.plane.ctr)), float(np.degrees(outcome.plane.str_))
    sigma = np.degrees(np.sqrt(np.diag(outcome.angle_cov)))
    t = plan.target
    d_ctr, d_str = ctr - t.ctr_deg, str_ - t.str_deg
    return (Angles(ctr, str_, float(sigma[0]), float(sigma[1])),
            Deviation(d_ctr, d_str, bool(abs(d_ctr) <= t.tolerance_deg
                                         and abs(d_str) <= t.tolerance_deg)))


def result_document(case_id: str, outcome: SolveOutcome, plan: Plan,
                    views: list[ViewObservation], calibration_id: str, method: str) -> dict:
    plane = None
    if outcome.plane is not None:
        R_anat = plan.landmarks.T_tibia_anat().R
        plane = {"point_tibia_mm": outcome.plane.point.tolist(),
                 "normal_tibia": outcome.plane.normal.tolist(),
                 "normal_anatomical": (R_anat.T @ outcome.plane.normal).tolist()}
    measured = measured_angles(outcome, plan)
    return {
        "format": RESULT_FORMAT,
        "software": {"name": "slamtka", "version": software_version()},
        "case_id": case_id,
        "status": outcome.status,
        "reason": outcome.reason or None,
        "sign_convention": SIGN_CONVENTION,
        "angles": None if measured is None else measured[0].to_json(),
        "deviation": None if measured is None else measured[1].to_json(),
        "target": {"ctr_deg": plan.target.ctr_deg, "str_deg": plan.target.str_deg,
                   "tolerance_deg": plan.target.tolerance_deg},
        "plane": plane,
        "poses": {
            "T_cam_tibia": {v.view_id: T.to_json() for v, T in zip(views, outcome.T_cam_tibia)},
            "T_tibia_pin": [T.to_json() for T in outcome.T_tibia_pin],
        },
        "solver": {
            "method": method,
            "converged": outcome.converged,
            "convergence_reason": outcome.convergence_reason,
            "start": outcome.initialisation,
            "bone_edges": "sought near the model" if outcome.bone_edges_sought else "extracted",
            "pin_edges_shared_in": list(outcome.pins_shared),
            "iterations": outcome.iterations,
            "seconds": outcome.seconds,
            "residual_rms_sigma": outcome.residual_rms,
            "term_costs": outcome.term_costs,
            "contour_points": outcome.point_counts,
            "edge_points": outcome.edge_point_counts,
        },
        "inputs": {
            "views": [v.view_id for v in views],
            "calibration_id": calibration_id,
            "plan": {"patient_id": plan.patient_id, "side": plan.side,
                     "bone_mesh_sha256": mesh_digest(plan.bone_meshes()),
                     "pin_mesh_sha256": mesh_digest([plan.pin_mesh])},
        },
    }
