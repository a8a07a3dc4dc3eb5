"""Closed-form starting pose of a pin from its contours in two or more views.

A pin is a thin straight rod: in each view its contour pixels lie along one image line, and
that line back-projects to a plane through the X-ray source that contains the pin's axis.
The planes of two views meet in the axis; the trocar tip is the end of the pin's pixels
nearest the tip side. This replaces the planned pin pose (which may be tens of millimetres
off) before the silhouette optimisation, so the pins start next to where they are seen.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera
from .geometry import Pose

__all__ = ["PinSighting", "triangulate_pin"]

# Below this angle between two back-projected planes the axis direction across the planes is
# not determined by the contours; the prior direction's component is kept there.
_MIN_PLANE_ANGLE_RAD = np.radians(3.0)


class PinSighting:
    """The contour pixels of one pin in one view, with that view's camera and pose."""

    def __init__(self, camera: Camera, T_cam_tibia: Pose, pixels: np.ndarray):
        self.camera, self.T_cam_tibia, self.pixels = camera, T_cam_tibia, pixels

    def source(self) -> np.ndarray:
        """X-ray source position in the tibia frame."""
        return self.T_cam_tibia.inverse().t

    def rays(self) -> np.ndarray:
        """Unit ray directions of the pixels, in the tibia frame."""
        return self.T_cam_tibia.inverse().rotate(self.camera.rays(self.pixels))

    def plane_normal(self) -> np.ndarray:
        """Unit normal (tibia frame) of the plane through the source and the pin's image line."""
        centred = self.pixels - self.pixels.mean(axis=0)
        direction = np.linalg.svd(centred, full_matrices=False)[2][0]
        ends = self.pixels.mean(axis=0) + np.outer([-50.0, 50.0], direction)
        r = self.camera.rays(ends)
        normal_cam = np.cross(r[0], r[1])
        return self.T_cam_tibia.inverse().rotate(normal_cam / np.linalg.norm(normal_cam))


def _axis_direction(normals: np.ndarray, prior: np.ndarray) -> np.ndarray:
    """Direction orthogonal to every plane normal, on the prior's side; where the planes are
    nearly parallel, the prior's component across them is kept."""
    _, s, vt = np.linalg.svd(normals)
    if len(s) >= 2 and s[1] / s[0] > np.sin(_MIN_PLANE_ANGLE_RAD):
        d = vt[2]
    else:
        n = vt[0]
        d = prior - np.dot(prior, n) * n
    d = d / np.linalg.norm(d)
    return d if np.dot(d, prior) >= 0 else -d


def triangulate_pin(sightings: list[PinSighting], prior: Pose) -> Pose | None:
    """Pin pose (+z along the axis from the tip, tip at the origin) seen in ``sightings``;
    ``prior`` (the planned pose) decides which way the pin points and its roll. None if the
    pin is seen in fewer than two views."""
    sightings = [s for s in sightings if len(s.pixels) >= 3]
    if len(sightings) < 2:
        return None
    normals = np.array([s.plane_normal() for s in sightings])
    offsets = np.array([np.dot(n, s.source()) for n, s in zip(normals, sightings)])
    d = _axis_direction(normals, prior.R[:, 2])
    # The axis point nearest the prior tip that lies in every plane (least squares).
    through = prior.t + np.linalg.pinv(normals) @ (offsets - normals @ prior.t)
    through -= np.dot(through - prior.t, d) * d

    # Each pixel's ray passes closest to the axis at parameter s along it; the tip is the
    # smallest s seen (a robust low percentile against contour noise).
    params = []
    for s in sightings:
        rays, w0 = s.rays(), s.source() - through
        b = rays @ d
        denom = np.maximum(1.0 - b**2, 1e-9)
        params.append((w0 @ d - b * (rays @ w0)) / denom)
    tip_s = np.percentile(np.concatenate(params), 0.5)

    x = prior.R[:, 0] - np.dot(prior.R[:, 0], d) * d
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return Pose(np.column_stack([x, np.cross(d, x), d]), through + tip_s * d)
