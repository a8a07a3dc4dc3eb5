"""What the OR display is told, in words, when a case has no new measurement.

The display only shows what it receives. A case waiting for its second view, a view that
cannot be used, views too close in angle, a clock mismatch, a refusal: each would otherwise
leave it blank while the surgeon waits. For each, the service sends a *status*: one Secondary
Capture frame (the view with the message burned in, wrapped to the image width) and a short
Comprehensive 3D SR ("not measured" with the message and what to do as TEXT items). A
refused measurement's own SR carries the same two items.

Status objects are in the case's study; their UIDs derive from the case and the situation,
so the same situation told again after a restart is the same object.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from typing import TYPE_CHECKING

import numpy as np
from pydicom.dataset import Dataset

from slamtka.service.refusals import RefusalCode
from slamtka.solver.gates import Why

if TYPE_CHECKING:  # annotations only: a status needs no result
    from slamtka.service.results import MeasurementResult, PreviousMeasurement

__all__ = ["Status", "advice", "change_line", "build_status_objects", "STATUS_SERIES",
           "STATUS_SERIES_NUMBER"]

STATUS_SERIES = "slamtka status"  # the series description of every status SR and SC
STATUS_SERIES_NUMBER = 9703


@dataclass(frozen=True)
class Status:
    """One situation of a case told to the display: ``situation`` is a short key (for the
    audit and the benchmark), ``message`` what happened, ``action`` what to do."""

    situation: str  # waiting, unusable, no_pins, no_plan, too_close, clock, refused, output_failed
    message: str
    action: str


def advice(code: str, min_separation_deg: float) -> str:
    """What to do about a refusal (its :class:`RefusalCode`), in words."""
    if code == RefusalCode.NO_PLAN:
        return "add the patient's plan, then re-run the case (slamtka case rerun CASE)"
    if code == Why.VIEWS_TOO_CLOSE:
        return f"take another view at least {min_separation_deg:.0f} deg from the others"
    if code == Why.PINS_INDISTINCT:
        return "take another view from a different angle, so that the two pins are told apart"
    if code in (Why.TOO_FEW_VIEWS, RefusalCode.TOO_FEW_CONTOURS):
        return f"take a second view at least {min_separation_deg:.0f} deg from the first"
    if code == RefusalCode.NO_CALIBRATION:
        return "check the C-arm calibration, then re-run the case (slamtka case rerun CASE)"
    if code in (Why.BONE_OUTLINE_INSUFFICIENT, Why.PIN_NOT_SEEN,
                Why.GATE_FAILED):
        return "take a new view with both pins and the tibia clearly visible"
    return "take a new pair of views; if it persists, measure by hand"


def change_line(previous: PreviousMeasurement | None, result: MeasurementResult) -> str | None:
    """``"STR 6.7 -> 5.1, now within +-3"``: the change since the previous measurement."""
    a, t, d = result.angles, result.target, result.deviation
    if (previous is None or previous.ctr_deg is None or previous.str_deg is None
            or a is None or t is None or d is None):
        return None
    parts = [f"{name} {before:+.1f} -> {now:+.1f}"
             for name, before, now in (("CTR", previous.ctr_deg, a.ctr_deg),
                                       ("STR", previous.str_deg, a.str_deg))
             if abs(before - now) >= 0.05]
    verdict = "within" if d.within_tolerance else "outside"
    was = "within" if previous.verdict == "pass" else "outside"
    change = ", ".join(parts) or "angles unchanged"
    return (f"{change}, now {verdict} +-{t.tolerance_deg:.0f}"
            + ("" if verdict == was else f" (was {was})"))


def build_status_objects(header: Dataset, pixels: np.ndarray | None, status: Status, *,
                         laterality: str | None, version: str, uid_for: Callable[[str], str],
                         when: datetime, institution: str = "") -> tuple[Dataset, Dataset]:
    """The status SR and SC of one situation, in the study of ``header`` (sanitised);
    ``uid_for(what)`` names every UID, ``pixels`` is the view to draw on (blank when None)."""
    from slamtka.service.dicom_sc import ScOverlay, build_sc, render_overlay  # highdicom, OpenCV: not for
    from slamtka.service.dicom_sr import build_sr  # `slamtka status`, which imports this module's neighbours
    from slamtka.service.plans import LATERALITY_TO_SIDE

    sr = build_sr([header], None, side=LATERALITY_TO_SIDE.get(laterality or ""),
                  version=version, series_uid=uid_for("sr-series"),
                  sop_instance_uid=uid_for("sr"), uid_for=uid_for, content_datetime=when,
                  institution=institution, series_number=STATUS_SERIES_NUMBER,
                  series_description=STATUS_SERIES,
                  notes=[("service_status", status.message), ("action", status.action)])
    image = np.zeros((512, 512), np.uint16) if pixels is None else pixels
    rgb = render_overlay(image, ScOverlay({}, text=["SLAMTKA: NOT MEASURED", status.message,
                                                   "Next: " + status.action]))
    sc = build_sc(header, rgb, series_uid=uid_for("sc-series"), sop_instance_uid=uid_for("sc"),
                  instance_number=1, orientation=None, content_datetime=when,
                  institution=institution, description=STATUS_SERIES,
                  series_number=STATUS_SERIES_NUMBER)
    return sr, sc
