"""The re-measurement loop of a case: pin sets, numbered runs, and what the display is told.

The worker hands every new view to :meth:`Workflow.place`, which puts it in a pin set
(:mod:`service.pinsets`) and says whether the case's current set is due for a run; when it
is not, the display is told why (:mod:`service.display`) within the same step, so the OR
never waits in silence. :meth:`Workflow.begin_run` numbers a run within its set and finds
the case's previous measurement; :meth:`Workflow.finish_run` records the outcome.

Operators reach a running service through request files in ``requests/`` of the data
folder (``slamtka case new-set|rerun``), which the worker takes on its next step.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from slamtka.service.atomic_files import write_atomic, write_json_atomic
from slamtka.service.audit import AuditLog
from slamtka.service.cases import Case, View, run_id_of
from slamtka.service.display import Status, build_status_objects
from slamtka.service.headers import sanitised_header
from slamtka.service.pinsets import (
    MIN_PIN_THRESHOLD_PX,
    NO_CONTOURS,
    PIN_NOISE_FACTOR,
    CasePinSets,
    PinSet,
    PinSetStore,
    pin_disagreement_px,
)
from slamtka.service.results import MeasurementResult
from slamtka.service.sender import OutgoingObject, Sender
from slamtka.solver.measurement import pin_axis_points

__all__ = ["Workflow", "write_request", "REQUEST_KINDS"]

log = logging.getLogger("slamtka.workflow")
REQUEST_KINDS = ("new-set", "rerun")
_SR_CLASS = "1.2.840.10008.5.1.4.1.1.88.34"
_SC_CLASS = "1.2.840.10008.5.1.4.1.1.7"


def write_request(requests_dir: Path, kind: str, case_id: str, who: str) -> Path:
    """Leave a request for the running service (or the next start): ``kind`` of
    :data:`REQUEST_KINDS` for ``case_id``."""
    if kind not in REQUEST_KINDS:
        raise ValueError(f"unknown request {kind!r}; one of {', '.join(REQUEST_KINDS)}")
    requests_dir.mkdir(parents=True, exist_ok=True)
    stamp = f"{time.time_ns()}-{os.getpid()}"
    path = requests_dir / f"{stamp}-{kind}-{case_id}.json"
    write_json_atomic(path, {"kind": kind, "case_id": case_id, "who": who,
                             "requested": datetime.now(UTC).isoformat()})
    return path


class Workflow:
    def __init__(self, pipeline, sender: Sender, audit: AuditLog, data_dir: Path, *,
                 min_separation_deg: float, max_views: int, new_set_on_new_series: bool,
                 institution: str = ""):
        self.pipeline, self.sender, self.audit = pipeline, sender, audit
        self.store = PinSetStore(Path(data_dir) / "pinsets")
        self.requests_dir = Path(data_dir) / "requests"
        self.min_separation, self.max_views = min_separation_deg, max_views
        self.new_set_on_new_series, self.institution = new_set_on_new_series, institution

    # -- pin sets -------------------------------------------------------------------------
    def current_views(self, case: Case) -> list[View]:
        """The usable views of the case's current pin set (what its next run uses)."""
        sets = self.store.get(case.case_id)
        current = sets.current
        if current is None:
            return []
        allowed = set(current.views)
        return [v for v in case.ordered() if v.usable and v.sop_instance_uid in allowed]

    def selection(self, case: Case) -> list[View]:
        return self.current_views(case)[-self.max_views:]

    def is_due(self, case: Case) -> bool:
        views = self.selection(case)
        return len(views) >= 2 and case.separation_deg(views) >= self.min_separation

    def place(self, case: Case, view: View, tell: bool = True) -> bool:
        """Put a new view in a pin set; whether the current set is now due for a run. When it
        is not (and ``tell``), the display is told why."""
        sets = self.store.get(case.case_id)
        sets.describe = {"patient_id": case.patient_id, "study_instance_uid": case.study_uid,
                         "laterality": case.laterality}
        uid = view.sop_instance_uid
        if sets.set_of(uid) is not None or uid in sets.left_out:
            return False
        if not view.usable:
            sets.left_out[uid] = f"no usable geometry: {view.pairing.problem}"
            self.store.save(sets)
            if tell:
                self.tell(case, view, Status(
                    "unusable", f"This view cannot be used: {view.pairing.problem}.",
                    "check the encoder link and the C-arm's positioner angles, then take the "
                    "view again"))
            return False
        contours, why = self.pipeline.view_contours(case, view)
        if contours is None and why.startswith(NO_CONTOURS):  # (else: no plan, calibration)
            sets.left_out[uid] = why
            self.store.save(sets)
            if tell:
                self.tell(case, view, Status("no_pins", f"No pins seen in this view: {why}.",
                                             "take a view showing both pins and the tibia"))
            return False
        current = self._set_for(case, view, sets, contours)  # untested without contours
        current.views.append(uid)
        if view.series_uid not in current.series:
            current.series.append(view.series_uid)
        self.store.save(sets)
        if self.is_due(case):
            return True  # the run tells, its clock notes included
        if tell:
            status = self._waiting(case, current, why == "no plan")
            if view.pairing.clock is not None:  # said with what the set waits for
                status = Status("clock", f"{view.pairing.clock['message']}. {status.message}",
                                status.action)
            self.tell(case, view, status)
        return False

    def _set_for(self, case: Case, view: View, sets: CasePinSets,
                 contours: dict | None) -> PinSet:
        """The set the view joins: the current one, or a new one (audited, with why)."""
        current = sets.current
        if current is None:
            return sets.start("first view")
        why = None
        if sets.new_set_requested:
            why = f"operator ({sets.new_set_requested})"
        elif self.new_set_on_new_series and view.series_uid not in current.series:
            why = "new DICOM series"
        elif contours is not None:
            try:
                why = self._pins_moved(case, view, current, contours)
            except (ValueError, KeyError, OSError) as exc:  # e.g. the plan was removed meanwhile
                log.error("case %s: the pins of view %s could not be compared (%s); it joins "
                          "pin set %d", case.case_id, view.sop_instance_uid, exc, current.number)
        if why is None:
            return current
        new = sets.start(why)
        self.audit.record("pin_set_started", case_id=case.case_id, pin_set=new.number,
                          sop_instance_uid=view.sop_instance_uid, reason=why)
        return new

    def _pins_moved(self, case: Case, view: View, current: PinSet,
                    contours: dict) -> str | None:
        """Why the view's pins disagree with the set's measured pins, or None when they agree
        (or the set has no measurement to test against)."""
        reference = self._latest_measured(case, current)
        if reference is None:
            return None
        result, views = reference
        plan = self.pipeline.plans.find(case.patient_id, case.laterality)
        solved = result.solved_view_poses()
        beam = view.beam_anat
        if beam is None:
            raise ValueError(f"view {view.sop_instance_uid} has no beam direction")
        candidates = [(v, v.beam_anat) for v in views
                      if v.sop_instance_uid in solved and v.beam_anat is not None]
        if not candidates:
            return None
        # The reference view the C-arm moved least from: its relative motion is the surest.
        ref, _ = max(candidates, key=lambda c: float(np.dot(c[1], beam)))
        start = self.pipeline.geometry.initial_views(plan, [ref.pairing, view.pairing],
                                                     [ref.positioner, view.positioner])
        T_ref0, T_new0 = start.T_cam_tibia
        T_new = T_new0 @ T_ref0.inverse() @ solved[ref.sop_instance_uid]
        axes = [pin_axis_points(T, plan.pin_length())[[0, -1]]
                for T in result.solved_pin_poses()]
        off = pin_disagreement_px(self.pipeline.calibration.camera, T_new, axes,
                                  [contours["pin1"], contours["pin2"]])
        misfit = (result.measurement and result.measurement.pin_misfit_px) or 0.0
        threshold = max(MIN_PIN_THRESHOLD_PX, PIN_NOISE_FACTOR * misfit)
        self.audit.record("pin_check", case_id=case.case_id, pin_set=current.number,
                          sop_instance_uid=view.sop_instance_uid, offset_px=round(off, 2),
                          threshold_px=round(threshold, 2), reference_run=result.run_id)
        if off <= threshold:
            return None
        return (f"pins moved: {off:.1f} px from pin set {current.number}'s measured pins "
                f"(threshold {threshold:.1f} px)")

    def _latest_measured(self, case: Case, current: PinSet
                         ) -> tuple[MeasurementResult, list[View]] | None:
        """The set's newest measured result and the case's views it used."""
        for record in reversed(current.runs):
            if record.get("verdict") in ("pass", "fail"):
                path = self.pipeline.output_root / case.case_id / record["run_id"] / "result.json"
                try:
                    result = MeasurementResult.from_document(json.loads(path.read_text()))
                except (OSError, ValueError):
                    continue
                used = {s.sop_instance_uid for s in result.sources if s.used}
                return result, [v for v in case.views.values() if v.sop_instance_uid in used]
        return None

    def _waiting(self, case: Case, current: PinSet, no_plan: bool) -> Status:
        views = self.current_views(case)
        n = current.number
        if no_plan:
            return Status("no_plan", f"No plan for this patient ({case.patient_id}, side "
                                     f"{case.laterality or '?'}): nothing can be measured.",
                          "add the plan, then re-run the case (slamtka case rerun CASE)")
        if len(views) < 2:
            started = "" if current.started_by == "first view" else f" ({current.started_by})"
            return Status("waiting", f"Pin set {n}{started}: one view so far.",
                          f"second view needed, at least {self.min_separation:.0f} deg from the "
                          "first")
        separation = case.separation_deg(self.selection(case))
        return Status("too_close", f"Pin set {n}: views too close, {separation:.1f} deg apart "
                                   f"(at least {self.min_separation:.0f} needed).",
                      f"take another view at least {self.min_separation:.0f} deg from the others")

    def restore(self, case: Case) -> None:
        """After a restart: place the views a crash left unplaced, telling no one again."""
        for view in case.ordered():
            self.place(case, view, tell=False)

    # -- runs -----------------------------------------------------------------------------
    def begin_run(self, case: Case, views: list[View], rerun: bool = False
                  ) -> tuple[str, dict, datetime]:
        """(run id, measurement section, trigger time) of a run of ``views``: numbered within
        its pin set; a run already begun (repeated after a crash) keeps its number and time."""
        sets = self.store.get(case.case_id)
        uids = [v.sop_instance_uid for v in views]
        pin_set = sets.set_of(uids[0]) or sets.current
        assert pin_set is not None, "a run's views were placed in a pin set"
        base = run_id_of(uids)
        earlier = sum(r.get("base", r["run_id"]) == base for s in sets.sets for r in s.runs)
        run_id = run_id_of(uids + [f"rerun-{earlier}"]) if rerun and earlier else base
        found = sets.run_record(run_id)
        if found is None:
            finished = [r for s in sets.sets for r in s.runs if r.get("verdict") in ("pass", "fail")]
            last = max(finished, key=lambda r: r["triggered"], default=None)
            previous = None if last is None else {
                "run_id": last["run_id"], "pin_set": last["pin_set"], "number": last["number"],
                "ctr_deg": last["ctr_deg"], "str_deg": last["str_deg"], "verdict": last["verdict"]}
            record: dict = {"run_id": run_id, "base": base, "pin_set": pin_set.number,
                      "number": len(pin_set.runs) + 1, "previous": previous,
                      "triggered": datetime.now(UTC).isoformat()}
            pin_set.runs.append(record)
            self.store.save(sets)
            found = (pin_set, record)
        pin_set, record = found
        measurement = {"pin_set": pin_set.number, "number": record["number"],
                       "started_by": pin_set.started_by, "previous": record["previous"]}
        return run_id, measurement, datetime.fromisoformat(record["triggered"])

    def finish_run(self, case: Case, run_id: str, result: MeasurementResult) -> None:
        sets = self.store.get(case.case_id)
        found = sets.run_record(run_id)
        if found is None:
            return
        angles = result.angles
        found[1].update(verdict=result.verdict,
                        ctr_deg=None if angles is None else angles.ctr_deg,
                        str_deg=None if angles is None else angles.str_deg)
        self.store.save(sets)
        error = result.outputs.dicom_error
        if error:
            self.audit.record("output_failed", case_id=case.case_id, run_id=run_id, error=error)
            views = self.selection(case)
            if views:
                self.tell(case, views[-1], Status(
                    "output_failed", "The result could not be made into DICOM "
                    f"({error[:120]}); it is in result.json.",
                    "read the result on the service workstation (slamtka case show CASE)"))

    # -- requests -------------------------------------------------------------------------
    def take_requests(self, cases: dict[str, Case]) -> list[tuple[Case, str]]:
        """Requests left by ``slamtka case``: new sets are started here; (case, "rerun") for
        the worker to run. A request for an unknown case is dropped, audited."""
        out = []
        for path in sorted(self.requests_dir.glob("*.json")) if self.requests_dir.is_dir() else []:
            try:
                request = json.loads(path.read_text())
                kind, case_id, who = request["kind"], request["case_id"], request.get("who", "")
            except (OSError, ValueError, KeyError, TypeError) as exc:
                log.error("%s: unreadable request (%s); removed", path, exc)
                path.unlink(missing_ok=True)
                continue
            case = cases.get(case_id)
            if case is not None and kind == "new-set":
                sets = self.store.get(case_id)
                sets.new_set_requested = who or "operator"
                self.store.save(sets)
            elif case is not None and kind == "rerun":
                out.append((case, "rerun"))
            # Audited once in effect: whoever reads the audit line finds the new set saved.
            self.audit.record("operator_request", kind=kind, case_id=case_id, who=who,
                              known_case=case is not None)
            path.unlink(missing_ok=True)
        return out

    # -- the display ----------------------------------------------------------------------
    def tell(self, case: Case, view: View, status: Status) -> None:
        """Send one status (SR + SC on ``view``) to the display; audited. Never raises: a
        status that cannot be built is logged, the case goes on."""
        sets = self.store.get(case.case_id)
        n = sets.current.number if sets.current else 0
        key = hashlib.sha256(f"{n}/{status.situation}/{view.sop_instance_uid}".encode()
                             ).hexdigest()[:16]
        run_id = f"status-{key}"
        try:
            from slamtka.service.pipeline import result_uid  # the pipeline module is loaded by then
            from slamtka.solver.result import software_version

            decoded = self.pipeline.spool.decoded.get(view.entry)
            when = view.acquisition_datetime or datetime(1970, 1, 1, tzinfo=UTC)
            sr, sc = build_status_objects(
                sanitised_header(decoded.header), decoded.frame.pixels, status, laterality=case.laterality,
                version=software_version(), when=when, institution=self.institution,
                uid_for=lambda what: result_uid(case.case_id, run_id, what))
            folder = self.pipeline.output_root / case.case_id / run_id
            folder.mkdir(parents=True, exist_ok=True)
            objects = []
            for ds_out, name, kind, sop_class in ((sr, "sr.dcm", "sr", _SR_CLASS),
                                                  (sc, "sc.dcm", "sc", _SC_CLASS)):
                buffer = io.BytesIO()
                ds_out.save_as(buffer, enforce_file_format=True)
                write_atomic(folder / name, buffer.getvalue())
                objects.append(OutgoingObject(folder / name, kind, sop_class,
                                              str(ds_out.SOPInstanceUID)))
            write_json_atomic(folder / "status.json", {
                "case_id": case.case_id, "situation": status.situation,
                "message": status.message, "action": status.action, "pin_set": n,
                "sop_instance_uid": view.sop_instance_uid})
            self.sender.enqueue(objects, case.case_id, run_id)
        except Exception:
            log.exception("case %s: the status %r could not be sent", case.case_id,
                          status.situation)
            return
        self.audit.record("status_sent", case_id=case.case_id, situation=status.situation,
                          message=status.message, action=status.action, pin_set=n,
                          sop_instance_uid=view.sop_instance_uid, run_id=run_id)
