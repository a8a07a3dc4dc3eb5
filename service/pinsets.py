"""Pin sets: the views of a case taken with one placement of the pins.

The loop the service serves is measure, move the pins, measure again, all in one study. A
run must therefore use the views of one pin placement only: mixing views of the old and the
new pins gives an angle that belongs to neither (issue 27: -2 deg of re-pinning read as a
1.6 deg error and a wrong verdict). Each view of a case is assigned, once, to a numbered pin
set; the assignment is kept on disk (``pinsets/<case>.json`` in the data folder) so a restart
rebuilds the same sets.

A view joins the case's current set unless
- its pins disagree with the set's measured pins (:func:`pin_disagreement_px`): the set's
  solved pin axes, projected into the new view with the pose the encoders' relative motion
  gives from a solved view of the set, fall off the pin contours extracted in the new view by
  more than the threshold;
- an operator asked for a new set (``slamtka case new-set``), or
- the configuration starts one on a new DICOM series (``pipeline.new_set_on_new_series``).

The test needs a measured set; before its first measurement a view joins it. A view in
which no pins are seen starts no measurement (the display is told).

Each run of a set is numbered (1, 2, ...) in the order it was triggered, and remembers the
measurement before it, so the result shows the change ("STR 6.7 -> 5.1").
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slamtka.service.atomic_files import write_json_atomic
from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose

__all__ = ["pin_disagreement_px", "PinSet", "CasePinSets", "PinSetStore",
           "PIN_NOISE_FACTOR", "MIN_PIN_THRESHOLD_PX", "NO_CONTOURS"]

log = logging.getLogger("slamtka.pinsets")

# A view's pins disagree with the set when a pin's contour lies further from the set's
# projected pin axis than this many times the set's own misfit (the same statistic in the
# views the set was measured from, at their solved poses), but never less than the floor:
# the misfit of unmoved pins seen again, measured in `bench workflow` (docs/workflow.md).
PIN_NOISE_FACTOR = 3.0
MIN_PIN_THRESHOLD_PX = 1.0
# How a view's contour failure begins: such a view (no pins found) joins no set.
NO_CONTOURS = "contours could not be extracted"


def _pin_offset_px(uv_axis: np.ndarray, contour: np.ndarray) -> float:
    """How far (px) a pin's observed shaft edges lie off the projected axis ``uv_axis``
    (2, 2): the median of each edge point's excess over the typical edge distance; inf
    when the contour is missing.

    The shaft's two edges lie at +-radius from its axis, so an edge point's unsigned distance
    from the projected axis is the radius where the pin has not moved; a pin shifted or
    tilted by d moves one edge to radius + d and the other to radius - d. Medians keep the
    statistic to the pin itself where the two pins' outlines overlap in the image (the
    contour extraction then splits them imperfectly)."""
    if len(contour) < 6:
        return float("inf")
    a, b = np.asarray(uv_axis, float)
    length = float(np.linalg.norm(b - a))
    if length < 1e-6:
        return float("inf")
    u = (b - a) / length
    distance = np.abs((np.asarray(contour, float) - a) @ np.array([-u[1], u[0]]))
    return float(np.median(np.abs(distance - np.median(distance))))


def pin_disagreement_px(camera: Camera, T_cam_tibia: Pose, pin_axes_tibia: list[np.ndarray],
                        pin_contours: list[np.ndarray]) -> float:
    """How far (px, the worse pin) the pins seen in a view lie from given pin axes.

    ``pin_axes_tibia``: each pin's axis as (2, 3) points (tip, end) in the tibia frame;
    ``pin_contours``: the two pin contours in the view, undistorted pixels. Which contour is
    which pin is not trusted (labels come from the planned pins): the better pairing counts."""
    uv = [camera.project(T_cam_tibia.apply(np.asarray(axis, float))) for axis in pin_axes_tibia]
    offsets = np.array([[_pin_offset_px(axis, contour) for contour in pin_contours] for axis in uv])
    return float(min(max(offsets[0, 0], offsets[1, 1]), max(offsets[0, 1], offsets[1, 0])))


@dataclass
class PinSet:
    """One placement of the pins: its views, why it started, its numbered runs."""

    number: int
    started_by: str  # "first view", "pins moved (...)", "operator", "new series"
    views: list[str] = field(default_factory=list)  # SOP Instance UIDs, in arrival order
    series: list[str] = field(default_factory=list)
    runs: list[dict] = field(default_factory=list)  # {run_id, number, previous, triggered}

    def to_json(self) -> dict:
        return {"number": self.number, "started_by": self.started_by, "views": self.views,
                "series": self.series, "runs": self.runs}

    @staticmethod
    def from_json(d: dict) -> PinSet:
        return PinSet(int(d["number"]), str(d["started_by"]), list(d.get("views", [])),
                      list(d.get("series", [])), list(d.get("runs", [])))


@dataclass
class CasePinSets:
    """The pin sets of one case, and an operator's pending request for a new one."""

    case_id: str
    sets: list[PinSet] = field(default_factory=list)
    new_set_requested: str | None = None  # who asked, until the next view starts it
    left_out: dict[str, str] = field(default_factory=dict)  # SOP Instance UID -> why in no set
    describe: dict = field(default_factory=dict)  # patient, study, laterality (for `case list`)

    def set_of(self, sop_instance_uid: str) -> PinSet | None:
        return next((s for s in self.sets if sop_instance_uid in s.views), None)

    @property
    def current(self) -> PinSet | None:
        return self.sets[-1] if self.sets else None

    def start(self, why: str) -> PinSet:
        new = PinSet(len(self.sets) + 1, why)
        self.sets.append(new)
        self.new_set_requested = None
        return new

    def run_record(self, run_id: str) -> tuple[PinSet, dict] | None:
        for s in self.sets:
            for r in s.runs:
                if r["run_id"] == run_id:
                    return s, r
        return None

    def to_json(self) -> dict:
        return {"case_id": self.case_id, **self.describe,
                "sets": [s.to_json() for s in self.sets],
                "new_set_requested": self.new_set_requested, "left_out": self.left_out}

    @staticmethod
    def from_json(d: dict) -> CasePinSets:
        describe = {k: d.get(k) for k in ("patient_id", "study_instance_uid", "laterality")}
        return CasePinSets(str(d["case_id"]), [PinSet.from_json(s) for s in d.get("sets", [])],
                           d.get("new_set_requested"), dict(d.get("left_out", {})), describe)


class PinSetStore:
    """The pin sets of every case, one crash-safe JSON file per case."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._cases: dict[str, CasePinSets] = {}

    def path(self, case_id: str) -> Path:
        return self.folder / f"{case_id}.json"

    def get(self, case_id: str) -> CasePinSets:
        if case_id not in self._cases:
            self._cases[case_id] = self.load(self.folder, case_id)
        return self._cases[case_id]

    @staticmethod
    def load(folder: Path, case_id: str) -> CasePinSets:
        path = Path(folder) / f"{case_id}.json"
        try:
            return CasePinSets.from_json(json.loads(path.read_text()))
        except FileNotFoundError:
            return CasePinSets(case_id)
        except (ValueError, KeyError, TypeError) as exc:  # damaged: start afresh, say so
            log.error("%s: unreadable pin sets (%s); the case's views are assigned again",
                      path, exc)
            return CasePinSets(case_id)

    def save(self, sets: CasePinSets) -> None:
        write_json_atomic(self.path(sets.case_id), sets.to_json())
