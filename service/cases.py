"""Case assembly and automatic triggering.

Received instances are grouped into cases by Patient ID, Study Instance UID and laterality.
Each frame is paired, once, with the C-arm geometry (the encoder reading at its acquisition
time, else its DICOM positioner angles); the pairing is kept in the spool beside the instance
so a restart rebuilds every case as it was. The assembler reads the facts the receiver
decoded (:mod:`service.decoded`), never the instance itself. A view is usable when its geometry is known. A
case is due (here, by geometry alone) as soon as it holds two usable views whose beams are at
least ``min_view_separation_deg`` apart; the service asks the same of the views of the case's
current pin set (:mod:`service.workflow`). Adding an instance already in the case changes
nothing (idempotent by SOP Instance UID).

A run is identified by the digest of the SOP Instance UIDs it uses (``run_id``), so a case
that was already measured with exactly these views is never measured (or sent) twice.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from datetime import datetime

import numpy as np

from slamtka.service.poses import ViewGeometry, ViewPairing, view_separation_deg
from slamtka.service.spool import Spool, SpoolEntry

__all__ = ["View", "Case", "CaseAssembler", "run_id_of", "case_id_of"]

log = logging.getLogger("slamtka.cases")


def case_id_of(patient_id: str, study_uid: str, laterality: str | None) -> str:
    key = "\0".join((patient_id, study_uid, laterality or "-"))
    return "case-" + hashlib.sha256(key.encode()).hexdigest()[:16]


def run_id_of(sop_instance_uids: list[str]) -> str:
    return hashlib.sha256("\n".join(sorted(sop_instance_uids)).encode()).hexdigest()[:16]


@dataclass
class View:
    """One received frame of a case (metadata only; pixels stay in the spool)."""

    entry: SpoolEntry
    sop_class_uid: str
    series_uid: str
    acquisition_datetime: datetime | None
    positioner: dict  # primary_angle_deg, secondary_angle_deg, sid_mm, sod_mm (None if absent)
    pairing: ViewPairing
    beam_anat: np.ndarray | None

    @property
    def sop_instance_uid(self) -> str:
        return self.entry.sop_instance_uid

    @property
    def usable(self) -> bool:
        return self.beam_anat is not None

    def order_key(self) -> tuple:
        when = self.acquisition_datetime.timestamp() if self.acquisition_datetime else float("inf")
        return (when, self.sop_instance_uid)


@dataclass
class Case:
    case_id: str
    patient_id: str
    study_uid: str
    laterality: str | None
    views: dict[str, View] = field(default_factory=dict)  # by SOP Instance UID

    def ordered(self) -> list[View]:
        return sorted(self.views.values(), key=View.order_key)

    def selection(self, max_views: int) -> list[View]:
        """The usable views a run uses: the latest ``max_views`` in acquisition order."""
        return [v for v in self.ordered() if v.usable][-max_views:]

    def separation_deg(self, views: list[View]) -> float:
        return view_separation_deg([v.beam_anat for v in views if v.beam_anat is not None])

    def describe(self) -> dict:
        views = list(self.views.values())  # a snapshot: the worker may be adding a view
        return {"case_id": self.case_id, "patient_id": self.patient_id,
                "study_instance_uid": self.study_uid, "laterality": self.laterality,
                "views": len(views), "usable_views": sum(v.usable for v in views)}


class CaseAssembler:
    """Builds cases from spooled instances; :meth:`add` says when a case is due."""

    def __init__(self, spool: Spool, geometry: ViewGeometry, min_view_separation_deg: float,
                 max_views: int):
        self.spool, self.geometry = spool, geometry
        self.min_separation, self.max_views = min_view_separation_deg, max_views
        self.cases: dict[str, Case] = {}

    def add(self, entry: SpoolEntry) -> tuple[Case | None, bool]:
        """Put an instance into its case: (the case, whether the pipeline is now due)."""
        # Decoded on receipt: a FrameError here means a file damaged since (or, spooled
        # without facts, one that no longer decodes); the caller audits it (the worker) or
        # quarantines the file (start-up recovery).
        facts, stored = self.spool.decoded.facts(entry)
        case_id = case_id_of(facts.patient_id, facts.study_uid, facts.laterality)
        case = self.cases.setdefault(case_id, Case(case_id, facts.patient_id, facts.study_uid,
                                                   facts.laterality))
        if entry.sop_instance_uid in case.views:
            return case, False
        if stored is not None:
            pairing = ViewPairing.from_json(stored)
        else:
            taken = {v.pairing.encoder_reading["sequence"] for v in case.views.values()
                     if v.pairing.encoder_reading is not None}
            pairing = self.geometry.pair(facts, taken)
            self.spool.decoded.save_pairing(entry, facts, pairing.to_json())
        positioner = {"primary_angle_deg": facts.primary_angle_deg,
                      "secondary_angle_deg": facts.secondary_angle_deg,
                      "sid_mm": facts.sid_mm, "sod_mm": facts.sod_mm}
        beam = None
        if pairing.initialisation is not None:
            beam = self.geometry.beam_anat(pairing, facts.primary_angle_deg,
                                           facts.secondary_angle_deg)
        view = View(entry, facts.sop_class_uid, facts.series_uid, facts.acquisition_datetime,
                    positioner, pairing, beam)
        case.views[entry.sop_instance_uid] = view
        if not view.usable:
            log.warning("case %s: view %s is not usable: %s", case_id, entry.id, pairing.problem)
            return case, False
        return case, self.is_due(case)

    def is_due(self, case: Case) -> bool:
        views = case.selection(self.max_views)
        return len(views) >= 2 and case.separation_deg(views) >= self.min_separation
