"""Initial poses: each view from the C-arm geometry, each pin from the planned resection.

Views. The patient set-up is nominal (``drivers.kinematics.PatientSetup``): supine, the leg
along the table, the isocentre at a configurable point of the tibia's anatomical frame. A
frame is paired with the encoder reading taken at its acquisition time (the C-arm link) and
its pose follows through the C-arm kinematics, with the encoders' relative motion between
views and its uncertainty; a frame without a reading falls back to its DICOM positioner
angles (PS3.3 C.8.7.5): at primary = secondary = 0 the beam runs from the source
under the table straight up (posterior to anterior); the primary angle turns the detector
towards the patient's left (LAO, positive), the secondary angle towards the head (cranial,
positive). In the anatomical frame (+x patient's right, +y anterior, +z head) the beam
direction is therefore ``(-sin a cos b, cos a cos b, sin b)``; image rows run towards the
feet, as the C-arm shows a leg.

Pins. Two parallel pins in the planned resection plane, anteromedial, drilled posteriorly
from the anterior cortex: a nominal block placement the joint solver refines.
"""

from __future__ import annotations

from collections.abc import Set
from dataclasses import dataclass

import numpy as np

from slamtka.drivers.kinematics import (
    AXIS_UNITS,
    CArmKinematics,
    JointReading,
    PatientSetup,
    check_dicom_angles,
    initial_view_poses,
)
from slamtka.service.clock import ReadingSource, review_pairing
from slamtka.service.frames import FrameHeader
from slamtka.solver.anatomy import Landmarks, plane_normal_from_angles
from slamtka.solver.block import block_axes, bone_entry_mm, pin_pose
from slamtka.solver.geometry import Pose, largest_angle_deg, look_at
from slamtka.solver.plan import Plan

__all__ = ["beam_direction_anat", "positioner_T_anat_cam", "planned_pins",
           "view_separation_deg", "ViewGeometry", "ViewPairing", "InitialViews"]

PLANNED_DEPTH_BELOW_PLATEAU_MM = 18.0
PLANNED_PIN_SPACING_MM = 30.0
PLANNED_MEDIAL_OFFSET_MM = 6.0
PLANNED_DRILL_DEPTH_MM = 30.0


def beam_direction_anat(primary_deg: float, secondary_deg: float) -> np.ndarray:
    """Unit direction from the X-ray source to the detector in the anatomical frame."""
    a, b = np.radians(primary_deg), np.radians(secondary_deg)
    return np.array([-np.sin(a) * np.cos(b), np.cos(a) * np.cos(b), np.sin(b)])


def positioner_T_anat_cam(primary_deg: float, secondary_deg: float, sod_mm: float,
                          isocentre_anat: np.ndarray) -> Pose:
    """Pose of the X-ray source camera in the anatomical frame from DICOM positioner angles."""
    beam = beam_direction_anat(primary_deg, secondary_deg)
    iso = np.asarray(isocentre_anat, float)
    up = np.array([0.0, 0.0, 1.0]) if abs(beam[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
    return look_at(iso - sod_mm * beam, iso, up)


def view_separation_deg(beams: list[np.ndarray]) -> float:
    """Largest angle between any two beam directions, degrees."""
    return largest_angle_deg(np.asarray(beams, float).reshape(-1, 3))


@dataclass(frozen=True)
class ViewPairing:
    """How one frame was paired with the C-arm's geometry (persisted beside the instance)."""

    initialisation: str | None  # "encoders", "dicom_positioner", or None: unusable
    encoder_reading: dict | None = None  # EncoderReading.to_json()
    angle_check: dict | None = None  # encoders against the DICOM positioner angles
    problem: str | None = None  # why the view cannot be initialised
    clock: dict | None = None  # a clock offset found and how it was handled (service.clock)

    def to_json(self) -> dict:
        return dict(vars(self))

    def joints(self) -> JointReading:
        """The joint values of the paired encoder reading (ValueError when there is none)."""
        if self.encoder_reading is None:
            raise ValueError(f"the view is not paired with an encoder reading ({self.initialisation})")
        joints = self.encoder_reading["joints"]
        return JointReading.from_axes({axis: joints[axis] for axis in AXIS_UNITS if axis in joints})

    @staticmethod
    def from_json(d: dict) -> ViewPairing:
        return ViewPairing(d.get("initialisation"), d.get("encoder_reading"), d.get("angle_check"),
                           d.get("problem"), d.get("clock"))


@dataclass(frozen=True)
class InitialViews:
    """Initial ``T_cam_tibia`` per view and the encoders' relative-motion uncertainty."""

    T_cam_tibia: list[Pose]
    odometry_sigma: tuple[float, float] | None  # (rad, mm) when every view has encoders


class ViewGeometry:
    """The C-arm side of the service: encoder pairing, beam directions, initial view poses."""

    def __init__(self, kinematics: CArmKinematics, setup: dict, link: ReadingSource | None,
                 max_reading_age_s: float, angle_check_deg: float, max_clock_offset_s: float = 0.0):
        self.kinematics, self.setup_config, self.link = kinematics, dict(setup), link
        self.max_reading_age_s, self.angle_check_deg = max_reading_age_s, angle_check_deg
        self.max_clock_offset_s = max_clock_offset_s
        # The set-up's orientation and isocentre do not depend on the plan: any landmarks do.
        self._nominal_setup = self.setup(Landmarks.nominal())

    def setup(self, landmarks: Landmarks) -> PatientSetup:
        return PatientSetup.from_config(landmarks, self.setup_config)

    def pair(self, frame: FrameHeader, taken: Set[int] = frozenset()) -> ViewPairing:
        """The encoder reading at the frame's acquisition time, else its positioner angles.

        ``taken``: sequence numbers of the readings other views of the case were paired
        with. A reading that shows a clock offset (:mod:`service.clock`) is replaced by the
        one at the corrected time, or by the header's angles, with a ``clock`` note."""
        reading = None
        if self.link is not None and frame.acquisition_datetime is not None:
            reading = self.link.reading_at(frame.acquisition_datetime, self.max_reading_age_s)
            review = review_pairing(self.link, self.kinematics, self._nominal_setup,
                                    frame.acquisition_datetime, reading, frame.primary_angle_deg,
                                    frame.secondary_angle_deg, set(taken), self.angle_check_deg,
                                    self.max_clock_offset_s)
            if review is not None:
                if review.reading is not None:
                    agreement = None if review.check is None else review.check.to_json()
                    return ViewPairing("encoders", review.reading.to_json(), agreement,
                                       clock=review.note)
                if review.note["status"] == "header_angles":
                    return ViewPairing("dicom_positioner", clock=review.note)
                return ViewPairing(None, problem=review.note["message"], clock=review.note)
        has_angles = frame.primary_angle_deg is not None and frame.secondary_angle_deg is not None
        if reading is not None:
            check = check_dicom_angles(self.kinematics, reading.joints, self._nominal_setup,
                                       frame.primary_angle_deg, frame.secondary_angle_deg,
                                       self.angle_check_deg)
            return ViewPairing("encoders", reading.to_json(), check.to_json())
        if has_angles:
            return ViewPairing("dicom_positioner")
        why = ("no encoder link" if self.link is None else
               "no acquisition time" if frame.acquisition_datetime is None else
               "no encoder reading at the acquisition time")
        return ViewPairing(None, problem=f"{why} and no positioner angles in the image")

    def beam_anat(self, pairing: ViewPairing, primary_deg: float | None,
                  secondary_deg: float | None) -> np.ndarray:
        """Beam direction (source to detector) in the anatomical frame of the nominal set-up."""
        if pairing.initialisation == "encoders":
            R_carm_cam = self.kinematics.T_carm_cam(pairing.joints()).R
            return self._nominal_setup.R_carm_anat().T @ R_carm_cam[:, 2]
        if primary_deg is None or secondary_deg is None:
            raise ValueError(f"view paired by {pairing.initialisation} has no positioner angles")
        return beam_direction_anat(primary_deg, secondary_deg)

    def initial_views(self, plan: Plan, pairings: list[ViewPairing],
                      positioners: list[dict]) -> InitialViews:
        """Initial ``T_cam_tibia`` of each view (all pairings must be usable)."""
        setup = self.setup(plan.landmarks)
        T_anat_tibia = plan.landmarks.T_tibia_anat().inverse()
        encoder_views = [k for k, p in enumerate(pairings) if p.initialisation == "encoders"]
        poses: dict[int, Pose] = {}
        odometry = None
        if encoder_views:
            joints = [pairings[k].joints() for k in encoder_views]
            from_encoders, relatives = initial_view_poses(self.kinematics, joints, setup)
            for k, T in zip(encoder_views, from_encoders):
                poses[k] = T
            if relatives and len(encoder_views) == len(pairings):
                odometry = (max(r.sigma_rad for r in relatives), max(r.sigma_mm for r in relatives))
        iso = np.asarray(setup.isocentre_in_anat_mm)
        for k, (pairing, pos) in enumerate(zip(pairings, positioners)):
            if pairing.initialisation == "dicom_positioner":
                sod = pos["sod_mm"] or self.kinematics.source_to_isocentre_mm
                T_anat_cam = positioner_T_anat_cam(pos["primary_angle_deg"],
                                                   pos["secondary_angle_deg"], sod, iso)
                poses[k] = T_anat_cam.inverse() @ T_anat_tibia
            elif pairing.initialisation != "encoders":
                raise ValueError(f"view {k} has no usable geometry: {pairing.problem}")
        return InitialViews([poses[k] for k in range(len(pairings))], odometry)


def planned_pins(plan: Plan) -> tuple[Pose, Pose]:
    """``T_tibia_pin`` of two pins placed for the planned CTR/STR (pin +z: tip to end)."""
    lm = plan.landmarks
    T_tibia_anat = lm.T_tibia_anat()
    normal = plane_normal_from_angles(np.radians(plan.target.ctr_deg),
                                      np.radians(plan.target.str_deg), lm.medial_sign)
    posterior, across = block_axes(normal)
    centre = np.array([0.0, 0.0, -PLANNED_DEPTH_BELOW_PLATEAU_MM])
    centre = centre + across * lm.medial_sign * PLANNED_MEDIAL_OFFSET_MM
    sdf = plan.bone_model().sdf
    pins = []
    for offset in (-PLANNED_PIN_SPACING_MM / 2, PLANNED_PIN_SPACING_MM / 2):
        start = centre + across * offset - posterior * 150.0  # well anterior of the bone
        entry = bone_entry_mm(sdf, T_tibia_anat, start, posterior, 1.0)
        if entry is None:
            entry = 150.0  # through the block's centre line, where the bone should have been
        tip = start + (entry + PLANNED_DRILL_DEPTH_MM) * posterior
        pins.append(pin_pose(T_tibia_anat, tip, posterior))
    return pins[0], pins[1]
