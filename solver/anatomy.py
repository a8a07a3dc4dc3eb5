"""The tibia's anatomical frame and the clinical angles of a resection plane.

Anatomical frame (README.md, Conventions): origin at the knee centre, +z the mechanical axis
from the ankle centre to the knee centre, +y anterior, +x = y cross z (the patient's right).
The medial side is therefore -x on a right leg and +x on a left leg.

Angles of a resection plane with unit normal ``n`` (anatomical frame, ``n_z > 0``):
- CTR, coronal: angle in the x-z plane between ``n`` and the mechanical axis, positive in
  varus (medial side cut lower, i.e. ``n`` leans towards medial).
- STR, sagittal: angle in the y-z plane, positive for posterior slope (posterior side cut
  lower, i.e. ``n`` leans towards posterior).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slamtka.solver.geometry import Pose
from slamtka.solver.jsonfile import read_json_object
from slamtka.solver.surface import UNIT_SCALE_TO_MM

__all__ = ["Landmarks", "SIGN_CONVENTION", "resection_angles", "plane_normal_from_angles"]

SIGN_CONVENTION = {
    "CTR": "coronal angle between the resection plane normal and the tibial mechanical axis; "
    "positive = varus (medial side cut lower)",
    "STR": "sagittal angle between the resection plane normal and the tibial mechanical axis; "
    "positive = posterior slope (posterior side cut lower)",
    "units": "degrees",
}

_SIDES = ("left", "right")


@dataclass(frozen=True)
class Landmarks:
    """Plan landmarks in the tibia mesh frame (mm)."""

    knee_centre: np.ndarray
    ankle_centre: np.ndarray
    anterior: np.ndarray  # a direction; only its part orthogonal to the mechanical axis is used
    side: str

    def __post_init__(self) -> None:
        if self.side not in _SIDES:
            raise ValueError(f"laterality must be 'left' or 'right', got {self.side!r}")
        for field in ("knee_centre", "ankle_centre", "anterior"):
            value = np.asarray(getattr(self, field), dtype=float).reshape(-1)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"landmark {field} must be three finite numbers")
            object.__setattr__(self, field, value)
        length = np.linalg.norm(self.knee_centre - self.ankle_centre)
        if not 250.0 <= length <= 500.0:
            raise ValueError(
                f"knee-to-ankle distance {length:.1f} mm is not a plausible tibial mechanical "
                "axis (250-500 mm); check the landmark units"
            )
        if not np.linalg.norm(self.anterior) > 0.0:
            # A zero vector would pass the parallelism test below (0 < 0 is false) and give
            # the anatomical frame NaN axes.
            raise ValueError("the anterior direction is a zero vector (or the tuberosity is at "
                             "the knee centre); give a direction pointing anterior")
        axis = (self.knee_centre - self.ankle_centre) / length
        across = self.anterior - np.dot(self.anterior, axis) * axis
        if np.linalg.norm(across) < 0.5 * np.linalg.norm(self.anterior):
            raise ValueError("the anterior direction is nearly parallel to the mechanical axis")

    @staticmethod
    def nominal() -> Landmarks:
        """A plausible right tibia in its own anatomical frame (knee centre at the origin, the
        ankle 370 mm below), for what must be set up before any plan is known."""
        return Landmarks(np.zeros(3), np.array([0.0, 0.0, -370.0]), np.array([0.0, 1.0, 0.0]),
                         "right")

    @property
    def medial_sign(self) -> float:
        """+1 if medial is +x of the anatomical frame (left leg), -1 if -x (right leg)."""
        return 1.0 if self.side == "left" else -1.0

    def T_tibia_anat(self) -> Pose:
        """Pose of the anatomical frame in the tibia mesh frame."""
        z = self.knee_centre - self.ankle_centre
        z /= np.linalg.norm(z)
        y = self.anterior - np.dot(self.anterior, z) * z
        y /= np.linalg.norm(y)
        x = np.cross(y, z)
        return Pose(np.column_stack([x, y, z]), self.knee_centre)

    def to_json(self) -> dict:
        return {
            "units": "mm",
            "knee_centre": self.knee_centre.tolist(),
            "ankle_centre": self.ankle_centre.tolist(),
            "anterior": self.anterior.tolist(),
            "side": self.side,
        }

    @staticmethod
    def from_json(d: dict, scale_to_mm: float | None = None) -> Landmarks:
        """Parse landmarks; ``units`` in the document (mm, cm, m) or ``scale_to_mm`` applies.

        ``anterior`` is a direction; ``tuberosity`` (a point) may be given instead.
        """
        units = d.get("units", "mm")
        if scale_to_mm is None:
            if units not in UNIT_SCALE_TO_MM:
                raise ValueError(f"landmarks: unknown units {units!r}")
            scale_to_mm = UNIT_SCALE_TO_MM[units]
        try:
            knee = np.asarray(d["knee_centre"], float) * scale_to_mm
            ankle = np.asarray(d["ankle_centre"], float) * scale_to_mm
            if "anterior" in d:
                anterior = np.asarray(d["anterior"], float)
            elif "tuberosity" in d:
                anterior = np.asarray(d["tuberosity"], float) * scale_to_mm - knee
            else:
                raise ValueError("landmarks need 'anterior' (a direction) or 'tuberosity' (a point)")
            return Landmarks(knee, ankle, anterior, d["side"])
        except KeyError as missing:
            raise ValueError(f"landmarks lack the field {missing}") from None

    @staticmethod
    def load(path: Path) -> Landmarks:
        """Landmarks from a JSON file; any refusal names the file."""
        doc = read_json_object(path)
        try:
            return Landmarks.from_json(doc)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None


def resection_angles(normal_anat: np.ndarray, medial_sign: float) -> tuple[float, float]:
    """(CTR, STR) in radians of a plane normal given in the anatomical frame."""
    n = np.asarray(normal_anat, float)
    if n[2] < 0:
        n = -n
    ctr = np.arctan2(medial_sign * n[0], n[2])
    str_ = np.arctan2(-n[1], n[2])
    return float(ctr), float(str_)


def plane_normal_from_angles(ctr: float, str_: float, medial_sign: float) -> np.ndarray:
    """Unit normal (anatomical frame) of the plane with the given CTR/STR (radians)."""
    n = np.array([medial_sign * np.tan(ctr), -np.tan(str_), 1.0])
    return n / np.linalg.norm(n)
