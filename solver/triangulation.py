"""Closed-form starting pose of a pin from its contours in two or more views.

A pin is a thin straight rod: in each view its contour pixels lie along one image segment.
The two ends of that segment (the trocar tip and the pin's back end) are seen in every view,
so each end is triangulated from its rays, and the pin runs from one to the other. This is
well posed even when the back-projected planes of the views nearly coincide (pins running
front to back, seen from both sides of antero-posterior, lie close to both planes), where
intersecting the planes would amplify small view errors into degrees of axis error. It
replaces the planned pin pose (which may be tens of millimetres off) before the silhouette
optimisation, so the pins start next to where they are seen.
"""

from __future__ import annotations

from itertools import product

import numpy as np

from slamtka.solver.camera import Camera
from slamtka.solver.geometry import Pose

__all__ = ["PinSighting", "sighting_score", "triangulate_pin", "triangulate_rays"]

# Ends of the pixels' spread along the segment (percentiles), robust to stray contour pixels.
_END_PERCENTILES = (0.5, 99.5)
# Millimetres of meeting gap worth one millimetre of length discrepancy, when pairing ends.
_LENGTH_WEIGHT = 0.1


class PinSighting:
    """The contour pixels of one pin in one view, with that view's camera and pose."""

    def __init__(self, camera: Camera, T_cam_tibia: Pose, pixels: np.ndarray):
        self.camera, self.T_cam_tibia, self.pixels = camera, T_cam_tibia, pixels

    def source(self) -> np.ndarray:
        """X-ray source position in the tibia frame."""
        return self.T_cam_tibia.inverse().t

    def end_rays(self) -> np.ndarray:
        """Unit rays (2, 3), tibia frame, through the two ends of the pin's image segment."""
        centre = self.pixels.mean(axis=0)
        direction = np.linalg.svd(self.pixels - centre, full_matrices=False)[2][0]
        along = (self.pixels - centre) @ direction
        ends = centre + np.outer(np.percentile(along, _END_PERCENTILES), direction)
        return self.T_cam_tibia.inverse().rotate(self.camera.rays(ends))


def triangulate_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, float]:
    """Point nearest to all rays (least squares) and its RMS distance to them, mm."""
    d = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    across = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # projectors across each ray
    point = np.linalg.solve(across.sum(axis=0), np.einsum("nij,nj->i", across, origins))
    gaps = np.einsum("nij,nj->ni", across, point - origins)
    return point, float(np.sqrt(np.mean(np.sum(gaps**2, axis=1))))


def _best_ends(sightings: list[PinSighting], length_mm: float | None
               ) -> tuple[float, np.ndarray, np.ndarray]:
    """The pin's two ends triangulated from the sightings' segment ends, and the pairing's
    score (mm): how badly the rays meet, plus how far the pin is from the model's length."""
    sources = np.array([s.source() for s in sightings])
    end_rays = [s.end_rays() for s in sightings]
    # Which end of each view's segment is which is not known. A pin running front to back
    # lies close to the epipolar plane of views on both sides of AP, so the wrong pairing
    # still nearly meets (a fraction of a millimetre): the pairing is chosen by how well its
    # rays meet and, above all, by how close the triangulated pin is to the model's length.
    best = None
    for flips in product((0, 1), repeat=len(sightings) - 1):
        order = (0,) + flips
        ends = []
        for end in (0, 1):
            rays = np.array([r[end ^ o] for r, o in zip(end_rays, order)])
            ends.append(triangulate_rays(sources, rays))
        score = ends[0][1] + ends[1][1]
        if length_mm is not None:
            score += _LENGTH_WEIGHT * abs(float(np.linalg.norm(ends[1][0] - ends[0][0])) - length_mm)
        if best is None or score < best[0]:
            best = (score, ends[0][0], ends[1][0])
    assert best is not None
    return best


def sighting_score(sightings: list[PinSighting], length_mm: float | None = None) -> float:
    """How well the sightings fit one pin (mm, lower is better; inf when under two views)."""
    sightings = [s for s in sightings if len(s.pixels) >= 3]
    return _best_ends(sightings, length_mm)[0] if len(sightings) >= 2 else float("inf")


def triangulate_pin(sightings: list[PinSighting], prior: Pose,
                    length_mm: float | None = None) -> Pose | None:
    """Pin pose (+z along the axis from the tip, tip at the origin) seen in ``sightings``;
    ``prior`` (the current or planned pose) decides which end is the tip and the roll;
    ``length_mm``, the pin model's length, helps to pair the segment ends across views.
    None if the pin is seen in fewer than two views."""
    sightings = [s for s in sightings if len(s.pixels) >= 3]
    if len(sightings) < 2:
        return None
    _, a, b = _best_ends(sightings, length_mm)
    axis = b - a
    if np.linalg.norm(axis) < 1e-6:
        return None
    axis /= np.linalg.norm(axis)
    tip = a
    if np.dot(axis, prior.R[:, 2]) < 0:
        axis, tip = -axis, b

    x = prior.R[:, 0] - np.dot(prior.R[:, 0], axis) * axis
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    return Pose(np.column_stack([x, np.cross(axis, x), axis]), tip)
