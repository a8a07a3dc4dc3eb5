"""The resection plane through the posed pins and its clinical angles with uncertainty.

The saw cut is parallel to the plane of the two trocar pins, so the resection plane is the
least-squares plane through both pins' axes (sampled along their length) in the tibia frame.
Its CTR/STR follow the sign conventions of :mod:`solver.anatomy`. The 1-sigma uncertainty is
propagated from the solver's marginal covariance of the two pin poses.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from slamtka.solver.anatomy import Landmarks, resection_angles
from slamtka.solver.geometry import Pose

__all__ = ["PinDivergence", "ResectionPlane", "angle_covariance", "fit_resection_plane",
           "pin_divergence", "pins_from_anteroposterior_deg", "plane_elevations_deg", "with_in_plane_sd"]

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


def _plane_through(pins: tuple[Pose, Pose] | list[Pose], pin_length_mm: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Centroid and unit normal of the least-squares plane through both pins' axes."""
    points = np.vstack([pin_axis_points(T, pin_length_mm) for T in pins])
    centroid = points.mean(axis=0)
    return centroid, np.linalg.svd(points - centroid)[2][-1]


def fit_resection_plane(
    pins: tuple[Pose, Pose] | list[Pose], pin_length_mm: float, landmarks: Landmarks
) -> ResectionPlane:
    centroid, normal = _plane_through(pins, pin_length_mm)
    T_tibia_anat = landmarks.T_tibia_anat()
    normal_anat = T_tibia_anat.R.T @ normal
    if normal_anat[2] < 0:
        normal, normal_anat = -normal, -normal_anat
    ctr, str_ = resection_angles(normal_anat, landmarks.medial_sign)
    return ResectionPlane(centroid, normal, ctr, str_)


class PinDivergence(NamedTuple):
    """How far the two pins' axes are from parallel (deg), split by the plane through them:
    ``out_of_plane`` tilts one pin against the other across that plane, ``in_plane`` turns
    one against the other within it; and the standard deviation of ``in_plane`` that the
    pins' covariance gives (NaN where not worked out)."""

    total: float
    out_of_plane: float
    in_plane: float
    in_plane_sd: float = float("nan")


def _pin_axes(pins: tuple[Pose, Pose] | list[Pose]) -> list[np.ndarray]:
    """The pins' unit axes (pin frame +z) in the tibia frame, the second pointing as the first."""
    axes = [T.R[:, 2] for T in pins]
    if axes[0] @ axes[1] < 0:
        axes[1] = -axes[1]
    return axes


def pin_divergence(pins: tuple[Pose, Pose] | list[Pose], pin_length_mm: float) -> PinDivergence:
    """The pins' divergence from parallel, whole and split by their plane."""
    axes = _pin_axes(pins)
    _, normal = _plane_through(pins, pin_length_mm)
    tilts = [np.arcsin(np.clip(axis @ normal, -1.0, 1.0)) for axis in axes]
    flat = [axis - (axis @ normal) * normal for axis in axes]
    turn = np.arctan2(abs(normal @ np.cross(flat[0], flat[1])), flat[0] @ flat[1])
    total = np.arccos(np.clip(axes[0] @ axes[1], -1.0, 1.0))
    return PinDivergence(*(float(np.degrees(a)) for a in (total, abs(tilts[0] - tilts[1]), turn)))


def pins_from_anteroposterior_deg(pins: tuple[Pose, Pose] | list[Pose], landmarks: Landmarks) -> float:
    """How far (deg) the pins' mean axis lies from the tibia's front-to-back axis (the
    anatomical +y, either way along it). The mean, not each pin's: where the views see the
    pins' plane edge-on, a pin's turn within it is not resolved (gates.pin_divergence)."""
    mean = np.sum(_pin_axes(pins), axis=0)
    anteroposterior = landmarks.T_tibia_anat().R[:, 1]
    cosine = abs(float(mean @ anteroposterior)) / float(np.linalg.norm(mean))
    return float(np.degrees(np.arccos(min(cosine, 1.0))))


def plane_elevations_deg(pins: list[Pose], T_cam_tibia: list[Pose], pin_length_mm: float) -> list[float]:
    """How far (deg) each view's X-ray source lies out of the plane through the pins, seen
    from the pins: 0 where a view sees that plane edge-on (both pins on one line)."""
    centroid, normal = _plane_through(pins, pin_length_mm)
    elevations = []
    for T in T_cam_tibia:
        to_source = T.inverse().t - centroid
        elevations.append(float(np.degrees(np.arcsin(min(1.0, abs(normal @ to_source) / np.linalg.norm(to_source))))))
    return elevations


def with_in_plane_sd(divergence: PinDivergence, pins: list[Pose], pin_covariance: np.ndarray,
                     pin_length_mm: float) -> PinDivergence:
    """``divergence`` with the standard deviation of its in-plane turn from the 12x12
    covariance of the pin increments."""
    J = _jacobian(pins, lambda moved: np.array([pin_divergence(moved, pin_length_mm).in_plane]))
    return divergence._replace(in_plane_sd=float(np.sqrt((J @ pin_covariance @ J.T)[0, 0])))


def angle_covariance(
    pins: list[Pose], pin_covariance: np.ndarray, pin_length_mm: float, landmarks: Landmarks
) -> np.ndarray:
    """2x2 covariance of (CTR, STR) in rad^2 from the 12x12 covariance of the pin increments."""
    def angles(moved: list[Pose]) -> np.ndarray:
        plane = fit_resection_plane(moved, pin_length_mm, landmarks)
        return np.array([plane.ctr, plane.str_])

    J = _jacobian(pins, angles)
    return J @ pin_covariance @ J.T


def _jacobian(pins: list[Pose], figures: Callable[[list[Pose]], np.ndarray]) -> np.ndarray:
    """Forward-difference Jacobian of ``figures`` of the two pins by their 12 increments."""
    base, eps = figures(pins), 1e-6
    J = np.zeros((len(base), 12))
    for k in range(12):
        d = np.zeros(12)
        d[k] = eps
        J[:, k] = (figures([pins[0].retract(d[:6]), pins[1].retract(d[6:])]) - base) / eps
    return J
