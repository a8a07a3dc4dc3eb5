"""The resection plane through the posed pins and its clinical angles with uncertainty.

The saw cut is parallel to the plane of the two trocar pins, so the resection plane is the
least-squares plane through both pins' axes (sampled along their length) in the tibia frame.
Its CTR/STR follow the sign conventions of :mod:`solver.anatomy`. The 1-sigma uncertainty is
propagated from the solver's marginal covariance of the two pin poses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slamtka.solver.anatomy import Landmarks, resection_angles
from slamtka.solver.geometry import Pose

__all__ = ["ResectionPlane", "fit_resection_plane", "angle_covariance"]

_AXIS_SAMPLES = 16


@dataclass(frozen=True)
class ResectionPlane:
    """A plane in the tibia frame, with its CTR/STR in radians."""

    point: np.ndarray  # (3,) mm, centroid of the pin axes
    normal: np.ndarray  # (3,) unit, pointing proximally
    ctr: float
    str_: float


def pin_axis_points(T_tibia_pin: Pose, length_mm: float) -> np.ndarray:
    """Points along a pin's axis (pin frame +z) from tip to end, in the tibia frame."""
    z = np.linspace(0.0, length_mm, _AXIS_SAMPLES)
    return T_tibia_pin.apply(np.column_stack([np.zeros_like(z), np.zeros_like(z), z]))


def fit_resection_plane(
    pins: tuple[Pose, Pose] | list[Pose], pin_length_mm: float, landmarks: Landmarks
) -> ResectionPlane:
    points = np.vstack([pin_axis_points(T, pin_length_mm) for T in pins])
    centroid = points.mean(axis=0)
    normal = np.linalg.svd(points - centroid)[2][-1]
    T_tibia_anat = landmarks.T_tibia_anat()
    normal_anat = T_tibia_anat.R.T @ normal
    if normal_anat[2] < 0:
        normal, normal_anat = -normal, -normal_anat
    ctr, str_ = resection_angles(normal_anat, landmarks.medial_sign)
    return ResectionPlane(centroid, normal, ctr, str_)


def angle_covariance(
    pins: list[Pose], pin_covariance: np.ndarray, pin_length_mm: float, landmarks: Landmarks
) -> np.ndarray:
    """2x2 covariance of (CTR, STR) in rad^2 from the 12x12 covariance of the pin increments."""
    base = fit_resection_plane(pins, pin_length_mm, landmarks)
    J = np.zeros((2, 12))
    eps = 1e-6
    for k in range(12):
        d = np.zeros(12)
        d[k] = eps
        moved = [pins[0].retract(d[:6]), pins[1].retract(d[6:])]
        plane = fit_resection_plane(moved, pin_length_mm, landmarks)
        J[:, k] = [(plane.ctr - base.ctr) / eps, (plane.str_ - base.str_) / eps]
    return J @ pin_covariance @ J.T
