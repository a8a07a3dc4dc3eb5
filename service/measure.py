"""``slamtka measure FRAME.dcm FRAME.dcm [...] --plan PLAN --calibration CALIB.json --out DIR``.

The service's own pipeline, offline: the frames are validated as the receiver validates
them, spooled, assembled into their case and measured by :class:`service.pipeline.Pipeline`,
which writes the same ``result.json``, DICOM SR and SC and rerun recording as the running
service (under ``DIR/CASE/RUN``). No network. Initial view poses come from the frames'
positioner angles, or from the encoder readings of ``--encoders`` (``{"readings":
[{"time_utc": ISO 8601 with offset, "axes": {"orbital": deg, ...}}]}``) at each frame's
acquisition time.

Bad input (a file that is not DICOM or not a usable frame, frames of two patients, a
calibration that does not fit the frames, a plan that does not exist or is another
patient's) is refused in one line naming the file, exit code 2.
"""

from __future__ import annotations

import argparse
import time
from datetime import datetime
from pathlib import Path

import pydicom
from pydicom.dataset import Dataset
from pydicom.errors import InvalidDicomError

from slamtka.drivers.kinematics import CArmKinematics, JointReading
from slamtka.drivers.reading_history import EncoderReading
from slamtka.service.cases import CaseAssembler
from slamtka.service.config import CarmConfig, PipelineConfig
from slamtka.service.frames import Frame, FrameError, decode_frame
from slamtka.service.plans import PlanFinder, PlanStore
from slamtka.service.poses import ViewGeometry
from slamtka.service.spool import Spool
from slamtka.solver.imaging.calibration_file import CalibrationError, load_calibration
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.plan import Plan

__all__ = ["add_measure_parser", "run_measure", "MeasureError"]

# Offline readings are matched to a frame's acquisition time within this (the live link's
# default 0.1 s assumes a device clock disciplined to the host's).
_READING_MATCH_S = 1.0


class MeasureError(ValueError):
    """Input that ``slamtka measure`` refuses, in one line naming the file."""


class _RecordedReadings:
    """Encoder readings from a file, answering ``reading_at`` as the live link does."""

    def __init__(self, path: Path):
        try:
            doc = read_json_object(path)
            entries = doc["readings"]
            self.readings = []
            for i, entry in enumerate(entries):
                when = datetime.fromisoformat(entry["time_utc"])
                if when.tzinfo is None:
                    raise ValueError(f"reading {i}: time_utc {entry['time_utc']!r} has no UTC offset")
                joints = JointReading.from_axes(entry["axes"])
                self.readings.append(EncoderReading(i, 0, when, when, time.monotonic(), joints, 0))
        except (ValueError, KeyError, TypeError) as exc:
            raise MeasureError(f"{path}: not an encoder readings file ({exc})") from None
        if not self.readings:
            raise MeasureError(f"{path}: holds no readings")

    def reading_at(self, t_utc: datetime, max_age_s: float | None = None) -> EncoderReading | None:
        best = min(self.readings, key=lambda r: abs((r.time_utc - t_utc).total_seconds()))
        return best if abs((best.time_utc - t_utc).total_seconds()) <= _READING_MATCH_S else None

    def readings_between(self, t0_utc: datetime, t1_utc: datetime) -> list[EncoderReading]:
        """The readings between two instants, oldest first (as the live link answers)."""
        return sorted((r for r in self.readings if t0_utc <= r.time_utc <= t1_utc),
                      key=lambda r: r.time_utc)


class _OnePlan:
    """The plan store of a run: the one plan given, for its patient only."""

    def __init__(self, plan: Plan, where: Path):
        self.plan, self.where = plan, where

    def find(self, patient_id: str, laterality: str | None) -> Plan:
        if self.plan.patient_id != patient_id:
            raise ValueError(f"{self.where}: the plan is patient {self.plan.patient_id!r}, "
                             f"the frames patient {patient_id!r}")
        return self.plan


def _read_frames(paths: list[Path]) -> list[tuple[Path, Dataset, Frame]]:
    datasets: list[tuple[Path, Dataset, Frame]] = []
    first = None
    for path in paths:
        try:
            ds = pydicom.dcmread(path)
        except (InvalidDicomError, OSError) as exc:
            raise MeasureError(f"{path}: not a DICOM file ({exc})") from None
        try:
            frame = decode_frame(ds)
        except (FrameError, ValueError) as exc:
            raise MeasureError(f"{path}: not a usable X-ray frame ({exc})") from None
        if first is None:
            first = (path, frame.patient_id)
        elif frame.patient_id != first[1]:
            raise MeasureError(f"{path}: Patient ID {frame.patient_id!r} is not {first[1]!r} of "
                               f"{first[0]}: frames of two patients")
        datasets.append((path, ds, frame))
    return datasets


def _plan_store(path: Path, patient_id: str, laterality: str | None) -> PlanFinder:
    if not path.exists():
        raise MeasureError(f"{path}: no such plan")
    try:
        store: PlanFinder
        if (path / "plan.json").is_file():
            store = _OnePlan(Plan.load(path), path)
        else:
            store = PlanStore(path)
        store.find(patient_id, laterality)
    except ValueError as exc:
        raise MeasureError(f"{path}: {exc}") from None
    return store


def run_measure(args: argparse.Namespace) -> int:
    frames = _read_frames(args.frames)
    if len(frames) < 2:
        raise MeasureError(f"{args.frames[0]}: one frame; at least two views are needed")
    try:
        calibration = load_calibration(args.calibration)
    except (CalibrationError, OSError) as exc:
        raise MeasureError(f"{args.calibration}: {exc}") from None
    for path, _, frame in frames:
        problem = calibration.check_frame(frame)
        if problem:
            raise MeasureError(f"{path}: no calibration for this C-arm in {args.calibration} ({problem})")
    _, _, first = frames[0]
    store = _plan_store(args.plan, first.patient_id, first.laterality)
    link = None if args.encoders is None else _RecordedReadings(args.encoders)
    carm, pipeline_config = CarmConfig(), PipelineConfig()
    geometry = ViewGeometry(CArmKinematics.from_config(carm.kinematics), carm.setup, link,
                            _READING_MATCH_S, carm.angle_check_deg)
    from slamtka.service.pipeline import Pipeline  # loads rerun, highdicom and the imaging chain

    args.out.mkdir(parents=True, exist_ok=True)
    spool = Spool(args.out / ".spool")
    for _, ds, _ in frames:
        spool.store(ds)
    assembler = CaseAssembler(spool, geometry, pipeline_config.min_view_separation_deg,
                              pipeline_config.max_views)
    cases = {}
    for entry in spool.entries():
        case, _ = assembler.add(entry)
        if case is not None:
            cases[case.case_id] = case
    if len(cases) != 1:
        raise MeasureError(f"{args.frames[0]}: the frames belong to {len(cases)} cases "
                           "(study or laterality differ); give the frames of one")
    (case,) = cases.values()
    pipeline = Pipeline(spool, store, calibration, geometry, args.out)
    outcome = pipeline.run(case, case.selection(pipeline_config.max_views))
    result = outcome.result
    if result.angles is not None:
        a = result.angles
        print(f"measured: CTR {a.ctr_deg:+.2f} deg, STR {a.str_deg:+.2f} deg; "
              f"results in {outcome.folder}")
        return 0
    print(f"not measured: {result.reason}; results in {outcome.folder}")
    return 3


def add_measure_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("measure", help="run the service's pipeline offline on DICOM frames")
    p.add_argument("frames", type=Path, nargs="+", help="DICOM frames of one case (two or more views)")
    p.add_argument("--plan", type=Path, required=True,
                   help="a plan folder (plan.json), or a plans folder searched by Patient ID")
    p.add_argument("--calibration", type=Path, required=True, help="the C-arm's calibration file")
    p.add_argument("--encoders", type=Path, help="encoder readings (JSON) at the frames' times")
    p.add_argument("--out", type=Path, required=True)
    p.set_defaults(func=run_measure)
