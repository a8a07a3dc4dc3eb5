"""The result as a DICOM Comprehensive 3D SR with the TID 1500 Measurement Report (highdicom).

Content:

- a TID 1410 planar ROI group "Resection plane": the plane as a 3D polygon (a square patch
  centred on the fitted plane) in the tibia's frame of reference, with CTR and STR as numeric
  measurements in degrees, their 1-sigma (derivation "Standard Deviation") and their
  deviation from the plan, and the verdict "within plan tolerance" as a qualitative
  evaluation;
- one TID 1501 group per trocar pin: the angle between the pin axis and the tibial mechanical
  axis, inferred from the pin axis as a 3D polyline (tip to end);
- for a refused measurement, one TID 1501 group stating "not measured" (no numbers);
- notes in words at the root (TEXT items): why it was not measured and what to do, the
  pin set and measurement number with the previous measurement (the re-measurement loop),
  or, for a status report, what the service is waiting for.

Every UID of the content (tracking identifiers) and its date and time derive from the run
(``uid_for``, ``content_datetime``), so the same run built again after a crash is the same
object, byte for byte, under its SOP Instance UID.

Coordinates are in the tibia (plan) frame, mm; its Frame of Reference UID is derived from the
plan's mesh digest, so every result on the same plan shares it. CTR/STR have no standard
codes: they are in the private coding scheme ``99SLAMTKA`` declared in the Coding Scheme
Identification Sequence. Sign convention: CTR positive = varus, STR positive = posterior slope.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime

import highdicom as hd
import numpy as np
from pydicom.dataset import Dataset
from pydicom.sr.codedict import codes
from pydicom.sr.coding import Code
from pydicom.uid import generate_uid

from slamtka.service.headers import stamp_dates
from slamtka.solver.result import Angles, Deviation

__all__ = ["SrGeometry", "SrMeasurement", "build_sr", "tibia_frame_of_reference_uid", "CODES", "SR_SERIES_NUMBER"]

SCHEME = "99SLAMTKA"
SR_SERIES_NUMBER = 9701
_DEG = Code("deg", "UCUM", "degree")
CODES = {
    "ctr": Code("CTR", SCHEME, "Coronal tibial resection angle"),
    "str": Code("STR", SCHEME, "Sagittal tibial resection angle"),
    "ctr_dev": Code("CTRDEV", SCHEME, "Coronal resection angle deviation from plan"),
    "str_dev": Code("STRDEV", SCHEME, "Sagittal resection angle deviation from plan"),
    "pin_angle": Code("PINMA", SCHEME, "Trocar pin angle to tibial mechanical axis"),
    "plane": Code("RESPLANE", SCHEME, "Tibial resection plane"),
    "pin": Code("TROCARPIN", SCHEME, "Trocar pin"),
    "status": Code("MSTATUS", SCHEME, "Resection plane measurement status"),
    "measured": Code("MEASURED", SCHEME, "Measured"),
    "not_measured": Code("NOTMEASURED", SCHEME, "Not measured"),
    "within": Code("INTOL", SCHEME, "Within plan tolerance"),
    "algorithm": Code("SLAMTKA", SCHEME, "Joint C-arm pose and pin estimation (SLAM-TKA)"),
    "reason": Code("NMREASON", SCHEME, "Reason not measured"),
    "action": Code("NEXTSTEP", SCHEME, "What to do next"),
    "history": Code("MHISTORY", SCHEME, "Measurement history"),
    "service_status": Code("SVCSTATUS", SCHEME, "Measurement service status"),
}
_SD = Code("386136009", "SCT", "Standard Deviation")
_YES, _NO = Code("373066001", "SCT", "Yes"), Code("373067005", "SCT", "No")
_TIBIA = Code("12611008", "SCT", "Tibia")
_LATERALITY = {"left": Code("7771000", "SCT", "Left"), "right": Code("24028007", "SCT", "Right")}
_PROCEDURE = Code("609588000", "SCT", "Total knee replacement")


@dataclass(frozen=True)
class SrGeometry:
    """3D content of the report in the tibia frame (mm)."""

    frame_of_reference_uid: str
    plane_polygon: np.ndarray  # (5, 3) closed square patch of the plane
    pin_axes: list[np.ndarray]  # two (2, 3) arrays: tip, end
    pin_angles_deg: list[float]  # angle of each pin axis to the mechanical axis
    side: str


@dataclass(frozen=True)
class SrMeasurement:
    """What a measured report states: the result's angles and their deviation from the plan,
    with the 3D content they were measured on."""

    angles: Angles
    deviation: Deviation
    geometry: SrGeometry


def tibia_frame_of_reference_uid(bone_mesh_sha256: str) -> str:
    """The Frame of Reference of a plan's tibia mesh: stable for the same mesh."""
    return generate_uid(entropy_srcs=["slamtka tibia frame", bone_mesh_sha256])


def _measurement(name: Code, value: float, derivation: Code | None = None,
                 coordinates: hd.sr.CoordinatesForMeasurement3D | None = None) -> hd.sr.Measurement:
    return hd.sr.Measurement(name=name, value=float(value), unit=_DEG, derivation=derivation,
                             referenced_coordinates=None if coordinates is None else [coordinates])


def _groups(measured: SrMeasurement | None, algorithm: hd.sr.AlgorithmIdentification,
            site: hd.sr.FindingSite, uid_for: Callable[[str], str]) -> list:
    tracking = lambda text: hd.sr.TrackingIdentifier(  # noqa: E731
        uid=uid_for(f"tracking/{text}"), identifier=text)
    if measured is None:
        return [hd.sr.MeasurementsAndQualitativeEvaluations(
            tracking_identifier=tracking("Resection plane"), finding_type=CODES["plane"],
            algorithm_id=algorithm, finding_sites=[site],
            qualitative_evaluations=[hd.sr.QualitativeEvaluation(CODES["status"],
                                                                 CODES["not_measured"])])]
    a, d, geometry = measured.angles, measured.deviation, measured.geometry
    region = hd.sr.ImageRegion3D(graphic_type=hd.sr.GraphicTypeValues3D.POLYGON,
                                 graphic_data=np.asarray(geometry.plane_polygon, float),
                                 frame_of_reference_uid=geometry.frame_of_reference_uid)
    plane = hd.sr.PlanarROIMeasurementsAndQualitativeEvaluations(
        tracking_identifier=tracking("Resection plane"), referenced_region=region,
        finding_type=CODES["plane"], algorithm_id=algorithm, finding_sites=[site],
        measurements=[_measurement(CODES["ctr"], a.ctr_deg),
                      _measurement(CODES["str"], a.str_deg),
                      _measurement(CODES["ctr"], a.ctr_sigma_deg, _SD),
                      _measurement(CODES["str"], a.str_sigma_deg, _SD),
                      _measurement(CODES["ctr_dev"], d.ctr_deg),
                      _measurement(CODES["str_dev"], d.str_deg)],
        qualitative_evaluations=[
            hd.sr.QualitativeEvaluation(CODES["status"], CODES["measured"]),
            hd.sr.QualitativeEvaluation(CODES["within"], _YES if d.within_tolerance else _NO)])
    pins = []
    for k, (axis, angle) in enumerate(zip(geometry.pin_axes, geometry.pin_angles_deg), start=1):
        coords = hd.sr.CoordinatesForMeasurement3D(
            graphic_type=hd.sr.GraphicTypeValues3D.POLYLINE, graphic_data=np.asarray(axis, float),
            frame_of_reference_uid=geometry.frame_of_reference_uid)
        pins.append(hd.sr.MeasurementsAndQualitativeEvaluations(
            tracking_identifier=tracking(f"Trocar pin {k}"), finding_type=CODES["pin"],
            algorithm_id=algorithm, finding_sites=[site],
            measurements=[_measurement(CODES["pin_angle"], angle, coordinates=coords)]))
    return [plane, *pins]


def build_sr(evidence: list[Dataset], measured: SrMeasurement | None, *, side: str | None,
             version: str, series_uid: str, sop_instance_uid: str, uid_for: Callable[[str], str],
             content_datetime: datetime, notes: Sequence[tuple[str, str]] = (),
             manufacturer: str = "slamtka", institution: str = "",
             device_name: str = "SLAMTKA", series_number: int = SR_SERIES_NUMBER,
             series_description: str = "slamtka resection plane") -> Dataset:
    """The Comprehensive 3D SR of a result, in the study of the ``evidence`` frames (their
    headers already sanitised, :mod:`service.headers`): ``measured`` states the plane, or
    None reports "not measured".

    ``side`` (left, right or None) is the tibia's; ``version`` the software's;
    ``uid_for(what)`` gives the run's UID for ``what`` (tracking identifiers);
    ``notes``: (key of :data:`CODES`, text) pairs added as TEXT items to the report."""
    site = hd.sr.FindingSite(anatomic_location=_TIBIA,
                             laterality=_LATERALITY.get(side) if side else None)
    algorithm = hd.sr.AlgorithmIdentification(name="slamtka", version=version)
    observer = hd.sr.ObserverContext(
        observer_type=codes.DCM.Device,
        observer_identifying_attributes=hd.sr.DeviceObserverIdentifyingAttributes(
            uid=generate_uid(entropy_srcs=["slamtka device", device_name]), name=device_name,
            manufacturer_name=manufacturer))
    report = hd.sr.MeasurementReport(
        observation_context=hd.sr.ObservationContext(observer_device_context=observer),
        procedure_reported=_PROCEDURE,
        imaging_measurements=_groups(measured, algorithm, site, uid_for))
    content = report[0]
    for key, text in notes:
        content.ContentSequence.append(hd.sr.TextContentItem(
            name=CODES[key], value=text[:1024],
            relationship_type=hd.sr.RelationshipTypeValues.CONTAINS))
    sr = hd.sr.Comprehensive3DSR(
        evidence=evidence, content=content, series_instance_uid=series_uid,
        series_number=series_number, sop_instance_uid=sop_instance_uid, instance_number=1,
        manufacturer=manufacturer, institution_name=institution or None, is_complete=True,
        series_description=series_description)
    scheme = Dataset()
    scheme.CodingSchemeDesignator = SCHEME
    scheme.CodingSchemeName = "slamtka measurement concepts"
    scheme.CodingSchemeResponsibleOrganization = "slamtka project"
    sr.CodingSchemeIdentificationSequence = [scheme]
    stamp_dates(sr, content_datetime)
    return sr
